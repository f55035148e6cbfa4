"""The reference methods, one module each; found by id through `reference.registry`."""

from reference.registry import METHODS, get_method_class

__all__ = ["METHODS", "get_method_class"]
