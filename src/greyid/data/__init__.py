"""Data handling: checking DataFrames against a model."""

from .prepare import Series, as_frames, prepare_series

__all__ = ["Series", "as_frames", "prepare_series"]
