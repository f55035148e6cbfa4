"""The one place a `--device` (or a config's `device`) becomes a torch device.

"auto" (and None) is CUDA when this process can see a GPU, else the CPU. An explicit device
that this machine does not have is a `UserError` (one line, exit 2), raised before any work
starts, instead of a CUDA traceback minutes later. Both the benchmark (`evaluate --device`) and
the reference methods (`reproduce --device`, a config's `device` field, the diffusion stages'
accelerator) resolve through here.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from .errors import UserError


def resolve_device(name: str | None = "auto", *, what: str = "--device"):
    """`name` ("auto", None, "cpu", "cuda", "cuda:N", "mps", "meta") -> a `torch.device`
    that exists here. `what` names the option or field in the error."""
    import torch

    if name is None or name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError, ValueError):
        raise UserError(f"{what} {name!r}: not a torch device (expected auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch has no CUDA support" if torch.version.cuda is None else "no GPU is visible"
            raise UserError(f"{what} {name}: CUDA is not available on this machine ({why}, torch {torch.__version__}); "
                            "use --device cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UserError(f"{what} {name}: this machine has {torch.cuda.device_count()} CUDA device(s) "
                            f"(cuda:0 .. cuda:{torch.cuda.device_count() - 1})")
    elif dev.type == "mps":
        if not torch.backends.mps.is_available():
            raise UserError(f"{what} {name}: Apple MPS is not available on this machine; use --device cpu")
    elif dev.type not in ("cpu", "meta"):
        raise UserError(f"{what} {name!r}: unsupported device type {dev.type!r} (expected auto, cpu, cuda or cuda:N)")
    return dev


def device_name(name: str | None = "auto", *, what: str = "--device") -> str:
    """`resolve_device` as the string configs and results record ("cpu", "cuda", "cuda:1")."""
    return str(resolve_device(name, what=what))


@contextlib.contextmanager
def exact_fp32(device) -> Iterator[None]:
    """On CUDA, no TF32 within the block for cuDNN convolutions and matrix products (restored
    after), so float32 work on the GPU agrees with the CPU's to float rounding; elsewhere nothing.

    NOTE: torch rounds cuDNN convolution inputs to TF32's 10-bit mantissa by default, ~1e-3
    relative. torch >= 2.9 has the `fp32_precision` settings (and refuses some mixes of them with
    the legacy `allow_tf32` flags), older ones only the flags: whichever this torch has is used.
    """
    import torch

    if torch.device(device).type != "cuda":
        yield
        return
    conv, mm = torch.backends.cudnn.conv if hasattr(torch.backends.cudnn, "conv") else None, torch.backends.cuda.matmul
    if conv is not None and hasattr(conv, "fp32_precision") and hasattr(mm, "fp32_precision"):
        targets, name, value = (conv, mm), "fp32_precision", "ieee"
    else:
        targets, name, value = (torch.backends.cudnn, mm), "allow_tf32", False
    old = [getattr(t, name) for t in targets]
    for t in targets:
        setattr(t, name, value)
    try:
        yield
    finally:
        for t, v in zip(targets, old):
            setattr(t, name, v)
