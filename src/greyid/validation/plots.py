"""Figures for validation (section 5.3): returned, never shown, so scripts can save them.

Figures are built with `matplotlib.figure.Figure` directly, without
pyplot's global state, so they work in scripts, notebooks and reports alike.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from scipy import stats

from .independence import acf, pacf
from .series import residual_series
from .spectral import coherency, cross_correlation, cumulative_periodogram


def _stem(ax, frame: pd.DataFrame, column: str, title: str) -> None:
    ax.vlines(frame.index, 0, frame[column], color="C0")
    ax.plot(frame.index, frame[column], "o", color="C0", ms=3)
    ax.fill_between(frame.index, frame["lower"], frame["upper"], color="C1", alpha=0.2, lw=0)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_title(title)
    ax.set_xlabel("lag")


def residual_dashboard(residuals: pd.Series, inputs: pd.DataFrame | None = None, times=None,
                       lags: int | None = None, level: float = 0.05, title: str | None = None,
                       time_label: str = "time") -> Figure:
    """A residual dashboard: residuals over time, ACF, PACF, cumulative periodogram, histogram, QQ, input correlations.

    Parameters
    ----------
    residuals : pandas.Series
        Standardised residuals.
    inputs : pandas.DataFrame, optional
        The inputs, for the cross-correlations.
    times : array_like, optional
        The residuals' times.
    lags : int, optional
        The correlations' largest lag.
    level : float
        The bands' significance level.
    title : str, optional
        The figure's title.
    time_label : str
        The time axis' label.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    values = residual_series(residuals, 8)
    fig = Figure(figsize=(12, 9), layout="constrained")
    grid = fig.add_gridspec(3, 3)
    ax = fig.add_subplot(grid[0, :])
    x = residuals.index if times is None else times
    ax.plot(x, np.asarray(residuals, dtype=float), lw=0.7)
    z = stats.norm.ppf(1 - level / 2)
    for s in (-z, z):
        ax.axhline(s, color="C1", ls="--", lw=0.8)
    ax.set_title(title or f"standardised residuals {residuals.name or ''}".strip())
    ax.set_xlabel(time_label if times is not None else "row")

    _stem(fig.add_subplot(grid[1, 0]), acf(values, lags, level), "acf", "autocorrelation")
    _stem(fig.add_subplot(grid[1, 1]), pacf(values, lags, level), "pacf", "partial autocorrelation")

    ax = fig.add_subplot(grid[1, 2])
    cp = cumulative_periodogram(values)
    ax.plot(cp.index, cp["cumulative"], lw=1.0, label="residuals")
    ax.plot(cp.index, cp["white"], color="k", lw=0.6)
    for col, ls in zip([c for c in cp.columns if c.startswith("band_")], ("--", ":")):
        ax.plot(cp.index, np.clip(cp["white"] + cp[col], 0, 1), color="C1", ls=ls, lw=0.8, label=col[5:])
        ax.plot(cp.index, np.clip(cp["white"] - cp[col], 0, 1), color="C1", ls=ls, lw=0.8)
    ax.set_title("cumulative periodogram")
    ax.set_xlabel("frequency [cycles per sample]")
    ax.legend(fontsize=7, loc="lower right")

    ax = fig.add_subplot(grid[2, 0])
    ax.hist(values, bins="auto", density=True, alpha=0.6)
    grid_x = np.linspace(min(values.min(), -4), max(values.max(), 4), 200)
    ax.plot(grid_x, stats.norm.pdf(grid_x), color="k", lw=0.8)
    ax.set_title("histogram and N(0, 1)")

    ax = fig.add_subplot(grid[2, 1])
    theo = stats.norm.ppf((np.arange(1, len(values) + 1) - 0.5) / len(values))
    ax.plot(theo, np.sort(values), ".", ms=2)
    lim = [theo.min(), theo.max()]
    ax.plot(lim, lim, color="k", lw=0.8)
    ax.set_title("normal QQ plot")
    ax.set_xlabel("N(0, 1) quantiles")

    ax = fig.add_subplot(grid[2, 2])
    # A constant input has no correlation with anything: left out of the panel, named in its title.
    varying = [] if inputs is None else [name for name in inputs.columns if inputs[name].nunique(dropna=True) > 1]
    if varying:
        for i, name in enumerate(varying):
            cc = cross_correlation(residuals, inputs[name], lags, level)
            ax.plot(cc.index, cc["ccf"], "o-", ms=2, lw=0.7, label=name, color=f"C{i}")
        ax.fill_between(cc.index, cc["lower"], cc["upper"], color="C1", alpha=0.2, lw=0)
        ax.axhline(0, color="k", lw=0.6)
        ax.legend(fontsize=7)
        ax.set_xlabel("lag (input leads for lag > 0)")
    constant = [] if inputs is None else [name for name in inputs.columns if name not in varying]
    ax.set_title("cross-correlation with inputs" + (f" ({', '.join(constant)} constant)" if constant else ""))
    return fig


def coherency_figure(residuals: pd.Series, inputs: pd.DataFrame, m: int | None = None, dt: float = 1.0,
                     level: float = 0.05, time_unit: str | None = None) -> Figure:
    """The squared coherency with each input and the multiple coherency, with the (7.42) critical levels.

    Parameters
    ----------
    residuals : pandas.Series
        Standardised residuals.
    inputs : pandas.DataFrame
        The inputs.
    m : int, optional
        The Daniell smoother's half-width.
    dt : float
        The sampling interval.
    level : float
        The critical levels' significance level.
    time_unit : str, optional
        The time unit, for the frequency axis' label.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    from ..model.units import pretty

    coh = coherency(residuals, inputs, m=m, dt=dt, level=level)
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax = fig.add_subplot()
    for i, col in enumerate(coh.values.columns):
        color = "k" if col == "multiple" else f"C{i}"
        ax.plot(coh.values.index, coh.values[col], lw=1.2 if col == "multiple" else 0.8, color=color, label=col)
    # The critical levels (7.42) in greys no curve uses, each in the legend: one level serves every single
    # input's coherency (it depends on m alone), another the multiple coherency.
    singles = sorted({float(coh.critical[c]) for c in coh.values.columns if c != "multiple"})
    for k, value in enumerate(singles):
        label = f"{1 - level:.0%} critical level, one input" + (f" ({k + 1})" if len(singles) > 1 else "")
        ax.axhline(value, color="0.55", ls="--", lw=0.9, label=label)
    if "multiple" in coh.values.columns:
        ax.axhline(float(coh.critical["multiple"]), color="0.3", ls=":", lw=1.1,
                   label=f"{1 - level:.0%} critical level, multiple")
    ax.set_ylim(0, 1)
    ax.set_xlabel(f"frequency [1/{pretty(time_unit)}]" if time_unit else "frequency [cycles per time unit]")
    ax.set_ylabel("squared coherency")
    ax.set_title(f"coherency of residuals and inputs (Daniell m = {coh.m})")
    ax.legend(fontsize=8)
    return fig


def labelled(name: str, units=None) -> str:
    """``name [unit]`` where the model gives the name a unit, written as the report's tables write it
    (``kW/m²``, ``°C``: [`greyid.model.units.pretty()`][greyid.model.units.pretty])."""
    from ..model.units import pretty

    unit = (units or {}).get(name)
    return f"{name} [{pretty(unit)}]" if unit else name


def band_figure(frame: pd.DataFrame, time_name: str, outputs, title: str, band_label: str,
                centre_label: str = "simulated (deterministic)", units=None) -> Figure:
    """Measured outputs against a central curve (``<y>_simulated``) and a band (``<y>_lower``, ``<y>_upper``)."""
    fig = Figure(figsize=(11, 3.2 * len(outputs)), layout="constrained")
    axes = fig.subplots(len(outputs), 1, squeeze=False)[:, 0]
    t = frame[time_name]
    for ax, name in zip(axes, outputs):
        ax.fill_between(t, frame[f"{name}_lower"], frame[f"{name}_upper"], color="C0", alpha=0.25, lw=0,
                        label=band_label)
        ax.plot(t, frame[f"{name}_simulated"], color="C0", lw=1.0, label=centre_label)
        ax.plot(t, frame[name], ".", color="k", ms=2, label="measured")
        ax.set_ylabel(labelled(name, units))
        ax.legend(fontsize=7, loc="best")
    axes[0].set_title(title)
    axes[-1].set_xlabel(labelled(time_name, units))
    return fig


def prediction_figure(data: pd.DataFrame, predictions: pd.DataFrame, time_name: str, outputs, steps: int,
                      units=None) -> Figure:
    """Measured outputs against k-step predictions with ±2 standard deviations."""
    fig = Figure(figsize=(11, 3.2 * len(outputs)), layout="constrained")
    axes = fig.subplots(len(outputs), 1, squeeze=False)[:, 0]
    t = data[time_name]
    for ax, name in zip(axes, outputs):
        mean, sd = predictions[name], predictions[f"{name}_sd"]
        ax.fill_between(t, mean - 2 * sd, mean + 2 * sd, color="C2", alpha=0.25, lw=0, label="±2 sd")
        ax.plot(t, mean, color="C2", lw=1.0, label=f"{steps}-step prediction")
        ax.plot(t, data[name], ".", color="k", ms=2, label="measured")
        ax.set_ylabel(labelled(name, units))
        ax.legend(fontsize=7, loc="best")
    axes[0].set_title(f"measured and {steps}-step predicted outputs")
    axes[-1].set_xlabel(labelled(time_name, units))
    return fig
