"""Checking measured data against a model and turning it into arrays.

Data arrive as a pandas DataFrame with a time column, one column per input and
one per output.  Times may be irregular; a NaN in an output means "not
observed" (element by element).  Datetimes are converted to elapsed time since
the first row in ``time_unit`` (seconds unless said otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..errors import DataError

TIME_UNITS = {"s": 1.0, "min": 60.0, "h": 3600.0, "d": 86400.0}


@dataclass(frozen=True)
class Series:
    """One experiment as arrays: times (N,), inputs (N, nu), outputs (N, ny)."""

    times: np.ndarray
    inputs: np.ndarray
    outputs: np.ndarray
    index: pd.Index
    time_name: str

    @property
    def n_rows(self) -> int:
        return len(self.times)

    @property
    def observed(self) -> np.ndarray:
        return ~np.isnan(self.outputs)


def _numeric_column(df: pd.DataFrame, name: str, role: str) -> np.ndarray:
    if name not in df.columns:
        raise DataError(f"{role} column '{name}' not found in the data; columns are {list(df.columns)}")
    col = df[name]
    if pd.api.types.is_bool_dtype(col) or (not pd.api.types.is_numeric_dtype(col) and col.map(
            lambda v: isinstance(v, (bool, np.bool_)) or str(v).strip().lower() in ("true", "false")).any()):
        flags = np.flatnonzero(col.map(lambda v: isinstance(v, (bool, np.bool_))
                                       or str(v).strip().lower() in ("true", "false")).to_numpy())
        first = str(col.iloc[flags[0]])
        raise DataError(f"{role} column '{name}' holds true/false values (row {flags[0]}: {first!r}), "
                        "not numbers; write them as 1 and 0 if that is what they mean")
    if not (pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col)):
        converted = pd.to_numeric(col, errors="coerce")
        bad = np.flatnonzero(converted.isna() & col.notna())
        if len(bad):
            raise DataError(
                f"{role} column '{name}' is not numeric: row {bad[0]} holds {col.iloc[bad[0]]!r}"
            )
        col = converted
    return col.to_numpy(dtype=np.float64)


def time_values(df: pd.DataFrame, time: str, time_unit: str | None = None) -> np.ndarray:
    """The time column as float64, datetimes as elapsed ``time_unit`` since row 0."""
    if time not in df.columns:
        raise DataError(f"time column '{time}' not found in the data; columns are {list(df.columns)}")
    col = df[time]
    if pd.api.types.is_datetime64_any_dtype(col):
        unit = time_unit or "s"
        if unit not in TIME_UNITS:
            raise DataError(f"unknown time unit '{unit}'; use one of {list(TIME_UNITS)}")
        if col.isna().any():
            raise DataError(f"time column '{time}' has a missing value at row {int(np.flatnonzero(col.isna())[0])}")
        elapsed = (col - col.iloc[0]).dt.total_seconds().to_numpy(dtype=np.float64)
        return elapsed / TIME_UNITS[unit]
    if time_unit is not None and time_unit not in TIME_UNITS:
        raise DataError(f"unknown time unit '{time_unit}'; use one of {list(TIME_UNITS)}")
    return _numeric_column(df, time, "time")


def check_times(times: np.ndarray, time: str) -> None:
    """Times must be finite and strictly increasing."""
    bad = np.flatnonzero(~np.isfinite(times))
    if len(bad):
        raise DataError(f"time column '{time}' has a missing or infinite value at row {bad[0]}")
    steps = np.diff(times)
    dup = np.flatnonzero(steps == 0)
    if len(dup):
        raise DataError(f"time column '{time}' has a duplicated time {times[dup[0] + 1]} at row {dup[0] + 1}")
    back = np.flatnonzero(steps < 0)
    if len(back):
        raise DataError(
            f"times are not increasing: row {back[0] + 1} ({times[back[0] + 1]}) comes after {times[back[0]]}"
        )


def prepare_series(
    df: pd.DataFrame,
    input_names: tuple[str, ...],
    output_names: tuple[str, ...],
    time: str = "t",
    time_unit: str | None = None,
    require_outputs: bool = True,
) -> Series:
    """Check one DataFrame and return it as a [`Series`][greyid.data.prepare.Series]."""
    if not isinstance(df, pd.DataFrame):
        raise DataError(f"data must be a pandas DataFrame, got {type(df).__name__}")
    if len(df) == 0:
        raise DataError("the data set is empty")
    times = time_values(df, time, time_unit)
    check_times(times, time)
    inputs = np.empty((len(df), len(input_names)))
    for j, name in enumerate(input_names):
        values = _numeric_column(df, name, "input")
        bad = np.flatnonzero(~np.isfinite(values))
        if len(bad):
            raise DataError(
                f"input '{name}' has a missing or infinite value at row {bad[0]}; inputs must be known at every row"
            )
        inputs[:, j] = values
    outputs = np.full((len(df), len(output_names)), np.nan)
    for j, name in enumerate(output_names):
        if name not in df.columns and not require_outputs:
            continue
        values = _numeric_column(df, name, "output")
        bad = np.flatnonzero(np.isinf(values))
        if len(bad):
            raise DataError(f"output '{name}' has an infinite value at row {bad[0]}")
        if require_outputs and np.all(np.isnan(values)):
            raise DataError(f"output column '{name}' has no observation at all")
        outputs[:, j] = values
    return Series(times=times, inputs=inputs, outputs=outputs, index=df.index, time_name=time)


def as_frames(data) -> list[pd.DataFrame]:
    """One DataFrame or a list of them (independent experiments)."""
    if isinstance(data, pd.DataFrame):
        return [data]
    if isinstance(data, (list, tuple)):
        if not data:
            raise DataError("the list of data sets is empty")
        for i, d in enumerate(data):
            if not isinstance(d, pd.DataFrame):
                raise DataError(f"data set {i} must be a pandas DataFrame, got {type(d).__name__}")
        return list(data)
    raise DataError(f"data must be a pandas DataFrame or a list of them, got {type(data).__name__}")
