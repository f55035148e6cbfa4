"""LPIPS v0.1 network (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a
Perceptual Metric"), written without torchvision.

Distance = sum over 5 backbone layers of spatial_mean(conv1x1_w(|f0/|f0| - f1/|f1||^2)), on
inputs in [-1, 1] passed through the scaling layer. Backbone weights: torchvision's ImageNet
AlexNet / VGG16 state dicts (keys `features.N.weight`); linear heads: the `lpips==0.1.4`
wheel's v0.1 files (keys `linK.model.1.weight`).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

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

    def forward(self, x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
        n = x0.shape[0]
        feats = self.taps_of(torch.cat([x0, x1]))  # one pass for both halves
        total = 0.0
        for f, lin in zip(feats, self.lins):
            f = f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + EPS)
            d = (f[:n] - f[n:]) ** 2
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
