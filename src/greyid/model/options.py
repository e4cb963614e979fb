"""Default settings a model carries for its data, filter and estimation.

A model read from a file knows which column holds time, how inputs are held
between samples, which filter to run and how to estimate.  Calls such as
``model.fit(data)`` use these defaults; an argument given in the call wins.
"""

from __future__ import annotations

from typing import Mapping

# The settings' keys and their checks are part of the one validation layer (greyid.schema).
from ..schema import (  # noqa: F401  (re-exported: the settings' names are used across the package)
    ALL_KEYS, DATA_KEYS, ESTIMATION_KEYS, FILE_KEYS, FILTER_KEYS, FORMS, HOLDS, METHODS, check_options,
    prior_correlation)


def resolve(defaults: Mapping, given: Mapping, keys) -> dict:
    """Settings for one call: those given in the call, else the model's defaults."""
    out = {k: defaults[k] for k in keys if defaults.get(k) is not None}
    out.update({k: v for k, v in given.items() if v is not None})
    return out


def rename_columns(data, columns: Mapping[str, str] | None):
    """Rename data columns to model names (``columns`` maps model name → column)."""
    if not columns:
        return data
    if isinstance(data, (list, tuple)):
        return [rename_columns(d, columns) for d in data]
    import pandas as pd

    if not isinstance(data, pd.DataFrame):
        return data
    from ..errors import DataError

    # A frame that already carries the model's names (e.g. one a fit kept) passes as it is.
    missing = [f"'{col}' (for '{name}')" for name, col in columns.items()
               if col not in data.columns and name not in data.columns]
    if missing:
        raise DataError(f"column {missing[0]} named in the model's column mapping is not in the data; "
                        f"columns are {list(data.columns)}")
    return data.rename(columns={col: name for name, col in columns.items() if col in data.columns})
