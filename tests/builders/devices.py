"""Catch tensors made on the wrong device, without a GPU (issue 34).

On a GPU, a tensor that the project's code makes without naming a device (`torch.full(...)`,
`torch.arange(n)`, `torch.from_numpy(a)` used as is) lands on the CPU while the data lives on
CUDA, and the next operation that mixes them fails. On a CPU-only machine the two are the same
device, so nothing shows. `stray_device()` makes them differ: inside it, every tensor that code
in `reference/` or `skyeyes_bench/` creates *without saying where* (no `device=` argument) is
made on the `meta` device instead, while the inputs stay on the CPU. Mixing the two raises
("Tensor on device meta is not on the expected device cpu"), and a result that comes back on
`meta` shows the stray tensor went all the way through. Tensors made by torch, diffusers or
other libraries, and by `*_like` / `new_*` calls (which follow their input), are left alone.

Stricter than CUDA in one way (a 0-dim CPU scalar may mix with CUDA tensors, not with meta),
so a pass here is a pass on a GPU as far as tensor placement goes; numerics are for the `gpu`
tests.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Iterator

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._device import _device_constructors

_ROOT = Path(__file__).resolve().parents[2]
PROJECT_DIRS = tuple(str(_ROOT / d) + "/" for d in ("reference", "skyeyes_bench"))

#: Factories that take a `device=` (torch's own list, as `with torch.device(...)` uses).
_FACTORIES = _device_constructors()


def _from_project(depth: int = 2) -> str | None:
    """'file:line' of the first frame outside torch above the factory call, if it is project code."""
    frame = sys._getframe(depth)
    while frame is not None and "/torch/" in frame.f_code.co_filename:
        frame = frame.f_back
    if frame is None:
        return None
    name = frame.f_code.co_filename
    return f"{name}:{frame.f_lineno}" if name.startswith(PROJECT_DIRS) else None


class StrayDevice(TorchFunctionMode):
    """The mode behind `stray_device`; `sites` lists where it moved a tensor to meta."""

    def __init__(self):
        super().__init__()
        self.sites: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in _FACTORIES and kwargs.get("device") is None:
            # torch.tensor / as_tensor of a tensor keep that tensor's device: not a stray
            first = args[0] if args else kwargs.get("data")
            if not isinstance(first, torch.Tensor) and (site := _from_project()):
                self.sites.append(site)
                kwargs = {**kwargs, "device": "meta"}
        return func(*args, **kwargs)

    def from_numpy(self, array):
        """`torch.from_numpy` while the mode is on: it always makes a CPU tensor and takes no
        device, and it bypasses torch-function modes, so `stray_device` swaps it for this."""
        out = _FROM_NUMPY(array)
        if site := _from_project():
            self.sites.append(site)
            return out.to("meta")
        return out


_FROM_NUMPY = torch.from_numpy


@contextlib.contextmanager
def stray_device() -> Iterator[StrayDevice]:
    """Within the block, project code's device-less tensors are made on `meta` (see the module)."""
    mode = StrayDevice()
    torch.from_numpy = mode.from_numpy  # the one conversion modes do not see (module-level name)
    try:
        with mode:
            yield mode
    finally:
        torch.from_numpy = _FROM_NUMPY


def assert_on(device: str, *tensors) -> None:
    """Every tensor in `tensors` (nested lists, tuples and dicts too) is on `device`."""
    def walk(x):
        if isinstance(x, torch.Tensor):
            yield x
        elif isinstance(x, dict):
            for v in x.values():
                yield from walk(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                yield from walk(v)

    bad = [tuple(t.shape) for t in walk(tensors) if t.device.type != torch.device(device).type]
    assert not bad, f"tensors not on {device}: shapes {bad[:5]}"
