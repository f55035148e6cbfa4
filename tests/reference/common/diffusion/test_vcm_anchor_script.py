"""bench/vcm_anchor.py's settings (docs/skyeyes.md, "The prior anchor"): what each names, and a
one-line refusal of what names nothing."""

from __future__ import annotations

import argparse

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
