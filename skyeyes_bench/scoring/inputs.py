"""The inputs of a scoring run, and the checks made before any scoring: the submission, its
protocol and dataset (`open_inputs`), the output (`check_out`), the extractors
(`check_extractors`), the metrics that cannot be computed here (`missing_metrics`,
`MissingMetrics`), `--shard` and `--device`."""

from __future__ import annotations

from pathlib import Path

from .. import outputfiles, paths
from ..errors import UserError
from ..metricspec import metric_def, sequence_metrics
from ..results import FEATURES_OUTPUT, RESULTS_OUTPUT, features_path
from ..submission import read_submission


def builtin_protocol_ids() -> set[str]:
    """Ids of the protocols shipped with skyeyes-bench (official: no test-only extractors)."""
    from ..protocol import available

    return set(available(paths.builtin_protocols_dir()))


def parse_shard(text: str | tuple | None) -> tuple[int, int] | None:
    """'I/N' -> (I, N) with 0 <= I < N."""
    if text is None or isinstance(text, tuple):
        return text
    try:
        i, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise UserError(f"--shard {text!r}: expected I/N, e.g. 0/4") from None
    if not (n >= 1 and 0 <= i < n):
        raise UserError(f"--shard {text!r}: expected 0 <= I < N")
    return i, n


def scoring_device(device):
    """`--device` resolved (`devices.resolve_device`) to a device that computes numbers."""
    from ..devices import resolve_device

    dev = resolve_device(device)
    if dev.type == "meta":
        raise UserError(f"--device {device}: the meta device holds no data, so it cannot compute features "
                        "(expected auto, cpu, cuda or cuda:N)")
    return dev


def resolve_data(manifest: dict, protocol, data) -> Path:
    """The dataset folder: `data` if given, else `<cache>/data/<dataset name>`, else (for a test
    submission) the protocol's default location; the error names the command that makes it."""
    if data is not None:
        return Path(data)
    name = manifest["dataset"]["name"]
    val = manifest["dataset"].get("split", "test") == "val"
    candidates = [paths.data_dir() / name]
    loc = protocol.data.default_location
    if loc.startswith("cache:") and not val:
        candidates.append(paths.data_dir() / loc[len("cache:"):])
    for c in candidates:
        if (c / "dataset.json").is_file():
            return c
    if protocol.data.source == "synthtown":
        preset = name[len("synthtown-"):] if name.startswith("synthtown-") else "small"
        how = f"make it with `skyeyes-bench data synthtown --preset {preset}{' --split val' if val else ''}`"
    else:
        how = f"import it (`skyeyes-bench data --help`) and pass --data DIR"
    raise UserError(f"dataset {name!r} for {protocol.ref} not found (looked in "
                    f"{', '.join(str(c) for c in candidates)}); {how}")


def open_inputs(sub: Path, data=None, protocol: str | None = None, split: str | None = None):
    """(submission.json, the protocol that scores it, the dataset) of the submission folder `sub`:
    `protocol` (`id@N`) or the one submission.json names; the dataset `data` or `resolve_data`'s,
    seen as the split the submission holds scores it (`splits.scored_view`: "test", or "val").
    `split`: the split the caller expects (None: the submission's own).
    Raises UserError / ValidationError for a manifest, protocol or dataset that cannot be used."""
    from ..data.layout import open_dataset
    from ..protocol import load_protocol
    from ..splits import check_split, scored_view

    manifest = read_submission(sub)
    held = manifest["dataset"].get("split", "test")
    if split is not None and check_split(split) != held:
        raise UserError(f"{sub}/submission.json: field 'dataset.split' is {held!r}, --split asks for {split!r}")
    if protocol is not None:
        proto = load_protocol(protocol)
    else:
        try:
            proto = load_protocol(manifest["protocol"])
        except UserError as e:  # an unknown id or version: say which file names it
            raise UserError(f"{sub / 'submission.json'}: field 'protocol': {e}") from None
    return manifest, proto, scored_view(open_dataset(resolve_data(manifest, proto, data)), held, proto)


def check_out(out: Path, force: bool, inputs: list[Path]) -> None:
    """`out` and its features sidecar may be written (`outputfiles.check_output`), outside `inputs`."""
    if not out.name:  # '.', '/': no file name to put the sidecar beside
        raise UserError(f"{out}: is a folder; expected the path of an output file")
    outputfiles.check_output(out, force=force, sidecars=[features_path(out)], outside=inputs, kind=RESULTS_OUTPUT,
                             sidecar_kind=FEATURES_OUTPUT)


def check_extractors(protocol) -> None:
    """A built-in protocol names official extractors only, and each metric's `resize` is the one its
    extractor implements; else UserError."""
    from ..metrics.extractors import EXTRACTORS, assert_official, get_extractor

    if protocol.id in builtin_protocol_ids():
        for m in protocol.metrics:
            if m.extractor:
                assert_official(m.extractor, f"protocol {protocol.ref} metric {m.name}")
    # A protocol's resize mode must be the one its extractor implements: preprocessing is part
    # of the metric's definition, so a mismatch would silently score something else.
    for m in protocol.metrics:
        if m.extractor and m.resize and m.extractor in EXTRACTORS:
            have = get_extractor(m.extractor).resize
            if have is not None and have != m.resize:
                raise UserError(f"{protocol.path}: key 'metrics.{m.name}.resize' is {m.resize!r}, but extractor "
                                f"{m.extractor!r} implements {have!r}")


def missing_metrics(protocol, ds, scenes: list[str]) -> dict[str, dict]:
    """The metrics of `protocol` known before any scoring not to be computable on the `scenes` of
    `ds`: an extractor whose weight files are missing or wrong, a depth layer the dataset lacks.
    {name: {"reason", "fix"}}, the words the results would report them with."""
    out = missing_weights(protocol)
    depth_based = sequence_metrics()
    depth = [m.name for m in protocol.metrics if m.name in depth_based and m.name not in out]
    out.update(missing_depth(ds, scenes, depth))
    return out


def missing_weights(protocol) -> dict[str, dict]:
    """The metrics of `protocol` whose extractor's weight files are missing or wrong here:
    {name: {"reason", "fix"}}."""
    from ..metrics import MetricUnavailable
    from ..metrics.extractors import get_extractor

    out: dict[str, dict] = {}
    for m in protocol.metrics:
        if m.extractor:
            try:
                get_extractor(m.extractor).require()  # the weights' sha256, memoised: no network is loaded
            except MetricUnavailable as e:
                out[m.name] = {"reason": e.reason, "fix": e.fix}
    return out


def missing_depth(ds, scenes: list[str], names: list[str]) -> dict[str, dict]:
    """{name: {"reason", "fix"}} for each depth-based metric of `names` whose depth layers some of
    `scenes` lack."""
    out: dict[str, dict] = {}
    for name in names:
        missing = [f"{s}/{v}_depth/" for s in scenes for v in metric_def(name).depth
                   if not ds.scenes[s].layers()[f"{v}_depth"]]
        if missing:
            out[name] = {
                "reason": f"the dataset has no depth layer {missing[0]}" + (
                    f" (and {len(missing) - 1} more)" if len(missing) > 1 else "") + f": {name} needs it",
                "fix": "score a dataset with ground and aerial depth (SynthTown writes it; importers write it when "
                       "the capture has depth)"}
    return out


class MissingMetrics(UserError):
    """Metrics the protocol asks for that cannot be computed here, and `allow_missing` is off.

    Attributes:
        missing: {metric name: {"reason", "fix"}}, as the results would report them.
    """

    def __init__(self, ref: str, missing: dict[str, dict]):
        self.missing = dict(missing)
        names = list(self.missing)
        first = self.missing[names[0]]
        why = first.get("reason") or "unavailable"
        fix = f"; fix: {first['fix']}" if first.get("fix") else ""
        super().__init__(f"protocol {ref} requires {', '.join(names)}, which cannot be computed here "
                         f"({names[0]}: {why}{fix}); pass --allow-missing (allow_missing=True in Python) to "
                         f"score the other metrics and report {'these' if len(names) > 1 else 'it'} unavailable")
