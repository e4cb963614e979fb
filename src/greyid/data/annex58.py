"""IEA EBC Annex 58 Common Exercise 4 (the test box of the DTU course's Ex_3): the 10-minute series.

The course's R code (marcohv/exercises_ts_dtu, ``Ex_3/r``: ``readSeries("X5", Ts=10,
nlags=NA)`` then ``prepare_data(..., samples_after_Qi_step=5)``) turns the
1-minute series ``X5.rda`` into the 10-minute one the exercise fits.
[`ten_minutes()`][greyid.data.annex58.ten_minutes] does the same, step by step, so that the data set can be
derived from its public source; it reproduces the course's own 10-minute file to
rounding (``tests/test_datasets_fetch.py`` compares them).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .rda import read_rda

#: The test box's position (``readSeries``: series whose name starts with X).
LATITUDE, LONGITUDE = 37.097083, -2.364994
#: Hours left out at the start of the series (``readSeries``'s ``rmvHours``).
REMOVED_HOURS = 8
#: Samples after a switch of the heating marked by ``stepQi`` (``prepare_data``'s ``samples_after_Qi_step``).
AFTER_STEP = 5


def _resample(frame: pd.DataFrame, seconds: int) -> pd.DataFrame:
    """``resampleDF``: means over the periods (start + (k−1)·Ts, start + k·Ts], time at each period's end,
    a period with a missing value in a column missing there, periods without rows kept as missing."""
    t = ((frame["t"] - pd.Timestamp(0)).dt.total_seconds()).round().astype("int64")
    start, end = int(t.iloc[0]), int(t.iloc[-1])
    kept = frame.loc[(t > start) & (t <= end)].drop(columns="t")
    period = -((t[(t > start) & (t <= end)] - start) // -seconds)
    means = kept.groupby(period.to_numpy()).mean(numeric_only=True)
    means = means.where(kept.isna().groupby(period.to_numpy()).sum() == 0)  # R's mean(na.rm = FALSE)
    count = -((end - start) // -seconds)
    means = means.reindex(np.arange(1, count + 1))
    times = pd.to_datetime(start + seconds * means.index.to_numpy(), unit="s")
    return means.reset_index(drop=True).assign(t=times)[list(frame.columns)]


def _day_of_year(times: pd.Series) -> np.ndarray:
    """R's ``as.POSIXlt(time)$yday``: days since the 1st of January, from 0."""
    return times.dt.day_of_year.to_numpy() - 1


def _declination(times) -> np.ndarray:
    """``aoiSunDeclination`` [rad]."""
    day = _day_of_year(times) + 1
    return np.arcsin(np.sin(np.radians(23.45)) * np.sin(np.radians(360 / 365 * (day - 81))))


def _hour_angle(times, longitude: float) -> np.ndarray:
    """``aoiSunHourAngle`` [rad]: from the local solar time (the equation of time included)."""
    b = np.radians(360 / 365 * (_day_of_year(times) - 81))
    equation_of_time = 9.87 * np.sin(2 * b) - 7.53 * np.cos(b) - 1.5 * np.sin(b)  # minutes
    solar = times + pd.to_timedelta((4 * longitude + equation_of_time) * 60, unit="s")
    hours = (solar - solar.dt.floor("D")).dt.total_seconds().to_numpy() / 3600
    return np.radians(15 * (hours - 12))


def _elevation(times, latitude: float, longitude: float) -> np.ndarray:
    """``aoiSunElevationDeg`` (which returns radians)."""
    declination, hour = _declination(times), _hour_angle(times, longitude)
    phi = np.radians(latitude)
    return np.arcsin(np.cos(hour) * np.cos(declination) * np.cos(phi) + np.sin(declination) * np.sin(phi))


def _azimuth(times, latitude: float, longitude: float) -> np.ndarray:
    """``aoiSunAzimuthDeg`` (which returns radians, from north through east)."""
    declination, hour = _declination(times), _hour_angle(times, longitude)
    phi = np.radians(latitude)
    elevation = _elevation(times, latitude, longitude)
    cosine = (np.sin(declination) * np.cos(phi) - np.cos(declination) * np.sin(phi) * np.cos(hour)) / np.cos(elevation)
    azimuth = np.arccos(np.clip(cosine, -1.0, 1.0))
    return np.where(hour > 0, 2 * np.pi - azimuth, azimuth)


def ten_minutes(minutes: pd.DataFrame) -> pd.DataFrame:
    """The Annex 58 exercise's 10-minute data from its 1-minute series, as the course's R code derives them.

    Parameters
    ----------
    minutes : pandas.DataFrame
        The 1-minute series (``greyid.datasets.fetch("annex58_ce4_1min")``), its
        ``t`` timestamps in UTC.

    Returns
    -------
    pandas.DataFrame
        10-minute averages from the first whole hour after the removed start: ``t``,
        ``Ti`` and ``Te`` (the means of the two sensors), ``deltaT``, ``Qi``, ``Gv``,
        ``tod`` (the hour of day) and the sun's position; the data set
        ``annex58_ce4_10min``.
    """
    frame = minutes.copy()
    frame["t"] = pd.to_datetime(frame["t"])
    x = _resample(frame, 600)
    x["tod"] = (x["t"] - x["t"].dt.floor("D")).dt.total_seconds() / 3600
    x["Ti"] = (x["Ti.down"] + x["Ti.up"]) / 2
    x["Te"] = (x["Te.down"] + x["Te.middle"]) / 2
    x["deltaT"] = x["Ti"] - x["Te"]
    half = (x["t"].iloc[1] - x["t"].iloc[0]) / 2  # the azimuth at the middle of each period
    x["sunAzimuth"] = _azimuth(x["t"] - half, LATITUDE, LONGITUDE)
    x["sunElevation"] = _elevation(x["t"], LATITUDE, LONGITUDE)
    x = x.loc[x["t"] > x["t"].iloc[0].floor("h") + pd.Timedelta(hours=REMOVED_HOURS)].reset_index(drop=True)
    # prepare_data: time in seconds from the first sample, the output, and stepQi (1 from the start to
    # the first switch of the heating, then from one sample before each switch to AFTER_STEP after it).
    x["timedate"] = x["t"]
    x["t"] = (x["t"] - x["t"].iloc[0]).dt.total_seconds()
    x["yTi"] = x["Ti"]
    x["Gouter"] = x["Gvn.2"]
    switches = np.flatnonzero(np.abs(np.diff(x["Qi"].to_numpy())) > 10)  # 0-based: between k and k+1
    step = np.zeros(len(x))
    marked = sorted({k for s in switches for k in range(s - 1, s + AFTER_STEP + 1) if 0 <= k < len(x)})
    if marked:
        step[marked] = 1.0
        step[:marked[0] + 1] = 1.0
    x["stepQi"] = step
    return x


def read_x5(path) -> pd.DataFrame:
    """The course's ``X5.rda``: the data frame X, its POSIXct ``t`` (seconds since 1970, UTC) as timestamps."""
    frame = read_rda(path)
    frame["t"] = pd.to_datetime(frame["t"].astype(float), unit="s")
    return frame
