"""Per-Gaussian stage of splatting: 3D covariance, EWA projection, culling, SH colour.

Everything here is O(N) and differentiated by plain autograd; it runs in float64 internally so
needle-thin and huge covariances keep their determinant (float32 loses it to cancellation),
and returns the dtype it was given.
"""

from __future__ import annotations

import math

import torch

#: NOTE: 3DGS adds 0.3 px^2 to the projected covariance as a low-pass filter
#: (diff-gaussian-rasterization, forward.cu `computeCov2D`).
BLUR_PX2 = 0.3
#: NOTE: 3DGS clamps the view-space x/z, y/z used by the EWA Jacobian to 1.3 x tan(fov/2).
JACOBIAN_CLAMP = 1.3
#: Support of a Gaussian: pixels within Mahalanobis distance 3 (the ellipse the 3DGS radius
#: 3 sqrt(lambda_max) bounds). Using the ellipse, not the tile, makes images tile-independent.
SUPPORT_SIGMA = 3.0

# NOTE: real spherical-harmonics constants as in 3DGS (utils/sh_utils.py, forward.cu).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def _rotmat_entries(quats: torch.Tensor) -> list[torch.Tensor]:
    """The 9 entries r00, r01, ..., r22 ([N] each) of the rotations of quats [N, 4] (wxyz)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.t().contiguous()  # contiguous columns: strided ones are not vectorised
    return [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] (w, x, y, z; normalised here)."""
    return torch.stack(_rotmat_entries(quats), dim=-1).reshape(*quats.shape[:-1], 3, 3)


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T [N, 3, 3] from quats [N, 4] (wxyz) and linear scales [N, 3] (m)."""
    m = quat_to_rotmat(quats) * scales[:, None, :]  # R @ diag(s)
    # Broadcast products instead of a batched 3x3 matmul: bmm over N tiny matrices costs ~1 us
    # per matrix on the CPU, the broadcast form a few passes over N x 27 numbers.
    return (m[:, :, None, :] * m[:, None, :, :]).sum(-1)


def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Colour [N, 3] from SH coefficients [N, K, 3] (K >= (degree+1)^2) and unit dirs [N, 3].

    3DGS convention: returns SH value + 0.5, clamped at 0 (no upper clamp).
    """
    basis = sh_basis(degree, dirs.to(sh.dtype))  # [N, (degree+1)^2]
    # One weighted sum instead of a term per coefficient: each `sh[:, k]` term's backward
    # allocated and filled a full [N, K, 3] gradient.
    out = _ShDot.apply(basis, sh[:, :basis.shape[1]])
    return (out + 0.5).clamp_min(0.0)


class _ShDot(torch.autograd.Function):
    """sum_k basis[n, k] sh[n, k, c] ([N, K] x [N, K, 3] -> [N, 3]).

    A batched 1 x K by K x 3 matmul forward; the backward is one broadcast product. Plain
    autograd of the broadcast-and-sum form was ~4x slower (reductions and broadcasts over a
    trailing dim of size 3 are not vectorised).
    """

    @staticmethod
    def forward(ctx, basis, sh):
        ctx.save_for_backward(basis, sh)
        return torch.bmm(basis[:, None, :], sh)[:, 0]

    @staticmethod
    def backward(ctx, g):
        basis, sh = ctx.saved_tensors
        d_basis = torch.bmm(sh, g[:, :, None])[:, :, 0] if ctx.needs_input_grad[0] else None
        d_sh = basis[:, :, None] * g[:, None, :] if ctx.needs_input_grad[1] else None
        return d_basis, d_sh


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis [N, (degree+1)^2] at unit dirs [N, 3], with 3DGS's signs and order."""
    cols = [torch.full_like(dirs[:, 0], SH_C0)]
    if degree > 0:
        x, y, z = dirs.unbind(-1)
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            cols += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                     SH_C2[4] * (xx - yy)]
            if degree > 2:
                cols += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                         SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                         SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(cols, -1)


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmat: torch.Tensor,
            K: torch.Tensor, width: int, height: int, *, near: float = 0.01, far: float = 1e10,
            blur: float = BLUR_PX2) -> dict[str, torch.Tensor]:
    """EWA projection of 3D Gaussians to the image (pixel centres at +0.5, OpenCV camera).

    Args:
        means: [N, 3] world positions (m). quats: [N, 4] wxyz. scales: [N, 3] linear (m).
        viewmat: [4, 4] world-to-camera. K: [3, 3] intrinsics (px).
        near, far: planar depth range (m); centres outside it are culled.

    Returns dict with means2d [N, 2] (px), conics [N, 3] (a, b, c of the inverse 2D covariance),
    depths [N] (planar, m), radii [N] (px, 0 = culled), valid [N] bool. Culled entries hold
    finite dummies so nothing downstream sees NaN.
    """
    dtype = means.dtype
    f64 = torch.float64
    means, quats, scales = means.to(f64), quats.to(f64), scales.to(f64)
    viewmat, K = viewmat.to(f64), K.to(f64)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = R @ means.T + t[:, None]  # [3, N] camera space (rows contiguous: strided columns are slow)
    z = p[2]
    finite = torch.isfinite(p).all(0) & torch.isfinite(scales).all(-1) & torch.isfinite(quats).all(-1)
    valid = finite & (z > near) & (z < far)
    one = torch.ones_like(z)
    zs = torch.where(valid, z, one)
    xs = torch.where(valid, p[0], 0 * one)
    ys = torch.where(valid, p[1], 0 * one)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    means2d = torch.stack([fx * xs / zs + cx, fy * ys / zs + cy], -1)

    # EWA Jacobian of the pinhole at the (clamped) centre; clamping keeps it sane for centres
    # far outside the view (grazing ground views), as 3DGS does.
    lim_x = JACOBIAN_CLAMP * (0.5 * width / fx)
    lim_y = JACOBIAN_CLAMP * (0.5 * height / fy)
    txz = (xs / zs).clamp(-lim_x, lim_x)
    tyz = (ys / zs).clamp(-lim_y, lim_y)
    zero = torch.zeros_like(zs)
    # Everything per Gaussian below is written on [N] columns: batched 3x3 matmuls cost ~1 us
    # per Gaussian on the CPU and reductions over dims of size 2-3 are not much better, so
    # this is several times faster forward and backward than the matrix form
    # cov2d = J R Sigma R^T J^T (J the [2, 3] EWA Jacobian, R the camera rotation).
    j00, j02 = fx / zs, -fx * txz / zs
    j11, j12 = fy / zs, -fy * tyz / zs
    # T = J R, rows [N] x 3.
    T0 = [j00 * R[0, k] + j02 * R[2, k] for k in range(3)]
    T1 = [j11 * R[1, k] + j12 * R[2, k] for k in range(3)]
    safe_scales = torch.where(finite[:, None], scales, torch.ones_like(scales))
    safe_quats = torch.where(finite[:, None], quats, torch.ones_like(quats))
    Rg = _rotmat_entries(safe_quats)  # 9 x [N], row-major
    s0, s1, s2 = safe_scales.t().contiguous()
    # M = Rg diag(s) (Sigma = M M^T); TM = T M, [N] x 2 x 3; cov2d = TM TM^T.
    Mc = [[Rg[3 * k + j] * sj for j, sj in enumerate((s0, s1, s2))] for k in range(3)]
    TM0 = [T0[0] * Mc[0][j] + T0[1] * Mc[1][j] + T0[2] * Mc[2][j] for j in range(3)]
    TM1 = [T1[0] * Mc[0][j] + T1[1] * Mc[1][j] + T1[2] * Mc[2][j] for j in range(3)]
    a = TM0[0] * TM0[0] + TM0[1] * TM0[1] + TM0[2] * TM0[2] + blur
    b = TM0[0] * TM1[0] + TM0[1] * TM1[1] + TM0[2] * TM1[2]
    c = TM1[0] * TM1[0] + TM1[1] * TM1[1] + TM1[2] * TM1[2] + blur
    det = a * c - b * b
    valid = valid & (det > 0) & torch.isfinite(det)
    det = torch.where(valid, det, one)
    a, b, c = (torch.where(valid, v, w) for v, w in ((a, one), (b, zero), (c, one)))
    conics = torch.stack([c / det, -b / det, a / det], -1)
    mid = 0.5 * (a + c)
    lam_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.0))
    radii = SUPPORT_SIGMA * torch.sqrt(lam_max.detach())
    # Off-image: the support box misses the image entirely.
    mx, my = means2d[:, 0].detach(), means2d[:, 1].detach()
    on_image = (mx + radii > 0) & (mx - radii < width) & (my + radii > 0) & (my - radii < height)
    valid = valid & on_image & torch.isfinite(radii)
    radii = torch.where(valid, radii, torch.zeros_like(radii))
    return {
        "means2d": means2d.to(dtype), "conics": conics.to(dtype), "depths": zs.to(dtype),
        "radii": radii.to(dtype), "valid": valid,
    }


def view_dirs(means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """Unit directions [N, 3] from the camera centre to each mean (world frame)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    campos = -(R.T @ t)
    d = means - campos.to(means.dtype)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def sh_colors(sh: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB [N, 3] from SH [N, K, 3] seen from the camera of `viewmat` [4, 4]."""
    if degree == 0:
        return (SH_C0 * sh[:, 0] + 0.5).clamp_min(0.0)
    return eval_sh(degree, sh, view_dirs(means.detach(), viewmat))


def degree_for(num_bases: int) -> int:
    d = int(round(math.sqrt(num_bases))) - 1
    assert (d + 1) ** 2 == num_bases and 0 <= d <= 3, num_bases
    return d


def resolve_degree(sh: torch.Tensor, sh_degree: int | None) -> int:
    """The SH degree to render from sh [N, K, 3]: `sh_degree`, or all that sh holds (None);
    more than sh holds is refused."""
    held = degree_for(sh.shape[1])
    deg = held if sh_degree is None else sh_degree
    assert 0 <= deg <= held, f"sh_degree {deg} needs {(deg + 1) ** 2} SH bases, sh has {sh.shape[1]}"
    return deg
