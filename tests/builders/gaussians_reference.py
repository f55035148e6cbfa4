"""A slow reference of 3D Gaussian splatting that shares nothing with reference.common.gaussians:
a literal per-Gaussian, per-pixel transcription of the 3DGS forward pass (Kerbl et al. 2023,
diff-gaussian-rasterization forward.cu: computeCov3D, computeCov2D, computeColorFromSH,
preprocessCUDA, renderCUDA) in numpy float64, with plain Python loops.

Conventions where this project deliberately differs from the CUDA code (docs say so), followed
here from their statement, not from our code: pixel centres at (j + 0.5, i + 0.5) with
u = fx x / z + cx; a Gaussian touches a pixel when its Mahalanobis distance is <= 3 (the ellipse
the 3DGS radius 3 sqrt(lambda_max) bounds) and alpha >= 1/255; the determinant guard is det > 0
and lambda_max uses max(0, mid^2 - det) (3DGS: 0.1); centres with planar depth outside
(near, far) are culled.
"""

import math

import numpy as np

# NOTE: real SH normalisation constants from their closed forms (3DGS hard-codes their values).
C0 = 1 / (2 * math.sqrt(math.pi))
C1 = math.sqrt(3 / (4 * math.pi))
C2 = (math.sqrt(15 / math.pi) / 2, -math.sqrt(15 / math.pi) / 2, math.sqrt(5 / math.pi) / 4,
      -math.sqrt(15 / math.pi) / 2, math.sqrt(15 / math.pi) / 4)
C3 = (-math.sqrt(35 / (2 * math.pi)) / 4, math.sqrt(105 / math.pi) / 2, -math.sqrt(21 / (2 * math.pi)) / 4,
      math.sqrt(7 / math.pi) / 4, -math.sqrt(21 / (2 * math.pi)) / 4, math.sqrt(105 / math.pi) / 4,
      -math.sqrt(35 / (2 * math.pi)) / 4)
#: forward.cu computeCov2D: limx = 1.3f * tan_fovx.
JACOBIAN_LIMIT = 1.3
LOW_PASS = 0.3  # px^2 added to the 2D covariance's diagonal
ALPHA_MIN, ALPHA_MAX, T_STOP = 1 / 255, 0.99, 0.0001


def cov3d(q_wxyz, s):
    """computeCov3D: R from the normalised quaternion (r, x, y, z), M = S R, Sigma = M^T M."""
    q = np.asarray(q_wxyz, np.float64) / np.linalg.norm(q_wxyz)
    r, x, y, z = q
    R = np.array([  # glm row-major reading of forward.cu's mat3
        [1 - 2 * (y * y + z * z), 2 * (x * y - r * z), 2 * (x * z + r * y)],
        [2 * (x * y + r * z), 1 - 2 * (x * x + z * z), 2 * (y * z - r * x)],
        [2 * (x * z - r * y), 2 * (y * z + r * x), 1 - 2 * (x * x + y * y)]])
    S = np.diag(s)
    M = R @ S
    return M @ M.T


def cov2d(mean, Sigma, view, fx, fy, width, height):
    """computeCov2D: EWA Jacobian at the view-space centre, x/z and y/z clamped to 1.3 tan(fov/2)."""
    t = view[:3, :3] @ mean + view[:3, 3]
    tan_fovx, tan_fovy = width / (2 * fx), height / (2 * fy)
    limx, limy = JACOBIAN_LIMIT * tan_fovx, JACOBIAN_LIMIT * tan_fovy
    tx = min(limx, max(-limx, t[0] / t[2])) * t[2]
    ty = min(limy, max(-limy, t[1] / t[2])) * t[2]
    tz = t[2]
    J = np.array([[fx / tz, 0.0, -(fx * tx) / (tz * tz)],
                  [0.0, fy / tz, -(fy * ty) / (tz * tz)]])
    T = J @ view[:3, :3]
    cov = T @ Sigma @ T.T
    return cov + LOW_PASS * np.eye(2)


def color_from_sh(deg, sh, mean, campos):
    """computeColorFromSH: sh [K, 3]; direction from the camera centre; + 0.5, clamped at 0."""
    d = mean - campos
    x, y, z = d / np.linalg.norm(d)
    res = C0 * sh[0]
    if deg > 0:
        res = res - C1 * y * sh[1] + C1 * z * sh[2] - C1 * x * sh[3]
        if deg > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (res + C2[0] * xy * sh[4] + C2[1] * yz * sh[5] + C2[2] * (2 * zz - xx - yy) * sh[6]
                   + C2[3] * xz * sh[7] + C2[4] * (xx - yy) * sh[8])
            if deg > 2:
                res = (res + C3[0] * y * (3 * xx - yy) * sh[9] + C3[1] * xy * z * sh[10]
                       + C3[2] * y * (4 * zz - xx - yy) * sh[11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[12]
                       + C3[4] * x * (4 * zz - xx - yy) * sh[13] + C3[5] * z * (xx - yy) * sh[14]
                       + C3[6] * x * (xx - 3 * yy) * sh[15])
    return np.maximum(res + 0.5, 0.0)


def preprocess(means, quats, scales, view, K, width, height, near=0.01, far=1e10):
    """preprocessCUDA, one Gaussian at a time: list of dicts (None where culled) with the pixel
    centre, conic (a, b, c) of the inverse 2D covariance, planar depth and 3-sigma radius."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = []
    for mean, q, s in zip(means, quats, scales):
        t = view[:3, :3] @ mean + view[:3, 3]
        if not (near < t[2] < far):
            out.append(None)
            continue
        cov = cov2d(mean, cov3d(q, s), view, fx, fy, width, height)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        if not det > 0:
            out.append(None)
            continue
        conic = (cov[1, 1] / det, -cov[0, 1] / det, cov[0, 0] / det)
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        lam = mid + math.sqrt(max(0.0, mid * mid - det))
        uv = np.array([fx * t[0] / t[2] + cx, fy * t[1] / t[2] + cy])
        out.append({"uv": uv, "conic": conic, "depth": t[2], "radius": 3 * math.sqrt(lam), "cov2d": cov})
    return out


def render(means, quats, scales, opacities, sh, view, K, width, height, background=(0, 0, 0), sh_degree=None):
    """renderCUDA for every pixel: Gaussians front to back (stable sort by depth), alpha
    = min(0.99, o exp(-q/2)), skipped below 1/255 or beyond 3 sigma, stop before T < 1e-4.
    Returns rgb [H, W, 3], depth [H, W] (expected planar depth / alpha; 0 where alpha is 0),
    alpha [H, W]. Inputs: numpy float64 arrays (means [N, 3], quats [N, 4] wxyz, scales [N, 3],
    opacities [N], sh [N, K, 3], view [4, 4] world-to-camera, K [3, 3])."""
    deg = int(round(math.sqrt(sh.shape[1]))) - 1 if sh_degree is None else sh_degree
    campos = -view[:3, :3].T @ view[:3, 3]
    pre = preprocess(means, quats, scales, view, K, width, height)
    colours = [None if p is None else color_from_sh(deg, sh[i], means[i], campos) for i, p in enumerate(pre)]
    order = sorted((i for i, p in enumerate(pre) if p is not None), key=lambda i: pre[i]["depth"])
    rgb, depth, alpha = np.zeros((height, width, 3)), np.zeros((height, width)), np.zeros((height, width))
    bg = np.asarray(background, np.float64)
    for py in range(height):
        for px in range(width):
            T, C, D = 1.0, np.zeros(3), 0.0
            for i in order:
                g = pre[i]
                dx, dy = px + 0.5 - g["uv"][0], py + 0.5 - g["uv"][1]
                a, b, c = g["conic"]
                q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
                if q > 9.0:
                    continue
                al = min(ALPHA_MAX, opacities[i] * math.exp(-0.5 * q))
                if al < ALPHA_MIN:
                    continue
                test_T = T * (1 - al)
                if test_T < T_STOP:
                    break
                C += colours[i] * al * T
                D += g["depth"] * al * T
                T = test_T
            rgb[py, px] = C + T * bg
            alpha[py, px] = 1 - T
            depth[py, px] = D / (1 - T) if T < 1 else 0.0
    return {"rgb": rgb, "depth": depth, "alpha": alpha, "pre": pre}
