"""Tile-based front-to-back compositing with a custom autograd backward.

The forward walks the image in chunks of tiles (sorted by how many Gaussians touch them, so a
chunk's padding is small) and Gaussians in depth blocks with per-tile early stop. When a
gradient is wanted it keeps, per composited (pixel, Gaussian) pair of the blocks it processed,
the blending weight w = alpha T, the factor alpha / (1 - alpha) and a clamp mask; the backward
is then a handful of passes over those (no recomputation). Tiles list only the Gaussians whose
alpha can reach 1/255 inside the tile (exact ellipse-vs-rectangle test in `bin_tiles`), so few
(pixel, Gaussian) pairs are evaluated for nothing.

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
#: Tile side (px). 4x4 tiles waste fewer (pixel, Gaussian) pairs than 8x8 on small splats.
TILE = 4
#: Elements of one chunk's [tiles, pixels, gaussians] work arrays (bounds transient memory).
CHUNK_ELEMS = 1 << 21
#: Gaussians per depth block: tiles whose pixels have all stopped skip the remaining blocks.
BLOCK = 64
#: Floor of log2-space quantities before exp2 (2^-86 ~ 1e-26 stays a normal float32).
LOG2_FLOOR = -86.0
#: Relative and absolute slack on the binning's q bound, so float rounding can only add pairs
#: (which the per-pixel test then rejects), never drop one the compositing would use.
BIN_SLACK = 1e-4
#: The forward works with base-2 logs of alpha: torch's exp2 is ~3x faster than exp on this
#: CPU (0.29 vs 0.85 ms per 1M float32, AVX512 build), and the log base only rescales the GEMM's
#: coefficients and the thresholds.
LOG2E = 1.0 / math.log(2.0)
_LOG2_ALPHA_MIN = math.log2(ALPHA_MIN)
_LOG2_ALPHA_MAX = math.log2(ALPHA_MAX)


def _q_bound(opacities: torch.Tensor | None, n: int, dtype, device) -> torch.Tensor:
    """[N] largest Mahalanobis q a Gaussian can be composited at: q <= support^2 and
    o exp(-q/2) >= 1/255 (gsplat's opacity-aware radius); -1 if it can never pass."""
    q = torch.full((n,), SUPPORT_SIGMA ** 2, dtype=dtype, device=device)
    if opacities is not None:
        o = opacities.detach().to(dtype)
        q_alpha = 2 * torch.log((o * 255.0).clamp_min(1e-300))
        q = torch.minimum(q, torch.where(o > 0, q_alpha, torch.full_like(q, -math.inf)))
    return torch.where(q >= 0, q * (1 + BIN_SLACK) + BIN_SLACK, torch.full_like(q, -1.0))


def _band_x_range(a, b, c, q, ly, hy):
    """x-extent of {(x, y): a x^2 + 2b xy + c y^2 <= q, ly <= y <= hy} (a, c > 0, ac > b^2).

    The set is convex, so its x-extent is an interval. The right boundary x_r(y) =
    (-b y + sqrt(a q - det y^2)) / a is concave with its maximum at y = -b x_max / c, so over the
    band its maximum is at that y clamped to the band (likewise the left boundary's minimum).
    All arguments [R]; returns (x_lo, x_hi, nonempty).
    """
    det = a * c - b * b
    y_ext = torch.sqrt(q * a / det)
    lo, hi = torch.maximum(ly, -y_ext), torch.minimum(hy, y_ext)
    nonempty = lo <= hi
    x_ext = torch.sqrt(q * c / det)
    y_r = torch.minimum(torch.maximum(-b * x_ext / c, lo), hi)
    y_l = torch.minimum(torch.maximum(b * x_ext / c, lo), hi)
    x_hi = (-b * y_r + torch.sqrt((a * q - det * y_r * y_r).clamp_min(0))) / a
    x_lo = (-b * y_l - torch.sqrt((a * q - det * y_l * y_l).clamp_min(0))) / a
    return x_lo, x_hi, nonempty


def _argsort_depths(d: torch.Tensor) -> torch.Tensor:
    """Stable argsort of depths [N]. Positive floats sort like their bit patterns as integers,
    and torch's stable integer sort is a radix sort, ~3x faster than its float sort here."""
    if d.dtype in (torch.float32, torch.float64) and len(d) and bool((d > 0).all()):
        return torch.sort(d.contiguous().view(torch.int32 if d.dtype == torch.float32 else torch.int64),
                          stable=True).indices
    return torch.argsort(d, stable=True)


def bin_tiles(means2d: torch.Tensor, radii: torch.Tensor, depths: torch.Tensor, valid: torch.Tensor,
              width: int, height: int, tile: int = TILE, conics: torch.Tensor | None = None,
              opacities: torch.Tensor | None = None):
    """(tile, Gaussian) pairs sorted by tile then depth.

    Args:
        means2d: [N, 2] px. radii: [N] px support radius. depths: [N]. valid: [N] bool.
        conics: [N, 3] optional; with it a pair is kept only if the Gaussian's support ellipse
            (shrunk to where alpha >= 1/255 when `opacities` [N] is given too) reaches the
            rectangle of the tile's pixel centres (exact, per row of tiles). Without it, every
            tile the support square overlaps is listed. Either way the image is the same.

    Returns (gauss_ids [P] int64, tile_starts [T+1] int64, tiles_x, tiles_y).
    """
    tx, ty = (width + tile - 1) // tile, (height + tile - 1) // tile
    n_tiles = tx * ty
    with torch.no_grad():
        f64 = torch.float64
        ids = torch.nonzero(valid, as_tuple=False).squeeze(1)
        # Depth order first: pairs are generated in it, so a stable sort by tile id alone
        # (a small integer key) gives (tile, depth) order.
        ids = ids[_argsort_depths(depths.detach()[ids])]
        r = radii.detach()[ids].to(f64)
        if conics is not None:
            qmax = _q_bound(None if opacities is None else opacities[ids], len(ids), f64, ids.device)
            keep = qmax >= 0
            ids, r, qmax = ids[keep], r[keep], qmax[keep]
            cn = conics.detach()[ids].to(f64)
            det = (cn[:, 0] * cn[:, 2] - cn[:, 1] ** 2).clamp_min(1e-300)
            ry = torch.minimum(torch.sqrt(qmax * cn[:, 0] / det), r)  # y half-extent of q <= qmax
        else:
            ry = r
        m = means2d.detach()[ids].to(f64)
        mx_g, my_g = m[:, 0].contiguous(), m[:, 1].contiguous()
        # A pixel centre j + 0.5 inside [m - r, m + r] lies in tile floor(j / tile).
        y0 = torch.floor((my_g - ry - 0.5) / tile).clamp(0, ty - 1).long()
        y1 = torch.floor((my_g + ry - 0.5) / tile).clamp(0, ty - 1).long()
        # One entry per (Gaussian, row of tiles) it may touch (index_select: 1-D gathers are
        # several times cheaper than advanced indexing here).
        n_rows = (y1 - y0 + 1).clamp_min(0)
        owner = torch.repeat_interleave(n_rows)
        sel = lambda t, i: t.index_select(0, i)  # noqa: E731
        row = sel(y0 - (torch.cumsum(n_rows, 0) - n_rows), owner) + torch.arange(len(owner), device=owner.device)
        mx = sel(mx_g, owner)
        r_o = sel(r, owner)
        if conics is not None:
            # Pixel-centre rows of tile row `row` span [row t + 0.5, min(row t + t, H) - 0.5].
            my = sel(my_g, owner)
            ly = (row * tile).to(f64) + 0.5 - my
            hy = torch.clamp_max((row + 1) * tile, height).to(f64) - 0.5 - my
            x_lo, x_hi, nonempty = _band_x_range(sel(cn[:, 0].contiguous(), owner), sel(cn[:, 1].contiguous(), owner),
                                                 sel(cn[:, 2].contiguous(), owner), sel(qmax, owner), ly, hy)
            x_lo = torch.maximum(x_lo, -r_o)
            x_hi = torch.minimum(x_hi, r_o)
        else:
            x_lo, x_hi = -r_o, r_o
            nonempty = torch.ones_like(owner, dtype=torch.bool)
        x0 = torch.floor((mx + x_lo - 0.5) / tile).clamp_min(0).long()
        x1 = torch.floor((mx + x_hi - 0.5) / tile).clamp_max(tx - 1).long()
        n_cols = (x1 - x0 + 1).clamp_min(0) * nonempty
        # One entry per (tile, Gaussian) pair, still in depth order.
        pair_row = torch.repeat_interleave(n_cols)
        tile_id = (sel(row * tx + x0 - (torch.cumsum(n_cols, 0) - n_cols), pair_row)
                   + torch.arange(len(pair_row), device=pair_row.device))
        key_dtype = torch.int16 if n_tiles < 2 ** 15 else torch.int32  # radix sort on few bits
        perm = torch.sort(tile_id.to(key_dtype), stable=True).indices
        gauss_ids = sel(sel(sel(ids, owner), pair_row), perm)
        tile_counts = torch.bincount(tile_id, minlength=n_tiles)
        starts = torch.zeros(n_tiles + 1, dtype=torch.long, device=tile_id.device)
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


def _pixel_features(tile: int, dtype, device) -> torch.Tensor:
    """[P, 6] monomials (u^2, 2uv, v^2, u, v, 1) of tile-local pixel centres (u, v in px).

    The squared Mahalanobis distance of every pixel to every Gaussian of a tile is then one
    matmul with per-Gaussian coefficients (`_coefficients`), instead of ten elementwise passes.
    Tile-local coordinates keep the expansion well conditioned in float32.
    """
    oy, ox = torch.meshgrid(torch.arange(tile, device=device), torch.arange(tile, device=device), indexing="ij")
    u = ox.reshape(-1).to(dtype) + 0.5 - tile / 2
    v = oy.reshape(-1).to(dtype) + 0.5 - tile / 2
    return torch.stack([u * u, 2 * u * v, v * v, u, v, torch.ones_like(u)], -1)


def _tile_pixels(tiles: torch.Tensor, tx: int, tile: int, width: int, height: int):
    """Flat pixel indices [T, P] (0 outside the image), in-image mask [T, P], tile centres [T, 2] (px)."""
    dev = tiles.device
    oy, ox = torch.meshgrid(torch.arange(tile, device=dev), torch.arange(tile, device=dev), indexing="ij")
    px = (tiles % tx)[:, None] * tile + ox.reshape(1, -1)
    py = (tiles // tx)[:, None] * tile + oy.reshape(1, -1)
    inside = (px < width) & (py < height)
    flat = (py * width + px).masked_fill_(~inside, 0)
    centres = torch.stack([(tiles % tx) * tile, (tiles // tx) * tile], -1) + tile / 2
    return flat, inside, centres


def _gather(tiles, lo, hi, starts, gauss_ids):
    """Padded Gaussian indices [T, hi-lo] (depth slots lo..hi of each tile) and a real mask.

    Padding slots hold some valid index; the caller gives them an infinite alpha threshold.
    """
    s = starts[tiles]
    n = starts[tiles + 1] - s
    ar = torch.arange(lo, hi, device=starts.device)
    real = ar[None, :] < n[:, None]
    idx = (s[:, None] + ar[None, :]).clamp_max_(max(len(gauss_ids) - 1, 0))
    return gauss_ids[idx], real


#: Scale that turns a sign test into an exact 0/1 step by clamping: a nonzero difference of
#: two log-alphas near the thresholds is at least ~2^-50 (float64), so x 2^60 is >= 1.
_STEP = 2.0 ** 60


def _step(x: torch.Tensor) -> torch.Tensor:
    """1.0 where x > 0 else 0.0, in place on x: a multiply and a clamp, both vectorised passes
    (a compare plus masked_fill / where costs several times more on boolean masks)."""
    return x.mul_(_STEP).clamp_(0.0, 1.0)


def _stopping(Ta, stop, T_in, T_out, scalar):
    """Tiles with a pixel that stops in this block (`stop` [T, P]): mask the Gaussians it does not use (dense on
    those tiles only; a pixel that does not stop here uses all of its Gaussians). Returns T_out with the stopping
    pixels' T after their last used Gaussian, those tiles ts, dense, and the mask used (0/1; None: no ts)."""
    ts = stop.any(-1).nonzero().squeeze(1)
    dense = len(ts) > Ta.shape[0] // 2  # most tiles: cheaper on the whole block than gathered
    used = None
    if len(ts):
        Tsub = Ta if dense else Ta.index_select(0, ts)  # [k, B, P]
        used = _step(Tsub - torch.nextafter(scalar(T_MIN), scalar(0.0)))
        # T after the last used Gaussian (T_in if none) for the stopping pixels.
        n_used = used.sum(1).long()  # [k, P]
        val = Tsub.gather(1, (n_used - 1).clamp_min(0)[:, None, :])[:, 0, :]
        if dense:
            T_out = torch.where(stop, torch.where(n_used > 0, val, T_in), T_out)
        else:
            T_out[ts] = torch.where(stop[ts], torch.where(n_used > 0, val, T_in[ts]), T_out[ts])
    return T_out, ts, dense, used


def _block(feat, k, o, real, T_in, done_in, need_grad):
    """Composite one depth block of a chunk of tiles.

    Args: feat [P, 6]; k [6, T, B] coefficients of q (`_coefficients`); o [T, B]; real [T, B] bool; T_in [T, P] transmittance entering the block; done_in [T, P] bool.

    Returns w [T, B, P] blending weights alpha T, T_out [T, P], done_out [T, P], and for the
    backward (else None) r [T, B, P] = alpha / (1 - alpha) where alpha is not clamped at 0.99
    (else 0) and that not-clamped indicator lv [T, B, P] (0/1; None if all ones). w and r are 0 for Gaussians not
    composited; r is garbage on the columns of pixels that were already done when the block
    started, and the backward masks those per pixel (cheaper than per element).

    The work arrays are [T, B, P] (pixels innermost, so the distance and gradient matmuls are
    single GEMMs) and memory-bound, so every step is one vectorised pass where it can be, and no
    boolean [T, B, P] mask is built (masked_fill / where on them were the slowest passes).
    """
    dtype, dev = feat.dtype, feat.device

    def scalar(v: float) -> torch.Tensor:
        # A 0-dim operand on the data's device; `full` fills it there (`torch.tensor` would copy
        # from the host, a device sync per block on CUDA).
        return torch.full((), v, dtype=dtype, device=dev)

    log_amax = scalar(_LOG2_ALPHA_MAX)
    log2o = torch.log2(o.clamp_min(1e-30))
    # log2 alpha = log2 o - log2(e) q/2 as one matmul: the coefficients carry -log2(e)/2 and log2 o.
    k = (-0.5 * LOG2E) * k
    k[5] += log2o
    n_t, n_b = o.shape
    # [T B, 6] (a transposed view of the planes: the GEMM reads it as column-major) x [6, P].
    L = torch.mm(k.reshape(6, -1).T, feat.T).reshape(n_t, n_b, -1)  # [T, B, P], one GEMM
    # One threshold per Gaussian in log2 space: alpha >= 1/255 and inside the support ellipse
    # (q <= s^2  <=>  log2 alpha >= log2 o - log2(e) s^2/2); padding slots never pass. The
    # threshold is moved down one ulp so that `L - thr > 0` is exactly `L >= threshold`.
    thr = torch.clamp_min(log2o - (0.5 * LOG2E) * SUPPORT_SIGMA ** 2, _LOG2_ALPHA_MIN)
    thr = torch.nextafter(thr, scalar(-math.inf)).masked_fill_(~(real & (o > 0)), math.inf)
    keep = _step(torch.sub(L, thr[:, :, None]))
    # The backward needs which alphas are not clamped at 0.99; only a Gaussian with o > 0.99
    # can be clamped (0.989: margin for the rounding of L), so most blocks skip the mask
    # (None = all ones).
    lv = None
    if need_grad and bool((o > 0.989).any()):
        lv = _step(torch.rsub(L, torch.nextafter(log_amax, scalar(math.inf))))
    # Floor: exp2 never returns a subnormal (those run ~50x slower); it only touches skipped pairs.
    alpha = L.clamp_(LOG2_FLOOR, log_amax).exp2_().mul_(keep)
    om = torch.rsub(alpha, 1.0)
    # w = alpha T_before = T_after alpha / (1 - alpha); r = alpha / (1 - alpha) is the backward's.
    r = alpha.div_(om)
    # T after each Gaussian, by a cumulative product of (1 - alpha) with T_in folded into the
    # first factor (alpha <= 0.99, so it stays a normal float while T >= 1e-4, the only range
    # that is used). Stopped pixels enter with T = 0, so their weights are exactly 0.
    om[:, 0, :] *= T_in.masked_fill(done_in, 0.0)
    Ta = torch.cumprod(om, 1)
    last = Ta[:, -1, :].clone()
    # A Gaussian that would push T below 1e-4 is dropped with all later ones (T is monotone, so
    # the used ones are a prefix). Each pixel stops once, so the pixels where this happens are
    # few and handled apart; every other live pixel uses all its Gaussians.
    stop = ~done_in & (last < T_MIN)
    done_out = done_in | stop
    T_out = torch.where(done_out, T_in, last)
    T_out, ts, dense, used = _stopping(Ta, stop, T_in, T_out, scalar)
    w = Ta.mul_(r)
    if lv is not None:
        r.mul_(lv)
    if dense:
        w.mul_(used)
        if need_grad:
            r.mul_(used)
    elif len(ts):
        w.index_copy_(0, ts, w.index_select(0, ts).mul_(used))
        if need_grad:
            r.index_copy_(0, ts, r.index_select(0, ts).mul_(used))
    return w, T_out, done_out, (r if need_grad else None), lv


def _coefficients(mx, my, A, B, C):
    """q(u, v) = A u^2 + 2B uv + C v^2 + D u + E v + F for centres (mx, my) relative to the
    tile centre and conics (A, B, C), all [T, B]; returns planar [6, T, B] (stacking on a new
    last dim cost 2x the GEMM it feeds; the GEMM takes the planes as a transposed operand at
    the same speed)."""
    D = -2 * (A * mx + B * my)
    E = -2 * (B * mx + C * my)
    F = A * mx * mx + 2 * B * mx * my + C * my * my
    return torch.stack([A, B, C, D, E, F], 0)


def _pack(saved):
    """Flatten the per-chunk, per-block records of the forward into (tensors, layout), so they go
    through `save_for_backward` (freed after a backward that does not retain the graph)."""
    tensors, layout = [], []

    def put(t):
        if t is None:
            return -1
        tensors.append(t)
        return len(tensors) - 1

    for flat, inside, blocks in saved:
        layout.append((put(flat), put(inside),
                       [tuple(put(t) for t in (sel, g, *per_gauss, col, w, r, lv, live))
                        for sel, g, per_gauss, col, w, r, lv, live in blocks]))
    return tensors, layout


def _unpack(tensors, layout):
    """Inverse of `_pack`: per chunk (flat, inside, [(sel, g, mx, my, A, B, C, o, col, w, r, lv, live)])."""
    def get(i):
        return None if i < 0 else tensors[i]

    for fi, ii, blocks in layout:
        yield get(fi), get(ii), [tuple(get(i) for i in b) for b in blocks]


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height, tile, block,
                need_grad):
        n_ch = colors.shape[1]
        dtype, dev = colors.dtype, colors.device
        feat = _pixel_features(tile, dtype, dev)
        P = tile * tile
        # One per-Gaussian table, so a block gathers its Gaussians with one index_select; planar
        # (a row per quantity) so every per-Gaussian step runs on contiguous [T, B] planes.
        table = torch.cat([means2d, conics, opacities[:, None], colors], 1).to(dtype).T.contiguous()  # [6 + C, N]
        bg_cp = background.to(dtype)[None, :, None]  # [1, C, 1]
        # Pixels of tiles no Gaussian touches see only the background.
        out = background.to(dtype).expand(height * width, n_ch).clone()
        t_final = torch.ones(height * width, dtype=dtype, device=dev)
        saved = []  # per chunk: (flat, inside, blocks), for the backward
        for tiles, mcount in _chunks(starts, P, block):
            flat, inside, centres = _tile_pixels(tiles, tx, tile, width, height)
            n_t = len(tiles)
            # Colour sums channel-major, [T, C, P]: bmm(colours [T, C, B], w [T, B, P]) is ~4x
            # faster than producing [T, P, C] (a [P, B] x [B, C] product per tile).
            acc = torch.zeros(n_t, n_ch, P, dtype=dtype, device=dev)
            T = torch.ones(n_t, P, dtype=dtype, device=dev)
            # State of the tiles still compositing (early stop drops finished tiles from it).
            act = torch.arange(n_t, device=dev)
            a_tiles, a_centres = tiles, centres.to(dtype)
            a_counts = starts[tiles + 1] - starts[tiles]
            a_acc, a_T = torch.zeros_like(acc), torch.ones_like(T)
            a_done = torch.zeros(n_t, P, dtype=torch.bool, device=dev)
            blocks, sel = [], None
            for lo in range(0, mcount, block):
                g, real = _gather(a_tiles, lo, min(lo + block, mcount), starts, gauss_ids)
                planes = table.index_select(1, g.reshape(-1)).reshape(-1, *g.shape)  # [6 + C, T, B]
                # Centres relative to the tile centre.
                mx, my = planes[0] - a_centres[:, 0:1], planes[1] - a_centres[:, 1:2]
                A, B, C, o = planes[2], planes[3], planes[4], planes[5]
                col = planes[6:].transpose(0, 1)  # [T, C, B]
                w, T_blk, dn, r, lv = _block(feat, _coefficients(mx, my, A, B, C), o, real, a_T, a_done, need_grad)
                a_acc.baddbmm_(col, w)
                live = (~a_done).to(dtype)  # [T, P]: columns of done pixels in r are garbage
                if need_grad:
                    blocks.append((sel, g, (mx, my, A, B, C, o), col, w, r, lv, live))
                a_T, a_done, sel = T_blk, dn, None
                # Tiles whose pixels have all stopped, or whose list ends here, leave the set.
                fin = dn.all(-1) | (a_counts <= lo + block)
                if bool(fin.any()):
                    acc[act[fin]], T[act[fin]] = a_acc[fin], a_T[fin]
                    sel = ~fin
                    act, a_tiles, a_centres, a_counts = act[sel], a_tiles[sel], a_centres[sel], a_counts[sel]
                    a_acc, a_T, a_done = a_acc[sel], a_T[sel], a_done[sel]
                    if len(act) == 0:
                        break
            if len(act):
                acc[act], T[act] = a_acc, a_T
            rgb = torch.addcmul(acc, T[:, None, :], bg_cp).transpose(1, 2)  # [T, P, C]
            out[flat[inside]] = rgb[inside]
            t_final[flat[inside]] = T[inside]
            if need_grad:
                saved.append((flat, inside, blocks))
        tensors, layout = _pack(saved)
        ctx.save_for_backward(means2d, conics, opacities, colors, background, t_final, out, *tensors)
        ctx.meta = (tile, layout)
        return out.reshape(height, width, n_ch), (1.0 - t_final).reshape(height, width)

    @staticmethod
    def backward(ctx, g_out, g_alpha):
        means2d, conics, opacities, colors, background, t_final, out, *tensors = ctx.saved_tensors
        tile, layout = ctx.meta
        dtype, dev = colors.dtype, colors.device
        n_ch = colors.shape[1]
        feat_t = (-0.5 * _pixel_features(tile, dtype, dev)).T.contiguous()  # [6, P]; -1/2 from the coefficients
        g_out = g_out.reshape(-1, n_ch).to(dtype)
        g_alpha = torch.zeros_like(t_final) if g_alpha is None else g_alpha.reshape(-1).to(dtype)
        # Gradients of the per-Gaussian table, planar: (means2d, conics, opacity) [6, N], and
        # colours [C, N].
        d_table = torch.zeros(6, means2d.shape[0], dtype=dtype, device=dev)
        d_colors = torch.zeros(n_ch, means2d.shape[0], dtype=dtype, device=dev)  # planar, [C, N]
        d_bg = (g_out * t_final[:, None]).sum(0)  # d out / d bg = T_final everywhere
        # Per pixel: the whole composited sum <g, sum_j c_j w_j> and what the background and the
        # alpha output add behind every Gaussian; suffix sums then come from prefix sums.
        total = (g_out * (out - t_final[:, None] * background)).sum(-1)
        tail = (g_out * background).sum(-1) * t_final - g_alpha * t_final
        for flat, inside, blocks in _unpack(tensors, layout):
            # [T, C, P] (channel-major like the forward's sums); padding pixels carry nothing.
            a_go = (g_out[flat] * inside[..., None]).transpose(1, 2).contiguous()
            # dL/d log alpha_j = alpha_j T_j <g, c_j> - alpha_j / (1 - alpha_j) (sum over later
            # Gaussians + tail): with `pre` the prefix sum over earlier blocks minus (total +
            # tail), the bracket is the running prefix sum.
            a_pre = ((tail + total)[flat] * inside).neg_()  # [T, P]
            for sel, g, mx, my, A, B, C, o, col, w, r, lv, live in blocks:
                if sel is not None:
                    a_go, a_pre = a_go[sel], a_pre[sel]
                go = a_go  # done pixels have w = 0, so they take no part through go
                d_col = torch.bmm(go, w.transpose(1, 2))  # [T, C, B]
                gw = torch.bmm(col.transpose(1, 2), go).mul_(w)  # <dL/dout, c_j> w_j, [T, B, P]
                cs = torch.cumsum(gw, 1).add_((a_pre * live)[:, None, :])
                a_pre = cs[:, -1, :].clone()
                d_ar = cs.mul_(r).add_(gw if lv is None else gw.mul_(lv))  # dL / d log alpha
                # dL / d(A, B, C, D, E, F): six contiguous [T, B] planes from one GEMM with the
                # [6, P] operand on the left (~5x faster than d_ar [T B, P] @ [P, 6]).
                gA, gB, gC, gD, gE, gF = torch.mm(feat_t, d_ar.flatten(0, 1).T).unflatten(1, d_ar.shape[:2]).unbind(0)
                # Chain rule to the centre and conic (q = d^T Q d with d = p - m):
                # dL/dm = 2 Q (m gF - (gD, gE)), dL/dQ = G - (m v^T + v m^T) + m m^T gF.
                vx, vy = torch.addcmul(-gD, mx, gF), torch.addcmul(-gE, my, gF)
                ax, ay = vx - gD, vy - gE
                d6 = torch.stack([
                    2 * torch.addcmul(A * vx, B, vy),  # d mean x
                    2 * torch.addcmul(B * vx, C, vy),  # d mean y
                    torch.addcmul(gA, mx, ax),  # d conic a
                    torch.addcmul(torch.addcmul(gB, my, ax), mx, ay),  # d conic b
                    torch.addcmul(gC, my, ay),  # d conic c
                    # F also carries log o: dL/do = dL/d(log o) / o, and dL/d(log o) = -2 gF.
                    -2 * gF / o.clamp_min(1e-30),
                ], 0)
                gi = g.reshape(-1)
                d_table.index_add_(1, gi, d6.reshape(6, -1))
                d_colors.index_add_(1, gi, d_col.transpose(0, 1).reshape(n_ch, -1))
        d_means, d_conics, d_opac = d_table[0:2].T, d_table[2:5].T, d_table[5]
        return (d_means.to(means2d.dtype), d_conics.to(conics.dtype), d_opac.to(opacities.dtype),
                d_colors.T.to(colors.dtype), d_bg, None, None, None, None, None, None, None, None)


def composite(means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height, tile=TILE,
              block=BLOCK):
    """Composite binned Gaussians. Returns (out [H, W, C], alpha [H, W]).

    Args:
        means2d: [N, 2] px. conics: [N, 3] (a, b, c) inverse 2D covariance. opacities: [N] in [0, 1].
        colors: [N, C] (any C, e.g. RGB + depth). background: [C].
        gauss_ids, starts, tx: from `bin_tiles` (same `tile`).

    With a gradient wanted, the forward keeps w, alpha/(1-alpha) and a clamp mask for every
    (pixel, Gaussian) pair it evaluated (9 bytes each in float32) until the backward runs.
    """
    need_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, opacities, colors, background))
    return _Composite.apply(means2d, conics, opacities, colors, background, gauss_ids, starts, tx, width, height,
                           tile, block, need_grad)
