"""The Python API: what the command line computes, as functions that return plain values
(the dicts `--json` prints, floats). `import skyeyes_bench as sb` gives every name below.

```python
import skyeyes_bench as sb

res = sb.evaluate("sub/")                          # == `skyeyes-bench evaluate sub/ --json`
res["metrics"]["fid"]["value"]                     # a float (intervals, replicates beside it)
cmp = sb.compare("a.results.json", "b.results.json")   # == `skyeyes-bench compare A B --json`
fid = sb.compute_fid("frames_a/", "frames_b/")     # two folders of PNG frames -> a float
```

The folder metrics (`compute_fid`, `compute_kid`, `compute_fvd`, `compute_kvd`, `compute_lpips`)
score any two folders of 8-bit PNG frames with this project's extractors (TF Inception for
FID/KID, I3D for FVD/KVD, LPIPS v0.1) and a protocol's settings (KID subsets, clip length, the
LPIPS backbone; default: the latest `synthtown`), computed by the same functions `evaluate` uses
(`metricspec` names them) on features from the same cache. Frames are the `*.png` files under a
folder, at any depth, in path order; for FVD/KVD each folder that holds frames is one video, its
frames in name order, cut into clips of the protocol's `clip_length` frames every `clip_stride`;
LPIPS pairs the frames of the two folders by relative path (the same names in both).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

#: The protocol whose metric settings the folder metrics use when none is named (its latest version).
DEFAULT_PROTOCOL = "synthtown"


# --------------------------------------------------------------------------- submissions and results


def evaluate(submission, data=None, *, out=None, protocol: str | None = None, split: str | None = None,
             device: str | None = "cpu", shard=None, force: bool = False, allow_missing: bool = False,
             progress: bool = False) -> dict[str, Any]:
    """Score a submission folder, as `skyeyes-bench evaluate SUB --json` does.

    Args:
        submission: folder with `submission.json` and the frames (docs/evaluate.md).
        data: the dataset folder (default: found from `submission.json`, as the command does).
        out: also write the results file here (and its `.features.npz` sidecar); None: write nothing.
        protocol: score with this protocol (`id@N`) instead of the one `submission.json` names.
        split: the split the submission must hold ("test" or "val"; None: its own).
        device: where the extractors run: "cpu" (the reference), "cuda", "cuda:N", "auto".
        shard: (I, N) or "I/N": only sequences k with k % N == I (a partial result for `merge`).
        force: replace an existing `out`.
        allow_missing: False (as the command without `--allow-missing`): a metric the protocol
            requires that cannot be computed here raises `MissingMetrics` (a UserError); True: it is
            reported `"unavailable"` with the reason and the fix.
        progress: progress bars on stderr (drawn only on a terminal).

    Returns:
        The results document (format `skyeyes-bench/results@1`, docs/evaluate.md): per metric
        `results["metrics"][name]["value"]`, its interval and replicates, per-sequence and
        per-frame values, hashes of what was scored.

    Raises:
        skyeyes_bench.UserError: bad input (one line saying what and where); its subclass
            `ValidationError` lists every problem of the submission.
    """
    from .scoring.run import evaluate as score

    return score(submission, data=data, out=out, shard=shard, force=force, progress=progress,
                 protocol=protocol, device=device, split=split, allow_missing=allow_missing)


def compare(a, b, *, out=None, progress: bool = False) -> dict[str, Any]:
    """Paired comparison of two results files, as `skyeyes-bench compare A B --json` does.

    Args:
        a, b: results files written by `evaluate` (or `merge`) on the same protocol and frames.
        out: also write the comparison JSON here (replaced if it exists; never one of the inputs).
        progress: a progress bar on stderr while it runs (only on a terminal, after 2 s).

    Returns:
        Per metric `cmp["metrics"][name]`: "a", "b", "advantage" (> 0: A better), its
        "bootstrap_interval", "p_a_better_bootstrap" and the Student-t summary "bayes"; see
        docs/evaluate.md. `cmp.get("warnings")`: lines worth saying (a damaged features sidecar).
        When both files come from `reproduce --seeds N`, `cmp["seeds"]` names their seeds and
        `cmp["metrics"][name]["seeds"]` holds a t test on the seeds' values ("test": "paired" by seed
        when both ran the same seeds, else "welch"; "advantage", "se", "df", "interval", "verdict"); when only one does, `cmp["seeds"]["note"]` says so.

    Raises:
        skyeyes_bench.UserError: a file that is not a results file, or results that cannot be compared.
    """
    from . import outputfiles
    from .comparison import compare_results
    from .results import read_results

    if out is not None:  # before any work: compare's output is replaced freely, but never an input
        outputfiles.check_output(out, force=True, inputs=[a, b], inputs_are="the results being compared")
    doc_a, _ = read_results(a, features=False)
    doc_b, _ = read_results(b, features=False)
    warnings: list[str] = []
    res = compare_results(doc_a, doc_b, names=(str(a), str(b)), progress=progress,
                          sidecars=_sidecars([(Path(a), doc_a), (Path(b), doc_b)], warnings))
    if warnings:
        res["warnings"] = [*res.get("warnings", []), *warnings]
    if out is not None:
        outputfiles.write_json(out, res)
    return res


def _sidecars(files: list[tuple[Path, dict]], warnings: list[str]) -> Callable[[], tuple]:
    """For `compare_results`: a function reading the features sidecars of the results files
    `files` ((path, its document) for A and B): their features, or (None, None) when a sidecar is
    absent (results filed without them, as on the leaderboard: the stored replicates serve, and a
    metric that would need the features is skipped with that note; nothing to warn about) or
    cannot be used (then its one line goes to `warnings`)."""
    from .errors import UserError
    from .results import features_path, read_results

    def load() -> tuple:
        for path, doc in files:
            info = doc.get("features")
            name = info.get("file", features_path(path).name) if isinstance(info, dict) else features_path(path).name
            plain = isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name
            if plain and not (path.parent / name).exists():
                return None, None
        try:  # a sidecar that is there is checked in full (sha256, shapes); a bad one is said
            return tuple(read_results(path, features=True)[1] for path, _ in files)
        except UserError as e:
            warnings.append(str(e))
            return None, None

    return load


# --------------------------------------------------------------------------- folders of frames


def compute_fid(dir1, dir2, *, protocol: str = DEFAULT_PROTOCOL, device: str | None = "cpu",
                progress: bool = False) -> float:
    """FID of the PNG frames under `dir1` against those under `dir2` (TF Inception pool3 features,
    float64 statistics; clean-fid's `compute_fid(dir1, dir2)` with this project's extractor).
    Frames of any count; 0 for a folder against itself."""
    return folder_metrics(dir1, dir2, ["fid"], protocol=protocol, device=device, progress=progress)["fid"]


def compute_kid(dir1, dir2, *, protocol: str = DEFAULT_PROTOCOL, device: str | None = "cpu",
                progress: bool = False) -> float:
    """KID (unbiased polynomial MMD^2 over the protocol's random subsets) of the frames under
    `dir1` against those under `dir2`."""
    return folder_metrics(dir1, dir2, ["kid"], protocol=protocol, device=device, progress=progress)["kid"]


def compute_fvd(dir1, dir2, *, protocol: str = DEFAULT_PROTOCOL, device: str | None = "cpu",
                progress: bool = False) -> float:
    """FVD (I3D features of clips) of the videos under `dir1` against those under `dir2`: each
    folder holding frames is a video, cut into the protocol's clips (16 frames every 16)."""
    return folder_metrics(dir1, dir2, ["fvd"], protocol=protocol, device=device, progress=progress)["fvd"]


def compute_kvd(dir1, dir2, *, protocol: str = DEFAULT_PROTOCOL, device: str | None = "cpu",
                progress: bool = False) -> float:
    """KVD (polynomial MMD^2 of the I3D clip features) of the videos under `dir1` and `dir2`."""
    return folder_metrics(dir1, dir2, ["kvd"], protocol=protocol, device=device, progress=progress)["kvd"]


def compute_lpips(dir1, dir2, *, protocol: str = DEFAULT_PROTOCOL, device: str | None = "cpu",
                  progress: bool = False) -> float:
    """Mean LPIPS (the protocol's backbone, v0.1) over the frames of `dir1` paired by relative
    path with those of `dir2` (the same names in both; each pair the same size)."""
    return folder_metrics(dir1, dir2, ["lpips"], protocol=protocol, device=device, progress=progress)["lpips"]


def folder_metrics(dir1, dir2, metrics=("fid", "kid", "fvd", "kvd", "lpips"), *, protocol: str = DEFAULT_PROTOCOL,
                   device: str | None = "cpu", progress: bool = False) -> dict[str, float]:
    """Several folder metrics at once ({name: value}; features extracted once per extractor).

    Args:
        dir1, dir2: folders of 8-bit PNG frames (`dir1`: e.g. generated, `dir2`: reference).
        metrics: names among fid, kid, fvd, kvd, lpips (and fid_inf, fvd_inf) that `protocol` defines.
        protocol: whose settings to use, `id` (its latest version) or `id@N` to pin them.
        device: where the extractors run ("cpu", the reference; "cuda", "auto").
        progress: progress bars on stderr (only on a terminal).

    Raises:
        skyeyes_bench.UserError: a folder without frames, a metric the protocol does not define,
            unpaired frames (LPIPS), too few frames or clips; `MetricUnavailable` (a UserError)
            for missing weights, with the command that fetches them.
    """
    import numpy as np

    from .devices import resolve_device
    from .errors import UserError
    from .metrics.cache import extract_clip_features, extract_image_features
    from .metrics.extractors import on_device
    from .metricspec import CLIP_FEATURES, metric_def
    from .protocol import load_protocol
    from .registry import load_entry_point
    from .scoring.features import clips as cut

    proto = load_protocol(protocol)
    dev = resolve_device(device)
    frames = [_frames(d) for d in (dir1, dir2)]  # [(root, [relative paths])] * 2
    out: dict[str, float] = {}
    feats: dict[tuple, tuple] = {}  # (extractor, clip settings) -> (features 1, features 2)
    with on_device(dev):
        for name in metrics:
            spec, m = metric_def(name), proto.metric(name)
            if m is None:
                raise UserError(f"metric {name!r}: protocol {proto.ref} does not define it (it defines "
                                f"{', '.join(x.name for x in proto.metrics)})")
            if spec.kind == "frame" and spec.per_frame and not spec.per_sequence:
                out[name] = _paired_mean(frames, m, load_entry_point(spec.per_frame))
                continue
            if spec.kind != "set":
                raise UserError(f"metric {name!r} needs depth and poses (a dataset), not folders of frames; "
                                "score a submission with `evaluate`")
            clip = spec.features == CLIP_FEATURES
            key = (m.extractor, m.clip_length, m.clip_stride) if clip else (m.extractor,)
            if key not in feats:
                got = []
                for root, rel in frames:
                    if clip:
                        clips = [[root / r for r in seq[c.start:c.stop]] for seq in _videos(rel)
                                 for c in cut(len(seq), m.clip_length, m.clip_stride or m.clip_length)]
                        got.append(extract_clip_features(m.extractor, clips, progress=progress, device=dev)
                                   if clips else np.zeros((0, 1)))
                    else:
                        got.append(extract_image_features(m.extractor, [root / r for r in rel], progress=progress,
                                                          device=dev))
                feats[key] = tuple(got)
            xs, xg = feats[key]
            if min(len(xs), len(xg)) < spec.min_rows:
                what = f"clips of {m.clip_length} frames" if clip else "frames"
                raise UserError(f"{name}: {len(xs)} and {len(xg)} {what} in {dir1} and {dir2}; need at least "
                                f"{spec.min_rows} in each")
            out[name] = float(load_entry_point(spec.estimator)(xs, xg, m, proto.statistics.seed))
    return out


def _frames(folder) -> tuple[Path, list[Path]]:
    """(folder, the relative paths of the *.png files under it, sorted); UserError if there are none."""
    from .errors import UserError

    root = Path(folder)
    if not root.is_dir():
        raise UserError(f"{root}: not a folder (expected a folder of PNG frames)")
    rel = sorted(p.relative_to(root) for p in root.rglob("*") if p.suffix.lower() == ".png" and p.is_file())
    if not rel:
        raise UserError(f"{root}: no PNG frames in it (expected *.png files, in it or in folders under it)")
    return root, rel


def _videos(rel: list[Path]) -> list[list[Path]]:
    """Frames grouped by the folder that holds them (one video each), each in name order."""
    by: dict[Path, list[Path]] = {}
    for r in rel:
        by.setdefault(r.parent, []).append(r)
    return [sorted(v) for _, v in sorted(by.items())]


def _paired_mean(frames, spec, per_frame, batch: int = 16) -> float:
    """Mean of the per-frame metric `per_frame(preds [B, H, W, 3], gts [B, H, W, 3], spec) -> [B]`
    over the frames of two folders paired by relative path."""
    import numpy as np

    from .errors import UserError
    from .imagefiles import read_image

    (r1, rel1), (r2, rel2) = frames
    for (ra, a), (rb, b) in (((r1, rel1), (r2, rel2)), ((r2, rel2), (r1, rel1))):
        gone = sorted(set(a) - set(b))
        if gone:
            more = f" (and {len(gone) - 1} more)" if len(gone) > 1 else ""
            raise UserError(f"{rb}: no frame {gone[0].as_posix()} to pair with {ra / gone[0]}{more}; a per-frame "
                            "metric needs the same frame names in both folders")
    values = []
    for s in range(0, len(rel1), batch):
        part = rel1[s:s + batch]
        preds = [read_image(r1 / r) for r in part]
        gts = [read_image(r2 / r) for r in part]
        for r, p, g in zip(part, preds, gts):
            if p.shape != g.shape:
                raise UserError(f"{r1 / r}: {p.shape[1]}x{p.shape[0]} pixels, but {r2 / r} is "
                                f"{g.shape[1]}x{g.shape[0]}; paired frames must be the same size")
        by_shape: dict[tuple, list[int]] = {}  # frames of different sizes go through separately
        for j, p in enumerate(preds):
            by_shape.setdefault(p.shape, []).append(j)
        for group in by_shape.values():
            values.extend(per_frame(np.stack([preds[j] for j in group]), np.stack([gts[j] for j in group]), spec))
    return float(np.mean(np.asarray(values, np.float64)))
