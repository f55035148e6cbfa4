"""Leaderboard inputs -> tables: measured rows from `results/*.json`, reported rows from
`reported/*.toml`. No rendering here (`render`, `plots`), no marks (`marks`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..metricspec import METRICS, sample_count_warning
from .kinds import row_components, row_kind

#: Column order, headings and printed decimals: the metric table's (`metricspec`).
METRIC_ORDER = tuple(METRICS)
LABEL = {name: m.label for name, m in METRICS.items()}
DIGITS = {name: m.decimals for name, m in METRICS.items()}
#: Key of the filed results JSON where `leaderboard add` records what it added.
ADD_KEY = "leaderboard"
#: Default reason shown for a metric whose interval is null.
NO_INTERVAL = "too few scenes"


@dataclass
class Row:
    method: str
    version: str
    values: dict[str, float | None]  # metric -> value (None: unavailable)
    intervals: dict[str, tuple[float, float]] = field(default_factory=dict)
    no_interval: dict[str, str] = field(default_factory=dict)  # metric -> why its interval is null
    replicates: dict[str, list] = field(default_factory=dict)  # metric -> R bootstrap replicates (None: undefined)
    centres: dict[str, float] = field(default_factory=dict)  # metric -> its interval's centre (FD∞), where recorded
    seeds: dict[str, tuple[float, float | None, int]] = field(default_factory=dict)  # metric -> (mean, sd, n seeds)
    statistics: dict = field(default_factory=dict)  # the results' "statistics" (resamples, level, seed)
    sequences: dict[str, dict] = field(default_factory=dict)  # measured: per-sequence values
    run_s: float | None = None  # fit + render seconds
    fit_s: float | None = None
    render_s: float | None = None
    peak_mb: float | None = None
    hardware: str = ""
    hardware_added: bool = False  # recorded by `leaderboard add` on the filing machine, not by the run
    source: str = ""  # input file name
    reference: str = ""
    budget: str = ""  # a diffusion method's training budget, from its config ('' for the others)
    kind: str = ""  # measured: a key of `kinds.KINDS` (what the row is to the paper)
    components: list[str] = field(default_factory=list)  # measured: the parts its method runs (`kinds`)

    @property
    def n_seeds(self) -> int:
        """How many training seeds the row ran (0: one run, no `seeds` block)."""
        return max((n for _, _, n in self.seeds.values()), default=0)

    @property
    def name(self) -> str:
        """The filed name: `results/<name>.json` (also its frames folder)."""
        return self.source[: -len(".json")] if self.source.endswith(".json") else self.source


@dataclass
class Table:
    key: str  # "synthtown@1" (+ "#2" for a second extractor set)
    title: str
    protocol: str
    metrics: list[str]
    rows: list[Row]
    reported: bool
    note: str = ""
    citation: str = ""
    decimals: int | None = None  # reported tables: the precision the paper prints
    gt_sha: str = ""
    frames_key: str = ""  # measured: folder of frames/ holding this protocol + dataset's strip frames
    best: dict[str, list[int]] = field(default_factory=dict)
    not_credible: set[str] = field(default_factory=set)
    rules: dict[str, str] = field(default_factory=dict)  # metric -> the rule that decided its mark
    counts: dict = field(default_factory=dict)  # measured: a row's "metrics" (set metrics' sample counts `n`)

    @property
    def file_key(self) -> str:
        """`key` as a file name (no '#')."""
        return self.key.replace("#", "-")


def frames_key(doc: dict) -> str:
    """Folder under `frames/` for a results file: protocol id@N and the ground-truth digest, so
    every method scored on the same dataset and protocol shares one set of strip frames."""
    return f"{doc['protocol']['ref']}_{doc['sha256']['ground_truth'][:12]}"


def format_hardware(hw) -> str:
    """`{"cpu", "cores", "gpu"}` -> "CPU model (N cores), GPU" ('' when nothing is recorded)."""
    if not isinstance(hw, dict):
        return ""
    parts = []
    if hw.get("cpu"):
        parts.append(str(hw["cpu"]) + (f" ({hw['cores']} cores)" if hw.get("cores") else ""))
    if hw.get("gpu"):
        parts.append(str(hw["gpu"]))
    return ", ".join(parts)


#: How a diffusion config's `mixed_precision` trains ("auto": bf16 on CUDA, none on a CPU).
_PRECISION = {"no": "fp32", "bf16": "bf16", "fp16": "fp16", "auto": "bf16 on CUDA, else fp32"}


def training_budget(config) -> str:
    """A diffusion method's training budget in words, from the config fields the reference
    diffusion family records (`base_steps`, `acm_*`, `train_crop`, `mixed_precision`, `vcm*`);
    '' for a config without ACM steps (every other method)."""
    if not isinstance(config, dict) or _number(config.get("acm_steps")) is None:
        return ""
    c = config
    acm = f"ACM {c['acm_steps']} steps"
    if c.get("acm_anneal"):
        acm += f" (rate decaying over the last {c['acm_anneal']})"
    if c.get("acm_batch"):
        acm += f" at batch {c['acm_batch']}"
    if c.get("train_crop"):
        acm += f" on {c['train_crop']}-px crops"
    parts = [f"base UNet {c['base_steps']} steps"] if c.get("base_steps") else []
    parts.append(acm)
    if c.get("mixed_precision") in _PRECISION:
        parts.append(_PRECISION[c["mixed_precision"]])
    vcm = f"VCM {c.get('vcm_steps')} steps at batch {c.get('vcm_batch')}"
    if c.get("vcm_snr_gamma") == 0:  # its own loss weights (older configs lack the field: the ACM's)
        vcm += ", uniform loss weights"
    parts.append(vcm if c.get("vcm") else "no VCM")
    return ", ".join(parts)


def _number(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def measured_row(doc: dict, name: str, metrics: list[str]) -> Row:
    """One table row from a results document (`name`: its file name)."""
    s = doc["submission"]
    t = s.get("timings") or {}
    fit, ren = _number(t.get("fit_s")), _number(t.get("render_s"))
    added = doc.get(ADD_KEY) or {}
    hw = s.get("hardware")
    hw_added = not format_hardware(hw) and bool(format_hardware(added.get("hardware")))
    method, config = str(s.get("method")), s.get("config")
    row = Row(method=method, version=str(s.get("method_version") or ""), values={},
              sequences=doc["sequences"], statistics=dict(doc.get("statistics") or {}), fit_s=fit, render_s=ren,
              run_s=(fit or 0.0) + (ren or 0.0) if fit is not None or ren is not None else None,
              peak_mb=_number(s.get("peak_memory_mb")), source=name, budget=training_budget(config),
              kind=row_kind(method, config), components=row_components(method, config),
              hardware=format_hardware(added.get("hardware") if hw_added else hw), hardware_added=hw_added)
    for m in metrics:
        md = doc["metrics"].get(m) or {}
        if md.get("status") != "ok":
            row.values[m] = None
            continue
        row.values[m] = md["value"]
        iv = md.get("interval")
        if isinstance(iv, (list, tuple)) and len(iv) == 2 and all(_number(x) is not None for x in iv):
            row.intervals[m] = (float(iv[0]), float(iv[1]))
        else:
            row.no_interval[m] = str(md.get("interval_note") or md.get("interval_reason") or NO_INTERVAL)
        if isinstance(md.get("replicates"), list):
            row.replicates[m] = md["replicates"]
        if _number(md.get("interval_centre")) is not None:
            row.centres[m] = float(md["interval_centre"])
    # a run of several training seeds (`reproduce --seeds N`): the row's values and intervals are
    # its first seed's; the spread over the seeds is shown beside them
    block = doc.get("seeds") or {}
    for m, sm in (block.get("metrics") or {}).items():
        if m in metrics and _number(sm.get("mean")) is not None:
            row.seeds[m] = (float(sm["mean"]), _number(sm.get("sd")), len(block.get("seeds") or []))
    return row


def measured_tables(root: Path) -> list[Table]:
    from ..results import read_results
    from .checks import filed_name, results_fields

    groups: dict[tuple, list[tuple[dict, str]]] = {}
    for p in sorted((root / "results").glob("*.json")):
        # the file name becomes the row's strip folder (frames/<key>/<name>/)
        filed_name(f"{p}: file name", p.name[: -len(".json")], "a results file named <name>.json")
        doc, _ = read_results(p)
        results_fields(doc, p)
        # no weights: '' (not None, which does not sort against a sha256)
        ex = tuple(sorted((k, v.get("weights_sha256") or "") for k, v in doc.get("extractors", {}).items()
                          if v.get("status") == "ok"))
        key = (doc["protocol"]["ref"], doc["protocol"]["sha256"], ex, doc["sha256"]["ground_truth"])
        groups.setdefault(key, []).append((doc, p.name))
    tables = []
    seen: dict[str, int] = {}
    for (ref, sha, ex, gt), docs in sorted(groups.items(), key=lambda kv: kv[0]):
        seen[ref] = seen.get(ref, 0) + 1
        key = ref if seen[ref] == 1 else f"{ref}#{seen[ref]}"
        present = [m for m in METRIC_ORDER if any(m in d["metrics"] for d, _ in docs)]
        metrics = [m for m in present if not METRICS[m].reference]  # ranked columns
        rows = [measured_row(d, name, metrics) for d, name in docs]
        rows.sort(key=lambda r: (r.method.lower(), r.version, r.source))
        exs = ", ".join(f"{i} ({(w or '-')[:12]})" for i, w in ex) or "none"
        d0 = docs[0][0]
        note = (f"protocol sha256 {sha[:12]}…; extractors {exs}; dataset {d0['dataset']['name']} "
                f"({len(d0['dataset']['sequences'])} sequences, {len(d0['frames'])} frames)")
        note += _reference_note([m for m in present if METRICS[m].reference], [d for d, _ in docs])
        # rows of one table share protocol and frames: a guard
        differ = sample_count_warning([(name.removesuffix(".json"), d["metrics"]) for d, name in docs])
        note += f". Warning: {differ}" if differ else ""
        tables.append(Table(key, f"{ref} — measured", ref, metrics, rows, reported=False, note=note, gt_sha=gt,
                            frames_key=frames_key(d0), counts=d0["metrics"]))
    return tables


def protocol_version(ref: str) -> tuple[str, int]:
    """`"synthtown@4"` -> `("synthtown", 4)` (refs are checked `ID@N` when read: `checks.protocol_ref`)."""
    pid, _, version = ref.rpartition("@")
    return pid, int(version)


def current_first(tables: list[Table]) -> tuple[list[Table], list[Table]]:
    """(the tables of each protocol id's highest version, the tables of its older versions): the
    current protocol is what a reader compares against first (synthtown@4 before synthtown@3).
    Each list by protocol id, then newest version first, then key; versions compare as numbers."""
    newest: dict[str, int] = {}
    for t in tables:
        pid, v = protocol_version(t.protocol)
        newest[pid] = max(v, newest.get(pid, v))

    def order(t: Table):
        pid, v = protocol_version(t.protocol)
        return pid, -v, t.key

    current, older = [], []
    for t in sorted(tables, key=order):
        pid, v = protocol_version(t.protocol)
        (current if v == newest[pid] else older).append(t)
    return current, older


def _reference_note(names: list[str], docs: list[dict]) -> str:
    """'; of the ground truth, the same for every row: Unseen share 0.312, Warp floor 0.0123' ('' if none):
    metrics that describe the test data (`metricspec.MetricDef.reference`) are shown once, not ranked."""
    parts = []
    for m in names:
        v = next((d["metrics"][m]["value"] for d in docs if (d["metrics"].get(m) or {}).get("status") == "ok"), None)
        if v is not None:
            parts.append(f"{LABEL[m]} {v:.{DIGITS[m]}f}")
    return f"; of the ground truth, the same for every row: {', '.join(parts)}" if parts else ""


def reported_tables(root: Path) -> list[Table]:
    from .checks import reported_file

    tables = []
    for p in sorted((root / "reported").glob("*.toml")):
        raw = reported_file(p)  # every field checked: page text plain, scores finite numbers
        metrics = list(raw["metrics"])  # the paper's column order
        rows = [Row(method=r["method"], version="", values={m: r.get(m) for m in metrics}, source=p.name,
                    reference=r.get("reference", "")) for r in raw["rows"]]
        tables.append(Table(p.stem, raw["title"], raw["protocol"], metrics, rows, reported=True,
                            note=raw.get("note", ""), citation=raw["citation"], decimals=raw.get("decimals")))
    return tables


def unmeasured_protocols(measured: list[Table], reported: list[Table]) -> list[str]:
    """Protocol ids shipped with skyeyes-bench or printed in a paper that have no measured table
    at any version. Ids, not id@N: a new version of a shipped protocol must not make the committed
    page stale; the shipped folder, not `$SKYEYES_PROTOCOLS`: the page must not depend on the
    environment."""
    from .. import paths
    from ..protocol import available

    ids = set(available(paths.builtin_protocols_dir())) | {t.protocol.split("@")[0] for t in reported}
    return sorted(ids - {t.protocol.split("@")[0] for t in measured})
