"""Figures of the report that are not validation figures, and embedding of figures."""

from __future__ import annotations

import base64
import io

import pandas as pd
from matplotlib.figure import Figure

from ..validation.plots import labelled


def data_figure(frame: pd.DataFrame, time_name: str, outputs, inputs, units=None) -> Figure:
    """Every output (dots) and input (lines) of one data set against time, one panel each."""
    columns = [(name, "output") for name in outputs] + [(name, "input") for name in inputs]
    fig = Figure(figsize=(11, 1.9 * len(columns) + 0.6), layout="constrained")
    axes = fig.subplots(len(columns), 1, sharex=True, squeeze=False)[:, 0]
    t = frame[time_name]
    for ax, (name, role) in zip(axes, columns):
        if role == "output":
            ax.plot(t, frame[name], ".", color="k", ms=2)
        else:
            ax.plot(t, frame[name], color="C0", lw=0.9)
        ax.set_ylabel(f"{labelled(name, units)}\n({role})", fontsize=8)
        ax.tick_params(labelsize=8)  # the label and its ticks at one size
    axes[0].set_title("measured data")
    axes[-1].set_xlabel(labelled(time_name, units))
    return fig


def latent_force_figure(times, forces: pd.DataFrame, names, time_name: str, units=None) -> Figure:
    """Each latent force's smoothed path with its band of ±2 standard deviations, one panel each."""
    fig = Figure(figsize=(11, 1.9 * len(names) + 0.6), layout="constrained")
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    for ax, name in zip(axes, names):
        mean, sd = forces[name].to_numpy(), forces[f"{name}_sd"].to_numpy()
        ax.fill_between(times, mean - 2 * sd, mean + 2 * sd, color="C1", alpha=0.25, lw=0)
        ax.plot(times, mean, color="C1", lw=1.0)
        ax.set_ylabel(f"{labelled(name, units)}\n(latent)", fontsize=8)
        ax.tick_params(labelsize=8)
    axes[0].set_title("latent forces, smoothed (±2 standard deviations)")
    axes[-1].set_xlabel(labelled(time_name, units))
    return fig


def embedded_png(fig: Figure, dpi: int = 90) -> str:
    """An ``<img>`` holding the figure as a base64 PNG (the report stays one file)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img class="figure" alt="figure" src="data:image/png;base64,{data}">'
