"""Lazy `"module:attr"` entry points, shared by every registry (methods, extractors, ...)."""

from __future__ import annotations

import importlib
from typing import Any, Mapping

from .errors import UserError


def load_entry_point(spec: str) -> Any:
    """Import `"package.module:attr"` and return the attribute."""
    module, _, attr = spec.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split(".") if attr else []:
        obj = getattr(obj, part)
    return obj


def lookup(registry: Mapping[str, Any], key: str, kind: str) -> Any:
    """`registry[key]`, or a one-line UserError that lists the known ids."""
    try:
        return registry[key]
    except KeyError:
        known = ", ".join(sorted(registry)) or "(none)"
        raise UserError(f"unknown {kind} {key!r}; known: {known}") from None
