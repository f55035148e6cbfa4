"""Warped sampling: the frame already generated, moved into the next frame's view by the prior's
depth and the two poses, holds the pixels it reaches for the first DDIM steps (`vcm_warp`).

The view consistency module's inference side (Skyeyes Sec. 3.3 carries content from frame to
frame; issue 36). What the paper's VCM learns through attention, this enforces with geometry,
which the task gives at inference: the ground poses, and the depth of the 3D prior the ACM is
conditioned on (never the ground truth's). The held pixels are the previous frame's, noised to
the step's timestep with the new frame's own starting noise (as RePaint replaces the known
region, Lugmayr et al. CVPR 2022; as Control-A-Video and vid2vid-zero start frames from
shared or motion-aligned noise); after `hold` steps the model denoises the whole frame alone, so
it restores the detail the bilinear warp blurs and fills what the previous frame did not see.

Here: the backward warp of a generated image (`warp_coords` of the warp metric, on the prior's
depth), a validity mask in model space (`encode_mask`), and the target of the hold
(`WarpTargets`), which the samplers take as a callable.

The low-pass transfer (`vcm_lowpass`, `lowpass_transfer`) carries only the coarse part of each
frame on, after sampling: most of the frame-to-frame flicker of frames sampled one by one is
in their low frequencies (a building's colour, a road's brightness; the paper's "buildings with
different colors"), while holding the whole warped frame compounds the bilinear warp's blur from
frame to frame. Measured on `skyeyes-no-vcm` small frames made here (2 scenes, the ground
truth's depth): the warp error of the frames low-passed with a Gaussian of 2 px is 0.0753 of
their 0.0915, the high-passed rest 0.0362.

Carried noise (`vcm_noise_flow`, `carried_noise`) moves the frames' starting noise instead, along
the same flow, so frames agree before any step is taken and nothing is blurred or held.

The prior anchor (`vcm_anchor`, `prior_anchor`) moves nothing between frames: each frame's coarse
part moves towards its own render of the 3D prior, which is steady from frame to frame by
construction, with the render's colours first mapped to the frames' (`affine_colours`), so the
ACM's correction of the prior's colours stays.

The street from one view (`vcm_street`, `street_transfer`) moves nothing by a flow either: the
street is a plane under the prior's Gaussians (`prior_ground`), where the poses place every pixel
to a fraction of a pixel, so each point of it takes its colour from one frame's view of it, the
same whichever frame shows it. The sky (`vcm_sky`, `sky_fit`) is a direction at infinity, the
same colour from every pose: one smooth fit of the sequence's sky pixels paints it in every
frame. `FlowAlign` (`vcm_align`) gives the VCM's attention the frame
before moved into the new frame's view.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from skyeyes_bench.cameras import Camera
from skyeyes_bench.metrics.geometry import project, sample_bilinear, warp_coords

from .core import CoreConfig, decode, encode, from_diffused, to_diffused

#: Relative depth tolerance of the correspondence test between the prior's two depths (they come
#: from one model, so they agree to its rasterisation; wider than the metric's 0.01 for the
#: alpha-blended depth at edges).
DEPTH_TOL = 0.03


def scaled_camera(cam: Camera, width: int, height: int) -> Camera:
    """`cam` with its intrinsics scaled to an image of width x height (the model's square)."""
    K = np.array(cam.K, dtype=np.float64)
    K[0] *= width / cam.width
    K[1] *= height / cam.height
    return Camera(K, cam.c2w, width, height)


@torch.no_grad()
def prior_depth(prior, scene, frame, width: int, height: int) -> np.ndarray:
    """The expected planar depth (m) of a Gaussian prior's fitted scene (`sugar`, `gaussians3d`:
    `scene_model(scene)[0]` is its `GaussianModel`) seen from `frame`'s pose with its intrinsics
    scaled to width x height: float64 [height, width], +inf where the Gaussians cover less than
    half the pixel (the sky and the background: a direction, as the warp metric reads it)."""
    from reference.common.gaussians import rasterize

    model = prior.scene_model(scene)[0]
    cam = scaled_camera(frame.camera(), width, height)
    dev = model.means.device
    out = rasterize(model.means, model.quats, model.scales, model.opacities, model.sh,
                    torch.tensor(cam.w2c, dtype=torch.float32, device=dev),
                    torch.tensor(cam.K, dtype=torch.float32, device=dev), width, height,
                    sh_degree=prior.config.sh_degree, near=prior.config.render_near_m)
    depth = out["depth"].double().cpu().numpy()
    return np.where((out["alpha"].cpu().numpy() > 0.5) & (depth > 0), depth, np.inf)


def warp_image(src: torch.Tensor, uv: np.ndarray, valid: np.ndarray) -> torch.Tensor:
    """Backward warp: src [C, H, W] sampled bilinearly at uv [H, W, 2] (pixel coordinates, centres
    at +0.5, as `warp_coords` gives them) -> [C, H, W], zeros where not `valid` [H, W]."""
    c, h, w = src.shape
    uv = np.where(valid[..., None], uv, 0.0)
    grid = torch.as_tensor(np.stack([2.0 * uv[..., 0] / w - 1.0, 2.0 * uv[..., 1] / h - 1.0], -1),
                           dtype=src.dtype, device=src.device)
    out = F.grid_sample(src[None], grid[None], mode="bilinear", padding_mode="border", align_corners=False)[0]
    return out * torch.as_tensor(valid, device=src.device, dtype=src.dtype)


def encode_mask(valid: torch.Tensor, cfg: CoreConfig, channels: int) -> torch.Tensor:
    """A pixel mask [N, 1, res, res] (bool) -> [N, channels, h, w] float in model space: 1 where
    every pixel the model-space value stands for is valid (an unshuffled patch, or a latent cell
    of a pretrained VAE's 8x8), else 0."""
    m = valid.to(torch.float32)
    if cfg.pretrained:
        m = (F.avg_pool2d(m, 8) > 0.999).to(torch.float32)
        return m.expand(-1, channels, -1, -1)
    if cfg.patch > 1:
        m = F.pixel_unshuffle(m, cfg.patch)  # channel k of a patch: pixel k (order of `encode`)
        m = m.amin(dim=1, keepdim=True)  # the whole patch, so that each folded value is a pixel's
    return m.expand(-1, channels, -1, -1).contiguous()


class WarpTargets:
    """The hold targets of a sequence: `(z, i, js)` -> (targets [len(js), C, h, w], masks alike),
    frame i's sample z [C, h, w] (model space, clean) warped into each frame j of `js`.

    Args:
        conds: [N, Cc, h, w] the sequence's conditions in model space (`encode_cond`).
        depths: N arrays [res, res], the prior's planar depth at the model's resolution (+inf:
            a direction).
        cameras: N cameras scaled to res x res (`scaled_camera`).
    """

    def __init__(self, conds: torch.Tensor, depths: list[np.ndarray], cameras: list[Camera], cfg: CoreConfig,
                 *, tol: float = DEPTH_TOL):
        if not (len(conds) == len(depths) == len(cameras)):
            raise ValueError(f"{len(conds)} conditions, {len(depths)} depths, {len(cameras)} cameras")
        self.conds, self.depths, self.cameras, self.cfg, self.tol = conds, depths, cameras, cfg, tol

    def coords(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(uv, valid) of frame i seen from frame j: by the prior's depths and the poses."""
        return warp_coords(self.depths[j], self.cameras[j], self.depths[i], self.cameras[i], self.tol)

    def __call__(self, z: torch.Tensor, i: int, js: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.cfg
        img = decode(from_diffused(z[None].float().cpu(), self.conds[i:i + 1].cpu(), cfg), cfg)[0]  # [3, res, res]
        targets, masks = [], []
        for j in js:
            uv, valid = self.coords(i, j)
            warped = warp_image(img, uv, valid)
            targets.append(to_diffused(encode(warped[None], cfg), self.conds[j:j + 1].cpu(), cfg)[0])
            masks.append(torch.as_tensor(valid)[None, None])
        m = encode_mask(torch.cat(masks), cfg, z.shape[0])
        return torch.stack(targets) * m, m


class FlowAlign:
    """The VCM's view of the frame before (`vcm_align`): `(z, i, j)` -> frame i's clean sample z
    [C, h, w] (model space, on frame i's condition) moved into frame j's view by `coords(j)` (the
    optical flow between the two frames' conditions, `flow_coords`) and put on frame j's
    condition; the pixels the flow does not reach keep frame i's own. So the VCM's local
    attention looks for a frame's detail in the frame before at the same place of the picture,
    not where the camera's motion left it (up to 28 px a frame on the near road at `small`,
    beyond a 5 x 5 window at any level; bench/flow_accuracy.py)."""

    def __init__(self, conds: torch.Tensor, coords: Callable[[int], tuple[np.ndarray, np.ndarray]],
                 cfg: CoreConfig):
        self.conds, self.coords, self.cfg = conds, coords, cfg

    def __call__(self, z: torch.Tensor, i: int, j: int) -> torch.Tensor:
        if j != i + 1:
            raise ValueError(f"FlowAlign: frame {i} into frame {j}; the flow is between neighbours")
        cfg = self.cfg
        img = decode(from_diffused(z[None].float().cpu(), self.conds[i:i + 1].cpu(), cfg), cfg)[0]  # [3, res, res]
        uv, valid = self.coords(j)
        moved = torch.where(torch.as_tensor(valid)[None], warp_image(img, uv, valid), img)
        return to_diffused(encode(moved[None], cfg), self.conds[j:j + 1].cpu(), cfg)[0].to(z.dtype)


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian low-pass of a [C, H, W] array over H and W (reflected at the border)."""
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(a, (0, sigma, sigma), mode="reflect")


def blur_frames(x: torch.Tensor, sigma: float) -> np.ndarray:
    """Frames [N, C, H, W] -> their Gaussian low-passes (`_blur`, each frame on its own), float64."""
    return np.stack([_blur(f, sigma) for f in x.detach().double().cpu().numpy()])


def depth_coords(depths: list[np.ndarray], cameras: list[Camera],
                 tol: float = DEPTH_TOL) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """j -> (uv, valid) of frame j - 1 seen from frame j, by depth and the poses (`warp_coords`
    on the frames' depths and cameras, e.g. `WarpTargets`' prior depths)."""
    return lambda j: warp_coords(depths[j], cameras[j], depths[j - 1], cameras[j - 1], tol)


#: Forward-backward consistency of `flow_coords`, pixels at the model's resolution. NOTE: on the
#: `skyeyes-no-vcm` small frames made here (bench/vcm_lowpass.py, 1 scene, flow between the prior's
#: renders, sigma 4) 1 px kept too little: warp error 0.0704, against 0.0641 at 3 px.
FLOW_FB_PX = 3.0


def flow_coords(guides: np.ndarray, *, fb_px: float = FLOW_FB_PX,
                flow: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
                ) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """j -> (uv, valid) of frame j - 1 seen from frame j, by optical flow between guide images
    [N, H, W, 3] in [0, 1] (OpenCV's DIS flow, Kroeger et al. 2016, on their grey levels): uv the
    pixel centre plus the flow from j to j - 1, valid where it lands inside frame j - 1 and the
    flow back returns within `fb_px` pixels (forward-backward consistency). `flow`: another
    flow, (grey a, grey b) uint8 -> [H, W, 2] with a(x) ~ b(x + flow(x)) (bench/flow_accuracy.py
    compares them)."""
    import cv2

    if flow is None:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        flow = lambda a, b: dis.calc(a, b, None)  # noqa: E731
    grey = [cv2.cvtColor((np.clip(g, 0, 1) * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY) for g in guides]
    h, w = grey[0].shape
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)

    def coords(j: int) -> tuple[np.ndarray, np.ndarray]:
        back = flow(grey[j], grey[j - 1])  # I_j(x) ~ I_{j-1}(x + back(x))
        fwd = flow(grey[j - 1], grey[j])
        uv = np.stack([xs + back[..., 0], ys + back[..., 1]], -1)
        again = cv2.remap(fwd, (uv[..., 0] - 0.5).astype(np.float32), (uv[..., 1] - 0.5).astype(np.float32),
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        inside = (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
        return uv, inside & (np.hypot(*(back + again).transpose(2, 0, 1)) <= fb_px)

    return coords


#: OpenCV's DIS flow refuses images under this many pixels on both sides.
DIS_MIN_PX = 12


def grid_coords(coords: Callable[[int], tuple[np.ndarray, np.ndarray]], f: int) -> Callable[[int], tuple[np.ndarray, np.ndarray]]:
    """`coords` of an image f times the grid's size -> the same on the grid: each grid pixel
    takes the coordinates (divided by f) and validity of the fine pixel at its centre (f = 1:
    `coords` itself)."""
    if f == 1:
        return coords

    def on_grid(j: int) -> tuple[np.ndarray, np.ndarray]:
        uv, valid = coords(j)
        return uv[f // 2::f, f // 2::f] / f, valid[f // 2::f, f // 2::f]

    return on_grid


def lowpass_transfer(imgs: torch.Tensor, coords: Callable[[int], tuple[np.ndarray, np.ndarray]], sigma: float,
                     mix: float = 1.0) -> torch.Tensor:
    """A sequence's decoded frames [N, 3, res, res], in order -> the same frames with their low
    frequencies carried on: frame j's Gaussian low-pass (std `sigma` px) moves by `mix` towards
    the low-pass of output frame j - 1 warped into it, where that warp reaches, with a ramp of
    about `sigma` px into the pixels it does not reach; each frame's high frequencies stay its
    own. Frame 0 is unchanged. `coords`: j -> (uv, valid) of frame j - 1 seen from frame j
    (`flow_coords`, `depth_coords`).

    The warped frame's low-pass is a normalized convolution (its blur over the blur of its
    validity), so the pixels the warp does not reach do not darken it."""
    if not 0 < mix <= 1 or sigma <= 0:
        raise ValueError(f"lowpass_transfer: sigma {sigma} (> 0), mix {mix} (0 < mix <= 1)")
    x = imgs.detach().float().cpu().numpy()
    out = [x[0]]
    for j in range(1, len(x)):
        uv, valid = coords(j)
        warped = warp_image(torch.from_numpy(out[-1]), uv, valid).numpy()
        m = valid.astype(np.float32)[None]
        cover = _blur(m, sigma)
        low_warped = _blur(warped * m, sigma) / np.maximum(cover, 1e-6)
        weight = mix * m * np.clip(2.0 * cover - 1.0, 0.0, 1.0)  # 0 at holes, 1 a sigma or so inside
        out.append(np.clip(x[j] + weight * (low_warped - _blur(x[j], sigma)), 0.0, 1.0).astype(np.float32))
    return torch.from_numpy(np.stack(out)).to(imgs.device, imgs.dtype)


def affine_colours(src: torch.Tensor, dst: torch.Tensor, tiles: int = 1, fit: str = "lstsq",
                   sigma: float = 0.0) -> torch.Tensor:
    """src [N, 3, H, W] with its colours mapped by the affine map (a 3x3 matrix and an offset)
    that fits dst [N, 3, H, W] best in least squares over all N frames. tiles > 1: one map for each
    cell of a tiles x tiles grid of the screen, fitted on the pixels of all N frames within a cell
    of it either way around the cell's centre, and the maps blended bilinearly between the cells'
    centres (constant beyond the outer ones), so the map varies smoothly over the screen and not
    at all in time.

    fit "lstsq": the map that predicts dst best (a regression, so it shrinks src's contrast by
    as much as src fails to predict dst); "monge": the linear map that moves src's colour
    distribution onto dst's, means and covariances matched exactly (the Monge map between the
    two Gaussian fits, Pitie & Kokaram 2007), so the contrast is dst's. sigma > 0: fitted on the
    Gaussian low-passes of src and dst (std sigma px), and applied to src itself."""
    if fit not in ("lstsq", "monge"):
        raise ValueError(f"affine_colours: fit {fit!r}, expected 'lstsq' or 'monge'")
    n, _, h, w = src.shape
    cpu = torch.device("cpu")

    def design(x: torch.Tensor) -> torch.Tensor:  # [N, 3, H, W] -> [N, H, W, 4]: the colours and a 1
        return torch.cat([x.permute(0, 2, 3, 1).double().cpu(), torch.ones(n, h, w, 1, dtype=torch.float64, device=cpu)], -1)

    a = design(src)
    fa = design(torch.from_numpy(blur_frames(src, sigma))) if sigma > 0 else a  # what the map is fitted on
    b = (torch.from_numpy(blur_frames(dst, sigma)) if sigma > 0 else dst).permute(0, 2, 3, 1).double().cpu()
    cells = torch.arange(tiles, dtype=torch.float64, device=cpu) + 0.5
    cy, cx = cells * h / tiles, cells * w / tiles
    out = torch.zeros(n, h, w, 3, dtype=torch.float64, device=cpu)
    ys, xs = (torch.arange(k, dtype=torch.float64, device=cpu) + 0.5 for k in (h, w))
    wy = (1 - (ys[:, None] - cy[None]).abs() / (h / tiles)).clamp(min=0)  # [h, tiles] bilinear weights
    wx = (1 - (xs[:, None] - cx[None]).abs() / (w / tiles)).clamp(min=0)
    wy[ys < cy[0], 0], wy[ys > cy[-1], -1] = 1.0, 1.0  # constant beyond the outer centres
    wx[xs < cx[0], 0], wx[xs > cx[-1], -1] = 1.0, 1.0
    for i in range(tiles):
        rows = (ys - cy[i]).abs() < h / tiles
        for j in range(tiles):
            cols = (xs - cx[j]).abs() < w / tiles
            x, y = fa[:, rows][:, :, cols].reshape(-1, 4), b[:, rows][:, :, cols].reshape(-1, 3)
            m = torch.linalg.lstsq(x, y).solution if fit == "lstsq" else _monge(x[:, :3], y)
            out += (wy[:, i, None] * wx[None, :, j])[None, :, :, None] * (a @ m)
    return out.to(src.dtype).permute(0, 3, 1, 2)


def _monge(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """The affine map [4, 3] (rows: the 3x3 matrix, then the offset) that takes the Gaussian fit of
    the colours x [M, 3] onto that of y [M, 3] with the least mean squared move: A = S^-1/2
    (S^1/2 T S^1/2)^1/2 S^-1/2 for covariances S (x's) and T (y's), each with eps on its diagonal."""
    def root(c: torch.Tensor, p: float) -> torch.Tensor:
        val, vec = torch.linalg.eigh(c)
        return vec @ torch.diag(val.clamp(min=eps) ** p) @ vec.T

    eye = eps * torch.eye(3, dtype=x.dtype, device=x.device)
    mx, my = x.mean(0), y.mean(0)
    s, t = torch.cov((x - mx).T) + eye, torch.cov((y - my).T) + eye
    h, hi = root(s, 0.5), root(s, -0.5)
    a = hi @ root(h @ t @ h, 0.5) @ hi
    return torch.cat([a, (my - mx @ a)[None]], 0)


def anchored(x: torch.Tensor, target: torch.Tensor, sigma: float, mix: float = 1.0) -> torch.Tensor:
    """x [N, C, H, W] with its Gaussian low-pass (std `sigma` px, reflected at the border) moved
    `mix` of the way to `target`'s; the rest of x (its detail) stays its own."""
    x64 = x.detach().cpu().double()
    return (x64 + mix * torch.as_tensor(blur_frames(target, sigma) - blur_frames(x, sigma), device=x64.device)).to(x.dtype)


def prior_anchor(imgs: torch.Tensor, renders: torch.Tensor, sigma: float, mix: float = 1.0,
                 tiles: int = 1) -> torch.Tensor:
    """A sequence's decoded frames [N, 3, H, W] in [0, 1] -> the same anchored to the 3D prior:
    each frame's low-pass moves by `mix` towards its render's (`renders`, the same shape: what
    the ACM was conditioned on), whose colours are first mapped to the frames' by one affine fit
    over the sequence (`affine_colours`, on a `tiles` x `tiles` grid); clamped to [0, 1]. The renders hardly flicker, so the
    frames' coarse part flickers as little as `mix` makes it, with no correspondence between
    frames to get wrong (bench/vcm_anchor.py, docs/skyeyes.md "The VCM")."""
    if not 0 < mix <= 1 or sigma <= 0:
        raise ValueError(f"prior_anchor: sigma {sigma} (> 0), mix {mix} (0 < mix <= 1)")
    target = affine_colours(renders.float().cpu(), imgs.float().cpu(), tiles)
    return anchored(imgs.float().cpu(), target, sigma, mix).clamp(0.0, 1.0).to(imgs.device, imgs.dtype)


def carried_noise(own: torch.Tensor, coords: Callable[[int], tuple[np.ndarray, np.ndarray]],
                  share: float) -> torch.Tensor:
    """Motion-aligned starting noise of a sequence (`vcm_noise_flow`): own [N, C, h, w], each
    frame's own standard normal draw (`sample.frame_noise`), in sequence order -> [N, C, h, w],
    white like it: every pixel N(0, 1), independent of every other pixel of its frame.

    Frame 0 keeps its own. In frame j, the pixels the previous frame reaches (`coords(j)`:
    (uv, valid) on the h x w grid, `flow_coords` of the conditions at that size) come in groups,
    the k pixels whose nearest source is one pixel x of frame j - 1's noise. A group's mean
    times sqrt(k) is sqrt(share) x plus sqrt(1 - share) of the same of its own draw, and what
    the group holds beyond its mean is its own draw's (own minus the group's mean of own): the
    carried sample is split among the pixels it spreads to as an exact conditional draw (the
    discrete form of the noise transport of Chang et al., ICLR 2024, where nearest-neighbour
    copies would repeat one sample over a zoomed region). k = 1 gives sqrt(share) x + sqrt(1 -
    share) own; elsewhere the pixel is its own."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"carried_noise: share {share}, expected 0 <= share <= 1")
    n, c, h, w = own.shape
    dev = own.device
    out = [own[0]] if n else []
    for j in range(1, n):
        uv, valid = coords(j)
        if uv.shape[:2] != (h, w):
            raise ValueError(f"carried_noise: coordinates of shape {uv.shape[:2]} for noise of {(h, w)}")
        ix = np.clip(np.floor(uv[..., 0]).astype(np.int64), 0, w - 1)
        iy = np.clip(np.floor(uv[..., 1]).astype(np.int64), 0, h - 1)
        tgt = torch.as_tensor(np.flatnonzero(valid), device=dev)
        src = torch.as_tensor((iy * w + ix).ravel(), device=dev)[tgt]
        e = own[j].reshape(c, h * w).double()
        k = torch.bincount(src, minlength=h * w).double()[src]  # each target's group size
        group_e = torch.zeros(c, h * w, dtype=torch.float64, device=dev).index_add_(1, src, e[:, tgt])[:, src]
        carried = out[-1].reshape(c, h * w).double()[:, src]
        mean = share ** 0.5 * carried + (1.0 - share) ** 0.5 * group_e / k.sqrt()  # N(0, 1): the group's sum / sqrt(k)
        z = e.clone()
        z[:, tgt] = mean / k.sqrt() + e[:, tgt] - group_e / k
        out.append(z.reshape(c, h, w).to(own.dtype))
    return torch.stack(out) if n else own.clone()


def prior_ground(prior, scene) -> float | None:
    """The street's height (world z, up) under a Gaussian prior's fitted scene: `street_height` of
    its Gaussians' means under the ground cameras (`street_ceiling`); None where none lie there."""
    from reference.common.geometry.cloud import street_ceiling, street_height

    means = prior.scene_model(scene)[0].means.detach().cpu().numpy()
    return street_height(means[:, 2], below=street_ceiling([f.camera().c2w[2, 3] for f in scene.ground]), share=1.0)


#: `street_transfer`: the street is taken where it lies nearer than this (planar depth, m).
STREET_FAR_M = 30.0
#: `street_transfer`: a point of the street takes its colour from the frame that sees it at the
#: planar depth nearest this (m). NOTE: bench/vcm_street.py on SynthTown small's first test scene
#: (docs/skyeyes.md, "The street from one view"), LPIPS against the same frames without it: the
#: nearest view +0.011 (the ACM invents most where the prior's near road is empty, at the bottom
#: of the frame), 3 / 4 / 6 / 10 / 15 m +0.008 / +0.002 / +0.004 / +0.006 / +0.007, the warp
#: error within 0.001 of each other.
STREET_VIEW_M = 4.0
#: `street_transfer`'s minification of the owner's view: the Gaussians (px) it chooses from.
_MIP_SIGMAS = (0.0, 0.5, 1.0, 2.0, 4.0)


def street_points(cam: Camera, depth: np.ndarray, zg: float, *, tol: float = DEPTH_TOL,
                  far: float = STREET_FAR_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a frame sees the street, the plane z = zg (world z up), by its camera and the prior's
    planar depth [H, W] (+inf: nothing of the prior's): (points [HW, 3] where the pixels' rays
    meet the plane, their planar depth [HW] (+inf: the ray does not fall), street [HW]: the
    plane nearer than `far` and not behind the prior's surface (its depth, within `tol`, or
    +inf: the prior leaves most of the near road empty, bench/flow_accuracy.py))."""
    o, d = cam.rays(normalize=False)  # camera z = 1: t is planar depth
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (zg - o[:, 2]) / d[:, 2]
    t = np.where((d[:, 2] < 0) & (t > 0), t, np.inf)
    street = (t < far) & (t <= np.asarray(depth, np.float64).ravel() * (1.0 + tol))
    return o + d * np.where(np.isfinite(t), t, 0.0)[:, None], t, street


def _seen(uv: np.ndarray, masks: np.ndarray, h: int, w: int) -> np.ndarray:
    """uv [A, M, 2] in A frames -> [A, M]: within the frame's pixel centres and, at the nearest
    pixel, inside that frame's mask (masks [A, H*W])."""
    with np.errstate(invalid="ignore"):
        inside = (uv[..., 0] >= 0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= 0.5) & (uv[..., 1] <= h - 0.5)
    ix = np.clip(np.nan_to_num(uv[..., 0]).astype(np.int64), 0, w - 1)
    iy = np.clip(np.nan_to_num(uv[..., 1]).astype(np.int64), 0, h - 1)
    return inside & np.take_along_axis(masks, iy * w + ix, axis=1)


def _mip(x: np.ndarray, o: int, level: int, cache: dict) -> np.ndarray:
    """Frame o of x [N, H, W, 3] blurred by `_MIP_SIGMAS[level]` (made once per sequence)."""
    from scipy.ndimage import gaussian_filter

    if level == 0:
        return x[o]
    if (o, level) not in cache:
        cache[o, level] = gaussian_filter(x[o], (_MIP_SIGMAS[level], _MIP_SIGMAS[level], 0), mode="nearest")
    return cache[o, level]


def _blend(x: np.ndarray, target: np.ndarray, mask: np.ndarray, mix: float) -> np.ndarray:
    """A frame x [H, W, 3] moved `mix` of the way to target [H, W, 3] on mask [H, W] (bool), half
    of that on the mask's border pixels (those with a 3 x 3 neighbour outside it)."""
    from scipy.ndimage import uniform_filter

    m = mask.astype(np.float64)
    weight = mix * np.maximum(m * (uniform_filter(m, 3, mode="nearest") > 0.999), 0.5 * m)
    return x + weight[..., None] * (target - x)


def _as_frames(out: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """Frames [N, H, W, 3] (numpy) -> [N, 3, H, W] on `like`'s device and dtype, in [0, 1]."""
    return torch.as_tensor(out.transpose(0, 3, 1, 2).copy(), device=like.device).to(like.dtype).clamp(0.0, 1.0)


def street_transfer(imgs: torch.Tensor, cameras: list[Camera], depths: list[np.ndarray], zg: float, *,
                    mix: float = 1.0, view_m: float = STREET_VIEW_M, tol: float = DEPTH_TOL,
                    far: float = STREET_FAR_M) -> torch.Tensor:
    """A sequence's decoded frames [N, 3, H, W] in [0, 1] -> the same with the street taken from
    one view of each of its points (`vcm_street`), so that every frame shows it alike: where a
    frame sees the street (`street_points`), the point takes its colour from the frame that sees
    it at the planar depth nearest `view_m` (the same frame whichever frame asks; 0: the nearest
    view), that view blurred as much as it sees the point nearer (a Gaussian of 0.5 sqrt(s^2 -
    1) px for s times nearer, the nearest of `_MIP_SIGMAS`). By the poses and the plane, no
    flow: the road is the one surface whose geometry the method knows to a pixel (bench/
    flow_accuracy.py: the plane under the prior's Gaussians, median 0.42 px on the near road,
    where the renders' flow errs by 11 px). The rest of each frame stays its own. The street's
    pixels move `mix` of the way, half of it on its border pixels.

    cameras: the frames' cameras at H x W (`scaled_camera`); depths: the prior's planar depths
    [H, W] (`prior_depth`); zg: the street's height (world z, up; `prior_ground`)."""
    if not 0 < mix <= 1 or view_m < 0:
        raise ValueError(f"street_transfer: mix {mix} (0 < mix <= 1), view_m {view_m} (>= 0)")
    n, _, h, w = imgs.shape
    if not (n == len(cameras) == len(depths)):
        raise ValueError(f"street_transfer: {n} frames, {len(cameras)} cameras, {len(depths)} depths")
    x = imgs.detach().double().cpu().numpy().transpose(0, 2, 3, 1)  # [N, H, W, 3]
    parts = [street_points(c, d, zg, tol=tol, far=far) for c, d in zip(cameras, depths)]
    street = np.stack([p[2] for p in parts])  # [N, HW]
    c2ws, ks = np.stack([c.c2w for c in cameras]), np.stack([c.K for c in cameras])
    out, mips = x.copy(), {}
    for k, (pts, _, on) in enumerate(parts):
        target = x[k].reshape(-1, 3).copy()
        idx = np.flatnonzero(on)
        if len(idx):
            uv, z = project(pts[idx], np.ones(len(idx)), c2ws, ks)  # [N, M, 2], [N, M]
            seen = _seen(uv, street, h, w)
            pick = np.abs(z - view_m) if view_m else z
            owner = np.where(seen.any(axis=0), np.argmin(np.where(seen, pick, np.inf), axis=0), -1)
            scale = z[k] / np.take_along_axis(z, np.maximum(owner, 0)[None], 0)[0]
            want = 0.5 * np.sqrt(np.maximum(scale ** 2 - 1.0, 0.0))
            level = np.abs(want[:, None] - np.asarray(_MIP_SIGMAS)[None]).argmin(1)
            for o in np.unique(owner[owner >= 0]):  # -1: no frame sees it within its pixel centres
                for lv in np.unique(level[owner == o]):
                    sel = (owner == o) & (level == lv)
                    target[idx[sel]] = sample_bilinear(_mip(x, o, lv, mips), uv[o, sel])
        out[k] = _blend(x[k], target.reshape(h, w, 3), on.reshape(h, w), mix)
    return _as_frames(out, imgs)


def _sky_basis(d: np.ndarray, degree: int) -> np.ndarray:
    """Unit directions [M, 3] (world, z up) -> the monomials of their components up to `degree` [M, K]."""
    cols = [np.ones(len(d))]
    for total in range(1, degree + 1):
        for i in range(total + 1):
            for j in range(total - i + 1):
                k = total - i - j
                cols.append(d[:, 0] ** i * d[:, 1] ** j * d[:, 2] ** k)
    return np.stack(cols, 1)


def sky_fit(imgs: torch.Tensor, cameras: list[Camera], depths: list[np.ndarray], *, mix: float = 1.0,
            degree: int = 2, trim: float = 0.2, up: float = 0.0) -> torch.Tensor:
    """A sequence's frames [N, 3, H, W] in [0, 1] -> the same with the sky one smooth function of
    the direction for the whole sequence: where the prior sees nothing (depth +inf) above the
    horizon (world ray z > `up`), the colour moves `mix` of the way to a polynomial of degree
    `degree` in the ray's direction, least squares over every frame's sky pixels (refitted without
    the `trim` share of the largest residuals: the ghosts of buildings the generator paints); half
    of that on the sky's border pixels."""
    if not 0 < mix <= 1 or degree < 0 or not 0 <= trim < 1:
        raise ValueError(f"sky_fit: mix {mix} (0 < mix <= 1), degree {degree} (>= 0), trim {trim} (0 <= trim < 1)")
    n, _, h, w = imgs.shape
    if not (n == len(cameras) == len(depths)):
        raise ValueError(f"sky_fit: {n} frames, {len(cameras)} cameras, {len(depths)} depths")
    x = imgs.detach().double().cpu().numpy().transpose(0, 2, 3, 1)
    dirs, masks = [], []
    for c, dep in zip(cameras, depths):
        _, d = c.rays()
        dirs.append(d)
        masks.append(np.isinf(np.asarray(dep).ravel()) & (d[:, 2] > up))
    mask = np.stack(masks)
    if not mask.any():
        return imgs.clone()
    d_all = np.concatenate([d[m] for d, m in zip(dirs, masks)])
    y_all = np.concatenate([x[k].reshape(-1, 3)[m] for k, m in enumerate(masks)])
    step = max(1, len(d_all) // 200_000)
    a, y = _sky_basis(d_all[::step], degree), y_all[::step]
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    if trim:
        r = np.linalg.norm(a @ coef - y, axis=1)
        keep = r <= np.quantile(r, 1.0 - trim)
        coef = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
    out = x.copy()
    for k in range(n):
        if masks[k].any():
            target = np.clip(_sky_basis(dirs[k], degree) @ coef, 0, 1).reshape(h, w, 3)
            out[k] = _blend(x[k], target, masks[k].reshape(h, w), mix)
    return _as_frames(out, imgs)
