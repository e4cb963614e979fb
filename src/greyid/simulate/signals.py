"""Input signals for experiments: PRBS, steps and multisines.

The pseudo-random binary sequence is the maximal-length sequence of a linear
feedback shift register (Godfrey, 1980), as used for the heating in the
thesis' test-cell study (order 6, 8 h clock, section 7.2).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Feedback taps (exponents of a primitive polynomial) giving maximal length.
PRBS_TAPS = {
    2: (2, 1), 3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
    10: (10, 7), 11: (11, 9), 12: (12, 11, 10, 4), 13: (13, 12, 11, 8), 14: (14, 13, 12, 2),
    15: (15, 14), 16: (16, 15, 13, 4), 17: (17, 14), 18: (18, 11), 19: (19, 18, 17, 14),
    20: (20, 17), 21: (21, 19), 22: (22, 21), 23: (23, 18), 24: (24, 23, 22, 17),
}


def prbs(order: int, clock: int = 1, levels: tuple[float, float] = (0.0, 1.0), length: int | None = None,
         shift: int = 0) -> np.ndarray:
    """A maximal-length pseudo-random binary sequence (Godfrey 1980), each bit held for ``clock`` samples.

    Parameters
    ----------
    order : int
        The shift register's length n, 2 to 24: the period is 2ⁿ − 1 bits.
    clock : int
        Samples per bit.
    levels : tuple of float
        The low and high values.
    length : int, optional
        Samples returned (default one period, (2ⁿ − 1)·clock); the sequence repeats.
    shift : int
        Rotates the start of the sequence, in bits.

    Returns
    -------
    numpy.ndarray
        The signal, float64.

    Raises
    ------
    ValueError
        An order outside 2–24, a clock or length that is not a positive whole number.

    Examples
    --------
    >>> from greyid.simulate import prbs
    >>> prbs(3, levels=(0.0, 300.0))
    array([300., 300., 300.,   0.,   0., 300.,   0.])
    """
    if order not in PRBS_TAPS:
        raise ValueError(f"PRBS order must be between 2 and 24, got {order}")
    if not isinstance(clock, (int, np.integer)) or clock < 1:
        raise ValueError(f"clock must be a positive whole number of samples, got {clock!r}")
    period = 2**order - 1
    register = [1] * order
    bits = np.empty(period, dtype=np.int8)
    taps = PRBS_TAPS[order]
    for i in range(period):
        bits[i] = register[-1]
        feedback = 0
        for tap in taps:
            feedback ^= register[tap - 1]
        register = [feedback] + register[:-1]
    bits = np.roll(bits, -shift)
    samples = np.repeat(bits, clock)
    if length is None:
        length = len(samples)
    if length < 1:
        raise ValueError(f"length must be positive, got {length}")
    samples = np.resize(samples, length)
    low, high = levels
    return np.where(samples == 1, high, low).astype(np.float64)


def steps(times: Sequence[float], changes: Sequence[tuple[float, float]], initial: float = 0.0) -> np.ndarray:
    """A piecewise-constant signal: ``initial``, then each ``level`` from its time on.

    Parameters
    ----------
    times : array_like
        The sample times.
    changes : sequence of tuple
        ``[(time, level), ...]``.
    initial : float
        The level before the first change.

    Returns
    -------
    numpy.ndarray
        The signal at ``times``.
    """
    times = np.asarray(times, dtype=np.float64)
    out = np.full(times.shape, float(initial))
    for when, level in sorted(changes):
        out[times >= when] = level
    return out


def multisine(times: Sequence[float], frequencies: Sequence[float], power: Sequence[float] | None = None,
              total_power: float = 1.0, phases: str | Sequence[float] = "schroeder", seed: int = 0,
              offset: float = 0.0) -> np.ndarray:
    """A sum of sines at given frequencies with a chosen power split.

    Parameters
    ----------
    times : array_like
        The sample times.
    frequencies : sequence of float
        In cycles per time unit.
    power : sequence of float, optional
        Each frequency's share of ``total_power`` (default: equal shares).
    total_power : float
        The signal's variance.
    phases : {"schroeder", "random"} or sequence of float
        Schroeder's phases (a low crest factor), seeded random ones, or given ones.
    seed : int
        The seed of random phases.
    offset : float
        The signal's mean.

    Returns
    -------
    numpy.ndarray
        The signal at ``times``.
    """
    times = np.asarray(times, dtype=np.float64)
    freqs = np.asarray(frequencies, dtype=np.float64)
    k = len(freqs)
    if k == 0:
        raise ValueError("multisine needs at least one frequency")
    share = np.full(k, 1.0 / k) if power is None else np.asarray(power, dtype=np.float64)
    if share.shape != (k,) or np.any(share < 0) or share.sum() <= 0:
        raise ValueError("power must hold one non-negative share per frequency")
    share = share / share.sum()
    amplitudes = np.sqrt(2.0 * total_power * share)
    if isinstance(phases, str):
        if phases == "schroeder":
            idx = np.arange(1, k + 1)
            phi = -np.pi * idx * (idx - 1) / k
        elif phases == "random":
            phi = np.random.default_rng(seed).uniform(0, 2 * np.pi, k)
        else:
            raise ValueError(f"unknown phases '{phases}'; use 'schroeder', 'random' or an array")
    else:
        phi = np.asarray(phases, dtype=np.float64)
    return offset + np.sum(amplitudes[:, None] * np.sin(2 * np.pi * freqs[:, None] * times[None, :] + phi[:, None]),
                           axis=0)
