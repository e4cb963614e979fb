"""Heat diffusion through a homogeneous wall and its lumped RC approximations (thesis section 7.1).

The exact solution (7.9)–(7.12): with R = d/κ and C = dρχ per unit area,
the inner surface temperature is v₁ = (B/D) q₁ + (1/D) v₂ with

    B(s) = R sinh(√(sRC))/√(sRC),   D(s) = cosh(√(sRC))                   (7.15)

(q₁ the heat flux entering the inner surface, v₂ the outer surface
temperature).  A ladder of resistances r₁ … r_{n+1} and capacitances c₁ … c_n
(figure 7.3) has the transfer matrix Π [[1, r_i], [0, 1]]·[[1, 0], [c_i s, 1]],
whose upper-right and lower-right entries are the polynomials B_n and D_n.
The network "from the infinite product expansion" keeps the gain Σr_i = R and
the first n zeros of B (s = −k²π²/RC) and D (s = −(k − ½)²π²/RC) (7.16–7.17):
[`lumped_wall()`][greyid.library.walls.lumped_wall] solves for it at any order (the thesis prints orders 1
and 2, (7.20) and (7.23)), [`wall_frequency_response()`][greyid.library.walls.wall_frequency_response] puts the exact
and
lumped responses side by side so one sees over which band a lumped model is
adequate, and [`wall_model()`][greyid.library.walls.wall_model] is the n-node wall as a greyid model.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pandas as pd

from ..errors import ModelError
from ..api import Model


def ladder_polynomials(r, c, s):
    """The polynomials ``(B_n(s), D_n(s))`` of the ladder r₁, c₁, r₂, …, c_n, r_{n+1}.

    Parameters
    ----------
    r : array_like
        The n + 1 resistances.
    c : array_like
        The n capacitances.
    s : array_like
        Complex frequencies (any shape).

    Returns
    -------
    tuple of numpy.ndarray
        B_n(s) and D_n(s), shaped as ``s``.
    """
    s = np.asarray(s, dtype=complex)
    a, b = np.ones_like(s), np.zeros_like(s) + r[0]
    cc, d = np.zeros_like(s), np.ones_like(s)
    for ci, ri in zip(c, r[1:]):
        # M ← M · [[1, 0], [c s, 1]] · [[1, r], [0, 1]]
        a, b, cc, d = a + b * ci * s, b, cc + d * ci * s, d
        b, d = a * ri + b, cc * ri + d
    return b, d


@lru_cache(maxsize=None)
def lumped_wall(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Fractions ``(r/R, c/C)`` of the order-n network from the infinite product expansion (7.20, 7.23).

    The truncated products B_n(s) = Π_{k≤n}(1 + s/(k²π²)) and D_n(s) =
    Π_{k≤n}(1 + s/((k − ½)²π²)) (R = C = 1) are the ladder's own polynomials, so
    its elements follow from the continued-fraction (Cauer) expansion of the
    impedance B_n/D_n = r₁ + 1/(c₁s + 1/(r₂ + …)), exactly.

    Parameters
    ----------
    order : int
        n, the number of capacitances.

    Returns
    -------
    tuple of numpy.ndarray
        ``(r, c)``: n + 1 resistances and n capacitances as fractions of R and C.

    Raises
    ------
    ModelError
        An expansion that gives a non-physical network.
    """
    if not isinstance(order, (int, np.integer)) or order < 1:
        raise ModelError(f"the order of a lumped wall must be a positive integer, got {order!r}")
    n = int(order)
    k = np.arange(1, n + 1)
    # Coefficients, highest power first, each of degree n exactly.
    numerator = np.poly((-(k * np.pi) ** 2)) / np.prod((k * np.pi) ** 2)
    denominator = np.poly((-((k - 0.5) * np.pi) ** 2)) / np.prod(((k - 0.5) * np.pi) ** 2)
    r, c = [], []
    for _ in range(n):
        r.append(numerator[0] / denominator[0])  # Z(∞): the series resistance
        numerator = (numerator - r[-1] * denominator)[1:]  # one degree less
        c.append(denominator[0] / numerator[0])  # Y(s) ~ c s at infinity: the shunt capacitance
        denominator = (denominator - c[-1] * np.append(numerator, 0.0))[1:]
    r.append(numerator[0] / denominator[0])
    r, c = np.array(r), np.array(c)
    if np.any(~(r > 0)) or np.any(~(c > 0)):
        raise ModelError(f"the order-{n} expansion gives a non-physical network (r={r}, c={c})")
    return r, c


def wall_frequency_response(R: float, C: float, omega, orders=(1, 2)) -> pd.DataFrame:
    """Exact and lumped frequency responses of a homogeneous wall (figures 7.4–7.5).

    Parameters
    ----------
    R : float
        The wall's resistance per unit area [K m²/W] (or any consistent units).
    C : float
        Its capacity per unit area [J/(K m²)].
    omega : array_like
        Angular frequencies [rad per time unit of RC].
    orders : sequence of int
        The lumped networks' orders.

    Returns
    -------
    pandas.DataFrame
        ``omega``, then for ``exact`` and each order n: ``<model>_BD_gain`` and
        ``<model>_BD_phase`` (heat flux → inner temperature, B/D: gain in
        K/(W/m²), phase in degrees) and ``<model>_D_gain``, ``<model>_D_phase``
        (outer → inner temperature, 1/D).
    """
    if not (R > 0 and C > 0):
        raise ModelError(f"R and C must be positive, got R={R!r}, C={C!r}")
    omega = np.asarray(omega, dtype=np.float64)
    s = 1j * omega
    root = np.sqrt(s * R * C)
    with np.errstate(invalid="ignore", divide="ignore"):
        exact_b = np.where(np.abs(root) > 1e-12, R * np.sinh(root) / np.where(root == 0, 1, root), R)
    exact_d = np.cosh(root)
    out = {"omega": omega}

    def add(label, b, d):
        out[f"{label}_BD_gain"] = np.abs(b / d)
        out[f"{label}_BD_phase"] = np.degrees(np.angle(b / d))
        out[f"{label}_D_gain"] = np.abs(1 / d)
        out[f"{label}_D_phase"] = np.degrees(np.angle(1 / d))

    add("exact", exact_b, exact_d)
    for order in orders:
        r, c = lumped_wall(int(order))
        b, d = ladder_polynomials(R * r, C * c, s)
        add(f"order{int(order)}", b, d)
    return pd.DataFrame(out)


def wall_model(nodes: int = 2, name: str | None = None) -> Model:
    """A wall of ``nodes`` capacitances between its two surfaces (figure 7.3), as a greyid model.

    Inputs ``v1`` and ``v2`` (inner and outer surface temperatures), states
    ``T1 … Tn`` (node temperatures, from the inside out), output ``q1`` (the heat
    flux entering the inner surface, (v1 − T1)/r1).  Each node obeys (7.25):
    c_i dT_i = ((T_{i−1} − T_i)/r_i − (T_i − T_{i+1})/r_{i+1}) dt.

    Parameters
    ----------
    nodes : int
        The number of capacitances.
    name : str, optional
        The model's name.

    Returns
    -------
    Model
        Parameters ``r1 … r_{n+1}``, ``c1 … c_n`` (start values: the
        infinite-product network of a wall with R = 1, C = 1; set your own),
        process noise ``s1 … sn`` (log-intensities) and the measurement variance
        ``e`` (log).
    """
    if not isinstance(nodes, (int, np.integer)) or nodes < 1:
        raise ModelError(f"a wall needs at least one node, got {nodes!r}")
    n = int(nodes)
    r_start, c_start = lumped_wall(n)
    m = Model(name or f"wall{n}", f"Homogeneous wall, {n}-node RC ladder (thesis 7.1, figure 7.3). Inputs v1, v2 "
                                  "(inner, outer surface temperature); output q1 (heat flux into the inner surface).")
    temps = ["v1"] + [f"T{i}" for i in range(1, n + 1)] + ["v2"]
    for i in range(1, n + 1):
        left, here, right = temps[i - 1], temps[i], temps[i + 1]
        m.add_system(f"d{here} = (({left} - {here})/r{i} - ({here} - {right})/r{i + 1})/c{i}*dt + exp(s{i})*dw{i}")
    m.add_inputs("v1", "v2")
    m.add_observation("q1 = (v1 - T1)/r1", variance="exp(e)")
    m.set_initial_state(mean={f"T{i}": f"T{i}0" for i in range(1, n + 1)}, covariance="stationary")
    for i, value in enumerate(r_start, start=1):
        m.set_parameter(f"r{i}", init=float(value), lower=0.0)
    for i, value in enumerate(c_start, start=1):
        m.set_parameter(f"c{i}", init=float(value), lower=0.0)
    for i in range(1, n + 1):
        m.set_parameter(f"s{i}", init=-3.0)
        m.set_parameter(f"T{i}0", init=0.0)
    m.set_parameter("e", init=-5.0)
    m.add_derived("U", "1/(" + " + ".join(f"r{i}" for i in range(1, n + 2)) + ")")
    m.add_derived("C_lumped", " + ".join(f"c{i}" for i in range(1, n + 1)))
    return m
