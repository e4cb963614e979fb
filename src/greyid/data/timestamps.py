"""A time column of text read as timestamps, with the order of day and month stated or unambiguous.

``12.03.2024`` is the 12th of March in most of Europe and the 3rd of December in the
United States; a reader that guesses reads a month of data with gaps of a month.
So dates whose first two fields are both numbers are read only where one order fits
every row (a day above 12 somewhere settles it) or the order is stated with
``time_format`` (``[data] time_format`` in a model file); otherwise the data are
refused with both readings and the setting that chooses one.  Year-first dates
(ISO 8601, ``2024/03/12``) and month names are not ambiguous.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pandas as pd

from ..errors import DataError

#: Dates that start with two numbers (day and month in some order) before the year.
_TWO_NUMBERS_FIRST = re.compile(r"^\s*\d{1,2}[./\- ]\d{1,2}[./\- ]\d{2,4}")

#: The key ``frame.attrs`` carries: how the text was read (``"day-first"``, ``"month-first"``, a format).
READ_AS = "greyid_time_read_as"


def _to_datetime(column: pd.Series, time_format, dayfirst: bool) -> pd.Series:
    with warnings.catch_warnings():  # pandas' own warnings would be printed before greyid's message
        warnings.simplefilter("ignore")
        try:
            parsed = pd.to_datetime(column, format=time_format, dayfirst=dayfirst, errors="coerce")
        except ValueError:
            # Several UTC offsets (a daylight-saving change within the data): each timestamp is an
            # exact instant, and in UTC the elapsed times across the change are right.
            parsed = pd.to_datetime(column, format=time_format, dayfirst=dayfirst, errors="coerce", utc=True)
        if parsed.dtype == object:  # mixed offsets parsed one by one (older pandas)
            parsed = pd.to_datetime(column, format=time_format, dayfirst=dayfirst, errors="coerce", utc=True)
    return parsed


def _format_of(text: str, dayfirst: bool) -> str:
    """The strftime format pandas infers for ``text`` in one order, for the message."""
    from pandas.tseries.api import guess_datetime_format

    guessed = guess_datetime_format(text.strip(), dayfirst=dayfirst)
    return guessed or ("%d.%m.%Y %H:%M" if dayfirst else "%m/%d/%Y %H:%M")


def _read_text(column: pd.Series, time: str, time_format, where: str) -> tuple[pd.Series, str]:
    """The column as timestamps, and how it was read."""
    if time_format is not None:
        return _to_datetime(column, time_format, False), f"the format {time_format!r}"
    first = next((str(v) for v in column if isinstance(v, str) and v.strip()), "")
    if not _TWO_NUMBERS_FIRST.match(first):
        return _to_datetime(column, None, False), "inferred"
    month_first, day_first = _to_datetime(column, None, False), _to_datetime(column, None, True)
    fits = {"month-first": month_first.notna().all(), "day-first": day_first.notna().all()}
    if all(fits.values()) and not month_first.equals(day_first):
        row = int(np.flatnonzero((month_first != day_first).to_numpy())[0])
        text = column.iloc[row]
        raise DataError(
            f"time column '{time}' in {where}: the dates are ambiguous: row {row} ({text!r}) is "
            f"{day_first.iloc[row]:%d %B %Y} read day-first and {month_first.iloc[row]:%d %B %Y} read "
            f"month-first, and no row settles it (no day above 12). State the order: [data] time_format = "
            f"\"{_format_of(text, True)}\" (day-first) or \"{_format_of(text, False)}\" (month-first) in the "
            "model file, or time_format=... in Python")
    if fits["day-first"] and not fits["month-first"]:
        return day_first, "day-first"
    if fits["month-first"]:
        return month_first, "month-first"
    # Neither order reads every row: report the first row of the reading that gets furthest.
    best = day_first if day_first.notna().sum() > month_first.notna().sum() else month_first
    return best, "day-first" if best is day_first else "month-first"


def parse_timestamps(frame: pd.DataFrame, time: str, time_format=None, time_zone=None,
                     where: str = "the data") -> pd.DataFrame:
    """A time column of text turned into timestamps (``time_format``, else ISO 8601 or inferred).

    Parameters
    ----------
    frame : pandas.DataFrame
        The data; only its column ``time`` is read.
    time : str
        The name of the time column.
    time_format : str, optional
        A ``strftime`` format such as ``"%d.%m.%Y %H:%M"``.  Without it, dates that
        begin with two numbers are read in the one order (day-first or month-first)
        that fits every row, and refused where both do.
    time_zone : str, optional
        An IANA zone (``"Europe/Copenhagen"``): naive timestamps are read in it (so
        elapsed times cross daylight-saving changes correctly), aware ones converted to it.
    where : str
        How messages name the data (``"data file 'x.csv'"``).

    Returns
    -------
    pandas.DataFrame
        ``frame`` with the column parsed, and ``attrs["greyid_time_read_as"]`` saying
        how (``"day-first"``, ``"month-first"``, ``"the format '...'"``, ``"inferred"``).
        A column of numbers is returned as it is.

    Raises
    ------
    DataError
        Text that is not a time (names the row), ambiguous dates (names a row and the
        setting that decides), an unknown time zone or a local time that a daylight-saving
        change makes ambiguous.
    """
    if time not in frame.columns:
        return frame
    column = frame[time]
    if pd.api.types.is_datetime64_any_dtype(column):
        return _in_zone(frame, column, time, time_zone, where)
    if not (pd.api.types.is_object_dtype(column) or pd.api.types.is_string_dtype(column)):
        return frame
    numbers = pd.to_numeric(column, errors="coerce").notna()
    if numbers.mean() >= 0.5:
        # Numbers (perhaps with a bad row): read as numbers, whose check names the first bad row.
        return frame
    parsed, read_as = _read_text(column, time, time_format, where)
    if parsed.isna().all() and time_format is None:
        return frame  # not timestamps at all: the numeric check names the first bad row
    bad = np.flatnonzero(parsed.isna().to_numpy())
    if len(bad):
        hint = (f" in the format {time_format!r}" if time_format else
                f" (read {read_as}; state the format with [data] time_format, e.g. \"%d.%m.%Y %H:%M\")")
        raise DataError(f"time column '{time}' in {where}: row {bad[0]} holds {column.iloc[bad[0]]!r}, which is not "
                        f"a time{hint}")
    out = _in_zone(frame, parsed, time, time_zone, where)
    out.attrs[READ_AS] = read_as
    return out


def _in_zone(frame: pd.DataFrame, parsed: pd.Series, time: str, time_zone, where: str) -> pd.DataFrame:
    if time_zone:
        try:
            parsed = (parsed.dt.tz_localize(time_zone, ambiguous="raise", nonexistent="raise")
                      if parsed.dt.tz is None else parsed.dt.tz_convert(time_zone))
        except Exception as err:  # unknown zone, or a local time that DST makes ambiguous
            raise DataError(f"time column '{time}' in {where}: time zone {time_zone!r}: {err}") from None
    out = frame.assign(**{time: parsed})
    out.attrs = dict(frame.attrs)
    return out
