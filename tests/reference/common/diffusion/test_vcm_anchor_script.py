"""bench/vcm_anchor.py's settings (docs/skyeyes.md, "The prior anchor"): what each names, and a
one-line refusal of what names nothing."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch
from builders.bench_scripts import load_bench

from reference.common.diffusion import warp


@pytest.fixture(scope="module")
def va():
    return load_bench("vcm_anchor")


def test_settings_parse_to_what_they_name(va):
    assert va.parse("none") == ("none",)
    assert va.parse("after:3:0.7") == ("after", 3.0, 0.7, "render")
    assert va.parse("after:3:0.7:map4") == ("after", 3.0, 0.7, "map4")
    assert va.parse("after:2:1:carried") == ("after", 2.0, 1.0, "carried")
    assert va.parse("sampler:3:1:map:2:9") == ("sampler", 3.0, 1.0, "map", 2, 9)
    for bad in ("after", "after:x:1", "after:3:0.7:mapx", "sampler:3:1:carried:0:9", "sampler:3:1:map:2", "before:3:1"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected"):
            va.parse(bad)


def test_after_map_is_the_pipelines_anchor(va):
    """`after:S:M:mapN` is `vcm_anchor`'s `warp.prior_anchor` with N tiles, not a copy of it."""
    g = torch.Generator().manual_seed(0)
    imgs, renders = torch.rand(3, 3, 16, 16, generator=g), torch.rand(3, 3, 16, 16, generator=g)
    torch.testing.assert_close(va.after(imgs, renders, va.parse("after:2:0.7:map2")),
                               warp.prior_anchor(imgs, renders, 2.0, 0.7, 2))
    assert not torch.equal(va.after(imgs, renders, va.parse("after:2:0.7:map2")),
                           va.after(imgs, renders, va.parse("after:2:0.7:map")))


def test_luma_chroma_chain_and_window_settings_parse(va):
    assert va.parse("after:3:0.5:map4:0") == ("after", 3.0, 0.5, "map4", 0.0)
    assert va.parse("after:3:0.7:map4w4") == ("after", 3.0, 0.7, "map4w4")
    assert va.parse("after:3:0.5:map4+after:6:0.8:map4") == ("chain", ("after", 3.0, 0.5, "map4"),
                                                             ("after", 6.0, 0.8, "map4"))
    for bad in ("after:3:0.5:render:0", "after:3:0.5:carried:0", "after:3:0.5:map4w0", "after:3:0.5:map4wx",
                "after:3:0.5:map4:0:1", "after:3:0.5:map4+sampler:3:1:map:2:9", "after:3:0.5:map9"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected"):
            va.parse(bad)


def _pair(n: int = 3):
    g = torch.Generator().manual_seed(1)
    imgs = 0.3 + 0.4 * torch.rand(n, 3, 24, 24, generator=g)  # inside [0, 1] with room: no clamping below
    return imgs, torch.rand(n, 3, 24, 24, generator=g)


def test_luma_only_moves_each_pixel_by_a_grey_of_mix_times_the_lowpass_luma(va):
    """CHROMA 0: what is added to a pixel is grey (its chroma stays), and that grey is MIX times
    the luma (Rec. 601) of the low-pass's whole move to the target (scipy's Gaussian, reflected)."""
    from scipy.ndimage import gaussian_filter

    imgs, renders = _pair()
    out = va.after(imgs, renders, va.parse("after:2:0.6:map2:0"))
    add = (out - imgs).double()
    torch.testing.assert_close(add[:, 0], add[:, 1], atol=1e-6, rtol=0)
    torch.testing.assert_close(add[:, 0], add[:, 2], atol=1e-6, rtol=0)
    move = gaussian_filter((warp.affine_colours(renders, imgs, 2) - imgs).double().numpy(), (0, 0, 2, 2), mode="reflect")
    luma = np.tensordot([0.299, 0.587, 0.114], move, axes=([0], [1]))  # [N, H, W]
    np.testing.assert_allclose(add[:, 0].numpy(), 0.6 * luma, atol=1e-6)
    assert np.abs(luma).max() > 0.01  # the target is far enough for the check to mean something


def test_chroma_only_leaves_the_luma(va):
    imgs, renders = _pair()
    out = va.after(imgs, renders, va.parse("after:2:0:map2:0.8"))
    w = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)[None, :, None, None]
    added = (out - imgs).double()
    assert float(((added * w).sum(1)).abs().max()) < 1e-6
    assert float(added.abs().max()) > 0.01


def test_a_window_wider_than_the_sequence_is_the_sequence_map_and_a_chain_is_its_steps_in_turn(va):
    imgs, renders = _pair(4)
    torch.testing.assert_close(va.mapped(imgs, renders, "map2w9"), warp.affine_colours(renders, imgs, 2))
    assert not torch.allclose(va.mapped(imgs, renders, "map2w1"), warp.affine_colours(renders, imgs, 2))
    one = va.after(imgs, renders, va.parse("after:2:0.5:map2"))
    torch.testing.assert_close(va.after(imgs, renders, va.parse("after:2:0.5:map2+after:4:0.8:map")),
                               va.after(one, renders, va.parse("after:4:0.8:map")))


def _static_scene(n: int, size: int = 48):
    """A still camera: every render the same texture; frames its grey-scaled copy plus a detail
    pattern D that flips sign each frame, and a uniform offset that does the same."""
    g = torch.Generator().manual_seed(2)
    render = torch.rand(1, 3, size, size, generator=g).repeat(n, 1, 1, 1)
    flip = torch.tensor([(-1.0) ** t for t in range(n)])[:, None, None, None]
    detail = 0.05 * torch.sign(torch.randn(1, 3, size, size, generator=g))
    return render, flip, detail


def test_time_smooths_a_flickering_residual_as_a_gaussian_in_time_does(va):
    """The residual over the (static) render alternates by +-c each frame: `time` leaves each
    frame's offset the Gaussian in time of that alternation (scipy, the ends held)."""
    from scipy.ndimage import gaussian_filter1d

    n = 8
    render, flip, _ = _static_scene(n)
    imgs = (0.2 + 0.5 * render + 0.05 * flip).float()
    out = va.after(imgs, render, va.parse("time:3:1.5"))
    want = gaussian_filter1d(0.05 * flip.flatten().numpy(), 1.5, mode="nearest")  # [n]
    got = (out - (0.2 + 0.5 * render)).mean(dim=(1, 2, 3)).numpy()
    np.testing.assert_allclose(got, want, atol=2e-3)
    assert np.abs(want).max() < 0.6 * 0.05  # the check is a real reduction


def test_flow_mean_and_median_of_a_detail_that_flips_sign(va):
    """A still camera (zero flow): frames = a still base B plus a detail that flips sign, +-D. With
    h = D minus its 1-px low-pass, an interior frame's detail h_B + h, whose neighbours hold
    h_B - h, becomes h_B + (h - 2 h) / 3 under `flow:1:1:mean`, so the frame moves by -4 h / 3, and
    h_B - h (the median) under `median`, a move of -2 h; the first and last frames average with
    their one neighbour to h_B (a move of -h), or keep theirs (none)."""
    n = 5
    render, flip, detail = _static_scene(n)
    imgs = (0.3 + 0.4 * render).float() + flip * detail
    d = flip * detail
    h = d.double() - torch.from_numpy(warp.blur_frames(d, 1.0))
    mean = va.after(imgs, render, va.parse("flow:1:1:mean")).double() - imgs.double()
    med = va.after(imgs, render, va.parse("flow:1:1:median")).double() - imgs.double()
    torch.testing.assert_close(mean[1:-1], -4 * h[1:-1] / 3, atol=1e-4, rtol=0)
    torch.testing.assert_close(mean[[0, -1]], -h[[0, -1]], atol=1e-4, rtol=0)
    torch.testing.assert_close(med[1:-1], -2 * h[1:-1], atol=1e-4, rtol=0)
    torch.testing.assert_close(med[[0, -1]], torch.zeros_like(med[[0, -1]]), atol=1e-4, rtol=0)
    assert float(h.abs().max()) > 0.03


def test_fitted_map_targets_parse_and_fit_as_named(va):
    """`lmapN` fits the regression on the setting's low-passes, `omapN` matches the distributions
    there (`warp.affine_colours`' sigma and fit); the sampler takes the preset's map only."""
    assert va.parse("after:3:0.5:lmap4") == ("after", 3.0, 0.5, "lmap4")
    assert va.parse("after:2:0.7:omap2w3") == ("after", 2.0, 0.7, "omap2w3")
    for bad in ("after:3:0.5:xmap4", "after:3:0.5:lmap9", "sampler:3:1:omap4:2:9"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected"):
            va.parse(bad)
    g = torch.Generator().manual_seed(5)
    imgs, renders = torch.rand(3, 3, 16, 16, generator=g), torch.rand(3, 3, 16, 16, generator=g)
    torch.testing.assert_close(va.mapped(imgs, renders, "lmap2", 2.0), warp.affine_colours(renders, imgs, 2, sigma=2.0))
    torch.testing.assert_close(va.mapped(imgs, renders, "omap2", 2.0),
                               warp.affine_colours(renders, imgs, 2, fit="monge", sigma=2.0))
    torch.testing.assert_close(va.mapped(imgs, renders, "map2", 2.0), warp.affine_colours(renders, imgs, 2))


def test_anchor_frames_are_read_from_the_named_submission(va, tmp_path):
    """--anchor-frames: the target of a sequence is that submission's frames of it, in the
    sequence's order, as [N, 3, H, W] in [0, 1]."""
    from types import SimpleNamespace

    from skyeyes_bench.imagefiles import write_image

    rng = np.random.default_rng(0)
    imgs = [rng.integers(0, 256, (8, 8, 3), dtype=np.uint8) for _ in range(3)]
    frames = [SimpleNamespace(file=f"seq/{i:06d}.png") for i in (2, 0, 1)]
    (tmp_path / "scene-a" / "seq").mkdir(parents=True)
    for i, im in enumerate(imgs):
        write_image(tmp_path / "scene-a" / "seq" / f"{i:06d}.png", im.astype(np.float32) / 255)
    of = va._renders(SimpleNamespace(anchor_frames=tmp_path), None, [])
    got = of(SimpleNamespace(name="scene-a"), SimpleNamespace(frames=frames), 8, 8)
    want = torch.from_numpy(np.stack([imgs[2], imgs[0], imgs[1]]).astype(np.float32) / 255).permute(0, 3, 1, 2)
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
