"""The view consistency module's other wirings (issue 36): "previous" keys (each frame over its own
and the previous frame's tokens) and the local layers of the UNet's finer levels, each against a
slow loop written from its definition; both start as the ACM and are causal within a clip."""

from __future__ import annotations

import math

import pytest
import torch

from reference.common.diffusion import core, vcm

TINY = core.CoreConfig(resolution=16, channels=(16, 32), attention=(False, True), head_dim=8, embed_dim=16,
                       norm_groups=4, prediction="epsilon")

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


def _slow_previous_attention(attn, x: torch.Tensor, frames: int) -> torch.Tensor:
    """x [B*F, L, C]: frame i's queries over the keys of frames (i - 1, i) (frame 0: its own twice,
    the same softmax as once), each head by a loop over frames."""
    bf, length, _ = x.shape
    d = attn.to_q.out_features // attn.heads
    out = []
    for j in range(bf // frames):
        xs = x[j * frames:(j + 1) * frames]
        for i in range(frames):
            kv = torch.cat([xs[max(i - 1, 0)], xs[i]])  # [2L, C]
            q, k, v = attn.to_q(xs[i]), attn.to_k(kv), attn.to_v(kv)
            heads = []
            for h in range(attn.heads):
                s = slice(h * d, (h + 1) * d)
                heads.append(torch.softmax(q[:, s] @ k[:, s].T * attn.scale, dim=-1) @ v[:, s])
            out.append(attn.to_out[0](torch.cat(heads, dim=-1)))
    return torch.stack(out)


def test_previous_keys_match_slow_reference():
    m = core.build_model(TINY, control=True, seed=0).eval()
    attn = next(iter(vcm.self_attention_layers(m).values()))
    proc = vcm.ClipSelfAttnProcessor(vcm.ClipContext(3, keys="previous"))
    x = torch.randn(6, 10, attn.to_q.in_features)  # 2 clips x 3 frames, 10 tokens
    with torch.no_grad():
        got, want = proc(attn, x), _slow_previous_attention(attn, x, 3)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="VCM keys"):
        vcm.ClipContext(2, keys="all")


def _slow_local(layer: vcm.LocalFrameAttention, h: torch.Tensor, frames: int) -> torch.Tensor:
    """Token by token: softmax over the previous frame's window (out-of-frame neighbours are zero
    keys and values, as zero padding makes them) and its own token; the first frame: its own."""
    c = h.shape[1]
    q, k, v = layer.qkv(layer.norm(h)).chunk(3, dim=1)
    r = layer.window // 2
    out = torch.zeros_like(h)
    for n in range(h.shape[0]):
        first = n % frames == 0
        for y in range(h.shape[2]):
            for x in range(h.shape[3]):
                keys, vals = [k[n, :, y, x]], [v[n, :, y, x]]
                for dy in range(-r, r + 1):
                    for dx in range(-r, r + 1):
                        if first:
                            continue
                        yy, xx = y + dy, x + dx
                        inside = 0 <= yy < h.shape[2] and 0 <= xx < h.shape[3]
                        keys.append(k[n - 1, :, yy, xx] if inside else torch.zeros(c))
                        vals.append(v[n - 1, :, yy, xx] if inside else torch.zeros(c))
                w = torch.softmax(torch.stack([q[n, :, y, x] @ kk for kk in keys]) / math.sqrt(c), dim=0)
                out[n, :, y, x] = (w[:, None] * torch.stack(vals)).sum(0)
    return h + layer.out(out)


def test_local_layer_matches_slow_reference():
    torch.manual_seed(0)
    ctx = vcm.ClipContext(3)
    layer = vcm.LocalFrameAttention(8, ctx, window=3, groups=2)
    with torch.no_grad():  # a trained layer: the zero output projection would hide everything
        layer.out.weight.normal_(0, 0.5)
        layer.out.bias.normal_(0, 0.1)
        h = torch.randn(6, 8, 5, 4)  # 2 clips x 3 frames, a frame that is not square
        torch.testing.assert_close(layer(h), _slow_local(layer, h, 3), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="odd"):
        vcm.LocalFrameAttention(8, ctx, window=4, groups=2)


def _perturbed_outputs(m, frames: int):
    g = torch.Generator().manual_seed(0)  # the same inputs for every model
    x, t, c = torch.randn(frames, 3, 16, 16, generator=g), torch.full((frames,), 500), torch.rand(frames, 3, 16, 16, generator=g)
    outs = []
    with torch.no_grad(), vcm.clip_frames(m, frames):
        for k in (None, *range(frames)):
            xk = x.clone()
            if k is not None:
                xk[k] += 1.0
            outs.append(m(xk, t, c))
    return outs


def test_local_layers_start_as_the_acm_are_trained_and_are_causal():
    base = core.build_model(TINY, control=True, seed=0).eval()
    plain, local = (base, core.build_model(TINY, control=True, seed=0).eval())
    vcm.install_vcm(plain, vcm.ClipContext(keys="previous"))
    vcm.install_vcm(local, vcm.ClipContext(keys="previous"), local_window=3, seed=2)
    names = vcm.vcm_parameter_names(local)
    assert [n for n in names if ".local." in n or n.endswith("local.")], names
    layers = [m for m in local.modules() if isinstance(m, vcm.LocalFrameAttention)]
    # TINY's level without attention: 1 resnet in its down block, 2 in its up block
    assert len(layers) == 3 and all(m.window == 3 for m in layers)
    trained = core.trainable(local, names)
    assert sum(p.numel() for p in trained) > sum(p.numel() for p in core.trainable(plain, vcm.vcm_parameter_names(plain)))
    a, b = _perturbed_outputs(plain, 3)[0], _perturbed_outputs(local, 3)[0]
    torch.testing.assert_close(a, b)  # zero output projections: the model starts as without them
    with torch.no_grad():
        for m in layers:
            m.out.weight.normal_(0, 0.3)
    ref, *pert = _perturbed_outputs(local, 3)
    torch.testing.assert_close(pert[2][:2], ref[:2])  # a later frame never reaches an earlier one
    torch.testing.assert_close(pert[1][:1], ref[:1])
    assert (pert[0][1] - ref[1]).abs().max() > 1e-4  # the previous frame does


def _slow_clip_layer(layer: vcm.ClipFrameAttention, h: torch.Tensor, frames: int) -> torch.Tensor:
    """Token by token and head by head: softmax(q . k / sqrt(d)) over every token of every frame of
    its clip (the paper's attention, written from its definition)."""
    c, heads = h.shape[1], layer.heads
    d = c // heads
    q, k, v = layer.qkv(layer.norm(h)).chunk(3, dim=1)
    out = torch.zeros_like(h)
    for n in range(h.shape[0]):
        clip = range(n - n % frames, n - n % frames + frames)
        keys = torch.stack([k[m, :, y, x] for m in clip for y in range(h.shape[2]) for x in range(h.shape[3])])
        vals = torch.stack([v[m, :, y, x] for m in clip for y in range(h.shape[2]) for x in range(h.shape[3])])
        for y in range(h.shape[2]):
            for x in range(h.shape[3]):
                for e in range(heads):
                    s = slice(e * d, (e + 1) * d)
                    w = torch.softmax(keys[:, s] @ q[n, s, y, x] / math.sqrt(d), dim=0)
                    out[n, s, y, x] = w @ vals[:, s]
    return h + layer.out(out)


def test_clip_layer_matches_slow_reference():
    torch.manual_seed(0)
    layer = vcm.ClipFrameAttention(8, vcm.ClipContext(3), groups=2, head_dim=4)
    with torch.no_grad():  # a trained layer: the zero output projection would hide everything
        layer.out.weight.normal_(0, 0.5)
        layer.out.bias.normal_(0, 0.1)
        h = torch.randn(6, 8, 3, 4)  # 2 clips x 3 frames, a frame that is not square
        torch.testing.assert_close(layer(h), _slow_clip_layer(layer, h, 3), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="whole heads"):
        vcm.ClipFrameAttention(8, vcm.ClipContext(3), groups=2, head_dim=3)


THREE = core.CoreConfig(resolution=16, channels=(8, 16, 16), attention=(False, False, True), head_dim=8,
                        embed_dim=16, norm_groups=4, prediction="epsilon")


@pytest.mark.parametrize("levels, where", [(1, {"unet.down_blocks.1", "unet.up_blocks.1"}),
                                           (2, {"unet.down_blocks.0", "unet.down_blocks.1", "unet.up_blocks.1",
                                                "unet.up_blocks.2"})])
def test_clip_layers_go_to_the_coarsest_levels_without_attention_start_as_the_acm_and_link_a_clip(levels, where):
    """`small`'s shape (attention at the coarsest of three levels): levels=1 puts the layers at the
    middle level (down block 1, up block 1), 2 at both finer ones; the model starts as without them;
    once trained, every frame of a clip reaches every other (the paper's attention is not causal)
    and no other clip."""
    plain, clip = core.build_model(THREE, control=False, seed=0).eval(), core.build_model(THREE, control=False, seed=0).eval()
    vcm.install_vcm(plain)
    vcm.install_vcm(clip, levels=levels, seed=2)
    found = {n.rsplit(".resnets.", 1)[0] for n, m in clip.named_modules() if isinstance(m, vcm.ClipFrameAttention)}
    assert found == where
    names = vcm.vcm_parameter_names(clip)
    assert sum(p.numel() for p in core.trainable(clip, names)) > sum(
        p.numel() for p in core.trainable(plain, vcm.vcm_parameter_names(plain)))
    torch.testing.assert_close(_perturbed_outputs(plain, 3)[0], _perturbed_outputs(clip, 3)[0])
    with torch.no_grad():
        for m in clip.modules():
            if isinstance(m, vcm.ClipFrameAttention):
                m.out.weight.normal_(0, 0.3)
    ref, *pert = _perturbed_outputs(clip, 3)
    assert (pert[2][0] - ref[0]).abs().max() > 1e-4  # a later frame reaches an earlier one
    assert (pert[0][2] - ref[2]).abs().max() > 1e-4
    g = torch.Generator().manual_seed(0)
    x, t, c = torch.randn(4, 3, 16, 16, generator=g), torch.full((4,), 500), torch.rand(4, 3, 16, 16, generator=g)
    x2 = x.clone()
    x2[0] += 1.0
    with torch.no_grad(), vcm.clip_frames(clip, 2):
        torch.testing.assert_close(clip(x, t, c)[2:], clip(x2, t, c)[2:])  # clip 2 never sees clip 1
    with pytest.raises(ValueError, match="exclude each other"):
        vcm.install_vcm(core.build_model(THREE, control=False, seed=0), local_window=3, levels=1)
