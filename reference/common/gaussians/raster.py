"""Tile-based front-to-back compositing with a custom backward that recomputes per tile.

Forward and backward both walk the image in chunks of 8x8 tiles (tiles sorted by how many
Gaussians touch them, so a chunk's padding is small) and never keep per-pixel x per-Gaussian
intermediates beyond one chunk: the backward recomputes alphas and transmittances from the
per-Gaussian inputs and the saved final transmittance.

Compositing rule (3DGS, diff-gaussian-rasterization `renderCUDA`): Gaussians in increasing
depth; alpha = min(0.99, o exp(-q/2)), skipped if alpha < 1/255; a Gaussian whose alpha would
bring the transmittance below 1e-4 is not composited, nor any after it.
"""

from __future__ import annotations

import math

import torch

from .project import SUPPORT_SIGMA

#: NOTE: thresholds of 3DGS `renderCUDA` (alpha skip 1/255, clamp 0.99, transmittance 1e-4).
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
TILE = 8
#: Elements of one chunk's [tiles, pixels, gaussians] work arrays (bounds memory).
CHUNK_ELEMS = 1 << 22
#: Gaussians per depth block: tiles whose pixels have all stopped skip the remaining blocks.
BLOCK = 128
#: Floor of log-space quantities (e^-60 ~ 1e-26 stays a normal float32).
LOG_FLOOR = -60.0


def bin_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, valid: torch.Tensor,
              width: int, height: int, tile: int = TILE):
    """(tile, Gaussian) pairs sorted by tile then depth.

    Args:
        means2d: [N, 2] px. radii: [N] px support radius. depths: [N]. valid: [N] bool.

    Returns (gauss_ids [P] int64, tile_starts [T+1] int64, tiles_x, tiles_y).
    """
    tx, ty = (width + tile - 1) // tile, (height + tile - 1) // tile
    n_tiles = tx * ty
    ids = torch.nonzero(valid, as_tuple=False).squeeze(1)
    with torch.no_grad():
        m, r = means2d[ids].detach().float(), radii[ids].detach().float()
        # A pixel centre j + 0.5 inside [m - r, m + r] lies in tile floor(j / tile).
        x0 = torch.floor((m[:, 0] - r - 0.5) / tile).clamp(0, tx - 1).long()
        x1 = torch.floor((m[:, 0] + r) / tile).clamp(0, tx - 1).long()
        y0 = torch.floor((m[:, 1] - r - 0.5) / tile).clamp(0, ty - 1).long()
        y1 = torch.floor((m[:, 1] + r) / tile).clamp(0, ty - 1).long()
        w, h = x1 - x0 + 1, y1 - y0 + 1
        counts = w * h
        total = int(counts.sum())
        owner = torch.repeat_interleave(torch.arange(len(ids)), counts)  # [P] index into ids
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(total) - first[owner]
        lx = local % w[owner]
        ly = local // w[owner]
        tile_id = (y0[owner] + ly) * tx + (x0[owner] + lx)
        # Depth rank as an integer so (tile, depth) sorts with one int64 key.
        order = torch.argsort(depths[ids].detach(), stable=True)
        rank = torch.empty_like(order)
        rank[order] = torch.arange(len(ids))
        key = tile_id * max(len(ids), 1) + rank[owner]
        key, perm = torch.sort(key, stable=True)
        gauss_ids = ids[owner[perm]]
        tile_counts = torch.bincount(tile_id, minlength=n_tiles)
        starts = torch.zeros(n_tiles + 1, dtype=torch.long)
        starts[1:] = torch.cumsum(tile_counts, 0)
    return gauss_ids, starts, tx, ty


def _chunks(starts: torch.Tensor, pix_per_tile: int, block: int):
    """Yield (tile index tensor, max count) chunks of non-empty tiles with bounded work size.

    Tiles are sorted by count so a chunk's padding is small; a chunk's work arrays hold at most
    CHUNK_ELEMS elements per depth block of `block` Gaussians.
    """
    counts = (starts[1:] - starts[:-1])
    nz = torch.nonzero(counts > 0, as_tuple=False).squeeze(1)
    if len(nz) == 0:
        return
    order = nz[torch.argsort(counts[nz], stable=True)]
    c_sorted = counts[order].tolist()
    i, n = 0, len(order)
    while i < n:
        j = i + 1
        while j < n and (j - i + 1) * pix_per_tile * min(c_sorted[j], block) <= CHUNK_ELEMS:
            j += 1
        yield order[i:j], c_sorted[j - 1]
        i = j


def _pixel_features(tile: int, dtype) -> torch.Tensor:
    """[P, 6] monomials (u^2, 2uv, v^2, u, v, 1) of tile-local pixel centres (u, v in px).

    The squared Mahalanobis distance of every pixel to every Gaussian of a tile is then one
    matmul with per-Gaussian coefficients (`_coefficients`), instead of ten elementwise passes.
    Tile-local coordinates keep the expansion well conditioned in float32.
    """
    oy, ox = torch.meshgrid(torch.arange(tile), torch.arange(tile), indexing="ij")
    u = ox.reshape(-1).to(dtype) + 0.5 - tile / 2
    v = oy.reshape(-1).to(dtype) + 0.5 - tile / 2
    return torch.stack([u * u, 2 * u * v, v * v, u, v, torch.ones_like(u)], -1)


def _tile_pixels(tiles: torch.Tensor, tx: int, tile: int, width: int, height: int):
    """Flat pixel indices [T, P], in-image mask [T, P], tile centres [T, 2] (px)."""
    oy, ox = torch.meshgrid(torch.arange(tile), torch.arange(tile), indexing="ij")
    px = (tiles % tx)[:, None] * tile + ox.reshape(1, -1)
    py = (tiles // tx)[:, None] * tile + oy.reshape(1, -1)
    inside = (px < width) & (py < height)
    flat = torch.where(inside, py * width + px, torch.zeros_like(px))
    centres = torch.stack([(tiles % tx) * tile, (tiles // tx) * tile], -1) + tile / 2
    return flat, inside, centres


def _gather(tiles, lo, hi, starts, gauss_ids):
    """Padded Gaussian indices [T, hi-lo] (depth slots lo..hi of each tile) and a real mask."""
    s = starts[tiles]
    n = starts[tiles + 1] - s
    ar = torch.arange(lo, hi)
    real = ar[None, :] < n[:, None]
    idx = torch.where(real, s[:, None] + ar[None, :], torch.zeros_like(real, dtype=torch.long))
    g = torch.where(real, gauss_ids[idx], torch.zeros_like(idx))
    return g, real


def _coefficients(m, cn):
    """q(u, v) = A u^2 + 2B uv + C v^2 + D u + E v + F for centres m [T, B, 2] relative to the
    tile centre and conics cn [T, B, 3]; returns [T, 6, B]."""
    A, B, C = cn.unbind(-1)
    mx, my = m.unbind(-1)
    D = -2 * (A * mx + B * my)
    E = -2 * (B * mx + C * my)
    F = A * mx * mx + 2 * B * mx * my + C * my * my
    return torch.stack([A, B, C, D, E, F], 1)


class _Block:
    """Recomputed state of one depth block of one chunk of tiles (forward and backward)."""

    def __init__(self, feat, tiles_c, g, real, means2d, conics, opacities, T_in, done_in):
        m = means2d[g] - tiles_c[:, None, :]  # [T, B, 2] relative to the tile centre
        cn = conics[g]
        o = opacities[g]
        self.m, self.cn, self.o = m, cn, o
        # log alpha = log o - q/2 as one matmul: the coefficients carry -1/2 and log o.
        k = -0.5 * _coefficients(m, cn)
        k[:, 5] = k[:, 5] + torch.log(o.clamp_min(1e-30))
        # Clamped so exp never returns a subnormal float: those run ~20x slower on x86 and the
        # clamp only touches alphas far below the 1/255 threshold.
        self.raw = torch.exp(torch.matmul(feat, k).clamp_min(LOG_FLOOR))  # o exp(-q/2), [T, P, B]
        # One threshold per Gaussian: alpha >= 1/255 and inside the 3-sigma ellipse
        # (q <= 9  <=>  raw >= o e^-4.5); padding slots never pass.
        thr = torch.clamp_min(o * math.exp(-0.5 * SUPPORT_SIGMA ** 2), ALPHA_MIN)
        thr = torch.where(real & (o > 0), thr, torch.full_like(thr, math.inf))
        self.keep = self.raw >= thr[:, None, :]
        alpha = torch.where(self.keep, self.raw.clamp_max(ALPHA_MAX), torch.zeros_like(self.raw))
        self.om = 1.0 - alpha
        # Stopped pixels enter with T = 0, so every `incl` is below 1e-4 and nothing is used.
        T_eff = torch.where(done_in, torch.zeros_like(T_in), T_in)
        # T after each Gaussian, as exp(cumsum(log)) floored at e^-60 (< 1e-4, so the result is
        # the same) instead of a cumprod that underflows into subnormals behind opaque layers.
        incl = T_eff[..., None] * torch.exp(torch.cumsum(torch.log(self.om), -1).clamp_min(LOG_FLOOR))
        # A Gaussian that would push T below 1e-4 is dropped with all later ones (incl is
        # monotone, so `used` is a prefix).
        self.used = incl >= T_MIN
        self.T = torch.cat([T_eff[..., None], incl[..., :-1]], -1)  # T before each Gaussian
        self.w = torch.where(self.used, alpha * self.T, torch.zeros_like(alpha))
        n_used = self.used.sum(-1)
        last = torch.gather(incl, -1, (n_used - 1).clamp_min(0)[..., None])[..., 0]
        self.T_out = torch.where(n_used > 0, last, T_in)
        self.done_out = done_in | (incl[..., -1] < T_MIN)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height, tile, block):
        n_ch = colors.shape[1]
        dtype = colors.dtype
        feat = _pixel_features(tile, dtype)
        out = torch.empty(height * width, n_ch, dtype=dtype)
        t_final = torch.ones(height * width, dtype=dtype)
        for tiles, mcount in _chunks(starts, tile * tile, block):
            flat, inside, centres = _tile_pixels(tiles, tx, tile, width, height)
            centres = centres.to(dtype)
            acc = torch.zeros(len(tiles), tile * tile, n_ch, dtype=dtype)
            T = torch.ones(len(tiles), tile * tile, dtype=dtype)
            done = torch.zeros(len(tiles), tile * tile, dtype=torch.bool)
            act = torch.arange(len(tiles))  # tiles still compositing (early stop drops them)
            for lo in range(0, mcount, block):
                g, real = _gather(tiles[act], lo, min(lo + block, mcount), starts, gauss_ids)
                b = _Block(feat, centres[act], g, real, means2d, conics, opacities, T[act], done[act])
                acc[act] += torch.bmm(b.w, colors[g])
                T[act], done[act] = b.T_out, b.done_out
                act = act[~b.done_out.all(-1)]
                if len(act) == 0:
                    break
            rgb = acc + T[..., None] * background
            out[flat[inside]] = rgb[inside]
            t_final[flat[inside]] = T[inside]
        # Pixels of tiles no Gaussian touches see only the background.
        empty = torch.ones(height * width, dtype=torch.bool)
        for tiles, _ in _chunks(starts, tile * tile, block):
            flat, inside, _ = _tile_pixels(tiles, tx, tile, width, height)
            empty[flat[inside]] = False
        out[empty] = background.to(dtype)
        ctx.save_for_backward(means2d, conics, opacities, colors, background, gauss_ids, starts, t_final, out)
        ctx.meta = (tx, width, height, tile, block)
        return out.reshape(height, width, n_ch), (1.0 - t_final).reshape(height, width)

    @staticmethod
    def backward(ctx, g_out, g_alpha):
        means2d, conics, opacities, colors, background, gauss_ids, starts, t_final, out = ctx.saved_tensors
        tx, width, height, tile, block = ctx.meta
        dtype = colors.dtype
        n_ch = colors.shape[1]
        feat = _pixel_features(tile, dtype)
        g_out = g_out.reshape(-1, n_ch).to(dtype)
        g_alpha = torch.zeros(height * width, dtype=dtype) if g_alpha is None else g_alpha.reshape(-1).to(dtype)
        d_means = torch.zeros_like(means2d)
        d_conics = torch.zeros_like(conics)
        d_opac = torch.zeros_like(opacities)
        d_colors = torch.zeros_like(colors)
        d_bg = (g_out * t_final[:, None]).sum(0)  # d out / d bg = T_final everywhere
        # Per pixel: the whole composited sum <g, sum_j c_j w_j> and what the background and the
        # alpha output add behind every Gaussian; suffix sums then come from prefix sums.
        total = (g_out * (out - t_final[:, None] * background)).sum(-1)
        tail = (g_out * background).sum(-1) * t_final - g_alpha * t_final
        for tiles, mcount in _chunks(starts, tile * tile, block):
            flat, inside, centres = _tile_pixels(tiles, tx, tile, width, height)
            centres = centres.to(dtype)
            go_all = g_out[flat] * inside[..., None]  # [T, P, C]; padding pixels carry nothing
            tot_all = total[flat] * inside
            tail_all = tail[flat] * inside
            T = torch.ones(len(tiles), tile * tile, dtype=dtype)
            done = torch.zeros(len(tiles), tile * tile, dtype=torch.bool)
            pre = torch.zeros(len(tiles), tile * tile, dtype=dtype)
            act = torch.arange(len(tiles))
            for lo in range(0, mcount, block):
                g, real = _gather(tiles[act], lo, min(lo + block, mcount), starts, gauss_ids)
                b = _Block(feat, centres[act], g, real, means2d, conics, opacities, T[act], done[act])
                go = go_all[act]
                gi = g.reshape(-1)
                d_colors.index_add_(0, gi, torch.bmm(b.w.transpose(1, 2), go).reshape(-1, n_ch))
                gc = torch.bmm(go, colors[g].transpose(1, 2))  # <dL/dout, c_j>, [T, P, B]
                incl_sum = torch.cumsum(gc * b.w, -1) + pre[act][..., None]
                after = tot_all[act][..., None] - incl_sum  # sum over later Gaussians
                d_a = b.T * gc - (after + tail_all[act][..., None]) / b.om
                live = b.used & b.keep & (b.raw <= ALPHA_MAX)
                d_ar = d_a * torch.where(live, b.raw, torch.zeros_like(d_a))  # dL / d log alpha
                dk = -0.5 * torch.matmul(feat.T, d_ar)  # dL / d(A, B, C, D, E, F), [T, 6, B]
                gA, gB, gC, gD, gE, gF = dk.unbind(1)
                # F also carries log o: dL/do = dL/d(log o) / o, and dL/d(log o) = -2 gF.
                d_opac.index_add_(0, gi, (-2 * gF / b.o.clamp_min(1e-30)).reshape(-1))
                A, B, C = b.cn.unbind(-1)
                mx, my = b.m.unbind(-1)
                dA = gA - 2 * mx * gD + mx * mx * gF
                dB = gB - 2 * my * gD - 2 * mx * gE + 2 * mx * my * gF
                dC = gC - 2 * my * gE + my * my * gF
                dmx = -2 * A * gD - 2 * B * gE + 2 * (A * mx + B * my) * gF
                dmy = -2 * B * gD - 2 * C * gE + 2 * (B * mx + C * my) * gF
                d_conics.index_add_(0, gi, torch.stack([dA, dB, dC], -1).reshape(-1, 3))
                d_means.index_add_(0, gi, torch.stack([dmx, dmy], -1).reshape(-1, 2))
                pre[act] = incl_sum[..., -1]
                T[act], done[act] = b.T_out, b.done_out
                act = act[~b.done_out.all(-1)]
                if len(act) == 0:
                    break
        return d_means, d_conics, d_opac, d_colors, d_bg, None, None, None, None, None, None, None


def composite(means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height, tile=TILE,
              block=BLOCK):
    """Composite binned Gaussians. Returns (out [H, W, C], alpha [H, W]).

    Args:
        means2d: [N, 2] px. conics: [N, 3] (a, b, c) inverse 2D covariance. opacities: [N] in [0, 1].
        colors: [N, C] (any C, e.g. RGB + depth). background: [C].
        gauss_ids, starts, tx: from `bin_tiles`.
    """
    return _Composite.apply(means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height,
                           tile, block)
