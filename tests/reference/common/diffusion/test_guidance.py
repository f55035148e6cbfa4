"""Classifier-free guidance on image and text (InstructPix2Pix) and the condition channels of the
core: the guided combination against its closed form, condition dropout against binomial
bounds, null conditions, the unconditional text embedding, conv_in widening at initialisation,
extra condition channels against an independent pixel-unshuffle."""

from __future__ import annotations

import math

import pytest
import torch

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

from reference.common.diffusion import core, guidance, train  # noqa: E402

TINY = core.CoreConfig(resolution=8, channels=(16, 32), attention=(False, True), head_dim=8, embed_dim=16,
                       norm_groups=4, conditioning="concat")

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


class StubModel(torch.nn.Module):
    """Returns x_t + A[image on][text on]: known outputs per condition. Records its calls."""

    A = {(False, False): 1.0, (True, False): 3.0, (True, True): 4.0, (False, True): 100.0}

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        self.w = torch.nn.Parameter(torch.zeros(1))  # a parameter, so the model has a device
        self.calls = []

    def forward(self, x_t, t, cond, text=None):
        self.calls.append((cond.clone(), text.clone()))
        image_on = cond[:, :self.cfg.image_cond_channels].flatten(1).abs().sum(1) > 0  # [B]
        add = torch.tensor([self.A[(bool(i), bool(s))] for i, s in zip(image_on, text)])
        return x_t + add.view(-1, 1, 1, 1)


def test_guided_prediction_is_the_closed_form():
    cfg = core.replace_config(TINY, coords=True)
    stub = StubModel(cfg)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 4, 4, generator=g)
    c = core.encode_cond(torch.rand(2, 3, 4, 4, generator=g) * 0.5 + 0.25, cfg)  # image channels never 0
    out = guidance.GuidedModel(stub, 1.5, 7.5)(x, torch.tensor([10, 10]), c)
    # By hand: 1 + 1.5 (3 - 1) + 7.5 (4 - 3) = 11.5; the text-only output (100) is never used.
    torch.testing.assert_close(out, x + 11.5)
    # The defaults are InstructPix2Pix's scales.
    assert (guidance.GuidedModel(stub).s_image, guidance.GuidedModel(stub).s_text) == (1.5, 7.5)
    # One call of 3B rows; the null image keeps the coordinate channels.
    conds, text = stub.calls[0]
    assert conds.shape[0] == 6 and text.tolist() == [False, False, False, False, True, True]
    assert torch.equal(conds[:2, :3], torch.zeros(2, 3, 4, 4)) and torch.equal(conds[:2, 3:], c[:, 3:])
    assert torch.equal(conds[2:4], c) and torch.equal(conds[4:], c)


def test_drop_rates_within_binomial_bounds_over_many_draws():
    """IP2P's 5% / 5% / 5% over 20000 training steps of batch 8, each from its own step generator."""
    drops = [guidance.draw_drops(8, train.step_generator(3, step), 0.05, 0.05, 0.05) for step in range(20000)]
    di = torch.cat([d[0] for d in drops])
    dt = torch.cat([d[1] for d in drops])
    n = len(di)
    for count, p in [((di & ~dt).sum(), 0.05), ((~di & dt).sum(), 0.05), ((di & dt).sum(), 0.05),
                     ((~di & ~dt).sum(), 0.85)]:
        sd = math.sqrt(n * p * (1 - p))
        assert abs(int(count) - n * p) < 5 * sd, (int(count), n * p, sd)  # 5 sigma: a false alarm ~6e-7
    # other rates are honoured too, and nothing is dropped at zero
    di, dt = guidance.draw_drops(100_000, torch.Generator().manual_seed(1), 0.2, 0.0, 0.1)
    assert abs(int((di & ~dt).sum()) - 20_000) < 5 * math.sqrt(1e5 * 0.2 * 0.8)
    assert int((~di & dt).sum()) == 0
    di, dt = guidance.draw_drops(1000, torch.Generator(), 0.0, 0.0, 0.0)
    assert not di.any() and not dt.any()
    with pytest.raises(ValueError, match="summing to <= 1"):
        guidance.draw_drops(4, torch.Generator(), 0.5, 0.5, 0.5)


def test_null_condition_zeroes_exactly_the_image_channels_of_the_dropped_rows():
    cfg = core.replace_config(TINY, patch=2, coords=True, cond_extra=2)
    c = core.encode_cond(torch.rand(3, 5, 8, 8) * 0.5 + 0.25, cfg)
    assert c.shape[1] == cfg.cond_channels == 12 + 8 + 2
    rows = torch.tensor([True, False, True])
    out = guidance.null_condition(c, cfg, rows)
    assert torch.equal(out[rows, :20], torch.zeros(2, 20, 4, 4))
    assert torch.equal(out[rows, 20:], c[rows, 20:])  # coordinates kept
    assert torch.equal(out[1], c[1])


def test_denoise_loss_hands_the_text_mask_to_the_model_and_splits_it_with_the_batch():
    cfg = TINY
    stub = StubModel(cfg)
    x0 = torch.rand(4, 3, 4, 4)
    c = core.encode_cond(torch.rand(4, 3, 4, 4), cfg)
    text = torch.tensor([True, False, False, True])
    train.denoise_loss(stub, core.train_scheduler(cfg), x0, c, torch.Generator().manual_seed(0), text=text,
                       part=(1, 2))
    assert stub.calls[-1][1].tolist() == [False, True]


def test_unconditional_embedding_leaves_other_weights_and_picks_rows():
    a = core.build_model(TINY, control=True, seed=0)
    b = core.build_model(core.replace_config(TINY, null_prompt=True), control=True, seed=0)
    assert a.null_prompt is None and b.null_prompt is not None
    sa, sb = a.state_dict(), b.state_dict()
    assert set(sb) - set(sa) == {"null_prompt"}
    assert all(torch.equal(sa[k], sb[k]) for k in sa)  # created last: the others initialise as before
    emb = b.text_embedding(3, torch.tensor([True, False, True]))
    assert torch.equal(emb[0], b.prompt[0]) and torch.equal(emb[1], b.null_prompt[0])
    assert torch.equal(emb[2], b.prompt[0])
    with pytest.raises(AssertionError, match="null_prompt"):
        a.text_embedding(2, torch.tensor([True, False]))


def test_widened_conv_in_keeps_the_output_at_initialisation():
    from diffusers import UNet2DConditionModel

    torch.manual_seed(0)
    unet = UNet2DConditionModel(sample_size=4, in_channels=4, out_channels=4, layers_per_block=1,
                                block_out_channels=(8, 16), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                                up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=16,
                                attention_head_dim=2, norm_num_groups=4).eval()
    g = torch.Generator().manual_seed(1)
    x, extra = torch.randn(2, 4, 4, 4, generator=g), torch.randn(2, 6, 4, 4, generator=g) * 3
    emb, t = torch.randn(2, 5, 16, generator=g), torch.tensor([3, 700])
    with torch.no_grad():
        want = unet(x, t, encoder_hidden_states=emb).sample
        core.widen_conv_in(unet, 10)
        got = unet(torch.cat([x, extra], 1), t, encoder_hidden_states=emb).sample
    assert unet.conv_in.in_channels == 10 and unet.config.in_channels == 10
    assert torch.count_nonzero(unet.conv_in.weight[:, 4:]) == 0
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="more than"):
        core.widen_conv_in(unet, 8)


def test_extra_condition_channels_follow_the_colour_folded_alike():
    """Against an independent unshuffle: channel c p^2 + i p + j at (y, x) is pixel (p y + i, p x + j)."""
    cfg = core.replace_config(TINY, patch=2, cond_extra=2, coords=True)
    img = torch.rand(1, 5, 8, 8, generator=torch.Generator().manual_seed(2))
    c = core.encode_cond(img, cfg)
    assert c.shape == (1, 12 + 8 + 2, 4, 4) and cfg.in_channels == 12 + 22
    for ch in range(5):
        for i in range(2):
            for j in range(2):
                torch.testing.assert_close(c[0, ch * 4 + i * 2 + j], img[0, ch, i::2, j::2] * 2 - 1)
    torch.testing.assert_close(c[0, 20, 0], torch.linspace(-1, 1, 4))  # x, then y
    torch.testing.assert_close(c[0, 21, :, 0], torch.linspace(-1, 1, 4))
    with pytest.raises(AssertionError):
        core.encode_cond(img[:, :3], cfg)
    with pytest.raises(ValueError, match="cond_extra"):
        core.replace_config(TINY, conditioning="controlnet", cond_extra=1)


def test_stage_keys_keep_their_old_form_while_the_new_fields_are_at_defaults():
    key = core.core_key(core.CoreConfig())
    assert not {"cond_extra", "null_prompt", "prompt_text", "beta_schedule"} & set(key)
    assert key == {k: v for k, v in __import__("dataclasses").asdict(core.CoreConfig()).items()
                   if k not in ("cond_extra", "null_prompt", "prompt_text", "flow_noise", "beta_schedule")}
    assert core.core_key(core.replace_config(TINY, beta_schedule="scaled_linear"))["beta_schedule"] == "scaled_linear"
    assert core.core_key(core.replace_config(TINY, cond_extra=2))["cond_extra"] == 2
