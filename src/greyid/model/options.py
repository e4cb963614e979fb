"""Default settings a model carries for its data, filter and estimation.

A model read from a file knows which column holds time, how inputs are held
between samples, which filter to run and how to estimate.  Calls such as
``model.fit(data)`` use these defaults; an argument given in the call wins.
"""

from __future__ import annotations

from typing import Mapping

from ..errors import ModelError

#: Data settings: time column, hold order, time unit of datetime columns, and the
#: mapping from model names (inputs, outputs) to the data's column names.
DATA_KEYS = ("time", "hold", "time_unit", "columns", "time_format", "time_zone")
#: Filter settings (see :func:`greyid.filters.api.filter_options`).
FILTER_KEYS = ("method", "form", "substeps", "iterations", "alpha", "beta", "kappa")
#: Estimation settings of :meth:`Model.fit`.
ESTIMATION_KEYS = ("criterion", "robust", "horizon", "starts", "seed", "maxiter", "prior_correlation", "cov_type",
                   "optimizer")
#: Where the data live, for the command line: a CSV file (relative to the model
#: file) and its field separator.
FILE_KEYS = ("file", "separator")
ALL_KEYS = DATA_KEYS + FILE_KEYS + FILTER_KEYS + ESTIMATION_KEYS

HOLDS = ("zoh", "foh")
METHODS = ("kalman", "ekf", "iekf", "ekf2", "ukf", "truncated2", "gaussian2")
FORMS = ("sqrt", "plain")


def check_options(options: Mapping) -> dict:
    """Validate settings by name and type; returns a plain dict."""
    out = {}
    for key, value in options.items():
        if key not in ALL_KEYS:
            raise ModelError(f"unknown setting '{key}'; settings are {list(ALL_KEYS)}")
        if value is None:
            continue
        if key in ("time", "file", "separator", "time_unit", "time_format", "time_zone") and not isinstance(value, str):
            raise ModelError(f"setting '{key}' must be a string, got {value!r}")
        if key == "hold" and value not in HOLDS:
            raise ModelError(f"setting 'hold' must be 'zoh' or 'foh', got {value!r}")
        if key == "method" and value not in METHODS:
            raise ModelError(f"setting 'method' must be one of {list(METHODS)}, got {value!r}")
        if key == "form" and value not in FORMS:
            raise ModelError(f"setting 'form' must be 'sqrt' or 'plain', got {value!r}")
        if key == "criterion" and value not in ("ml", "map"):
            raise ModelError(f"setting 'criterion' must be 'ml' or 'map', got {value!r}")
        if key == "cov_type" and value not in ("hessian", "opg", "sandwich"):
            raise ModelError(f"setting 'cov_type' must be 'hessian', 'opg' or 'sandwich', got {value!r}")
        if key == "optimizer" and value not in ("auto", "scoring", "newton"):
            raise ModelError(f"setting 'optimizer' must be 'auto', 'scoring' or 'newton', got {value!r}")
        if key in ("horizon", "starts", "substeps", "iterations", "maxiter") and not (
            isinstance(value, int) and not isinstance(value, bool) and value >= 1
        ):
            raise ModelError(f"setting '{key}' must be a positive integer, got {value!r}")
        if key == "seed" and not (isinstance(value, int) and not isinstance(value, bool)):
            raise ModelError(f"setting 'seed' must be an integer, got {value!r}")
        if key == "robust":
            value = tuple(value) if isinstance(value, list) else value
        if key == "columns":
            if not isinstance(value, Mapping) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in value.items()
            ):
                raise ModelError("setting 'columns' must map model names to column names (strings)")
            value = dict(value)
        if key == "prior_correlation":
            value = prior_correlation(value)
        out[key] = value
    return out


def prior_correlation(value) -> dict[tuple[str, str], float]:
    """``{("a", "b"): ρ}``; keys may also be written ``"a,b"`` (as in a TOML file)."""
    if not isinstance(value, Mapping):
        raise ModelError("prior_correlation must map parameter pairs to correlations")
    out = {}
    for key, rho in value.items():
        pair = tuple(s.strip() for s in key.split(",")) if isinstance(key, str) else tuple(key)
        if len(pair) != 2 or not all(isinstance(p, str) and p for p in pair):
            raise ModelError(f"prior correlation key {key!r} must name two parameters, e.g. 'Ci,Cw'")
        if not isinstance(rho, (int, float)) or not -1 < rho < 1:
            raise ModelError(f"prior correlation of {pair} must be a number in (-1, 1), got {rho!r}")
        out[pair] = float(rho)
    return out


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
