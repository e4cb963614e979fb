"""Sampling: information per sample and per unit time against the sampling interval (thesis section 6.4)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import ModelError
from .frequency import frequency_information_grid
from .multisine import optimal_multisine


def aliased(omegas, sampling_interval: float) -> np.ndarray:
    """The frequencies in [0, π/τ] that sampled (held) sinusoids at ``omegas`` cannot be told from.

    Parameters
    ----------
    omegas : array_like
        Angular frequencies.
    sampling_interval : float
        τ.

    Returns
    -------
    numpy.ndarray
        The aliases, one per frequency.
    """
    band = 2 * np.pi / sampling_interval
    return np.abs((np.asarray(omegas, dtype=np.float64) + band / 2) % band - band / 2)


def sampling_table(model, params, input: str, intervals, frequencies=None, weights=None, power: float = 1.0,
                   free=None, include_noise: bool = True) -> pd.DataFrame:
    """The D-criterion per sample and per unit time against the sampling interval (section 6.4, (6.72)).

    For each interval τ the information per sample M(τ) = M̄_c(τ) + power·Σ w_l M_u(ω_l; τ)
    of the input design, and per unit time M(τ)/τ (a fixed experiment time).

    Parameters
    ----------
    model : Model
        A linear time-invariant model.
    params : mapping of str to float
        The assumed parameter values.
    input : str
        The input designed.
    intervals : array_like
        The sampling intervals τ.
    frequencies : array_like, optional
        The design's frequencies (rad per time unit; one above the Nyquist
        frequency π/τ acts as its alias); without them, the D-optimal multisine for
        each τ (the joint input and sampling design of a fixed number of samples).
    weights : array_like, optional
        Their power shares.
    power : float
        The input's variance.
    free : sequence of str, optional
        The parameters.
    include_noise : bool
        Include M̄_c.

    Returns
    -------
    pandas.DataFrame
        Columns ``interval``, ``D_per_sample`` = −log det M, ``D_per_time`` =
        −log det(M/τ), and the ``frequencies`` and ``weights`` of the design used.
    """
    rows = []
    for tau in np.asarray(intervals, dtype=np.float64):
        if not tau > 0:
            raise ModelError(f"sampling intervals must be positive, got {tau!r}")
        if frequencies is None:
            best = optimal_multisine(model, params, input, float(tau), power=power, free=free,
                                     include_noise=include_noise)
            freqs, share, M = best.frequencies, best.weights, best.information.to_numpy()
        else:
            freqs = aliased(frequencies, tau)
            share = np.full(len(freqs), 1.0 / len(freqs)) if weights is None else np.asarray(weights, float)
            if share.shape != freqs.shape or np.any(share < 0) or not np.isclose(share.sum(), 1.0):
                raise ModelError("weights must hold one non-negative power fraction per frequency, summing to 1")
            M_u, M_c, _ = frequency_information_grid(model, params, freqs, input, float(tau), free)
            M = (M_c if include_noise else 0.0) + power * np.einsum("l,lij->ij", share, M_u)
        sign, logdet = np.linalg.slogdet(M)
        per_sample = -logdet if sign > 0 else np.inf
        per_time = per_sample + M.shape[0] * np.log(tau) if sign > 0 else np.inf
        rows.append(dict(interval=float(tau), D_per_sample=float(per_sample), D_per_time=float(per_time),
                         frequencies=tuple(np.round(freqs, 6)), weights=tuple(np.round(share, 4))))
    return pd.DataFrame(rows)
