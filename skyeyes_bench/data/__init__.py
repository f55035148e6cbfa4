"""The canonical dataset layout (see DESIGN.md) and the tools that write it."""

from .layout import Dataset, DatasetWriter, Frame, Scene, Sequence, open_dataset, validate_dataset

__all__ = ["Dataset", "DatasetWriter", "Frame", "Scene", "Sequence", "open_dataset", "validate_dataset"]
