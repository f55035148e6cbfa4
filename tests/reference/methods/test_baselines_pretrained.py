"""`ip2p` and `gvg` with `--pretrained DIR`, on a Stable Diffusion 1.5-layout folder (a tiny
random one, `builders.tiny_sd`). ip2p: the UNet's conv_in widened with zero-initialised inputs
for the aerial view's latent (the pretrained UNet's output unchanged at initialisation), the
instruction and the empty prompt encoded by the frozen CLIP text encoder, end to end. gvg: the
projected colour's latent and the depth and mask averaged onto the latent grid, end to end."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)
import transformers  # noqa: F401

from builders.skyeyes import SIZE, StandInGeometryPrior, make_tiny_dataset  # noqa: E402
from builders.tiny_sd import RES, make_tiny_sd  # noqa: E402
from reference.common.diffusion import core  # noqa: E402
from reference.methods import gvg  # noqa: E402
from reference.methods.ip2p import INSTRUCTION, PRESETS, InstructPix2Pix  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


@pytest.fixture(scope="module")
def sd(tmp_path_factory) -> Path:
    return make_tiny_sd(tmp_path_factory.mktemp("sd") / "sd15")


def _method(sd, workdir) -> InstructPix2Pix:
    cfg = dataclasses.replace(PRESETS["small"], core=dataclasses.replace(PRESETS["small"].core, resolution=RES),
                              pretrained=str(sd), acm_steps=2, acm_batch=2, sample_steps=2, ckpt_every=1,
                              figure_frames=2, device="cpu", threads=1,
                              acm_anneal=0, mixed_precision="no")  # `small`'s budget, cut to 2 fp32 steps
    return InstructPix2Pix(cfg, workdir, progress=False)


def test_widened_pretrained_unet_predicts_as_before_at_initialisation(sd, tmp_path):
    from diffusers import UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    m = _method(sd, tmp_path / "w")
    c = m.config.core
    assert (c.conditioning, c.prediction, c.residual, c.coords, c.null_prompt) == ("concat", "epsilon", False, False, True)
    assert c.in_channels == 8  # the noisy latent + the aerial view's latent
    model = core.build_model(c, control=False)
    assert model.unet.conv_in.in_channels == 8 and torch.count_nonzero(model.unet.conv_in.weight[:, 4:]) == 0
    # the prompt is the instruction, the unconditional text the empty prompt, both encoded here independently
    tok, enc = CLIPTokenizer.from_pretrained(sd / "tokenizer"), CLIPTextModel.from_pretrained(sd / "text_encoder")
    with torch.no_grad():
        want = enc(tok([INSTRUCTION, ""], padding="max_length", max_length=77, return_tensors="pt").input_ids)[0]
    torch.testing.assert_close(model.prompt.detach(), want[:1])
    torch.testing.assert_close(model.null_prompt.detach(), want[1:])
    # whatever the aerial latent holds, the widened UNet predicts what the folder's UNet does
    unet = UNet2DConditionModel.from_pretrained(sd / "unet").eval()
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 4, RES // 8, RES // 8, generator=g)
    cond = core.encode_cond(torch.rand(2, 3, RES, RES, generator=g), c)
    assert cond.shape == (2, 4, RES // 8, RES // 8)  # the VAE latent of the aerial view
    t = torch.tensor([10, 900])
    with torch.no_grad():
        got = model(x, t, cond, text=torch.tensor([True, False]))
        ref = unet(x, t, encoder_hidden_states=torch.cat([want[:1], want[1:]])).sample
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-6)


def test_pretrained_ip2p_end_to_end(sd, tmp_path):
    from diffusers import UNet2DConditionModel

    ds = open_dataset(make_tiny_dataset(tmp_path / "ds", frames=3, seqs=1))
    m = _method(sd, tmp_path / "w")
    m.fit_train(ds)
    assert set(m.training) == {"acm"}
    assert not m.acm.prompt.requires_grad and not m.acm.null_prompt.requires_grad  # CLIP stays frozen
    before = UNet2DConditionModel.from_pretrained(sd / "unet").state_dict()
    after = m.acm.unet.state_dict()
    assert not torch.equal(after["conv_in.weight"][:, :4], before["conv_in.weight"])  # the UNet is fine-tuned
    scene = ds.split("test")[0]
    m.fit_scene(scene)
    for seq in scene.sequences.values():
        frames = np.stack(list(m.render_sequence(scene, seq)))
        assert frames.shape == (len(seq), SIZE, SIZE, 3) and np.isfinite(frames).all()
        assert frames.min() >= 0 and frames.max() <= 1


def test_pretrained_gvg_condition_on_the_latent_grid_end_to_end(sd, tmp_path):
    from diffusers import AutoencoderKL

    cfg = dataclasses.replace(gvg.PRESETS["small"], core=dataclasses.replace(gvg.PRESETS["small"].core, resolution=RES),
                              pretrained=str(sd), acm_steps=1, acm_batch=2, sample_steps=2, ckpt_every=1,
                              figure_frames=2, device="cpu", threads=1,
                              acm_anneal=0, mixed_precision="no")  # `small`'s budget, cut to 1 fp32 step
    m = gvg.GVG(cfg, tmp_path / "w", prior_method=StandInGeometryPrior(tmp_path / "p"), progress=False)
    c = m.config.core
    assert (c.conditioning, c.residual, c.coords, c.cond_extra, c.in_channels) == ("concat", False, False, 2, 4 + 4 + 2)
    # the colour's VAE latent, then depth and mask averaged over each latent cell (8 x 8 pixels), in [-1, 1]
    img = torch.rand(1, 5, RES, RES, generator=torch.Generator().manual_seed(3))
    cond = core.encode_cond(img, c)
    vae = AutoencoderKL.from_pretrained(sd / "vae")
    with torch.no_grad():
        latent = vae.encode(img[:, :3] * 2 - 1).latent_dist.mean * vae.config.scaling_factor
    torch.testing.assert_close(cond[:, :4], latent)
    cells = (img[:, 3:] * 2 - 1).reshape(1, 2, RES // 8, 8, RES // 8, 8).mean((3, 5))
    torch.testing.assert_close(cond[:, 4:], cells)
    ds = open_dataset(make_tiny_dataset(tmp_path / "ds", frames=3, seqs=1))
    m.fit_train(ds)
    assert m.acm.unet.conv_in.in_channels == 10
    scene = ds.split("test")[0]
    m.fit_scene(scene)
    for seq in scene.sequences.values():
        frames = np.stack(list(m.render_sequence(scene, seq)))
        assert frames.shape == (len(seq), SIZE, SIZE, 3) and np.isfinite(frames).all()
