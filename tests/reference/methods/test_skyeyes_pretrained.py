"""`--pretrained DIR` (issue 13): a Stable Diffusion 1.5-layout diffusers folder, here a tiny
randomly initialised one the test builds itself (`builders.tiny_sd`: UNet, VAE, CLIP text
encoder and tokenizer, saved with `save_pretrained`), drives Skyeyes end to end: its UNet replaces the base stage, its
VAE the pixel codec, its text encoder the learned prompt, with a ControlNet branch and the
epsilon objective (the paper's ACM)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)
import transformers  # noqa: F401

from reference.common.diffusion import core  # noqa: E402
from reference.methods.skyeyes import PRESETS, Skyeyes  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402
from skyeyes_bench.errors import UserError  # noqa: E402
from builders.skyeyes import SIZE, StandInPrior, make_tiny_dataset  # noqa: E402
from builders.tiny_sd import RES, make_tiny_sd  # noqa: E402


@pytest.fixture(scope="module")
def sd(tmp_path_factory) -> Path:
    return make_tiny_sd(tmp_path_factory.mktemp("sd") / "sd15")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds")


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest: tiny tensors, one thread


def test_pretrained_folder_drives_the_whole_method(sd, tiny, tmp_path):
    from diffusers import AutoencoderKL
    from transformers import CLIPTextModel, CLIPTokenizer

    cfg = dataclasses.replace(PRESETS["small"], core=dataclasses.replace(PRESETS["small"].core, resolution=RES),
                              pretrained=str(sd), acm_steps=2, acm_anneal=1, acm_batch=2, vcm_steps=1, clip_frames=3,
                              sample_steps=2, ckpt_every=1, figure_frames=2, device="cpu",
                              threads=1)  # a second thread spins on a shared 2-core machine
    m = Skyeyes(cfg, tmp_path / "w", prior_method=StandInPrior(tmp_path / "p"), progress=False)
    # the paper's formulation: ControlNet branch, epsilon, frames (no residual), whole frames
    c = m.config.core
    assert (c.pretrained, c.prediction, c.conditioning, c.residual) == (str(sd), "epsilon", "controlnet", False)
    assert m.config.train_crop == 0 and m.config.sample_strength == 1.0
    ds = open_dataset(tiny)
    m.fit_train(ds)
    assert "base" not in m.training and set(m.training) == {"acm", "vcm"}
    # the folder's UNet weights, untouched by ACM training (only the branch is trained)
    from diffusers import UNet2DConditionModel

    unet = UNet2DConditionModel.from_pretrained(sd / "unet")
    for k, v in unet.state_dict().items():
        torch.testing.assert_close(m.acm.unet.state_dict()[k], v)
    assert m.acm.controlnet is not None
    # the prompt is the frozen CLIP encoding of the paper's prompt, computed here independently
    tok, enc = CLIPTokenizer.from_pretrained(sd / "tokenizer"), CLIPTextModel.from_pretrained(sd / "text_encoder")
    ids = tok([core.PROMPT], padding="max_length", max_length=tok.model_max_length, return_tensors="pt").input_ids
    with torch.no_grad():
        torch.testing.assert_close(m.acm.prompt.detach(), enc(ids)[0])
    assert not m.acm.prompt.requires_grad
    # latents are the VAE's (8x down, 4 channels, scaled)
    vae = AutoencoderKL.from_pretrained(sd / "vae")
    img = torch.rand(1, 3, RES, RES)
    with torch.no_grad():
        want = vae.encode(img * 2 - 1).latent_dist.mean * vae.config.scaling_factor
    z = core.encode(img, m.config.core)
    assert z.shape == (1, 4, RES // 8, RES // 8)
    torch.testing.assert_close(z, want)
    scene = ds.split("test")[0]
    m.fit_scene(scene)
    for seq in scene.sequences.values():
        frames = np.stack(list(m.render_sequence(scene, seq)))
        assert frames.shape == (len(seq), SIZE, SIZE, 3) and np.isfinite(frames).all()
        assert frames.min() >= 0 and frames.max() <= 1


def test_pretrained_refuses_what_is_not_a_diffusers_folder(tmp_path):
    from reference.reproduce import run

    (tmp_path / "x").mkdir()
    with pytest.raises(UserError, match=r"x: not a diffusers Stable Diffusion folder \(expected unet/config.json\)"):
        run("skyeyes", "smoke", out=tmp_path / "o", pretrained=str(tmp_path / "x"))
    with pytest.raises(UserError, match="takes no pretrained model"):
        run("mean-frame", "smoke", out=tmp_path / "o", pretrained=str(tmp_path / "x"))
