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


# --------------------------------------------------------------------------- the folder's schedule (issue 34)


def _scaled_linear_alpha_bar(start: float, end: float, n: int) -> np.ndarray:
    """SD1.5's schedule computed here: betas = linspace(sqrt(start), sqrt(end), n)^2 (the LDM
    repository's "scaled_linear"), alpha_bar_t = prod_{s <= t} (1 - beta_s)."""
    betas = np.linspace(start ** 0.5, end ** 0.5, n, dtype=np.float64) ** 2
    return np.cumprod(1.0 - betas)


def test_pretrained_trains_and_samples_on_the_folders_schedule_and_recipe_rate(sd, tmp_path):
    from builders.tiny_sd import SD15_SCHEDULER
    from reference.methods.ip2p import InstructPix2Pix

    cfg = dataclasses.replace(PRESETS["small"], pretrained=str(sd), device="cpu")
    m = Skyeyes(cfg, tmp_path / "w", prior_method=StandInPrior(tmp_path / "p"), progress=False)
    c = m.config.core
    assert (c.beta_schedule, c.beta_start, c.beta_end, c.train_timesteps, c.prediction) == (
        "scaled_linear", 0.00085, 0.012, 1000, "epsilon")
    want = _scaled_linear_alpha_bar(SD15_SCHEDULER["beta_start"], SD15_SCHEDULER["beta_end"], 1000)
    for sched in (core.train_scheduler(c), core.sample_scheduler(c)):
        np.testing.assert_allclose(sched.alphas_cumprod.double().numpy(), want, rtol=2e-6)
    # ours from scratch stays the linear 1e-4..0.02 schedule: alpha_bar_T = 4.0e-5 (core.py)
    assert float(core.train_scheduler(PRESETS["small"].core).alphas_cumprod[-1]) == pytest.approx(4.04e-5, rel=0.01)
    # the learning rate is the recipe's: ControlNet's 1e-5 for a branch, IP2P's 1e-4 for a whole UNet
    assert (PRESETS["small"].acm_lr, m.config.acm_lr) == (1e-3, 1e-5)
    ip2p = InstructPix2Pix(dataclasses.replace(InstructPix2Pix.presets["small"], pretrained=str(sd), device="cpu"),
                           tmp_path / "i", prior_method=StandInPrior(tmp_path / "p2"), progress=False)
    assert ip2p.config.acm_lr == 1e-4 and ip2p.config.core.beta_schedule == "scaled_linear"
    # a v-prediction folder (SD 2.x) trains on v
    import json

    v_sd = tmp_path / "sd2"
    import shutil

    shutil.copytree(sd, v_sd)
    (v_sd / "scheduler" / "scheduler_config.json").write_text(
        json.dumps({**SD15_SCHEDULER, "prediction_type": "v_prediction"}))
    m2 = Skyeyes(dataclasses.replace(cfg, pretrained=str(v_sd)), tmp_path / "w2",
                 prior_method=StandInPrior(tmp_path / "p3"), progress=False)
    assert m2.config.core.prediction == "v_prediction"


@pytest.mark.parametrize("content,match", [
    (None, "scheduler_config.json: missing"),
    ({"beta_schedule": "cosine-ish", "beta_start": 0.00085, "beta_end": 0.012, "num_train_timesteps": 1000},
     "field 'beta_schedule' is 'cosine-ish'; expected linear or scaled_linear or squaredcos_cap_v2"),
    ({"beta_schedule": "linear", "beta_start": "x", "beta_end": 0.012, "num_train_timesteps": 1000},
     "field 'beta_start' is 'x'"),
])
def test_pretrained_schedule_refuses_a_bad_scheduler_config_in_one_line(sd, tmp_path, content, match):
    import json
    import shutil

    bad = tmp_path / "sd"
    shutil.copytree(sd, bad)
    if content is None:
        shutil.rmtree(bad / "scheduler")
    else:
        (bad / "scheduler" / "scheduler_config.json").write_text(json.dumps(content))
    with pytest.raises(UserError, match=match) as e:
        Skyeyes(dataclasses.replace(PRESETS["small"], pretrained=str(bad), device="cpu"), tmp_path / "w",
                prior_method=StandInPrior(tmp_path / "p"), progress=False)
    assert "\n" not in str(e.value)


def test_vae_runs_in_chunks_with_the_result_of_one_frame_at_a_time(sd):
    cfg = dataclasses.replace(PRESETS["small"].core, pretrained=str(sd), resolution=RES)
    n = core.VAE_CHUNK + 3  # two chunks, the second partial
    img = torch.rand(n, 3, RES, RES, generator=torch.Generator().manual_seed(3))
    z = core.encode(img, cfg, "cpu")
    assert z.shape == (n, 4, RES // 8, RES // 8)
    one = torch.cat([core.encode(img[i:i + 1], cfg) for i in range(n)])
    torch.testing.assert_close(z, one, rtol=1e-5, atol=1e-6)
    x = core.decode(z, cfg, "cpu")
    assert x.shape == (n, 3, RES, RES)
    torch.testing.assert_close(x, torch.cat([core.decode(z[i:i + 1], cfg) for i in range(n)]), rtol=1e-4, atol=1e-5)
