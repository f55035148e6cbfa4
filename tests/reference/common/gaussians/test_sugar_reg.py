"""SuGaR's SDF and normal terms (sugar_reg.sdf_terms) against a per-sample loop written from the
paper's formulas (Guedon & Lepetit 2024; the Skyeyes paper's Eq. sdf-loss) in numpy, with its
own rotations (scipy), on the same random draws (the generator is replayed)."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from reference.common.gaussians.model import GaussianModel
from reference.common.gaussians.sugar_reg import sdf_terms


def _slow_sdf_terms(means, scales, quats_wxyz, opac, knn, src, eps):
    """For each sample p ~ N(mu_src, Sigma_src): density d(p) = sum_k o_k exp(-|y_k|^2 / 2)
    over the neighbours (y_k = S_k^-1 R_k^T (p - mu_k)), clipped to (1e-6, 1 - 1e-6); g* the
    largest contribution, n* its shortest axis, s* that scale; SDF term
    |s* sqrt(-2 ln d(p)) - |<p - mu*, n*>|| / s*, normal term 1 - |<grad d / |grad d|, n*>|."""
    R = Rotation.from_quat(np.roll(quats_wxyz, -1, axis=1)).as_matrix()  # scipy wants xyzw
    sdf, normal = [], []
    for s_i, e in zip(src, eps):
        p = means[s_i] + R[s_i] @ (e * scales[s_i])
        g, grad = [], np.zeros(3)
        for j in knn[s_i]:
            y = R[j].T @ (p - means[j]) / scales[j]
            gj = opac[j] * math.exp(-0.5 * y @ y)
            g.append(gj)
            grad -= gj * R[j] @ (y / scales[j])  # d/dp of o exp(-q/2) = -o e^{-q/2} Sigma^-1 (p - mu)
        d = min(max(sum(g), 1e-6), 1 - 1e-6)
        star = knn[s_i][int(np.argmax(g))]
        axis = int(np.argmin(scales[star]))
        s_min, n_star = scales[star, axis], R[star][:, axis]
        ideal = abs((p - means[star]) @ n_star)
        implied = s_min * math.sqrt(-2.0 * math.log(d))
        sdf.append(abs(implied - ideal) / s_min)
        normal.append(1.0 - abs(grad / max(np.linalg.norm(grad), 1e-12) @ n_star))
    return float(np.mean(sdf)), float(np.mean(normal))


@pytest.mark.parametrize("seed", [0, 1])
def test_sdf_terms_match_a_per_sample_loop(seed):
    rng = np.random.default_rng(seed)
    n, samples, k = 24, 200, 6
    xyz = rng.uniform(-1.0, 1.0, size=(n, 3))
    m = GaussianModel.from_points(xyz, rng.random((n, 3)), 0, opacity=0.5)
    with torch.no_grad():  # flat-ish, randomly oriented Gaussians of mixed opacity
        m.params["quats"].copy_(torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32))
        m.params["log_scales"].copy_(torch.tensor(np.log(rng.uniform([0.1, 0.1, 0.01], [0.4, 0.4, 0.05], (n, 3))),
                                                  dtype=torch.float32))
        m.params["logit_opacities"].copy_(torch.tensor(rng.normal(0.0, 1.5, n), dtype=torch.float32))
    _, idx = cKDTree(xyz).query(xyz, k=k)
    knn = torch.from_numpy(idx)
    sdf, normal = sdf_terms(m, knn, samples, torch.Generator().manual_seed(seed))
    g = torch.Generator().manual_seed(seed)  # replay sdf_terms' draws: sources, then N(0, I)
    src = torch.randint(0, n, (samples,), generator=g).numpy()
    eps = torch.randn(samples, 3, generator=g).double().numpy()
    q = m.quats.detach().double().numpy()
    want_sdf, want_normal = _slow_sdf_terms(
        m.means.detach().double().numpy(), m.scales.detach().double().numpy(), q / np.linalg.norm(q, axis=1, keepdims=True),
        m.opacities.detach().double().numpy(), idx, src, eps)
    assert sdf.item() == pytest.approx(want_sdf, rel=1e-4)
    assert normal.item() == pytest.approx(want_normal, rel=1e-4, abs=1e-6)
    assert want_sdf > 0.1  # not a degenerate case where every term vanishes
