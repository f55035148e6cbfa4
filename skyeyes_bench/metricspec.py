"""The one table of metrics: what each metric is, as plain data.

Every module that needs to know about a metric reads it here: `protocol` (which names and
settings a protocol may use), `evaluate` / `results` (how a value is computed), `stats` (which
direction is better, which bootstrap resamples a set metric) and `leaderboard` (column order,
label, decimals). Adding a metric is one entry below (or one `register_metric` call beside its
function) plus the function it names; the lists of frame, set and sequence metrics are read from
the table when asked for, so a metric registered after import is one of them.

Code is named by lazy `"module:attr"` entry points (`registry.load_entry_point`), so importing
this module imports nothing beyond the standard library (no numpy: `skyeyes-bench --help` and
protocol validation stay instant; a test checks it).
"""

from __future__ import annotations

from dataclasses import dataclass

#: What a set metric's features are computed on, one row each (`MetricDef.features`): a frame, or
#: a clip (`clip_length` consecutive frames of one sequence). One idea, spelled three ways in stored
#: formats, which stay as they are (old files read the same, new output keeps its bytes):
#: results.json `metrics.<name>.unit` says "frame" / "clip", and `extractors.<id>.kind` (also
#: printed by `skyeyes-bench weights`) says "image" / "video" for the network that makes them.
#: Code names the idea "clip" and compares through these constants; "video" is only that kind's
#: stored spelling (and part of extractor ids: "random-video-64").
IMAGE_FEATURES = "image"
CLIP_FEATURES = "clip"
#: `Extractor.kind` of the extractors of image and of clip features (their stored spelling).
IMAGE_EXTRACTOR = "image"
CLIP_EXTRACTOR = "video"


@dataclass(frozen=True)
class Setting:
    """A key a protocol may give a metric under [metrics.<name>]: its type and its range."""

    key: str
    type: type  # str, int or float (a TOML integer given for a float is stored as a float)
    least: int | None = None  # the value must be >= least
    unit: str | None = None  # the value must lie in (0, 1); what it is, for the error


#: The settings the metrics below share, in the order a protocol's settings are shown
#: (`protocols show`). A metric with a key of its own declares it in `MetricDef.settings`.
SETTINGS: dict[str, Setting] = {s.key: s for s in (
    Setting("extractor", str),  # registry id of the feature extractor
    Setting("resize", str),  # resize mode before the extractor ("clean-bicubic", ...)
    Setting("aggregate", str),  # how per-frame values become one (psnr: inf handling)
    Setting("window", int, least=1),  # SSIM Gaussian window size
    Setting("sigma", float),
    Setting("k1", float),
    Setting("k2", float),
    Setting("subset_size", int, least=1),  # KID/KVD subsets
    Setting("num_subsets", int, least=1),
    Setting("clip_length", int),  # FVD/KVD clip length in frames (>= 2: `protocol` checks it)
    Setting("clip_stride", int, least=1),  # frames between clip starts within a sequence
    Setting("depth_tolerance", float),  # relative depth tolerance of the visibility / occlusion tests
    Setting("num_sizes", int, least=2),  # FID∞/FVD∞: how many subset sizes the line in 1/N is fitted to
    Setting("min_fraction", float, unit="the smallest subset size as a share of all rows"),  # FID∞/FVD∞
)}


@dataclass(frozen=True)
class MetricDef:
    """What a metric is. (`protocol.MetricSpec` holds the settings one protocol gives it.)"""

    name: str
    kind: str  # "frame": one value per frame | "set": one value over all frames / clips
    higher_is_better: bool
    keys: frozenset[str]  # settings a protocol may give under [metrics.<name>]
    label: str  # column heading
    decimals: int  # digits shown on the leaderboard
    extractor: bool = False  # the protocol must name the extractor (network weights) it uses
    features: str | None = None  # set metrics: IMAGE_FEATURES (a row per frame) or CLIP_FEATURES (a row per clip)
    # kind "frame": f(preds [B, H, W, 3], gts [B, H, W, 3], settings: protocol.MetricSpec) -> [B];
    #   may raise metrics.MetricUnavailable (the metric is then reported unavailable).
    per_frame: str | None = None
    # kind "set": the point estimate f(xs [N, D], xg [N, D], settings, seed: int) -> float ...
    estimator: str | None = None
    # ... and its bootstrap: f(xs [N, D], xg [N, D], seq [N], n_sequences, settings, seed) -> fn(w1, w2) -> float,
    #   the same quantity recomputed under resampling weights (see stats.set_metric_bootstrap).
    bootstrap: str | None = None
    # ... and, for an estimate drawn with random subsets, the centre of its interval: f(xs, xg, settings,
    #   seed) -> float, the estimate with its own subset noise averaged out (None: the estimate itself)
    centre: str | None = None
    # the smallest value the metric can take (Fréchet distances: 0); a bias-corrected interval
    # that reaches below it is clipped there (the true value cannot lie below it)
    lower_bound: float | None = None
    min_rows: int = 2  # set metrics: with fewer rows (frames or clips) the metric is unavailable
    # kind "frame" computed a sequence at a time from the ground truth's depth and poses (the
    # metrics naming one entry point are computed together):
    #   f(seq: estimators.SequenceData, specs: list[protocol.MetricSpec]) -> {name: (values [T], weights [T] | None)}
    per_sequence: str | None = None
    depth: tuple[str, ...] = ()  # the views ("ground", "aerial") whose depth layers it needs; the protocol
    # then gives `depth_tolerance`
    # Pixel-weighted frame metrics: each frame record holds the value on its region (null when the
    # region is empty) and `<name>_n`, the region's pixel count; the summary pools pixels:
    # pool "mean": sum(n v) / sum(n); "mse" (PSNR): -10 log10(sum(n 10^(-v/10)) / sum(n)).
    weighted: bool = False
    pool: str = "mean"
    # a property of the ground truth (the same for every submission on the dataset: the unseen
    # share, the warp floor): reported beside the scores, never ranked or compared
    reference: bool = False
    # settings of its own, keys `SETTINGS` does not hold (each also in `keys`): a new metric's new key
    settings: tuple[Setting, ...] = ()

    def setting(self, key: str) -> Setting:
        """The type and range of `key`, one of `keys`: the metric's own, else the shared one."""
        return next((s for s in self.settings if s.key == key), None) or SETTINGS[key]


_KID_KEYS = frozenset({"extractor", "resize", "subset_size", "num_subsets"})
_CLIP_KEYS = frozenset({"extractor", "resize", "clip_length", "clip_stride"})
_FRECHET = dict(estimator="skyeyes_bench.estimators:frechet",
                bootstrap="skyeyes_bench.stats:FrechetBootstrap.from_features", lower_bound=0.0)
_MMD = dict(estimator="skyeyes_bench.estimators:mmd", bootstrap="skyeyes_bench.stats:MMDBootstrap.from_features")
# FID∞ / FVD∞ (Chong & Forsyth 2020): the Fréchet distance extrapolated to 1 / N = 0 from random subsets of
# `num_sizes` sizes from `min_fraction` N to N, `num_subsets` subsets a size (docs/metrics.md, "FID∞ and FVD∞")
_INF_KEYS = frozenset({"extractor", "resize", "num_sizes", "min_fraction", "num_subsets"})
_FRECHET_INF = dict(estimator="skyeyes_bench.estimators:frechet_inf",
                    bootstrap="skyeyes_bench.frechet_inf:FrechetInfinity.from_features",
                    centre="skyeyes_bench.estimators:frechet_inf_centre", lower_bound=0.0,
                    min_rows=3)  # two subset sizes at least: a line to extrapolate
_SSIM_KEYS = frozenset({"window", "sigma", "k1", "k2"})
_DEPTH = frozenset({"depth_tolerance"})
# Seen / unseen regions of the ground views (docs/metrics.md): masks from the depth test against
# every aerial view of the scene; warp consistency from ground-truth depth and poses.
_REGIONS = dict(per_sequence="skyeyes_bench.estimators:regions", depth=("ground", "aerial"))
_LPIPS_REGIONS = dict(per_sequence="skyeyes_bench.estimators:lpips_regions", depth=("ground", "aerial"),
                      extractor=True)
_WARP = dict(per_sequence="skyeyes_bench.estimators:warp", depth=("ground",), weighted=True)

#: Every metric, in display order (leaderboard columns, results files follow the protocol's order).
METRICS: dict[str, MetricDef] = {m.name: m for m in (
    MetricDef("psnr", "frame", True, frozenset({"aggregate"}), "PSNR", 2,
              per_frame="skyeyes_bench.estimators:psnr"),
    MetricDef("ssim", "frame", True, frozenset({"aggregate", "window", "sigma", "k1", "k2"}), "SSIM", 3,
              per_frame="skyeyes_bench.estimators:ssim"),
    MetricDef("lpips", "frame", False, frozenset({"aggregate", "extractor"}), "LPIPS", 3, extractor=True,
              per_frame="skyeyes_bench.estimators:lpips"),
    MetricDef("fid", "set", False, frozenset({"extractor", "resize"}), "FID", 2, extractor=True,
              features=IMAGE_FEATURES, **_FRECHET),
    MetricDef("fid_inf", "set", False, _INF_KEYS, "FID∞", 2, extractor=True, features=IMAGE_FEATURES, **_FRECHET_INF),
    MetricDef("kid", "set", False, _KID_KEYS, "KID", 4, extractor=True, features=IMAGE_FEATURES, **_MMD),
    MetricDef("fvd", "set", False, _CLIP_KEYS, "FVD", 2, extractor=True, features=CLIP_FEATURES, **_FRECHET),
    MetricDef("fvd_inf", "set", False, _CLIP_KEYS | _INF_KEYS, "FVD∞", 2, extractor=True, features=CLIP_FEATURES,
              **_FRECHET_INF),
    MetricDef("kvd", "set", False, _CLIP_KEYS | _KID_KEYS, "KVD", 2, extractor=True, features=CLIP_FEATURES, **_MMD),
    MetricDef("psnr_seen", "frame", True, _DEPTH, "PSNR seen", 2, weighted=True, pool="mse", **_REGIONS),
    MetricDef("psnr_unseen", "frame", True, _DEPTH, "PSNR unseen", 2, weighted=True, pool="mse", **_REGIONS),
    MetricDef("ssim_seen", "frame", True, _DEPTH | _SSIM_KEYS, "SSIM seen", 3, weighted=True, **_REGIONS),
    MetricDef("ssim_unseen", "frame", True, _DEPTH | _SSIM_KEYS, "SSIM unseen", 3, weighted=True, **_REGIONS),
    MetricDef("lpips_seen", "frame", False, _DEPTH | {"extractor"}, "LPIPS seen", 3, weighted=True,
              **_LPIPS_REGIONS),
    MetricDef("lpips_unseen", "frame", False, _DEPTH | {"extractor"}, "LPIPS unseen", 3, weighted=True,
              **_LPIPS_REGIONS),
    MetricDef("unseen_share", "frame", False, _DEPTH, "Unseen share", 3, reference=True, **_REGIONS),
    MetricDef("warp", "frame", False, _DEPTH, "Warp error", 4, **_WARP),
    MetricDef("warp_floor", "frame", False, _DEPTH, "Warp floor", 4, reference=True, **_WARP),
)}



def register_metric(m: MetricDef) -> MetricDef:
    """Add `m` to `METRICS` (after those above, in display order): the one registry line of a
    metric defined elsewhere. Every key it accepts must have a `Setting` (shared or its own)."""
    if m.name in METRICS:
        raise ValueError(f"metric {m.name!r} is already registered")
    own = {s.key for s in m.settings}
    unknown = sorted(m.keys - own - set(SETTINGS)) + sorted(own - m.keys)
    if unknown:
        raise ValueError(f"metric {m.name!r}: key {unknown[0]!r} needs a Setting in MetricDef.settings and a "
                         "place in MetricDef.keys")
    METRICS[m.name] = m
    return m


def frame_metrics() -> tuple[str, ...]:
    """The frame metrics, in table order (read when called: a metric registered later is one)."""
    return tuple(n for n, m in METRICS.items() if m.kind == "frame")


def set_metrics() -> tuple[str, ...]:
    """The set metrics, in table order."""
    return tuple(n for n, m in METRICS.items() if m.kind == "set")


def sequence_metrics() -> tuple[str, ...]:
    """The frame metrics computed a sequence at a time from depth and poses (the rest: frame by frame)."""
    return tuple(n for n, m in METRICS.items() if m.per_sequence)


_LIVE = {"FRAME_METRICS": frame_metrics, "SET_METRICS": set_metrics, "SEQUENCE_METRICS": sequence_metrics}


def __getattr__(name: str):
    """`FRAME_METRICS`, `SET_METRICS`, `SEQUENCE_METRICS`: the functions above' tuples, as of now."""
    if name in _LIVE:
        return _LIVE[name]()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def known_keys() -> set[str]:
    """Every setting key some metric accepts (a `MetricSpec` answers None for one it was not given)."""
    return set(SETTINGS).union(*(m.keys for m in METRICS.values()))


def metric_def(name: str) -> MetricDef:
    """The table entry of `name`, or a one-line UserError listing the known metrics."""
    from .registry import lookup

    return lookup(METRICS, name, "metric")


#: Why differing sample counts matter (issue 39; docs/metrics.md, "FID∞ and FVD∞").
COUNTS_WHY = ("a Fréchet distance's bias shrinks like 1/N (Chong & Forsyth 2020), so FID/FVD of different counts "
              "are not on one scale (FID∞/FVD∞ are; KID/KVD are unbiased, their spread differs): docs/metrics.md")


def sample_count_warning(named: list[tuple[str, dict]]) -> str | None:
    """One line when results scored a set metric on different sample counts, else None.

    named: (label, a results document's "metrics") pairs; each set metric's `n` (frames or clips)
    is read where its status is "ok". E.g. "set metrics on different sample counts: FVD 128 clips (A),
    256 clips (B); a Fréchet distance's bias ...". Possible across protocols, or when a
    submission was scored in part."""
    parts = []
    for name in set_metrics():
        counts = [(label, m["n"], m.get("unit") or "row") for label, metrics in named
                  if (m := (metrics or {}).get(name)) and m.get("status") == "ok" and m.get("n") is not None]
        if len({n for _, n, _ in counts}) > 1:
            parts.append(f"{METRICS[name].label} " + ", ".join(f"{n} {unit}s ({label})" for label, n, unit in counts))
    return f"set metrics on different sample counts: {'; '.join(parts)}; {COUNTS_WHY}" if parts else None
