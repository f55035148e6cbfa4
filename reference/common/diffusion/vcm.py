"""View consistency module (Skyeyes Sec. 3.3) as a diffusers attention processor.

The self-attention layers (`attn1`) of the UNet and of the ControlNet branch are rewired to
spatial-temporal attention over a clip of F frames: the queries of frame i attend to the keys
and values of *all* F frames, with the layer's own (shared) projections:

    Q = W_Q x_i,   K = W_K x_{1:F},   V = W_V x_{1:F}.

Since every frame's queries see the same key set, this is one attention of the clip's F*L
tokens over the same F*L tokens; the batch is laid out clip-major ([B*F, ...], frames of a
clip adjacent). VCM adds no new kind of parameter: it changes the wiring of the self-attention
layers of the UNet's down and up blocks (`VCM_BLOCKS`), and training tunes *its own copy* of
those layers' projections, initialised from the appearance control module's. The ACM itself
stays frozen (the paper: "we freeze the appearance control module and train the view
consistency module") and generates each sequence's first frame.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import torch
import torch.nn.functional as F
from torch import nn


#: Which frames a frame's queries attend to (`ClipContext.keys`). "clip": every frame of the clip
#: (Skyeyes Sec. 3.3). "previous": its own and the frame before it (the first frame: its own), the
#: sparse-causal attention of vid2vid-zero (Wang et al. 2023) without its first-frame term, which a
#: 2-frame clip already has; a frame then copies from the frame it most resembles.
KEYS = ("clip", "previous")


class ClipContext:
    """Shared, mutable number of frames per clip (and which frames are keys), read by every
    installed processor and local layer."""

    def __init__(self, frames: int = 1, keys: str = "clip"):
        if keys not in KEYS:
            raise ValueError(f"VCM keys {keys!r}: expected one of {', '.join(KEYS)}")
        self.frames, self.keys = frames, keys


def _previous(x: torch.Tensor) -> torch.Tensor:
    """x [B, F, ...] -> the frame before each frame (the first frame's is itself)."""
    return torch.cat([x[:, :1], x[:, :-1]], dim=1)


class ClipSelfAttnProcessor:
    """Self-attention over all frames of a clip. Needs `ctx.frames` to divide the batch."""

    def __init__(self, ctx: ClipContext):
        self.ctx = ctx

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states=None,
                 attention_mask=None, temb=None, *args, **kwargs) -> torch.Tensor:
        assert encoder_hidden_states is None, "VCM replaces self-attention only (attn1)"
        assert attention_mask is None and attn.spatial_norm is None
        residual = hidden_states
        four_d = hidden_states.ndim == 4
        if four_d:
            bf, c, h, w = hidden_states.shape
            hidden_states = hidden_states.view(bf, c, h * w).transpose(1, 2)
        bf, length, _ = hidden_states.shape  # [B*F, L, C]
        f = self.ctx.frames
        assert bf % f == 0, f"batch {bf} is not a whole number of {f}-frame clips"
        b = bf // f
        if attn.group_norm is not None:
            hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)
        clip = hidden_states.reshape(b, f * length, -1)  # [B, F*L, C]: all tokens of a clip
        q, k, v = attn.to_q(clip), attn.to_k(clip), attn.to_v(clip)  # [B, F*L, D]
        heads = attn.heads
        d = q.shape[-1] // heads
        if self.ctx.keys == "previous":  # per frame: [previous frame's tokens, own tokens]
            q, k, v = (x.view(b, f, length, heads, d) for x in (q, k, v))
            k, v = (torch.cat([_previous(x), x], dim=2) for x in (k, v))  # [B, F, 2L, h, d]
            q, k, v = (x.reshape(b * f, -1, heads, d).transpose(1, 2) for x in (q, k, v))
        else:
            q, k, v = (x.view(b, f * length, heads, d).transpose(1, 2) for x in (q, k, v))  # [B, h, F*L, d]
        out = F.scaled_dot_product_attention(q, k, v, scale=attn.scale)
        out = out.transpose(1, 2).reshape(bf, length, heads * d)  # back to [B*F, L, D]
        out = attn.to_out[1](attn.to_out[0](out))
        if four_d:
            out = out.transpose(-1, -2).reshape(bf, c, h, w)
        if attn.residual_connection:
            out = out + residual
        return out / attn.rescale_output_factor


#: Where VCM goes. NOTE: Skyeyes Sec. 3.3: "VCM is integrated to the up-sampling and
#: down-sampling blocks of LDM": the self-attention of the denoising UNet's down and up blocks;
#: not its middle block and not the ControlNet branch (the frozen ACM).
VCM_BLOCKS = ("unet.down_blocks.", "unet.up_blocks.")


def self_attention_layers(model: nn.Module, prefixes: tuple[str, ...] | None = None) -> dict[str, nn.Module]:
    """name -> Attention module of every `attn1` (self-attention) in `model` whose name starts
    with one of `prefixes` (all when None)."""
    return {n: m for n, m in model.named_modules()
            if n.endswith("attn1") and (prefixes is None or n.startswith(prefixes))}


class _FrameLayer(nn.Module):
    """What the VCM's new layers share: a group norm, 1x1 q, k, v projections and a 1x1 output
    projection that starts at zero (the model starts as the ACM), over a batch of clips of
    `ctx.frames` frames."""

    def __init__(self, channels: int, ctx: ClipContext, groups: int):
        super().__init__()
        self.ctx = ctx
        self.norm = nn.GroupNorm(groups, channels, eps=1e-6)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.out = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def qkv_of(self, h: torch.Tensor):
        """h [B*F, C, H, W] -> (F, q, k, v), each [B*F, C, H, W]."""
        f = self.ctx.frames
        assert h.shape[0] % f == 0, f"batch {h.shape[0]} is not a whole number of {f}-frame clips"
        return (f, *self.qkv(self.norm(h)).chunk(3, dim=1))


class LocalFrameAttention(_FrameLayer):
    """Attention of each token over the previous frame's `window` x `window` neighbourhood of its
    position and its own token (the first frame of a clip: its own token alone), for the UNet's
    finer levels, which have no self-attention to rewire: a learned, local correspondence that can
    copy a frame's detail into the next one where the camera moved a little. One head; a new layer
    whose output projection starts at zero, so the model starts as the ACM (AnimateDiff's and
    Control-A-Video's temporal layers start so too)."""

    def __init__(self, channels: int, ctx: ClipContext, window: int, groups: int):
        if window < 1 or window % 2 == 0:
            raise ValueError(f"VCM local window {window}: expected an odd number >= 1")
        super().__init__(channels, ctx, groups)
        self.window = window

    def forward(self, h: torch.Tensor) -> torch.Tensor:  # [B*F, C, H, W]
        bf, c, hh, ww = h.shape
        f, q, k, v = self.qkv_of(h)
        r = self.window
        prev = [_previous(x.view(bf // f, f, c, hh, ww)).reshape(bf, c, hh, ww) for x in (k, v)]
        kn, vn = (F.unfold(x, r, padding=r // 2).view(bf, c, r * r, hh * ww) for x in prev)  # [B*F, C, r*r, HW]
        first = torch.zeros(bf // f, f, 1, 1, dtype=torch.bool, device=h.device)
        first[:, 0] = True  # the first frame has no previous frame: its neighbourhood is masked out
        q, k, v = (x.reshape(bf, c, 1, hh * ww) for x in (q, k, v))
        logits = torch.cat([(q * kn).sum(1), (q * k).sum(1)], dim=1) / c ** 0.5  # [B*F, r*r + 1, HW]
        mask = first.view(bf, 1, 1).expand(bf, r * r + 1, 1).clone()
        mask[:, -1] = False
        logits = logits.masked_fill(mask, float("-inf"))
        w = torch.softmax(logits.float(), dim=1).to(q.dtype)
        out = (torch.cat([vn, v], dim=2) * w[:, None]).sum(2).view(bf, c, hh, ww)
        return h + self.out(out)


class ClipFrameAttention(_FrameLayer):
    """The paper's spatial-temporal attention (every token of a clip over every token of its F
    frames) as a new layer, for the UNet's levels that have no self-attention to rewire: at `small`
    the UNet attends at its coarsest level only, where SD1.5 (the paper's) attends at three of its
    four. Heads of `head_dim` channels; the output projection starts at zero, so the model starts
    as the ACM (as `LocalFrameAttention`)."""

    def __init__(self, channels: int, ctx: ClipContext, groups: int, head_dim: int):
        if channels % head_dim:
            raise ValueError(f"VCM clip layer: {channels} channels are not whole heads of {head_dim}")
        super().__init__(channels, ctx, groups)
        self.heads = channels // head_dim

    def forward(self, h: torch.Tensor) -> torch.Tensor:  # [B*F, C, H, W]
        bf, c, hh, ww = h.shape
        f, *qkv = self.qkv_of(h)
        b, n, d = bf // f, self.heads, c // self.heads
        q, k, v = (x.reshape(b, f, n, d, hh * ww).permute(0, 2, 1, 4, 3).reshape(b, n, f * hh * ww, d)
                   for x in qkv)  # [B, heads, F*HW, d]: a clip's tokens
        out = F.scaled_dot_product_attention(q, k, v)
        out = out.view(b, n, f, hh * ww, d).permute(0, 2, 1, 4, 3).reshape(bf, c, hh, ww)
        return h + self.out(out)


class _WithLocal(nn.Module):
    """A resnet of the UNet followed by a `LocalFrameAttention` (or `ClipFrameAttention`) on its output."""

    def __init__(self, resnet: nn.Module, local: _FrameLayer):
        super().__init__()
        self.resnet, self.local = resnet, local

    def forward(self, *args, **kwargs):
        return self.local(self.resnet(*args, **kwargs))


def _plain_blocks(model: nn.Module, levels: int | None = None) -> list[tuple[str, nn.Module]]:
    """(name, block) of the UNet's down and up blocks that have no attention (its finer levels);
    with `levels`, only those of the `levels` coarsest such levels (down block i and up block
    n - 1 - i are level i)."""
    unet = model.unet
    n = len(unet.down_blocks)
    plain = sorted({i for i, blk in enumerate(unet.down_blocks) if not hasattr(blk, "attentions")}, reverse=True)
    keep = set(plain if levels is None else plain[:levels])
    return [(f"unet.{kind}.{i}", blk) for kind in ("down_blocks", "up_blocks")
            for i, blk in enumerate(getattr(unet, kind)) if not hasattr(blk, "attentions")
            and (i if kind == "down_blocks" else n - 1 - i) in keep]


def install_vcm(model: nn.Module, ctx: ClipContext | None = None, *, local_window: int = 0, levels: int = 0,
                seed: int = 0) -> ClipContext:
    """Replace the processor of every `attn1` of the UNet's down and up blocks (`VCM_BLOCKS`);
    with `local_window`, also follow every resnet of the down and up blocks without attention by
    a `LocalFrameAttention`; with `levels`, every resnet of the `levels` coarsest levels without
    attention by a `ClipFrameAttention` (new layers, initialised from `seed`, outputs at zero; the
    two exclude each other). Returns the context."""
    ctx = ctx or ClipContext()
    layers = self_attention_layers(model, VCM_BLOCKS)
    assert layers, "model has no self-attention layers in its down or up blocks"
    if local_window and levels:
        raise ValueError("VCM: local layers (vcm_local) and clip layers (vcm_levels) exclude each other")
    proc = ClipSelfAttnProcessor(ctx)
    for m in layers.values():
        m.set_processor(proc)
    if local_window or levels:
        first = next(iter(layers.values()))
        head_dim = first.to_q.out_features // first.heads  # the clip layers' heads are the UNet's
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            for _, blk in _plain_blocks(model, levels or None):
                for j, res in enumerate(blk.resnets):
                    groups = res.norm2.num_groups
                    new = (LocalFrameAttention(res.out_channels, ctx, local_window, groups) if local_window
                           else ClipFrameAttention(res.out_channels, ctx, groups, head_dim))
                    blk.resnets[j] = _WithLocal(res, new.to(next(res.parameters()).device))
    model._vcm_context = ctx  # noqa: SLF001  (found again by `clip_frames`)
    return ctx


def vcm_parameter_names(model: nn.Module) -> list[str]:
    """Prefixes of the parameters VCM trains: the projections of the `attn1` layers it rewires
    and its new layers (local or clip), where installed."""
    local = [f"{n}." for n, m in model.named_modules() if isinstance(m, _FrameLayer)]
    return [f"{n}." for n in self_attention_layers(model, VCM_BLOCKS)] + local


@contextlib.contextmanager
def clip_frames(model: nn.Module, frames: int) -> Iterator[None]:
    """Within the block, the model's batch is read as clips of `frames` frames."""
    ctx: ClipContext = model._vcm_context  # noqa: SLF001
    old, ctx.frames = ctx.frames, frames
    try:
        yield
    finally:
        ctx.frames = old


def reference_clip_attention(attn, x: torch.Tensor, frames: int) -> torch.Tensor:
    """Slow reference: loop over query frames i, softmax(Q_i K_{1:F}^T / sqrt(d)) V_{1:F} per head.

    x [B*F, L, C] -> [B*F, L, C_out]. For tests only (no group norm, no residual).
    """
    bf, length, _ = x.shape
    b = bf // frames
    d = attn.to_q.out_features // attn.heads
    outs = []
    for j in range(b):
        xs = x[j * frames:(j + 1) * frames]  # [F, L, C]
        kv = xs.reshape(1, frames * length, -1)[0]  # [F*L, C]
        k, v = attn.to_k(kv), attn.to_v(kv)  # [F*L, D]
        for i in range(frames):
            q = attn.to_q(xs[i])  # [L, D]
            heads = []
            for h in range(attn.heads):
                s = slice(h * d, (h + 1) * d)
                w = torch.softmax(q[:, s] @ k[:, s].T * attn.scale, dim=-1)
                heads.append(w @ v[:, s])
            outs.append(attn.to_out[0](torch.cat(heads, dim=-1)))
    return torch.stack(outs)
