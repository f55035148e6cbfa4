"""The diffusion family makes every tensor on the device of its data (issue 34), checked on a CPU.

Under `builders.devices.stray_device()` a tensor that project code creates without naming a
device lands on `meta` while the data stays on the CPU, so it breaks the run the way a CPU
tensor breaks a CUDA run (b99d601 failed so in `raster._q_bound` and, in this family, in the
host-side frames, noise draws, loss weights, coordinate channels and clip indices). Each run
here is also compared, frame for frame and bit for bit, with the same run outside the mode: the
explicit devices must change nothing on the CPU (the committed leaderboard rows depend on it).
The prior is the test-only stand-in of `builders.skyeyes`, so only the diffusion side runs.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import diffusers  # noqa: F401  (a hard dependency of reference: a broken install fails here, never skips)

from builders.devices import stray_device  # noqa: E402
from builders.skyeyes import SIZE, StandInGeometryPrior, StandInPrior, make_tiny_dataset, render_all  # noqa: E402
from reference.common.diffusion.additions import AdditionsConfig, PriorAnchorConfig  # noqa: E402
from reference.common.diffusion.config import DiffusionConfig, frame_by_frame  # noqa: E402
from reference.methods.controlnet import ControlNetBaseline  # noqa: E402
from reference.methods.gvg import GVG  # noqa: E402
from reference.methods.ip2p import InstructPix2Pix  # noqa: E402
from reference.methods.skyeyes import PRESETS, Skyeyes  # noqa: E402
from reference.methods.skyeyes_geo import ADDITIONS, SkyeyesGeo  # noqa: E402
from skyeyes_bench.data.layout import open_dataset  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")

_SMALL_CORE = dataclasses.replace(PRESETS["small"].core, resolution=SIZE, patch=2, channels=(16, 32),
                                  attention=(False, True), head_dim=8, embed_dim=16, norm_groups=4)
#: `small`'s formulation (concat, residual, coordinate channels, crops, EMA, min-SNR, a decay
#: phase after constant-rate steps, the VCM) on a tiny UNet.
SMALL_LIKE = dataclasses.replace(PRESETS["small"], core=_SMALL_CORE, acm_steps=3, acm_anneal=1, acm_batch=2,
                                 train_crop=4, vcm_steps=2, clip_frames=3, sample_steps=2, ckpt_every=1,
                                 figure_frames=2, mixed_precision="no", device="cpu", threads=1)
#: the paper's formulation: a ControlNet branch over a base UNet trained first, epsilon target.
CONTROLNET_LIKE = dataclasses.replace(
    PRESETS["smoke"], core=dataclasses.replace(PRESETS["paper"].core, resolution=SIZE, patch=1, channels=(16, 32),
                                               attention=(False, True), layers_per_block=1, head_dim=8,
                                               embed_dim=16, norm_groups=4),
    base_steps=2, base_batch=2, acm_steps=2, acm_batch=2, vcm_steps=1, clip_frames=3, sample_steps=2,
    ckpt_every=1, figure_frames=2, device="cpu", threads=1)
#: SDEdit start from the prior, on the rectified flow
FLOW_LIKE = dataclasses.replace(frame_by_frame(SMALL_LIKE),
                                core=dataclasses.replace(_SMALL_CORE, prediction="flow", flow_noise=0.5),
                                sample_strength=0.6, acm_anneal=0)


def _fields(cfg: DiffusionConfig) -> dict:
    """The family's fields of `cfg` (what an `AdditionsConfig` adds its additions to)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(DiffusionConfig)}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "ds", frames=4)


def _frames(cls, cfg, tiny: Path, workdir: Path, prior_cls=StandInPrior) -> dict[str, np.ndarray]:
    ds = open_dataset(tiny)
    m = cls(cfg, workdir, seed=0, prior_method=prior_cls(workdir / "prior"), progress=False)
    m.fit_train(ds)
    return render_all(m, ds)


def _both(cls, cfg, tiny, tmp_path, monkeypatch, prior_cls=StandInPrior):
    """(frames made under stray_device, frames made normally), each run from an empty cache."""
    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path / "cache-stray"))
    with stray_device() as mode:
        stray = _frames(cls, cfg, tiny, tmp_path / "stray", prior_cls)
    assert not mode.sites, f"tensors made without a device at {sorted(set(mode.sites))}"
    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path / "cache-plain"))
    plain = _frames(cls, cfg, tiny, tmp_path / "plain", prior_cls)
    return stray, plain


@pytest.mark.parametrize("name,cls,cfg", [
    ("small-like", Skyeyes, SMALL_LIKE),
    ("small-like-anchored", SkyeyesGeo, AdditionsConfig(**_fields(SMALL_LIKE),
                                                        anchor=PriorAnchorConfig(mix=0.5, sigma_px=2.0, tiles=2))),
    # every addition at `small`'s settings: the carried noise's flow, the stand-in prior's depth
    # and Gaussians (the street, the sky)
    ("small-like-geo", SkyeyesGeo, AdditionsConfig(**_fields(SMALL_LIKE), **ADDITIONS["small"])),
    ("controlnet-branch", Skyeyes, CONTROLNET_LIKE),
    ("flow-sdedit", Skyeyes, FLOW_LIKE),
    ("controlnet-baseline", ControlNetBaseline,
     dataclasses.replace(frame_by_frame(SMALL_LIKE), condition="aerial")),
])
def test_diffusion_methods_make_no_stray_tensors(name, cls, cfg, tiny, tmp_path, monkeypatch):
    stray, plain = _both(cls, cfg, tiny, tmp_path, monkeypatch)
    assert stray.keys() == plain.keys() and stray
    for k in stray:
        np.testing.assert_array_equal(stray[k], plain[k])


def _tiny_baseline(cls) -> object:
    """A baseline's own smoke preset on the tiny UNet."""
    base = cls.presets["smoke"]
    return dataclasses.replace(base, core=dataclasses.replace(base.core, resolution=SIZE, channels=(16, 32),
                                                              attention=(False, True), head_dim=8, embed_dim=16,
                                                              norm_groups=4),
                               acm_steps=2, acm_batch=4, sample_steps=2, ckpt_every=1, figure_frames=2, device="cpu",
                               threads=1)


@pytest.mark.parametrize("cls,prior_cls", [
    (InstructPix2Pix, StandInPrior),  # guidance: three branches, dropped conditions
    (GVG, StandInGeometryPrior),  # depth and coverage channels beside the colour
])
def test_baselines_make_no_stray_tensors(cls, prior_cls, tiny, tmp_path, monkeypatch):
    stray, plain = _both(cls, _tiny_baseline(cls), tiny, tmp_path, monkeypatch, prior_cls=prior_cls)
    assert stray.keys() == plain.keys() and stray
    for k in stray:
        np.testing.assert_array_equal(stray[k], plain[k])


def test_the_check_can_fail(tiny, tmp_path, monkeypatch):
    """A tensor made without a device in the sampler's hot path (the b99d601 kind of bug, written
    as if it were a line of sample.py) is caught, and named."""
    from reference.common.diffusion import sample

    src = ("import torch\n"
           "def _timesteps(t, n, dev):\n"
           "    return torch.full((n,), int(t), dtype=torch.long)\n")
    ns: dict = {}
    exec(compile(src, sample.__file__, "exec"), ns)  # noqa: S102  (a planted bug, in sample.py's name)
    monkeypatch.setattr(sample, "_timesteps", ns["_timesteps"])
    monkeypatch.setenv("SKYEYES_CACHE", str(tmp_path / "cache"))
    with pytest.raises((RuntimeError, NotImplementedError), match="meta"):
        with stray_device() as mode:
            _frames(Skyeyes, frame_by_frame(SMALL_LIKE), tiny, tmp_path / "w")
    assert any(site.startswith(sample.__file__) for site in mode.sites), mode.sites
