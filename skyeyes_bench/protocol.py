"""Versioned evaluation protocols: `protocols/<id>/v<N>.toml` -> frozen `Protocol`.

A protocol is data, never code. A change makes a new version; old versions stay loadable.
Its `sha256` is taken over the canonical JSON of the parsed content, so formatting and
comments in the TOML do not change it but any value does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from .errors import UserError, short
from .inputfiles import read_toml
from .metricspec import CLIP_FEATURES, METRICS, SETTINGS, known_keys, metric_def
from .paths import protocols_dir

#: Largest protocol version (9 digits): a longer number in a file name or a reference is refused in one
#: line instead of reaching int(), which stops at 4300 digits with a traceback.
MAX_VERSION = 999_999_999
_VERSION_FILE = re.compile(r"^v([1-9]\d{0,8})\.toml$")  # v1.toml, v2.toml ... (no v01; at most MAX_VERSION)
_REF = re.compile(r"^([a-z0-9][a-z0-9._-]*)(?:@(\d+))?$")

#: Resampling units `[statistics] cluster` may name: a scene (one lane: its sequences share one
#: fitted model, so they are not independent) or, as synthtown@1 does, a sequence.
CLUSTER_UNITS = ("scene", "sequence")

@dataclass(frozen=True)
class DataSpec:
    source: str  # "synthtown" | "carla" | "citysample"
    train: tuple[str, ...]  # towns / regions that make the train split
    test: tuple[str, ...]  # held out
    width: int  # ground and aerial image size, pixels
    height: int
    fov_deg: float  # horizontal field of view of ground and aerial cameras
    default_location: str = ""  # "" none; "cache:<name>" = `<cache>/data/<name>`
    # The protocol whose data this one scores (the `protocol` its datasets' dataset.json and older
    # submissions name): synthtown@3 scores synthtown@2's frames with more metrics. "": its own.
    dataset_protocol: str = ""


@dataclass(frozen=True)
class CaptureSpec:
    ground_height_m: float
    ground_pitch_deg: float
    ground_step_m: float
    yaws_deg: tuple[float, ...]
    aerial_height_m: float
    aerial_pitch_deg: float
    sequence: str  # prose: what one sequence is


@dataclass(frozen=True, init=False)
class MetricSpec:
    """The settings one protocol gives one metric: its name and {key: value} for the keys its
    `metricspec.MetricDef.keys` accepts (whose types and ranges `MetricDef.setting` gives).

    `MetricSpec("kid", subset_size=100)` or `MetricSpec("kid", {"subset_size": 100})`; a setting
    reads as an attribute (`spec.subset_size`), None when not given (for any key some metric
    accepts; another name is an AttributeError). Frozen and hashable; equal when the name and the
    given settings are (a None value is not given)."""

    name: str
    settings: tuple[tuple[str, Any], ...]  # (key, value), in `metricspec.SETTINGS` order, then its own keys

    def __init__(self, name: str, settings: Mapping[str, Any] | tuple = (), **more: Any):
        given = {k: v for k, v in {**dict(settings), **more}.items() if v is not None}
        allowed = metric_def(name).keys
        for key in given:
            if key not in allowed:
                raise UserError(f"metric {name!r}: unknown setting {key!r} (known: {', '.join(sorted(allowed))})")
        order = {k: i for i, k in enumerate(SETTINGS)}
        items = tuple(sorted(given.items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0])))
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "settings", items)

    def __getattr__(self, key: str) -> Any:
        # only called for names that are not attributes; pickle and copy ask for dunders before
        # `__dict__` is filled, so those (and the fields themselves) are never settings
        if key.startswith("_") or key in ("name", "settings"):
            raise AttributeError(key)
        for k, v in self.__dict__.get("settings", ()):
            if k == key:
                return v
        if key in known_keys():
            return None
        raise AttributeError(f"{type(self).__name__} {self.__dict__.get('name')!r} has no setting {key!r}")

    def as_dict(self) -> dict[str, Any]:
        """{key: value} of the settings given, in their order."""
        return dict(self.settings)


@dataclass(frozen=True)
class StatsSpec:
    bootstrap_resamples: int
    interval: float  # e.g. 0.95
    seed: int
    cluster: str  # resampling unit: "scene" (one lane, all its sequences) or "sequence" (v1 protocols)
    emcee_walkers: int
    emcee_steps: int
    emcee_burn: int


@dataclass(frozen=True)
class ValSpec:
    """The validation split of every version of a protocol (`protocols/<id>/val.toml`): where a
    method's settings are chosen, never ranked. Not part of a version's sha256: it changes no
    test score (tune on validation, report on test: docs/evaluate.md, "The split")."""

    towns: tuple[str, ...]  # the towns / regions whose lanes make it
    # "own": towns of their own, in a dataset of their own beside the test data (SynthTown:
    # `data synthtown --split val`); "train": a declared part of the train towns, which a run on
    # the validation split leaves out of its training (CARLA, CitySample: no other data exists)
    source: str
    why: str  # prose: why these towns


VAL_FILE = "val.toml"
VAL_SOURCES = ("own", "train")


@dataclass(frozen=True)
class Protocol:
    id: str
    version: int
    title: str
    description: str
    reference: str
    data: DataSpec
    capture: CaptureSpec
    metrics: tuple[MetricSpec, ...]
    statistics: StatsSpec
    sha256: str = field(default="", compare=False)
    path: str = field(default="", compare=False)
    val: ValSpec | None = field(default=None, compare=False)  # the family's val.toml; not hashed

    @property
    def ref(self) -> str:
        """`id@version`, the name that goes into every cache key and result file."""
        return f"{self.id}@{self.version}"

    def metric(self, name: str) -> MetricSpec | None:
        return next((m for m in self.metrics if m.name == name), None)

    @property
    def metric_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.metrics)

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d.pop("sha256"), d.pop("path"), d.pop("val")
        d["metrics"] = {m["name"]: dict(m["settings"]) for m in d["metrics"]}
        if not d["data"]["dataset_protocol"]:  # unset: absent, so older protocols keep their sha256
            del d["data"]["dataset_protocol"]
        return d

    @property
    def data_ref(self) -> str:
        """The protocol `id@N` its datasets are made for (dataset.json's `protocol`)."""
        return self.data.dataset_protocol or self.ref


# --------------------------------------------------------------------------- validation

_SECTIONS: dict[str, type] = {"data": DataSpec, "capture": CaptureSpec, "statistics": StatsSpec}
_TOP = {"id", "version", "title", "description", "reference", "data", "capture", "metrics", "statistics"}


def _type_ok(value: Any, annotation: str) -> bool:
    base = annotation.replace(" | None", "")
    if base == "str":
        return isinstance(value, str)
    if base == "bool":
        return isinstance(value, bool)
    if base == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if base == "float":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if base.startswith("tuple[str"):
        return isinstance(value, list) and all(isinstance(v, str) for v in value)
    if base.startswith("tuple[float"):
        return isinstance(value, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    raise AssertionError(annotation)


def _convert(value: Any, annotation: str) -> Any:
    base = annotation.replace(" | None", "")
    if base == "float":
        return float(value)
    if base.startswith("tuple[float"):
        return tuple(float(v) for v in value)
    if base.startswith("tuple"):
        return tuple(value)
    return value


def _build(cls: type, table: Any, where: str, file: str, extra: dict | None = None) -> Any:
    if not isinstance(table, dict):
        raise UserError(f"{file}: [{where}] must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = dict(extra or {})
    for key, value in table.items():
        if key not in fields or key in kwargs:
            known = ", ".join(k for k in fields if k not in (extra or {}))
            raise UserError(f"{file}: unknown key '{where}.{key}' (known: {known})")
        ann = str(fields[key].type)
        if not _type_ok(value, ann):
            raise UserError(f"{file}: key '{where}.{key}' must be {ann.replace(' | None', '')}, got {value!r}")
        kwargs[key] = _convert(value, ann)
    for name, f in fields.items():
        if name not in kwargs and f.default is dataclasses.MISSING:
            raise UserError(f"{file}: missing key '{where}.{name}'")
    return cls(**kwargs)


def _metric_spec(name: str, table: Any, file: str) -> MetricSpec:
    """[metrics.<name>] of a protocol file: the keys its `MetricDef` accepts, each of its setting's type."""
    if name not in METRICS:
        raise UserError(f"{file}: unknown metric 'metrics.{name}' (known: {', '.join(METRICS)})")
    if not isinstance(table, dict):
        raise UserError(f"{file}: [metrics.{name}] must be a table")
    spec = metric_def(name)
    settings = {}
    for key, value in table.items():
        if key not in spec.keys:
            raise UserError(f"{file}: unknown key 'metrics.{name}.{key}' (known: {', '.join(sorted(spec.keys))})")
        typ = spec.setting(key).type.__name__
        if not _type_ok(value, typ):
            raise UserError(f"{file}: key 'metrics.{name}.{key}' must be {typ}, got {value!r}")
        settings[key] = _convert(value, typ)
    return MetricSpec(name, settings)


def _check_ranges(m: MetricSpec, file: str) -> None:
    """Each setting of `m` within its range (`metricspec.Setting.least`, `.unit`)."""
    spec = metric_def(m.name)
    for key, v in m.settings:
        s = spec.setting(key)
        if s.least is not None and v < s.least:
            raise UserError(f"{file}: key 'metrics.{m.name}.{key}' must be >= {s.least}, got {v}")
        if s.unit is not None and not 0 < v < 1:
            raise UserError(f"{file}: key 'metrics.{m.name}.{key}' must lie in (0, 1) ({s.unit}), got {v}")


def canonical_sha256(content: dict[str, Any]) -> str:
    """sha256 of the canonical JSON (sorted keys, no whitespace) of a parsed protocol."""
    blob = json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def parse_protocol(raw: dict[str, Any], file: str) -> Protocol:
    """Validate a parsed TOML table; every error names the file and key."""
    for key in raw:
        if key not in _TOP:
            raise UserError(f"{file}: unknown key '{key}' (known: {', '.join(sorted(_TOP))})")
    for key in ("id", "version", "title", "description", "reference"):
        if key not in raw:
            raise UserError(f"{file}: missing key '{key}'")
    for key, typ in (("id", str), ("title", str), ("description", str), ("reference", str)):
        if not isinstance(raw[key], typ):
            raise UserError(f"{file}: key '{key}' must be str, got {raw[key]!r}")
    if (not isinstance(raw["version"], int) or isinstance(raw["version"], bool)
            or not 1 <= raw["version"] <= MAX_VERSION):
        raise UserError(f"{file}: key 'version' must be an int >= 1 (at most {MAX_VERSION}), "
                        f"got {short(raw['version'])}")
    for section in ("data", "capture", "metrics", "statistics"):
        if section not in raw:
            raise UserError(f"{file}: missing table [{section}]")
    sections = {name: _build(cls, raw[name], name, file) for name, cls in _SECTIONS.items()}
    if not isinstance(raw["metrics"], dict) or not raw["metrics"]:
        raise UserError(f"{file}: [metrics] must be a non-empty table of [metrics.<name>] tables")
    metrics = [_metric_spec(name, table, file) for name, table in raw["metrics"].items()]
    for m in metrics:
        if METRICS[m.name].depth and not (m.depth_tolerance is not None and 0 < m.depth_tolerance < 1):
            raise UserError(f"{file}: key 'metrics.{m.name}.depth_tolerance' must lie in (0, 1) (a relative depth "
                            f"tolerance), got {m.depth_tolerance!r}")
        if METRICS[m.name].features == CLIP_FEATURES and (m.clip_length or 0) < 2:
            raise UserError(f"{file}: key 'metrics.{m.name}.clip_length' must be >= 2")
        if METRICS[m.name].extractor and not m.extractor:
            raise UserError(f"{file}: missing key 'metrics.{m.name}.extractor'")
    stats = sections["statistics"]
    if not 0 < stats.interval < 1:
        raise UserError(f"{file}: key 'statistics.interval' must lie in (0, 1), got {stats.interval}")
    for key in ("bootstrap_resamples", "emcee_walkers", "emcee_steps"):
        if getattr(stats, key) < 1:
            raise UserError(f"{file}: key 'statistics.{key}' must be >= 1, got {getattr(stats, key)}")
    if stats.cluster not in CLUSTER_UNITS:
        raise UserError(f"{file}: key 'statistics.cluster' must be one of {', '.join(map(repr, CLUSTER_UNITS))}, "
                        f"got {stats.cluster!r}")
    if not 0 <= stats.emcee_burn < stats.emcee_steps:
        raise UserError(f"{file}: key 'statistics.emcee_burn' must lie in [0, emcee_steps), got {stats.emcee_burn}")
    data = sections["data"]
    own = f"{raw['id']}@{raw['version']}"
    if data.dataset_protocol and (not re.match(r"^[a-z0-9][a-z0-9._-]*@[1-9]\d*$", data.dataset_protocol)
                                  or data.dataset_protocol == own):
        raise UserError(f"{file}: key 'data.dataset_protocol' must name another protocol '<id>@<N>' (whose data "
                        f"this one scores), got {data.dataset_protocol!r}")
    if data.width < 1 or data.height < 1:
        raise UserError(f"{file}: keys 'data.width' and 'data.height' must be positive")
    if not 0 < data.fov_deg < 180:
        raise UserError(f"{file}: key 'data.fov_deg' must lie in (0, 180), got {data.fov_deg}")
    capture = sections["capture"]
    if not capture.yaws_deg:
        raise UserError(f"{file}: key 'capture.yaws_deg' must list at least one yaw")
    if not capture.ground_step_m > 0:
        raise UserError(f"{file}: key 'capture.ground_step_m' must be > 0, got {capture.ground_step_m}")
    for m in metrics:
        _check_ranges(m, file)
    proto = Protocol(
        id=raw["id"], version=raw["version"], title=raw["title"], description=raw["description"],
        reference=raw["reference"], data=data, capture=sections["capture"],
        metrics=tuple(metrics), statistics=stats,
    )
    return dataclasses.replace(proto, sha256=canonical_sha256(proto.to_dict()), path=file)


# --------------------------------------------------------------------------- registry of files


def available(root: Path | None = None) -> dict[str, list[int]]:
    """{protocol id: sorted versions} found under the protocols folder."""
    root = root or protocols_dir()
    out: dict[str, list[int]] = {}
    if root.is_dir():
        for sub in sorted(p for p in root.iterdir() if p.is_dir()):
            versions = sorted(int(m.group(1)) for f in sub.iterdir() if (m := _VERSION_FILE.match(f.name)))
            if versions:
                out[sub.name] = versions
    return out


def load_protocol_file(path: str | Path) -> Protocol:
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        raise UserError(f"{path}: protocol file not found")
    raw = read_toml(path, "a protocol TOML file")  # never blocks on a pipe; one line
    proto = parse_protocol(raw, str(path))
    m = _VERSION_FILE.match(path.name)
    if m and (int(m.group(1)) != proto.version or path.parent.name != proto.id):
        raise UserError(
            f"{path}: file says id={proto.id!r} version={proto.version}, "
            f"expected id={path.parent.name!r} version={int(m.group(1))} from its path"
        )
    val = path.parent / VAL_FILE
    if m and (val.exists() or val.is_symlink()):
        proto = dataclasses.replace(proto, val=load_val(val, proto))
    return proto


def load_val(path: Path, proto: Protocol) -> ValSpec:
    """The validation split `path` declares for `proto`'s family, checked against its towns: one
    line naming the file and key for anything else."""
    raw = read_toml(path, "a validation split TOML file")
    spec = _build(ValSpec, raw, "val", str(path))
    if not spec.towns:
        raise UserError(f"{path}: key 'towns' must name at least one town")
    if spec.source not in VAL_SOURCES:
        raise UserError(f"{path}: key 'source' is {spec.source!r}, expected one of {', '.join(VAL_SOURCES)}")
    clash = sorted(set(spec.towns) & set(proto.data.test))
    if clash:
        raise UserError(f"{path}: key 'towns' names the test town(s) {', '.join(clash)} of {proto.ref}; "
                        "a validation split is apart from test")
    inside = set(spec.towns) <= set(proto.data.train)
    if spec.source == "train" and not inside:
        raise UserError(f"{path}: key 'towns' must be train towns of {proto.ref} ({', '.join(proto.data.train)}) "
                        "with source = \"train\"")
    if spec.source == "own" and set(spec.towns) & set(proto.data.train):
        raise UserError(f"{path}: key 'towns' names train towns of {proto.ref} with source = \"own\" "
                        "(towns of their own); use source = \"train\" for a part of the train towns")
    return spec


def load_protocol(ref: str, root: Path | None = None) -> Protocol:
    """`load_protocol("carla-town04@1")`; without `@N`, the latest version."""
    m = _REF.match(ref.strip())
    if not m:
        raise UserError(f"protocol reference {short(ref)}: expected 'ID' or 'ID@N' (e.g. 'synthtown@1')")
    pid, version = m.group(1), m.group(2)
    if version is not None and len(version.lstrip("0") or "0") > len(str(MAX_VERSION)):
        raise UserError(f"protocol reference {short(ref)}: version of {len(version)} digits; expected at "
                        f"most {MAX_VERSION}")
    known = available(root)
    if pid not in known:
        raise UserError(f"unknown protocol {pid!r}; known: {', '.join(known) or '(none)'}")
    v = int(version) if version else known[pid][-1]
    if v not in known[pid]:
        raise UserError(f"protocol {pid!r} has no version {v}; versions: {', '.join(map(str, known[pid]))}")
    return load_protocol_file((root or protocols_dir()) / pid / f"v{v}.toml")


def current_for_data(data_ref: str, root: Path | None = None) -> str:
    """The protocol a new submission for data made for `data_ref` is scored with: the latest
    version of the same id that scores that data (`data.dataset_protocol`), else `data_ref`.

    synthtown@2's data (synthtown-v2-small) -> "synthtown@3" (same frames, more metrics);
    synthtown@1's -> "synthtown@1". An unknown id is returned as it is (the caller reports it)."""
    pid = data_ref.partition("@")[0]
    best = data_ref
    for v in available(root).get(pid, []):
        ref = f"{pid}@{v}"
        try:
            p = load_protocol(ref, root)
        except UserError:
            continue
        if p.data.dataset_protocol == data_ref:
            best = ref
    return best


def list_protocols(root: Path | None = None) -> list[Protocol]:
    return [load_protocol(f"{pid}@{v}", root) for pid, vs in available(root).items() for v in vs]
