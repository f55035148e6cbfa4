"""SynthTown: the built-in procedural, geo-aligned aerial/ground dataset (protocol synthtown@1).

```python
from skyeyes_bench.data.synthtown import ensure_dataset, generate_dataset, PRESETS
root = ensure_dataset("small")          # <cache>/data/synthtown-small, generated if absent
generate_dataset(Path("out"), "smoke")  # anywhere
```

Light at import (the CLI imports this package): the renderer loads on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .presets import PRESETS, Preset

if TYPE_CHECKING:  # pragma: no cover
    from .generate import ensure_dataset, generate_dataset

__all__ = ["PRESETS", "Preset", "ensure_dataset", "generate_dataset"]


def __getattr__(name: str):
    if name in ("ensure_dataset", "generate_dataset"):
        from . import generate

        return getattr(generate, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
