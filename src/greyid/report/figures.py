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


def embedded_png(fig: Figure, dpi: int = 90) -> str:
    """An ``<img>`` holding the figure as a base64 PNG (the report stays one file)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img class="figure" alt="figure" src="data:image/png;base64,{data}">'
