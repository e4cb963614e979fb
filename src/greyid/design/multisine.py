"""Optimal multisine inputs: local, Bayesian and minimax (thesis 6.3, theorem 6.1, 6.36–6.39, 7.49–7.50).

A design ξ puts power fractions α_l on sinusoids at frequencies ω_l; its
information per sample at parameter values θ is

    M(ξ; θ) = M̄_c(θ) + P Σ_l α_l M_u(ω_l; θ)                    (6.47–6.49)

([`frequency`][greyid.design.frequency]).  The criterion Φ (D or A) of M is convex in α, and so are

* the local design: Φ(M(ξ; θ₀)) at the assumed values;
* the Bayesian design (J₃ of 6.36–6.38): Σ_j π_j Φ(M(ξ; θ_j)) over draws or
  quadrature points θ_j of a prior with weights π_j;
* the minimax design (6.39): max_j Φ(M(ξ; θ_j)) over a grid θ_j on a box.

The first two are solved by the multiplicative algorithm for convex design on a
frequency grid with the averaged directional derivative.  The minimax design is
the saddle point max_π min_ξ Σ_j π_j Φ_j(ξ) (convex in ξ, linear in π): an
outer mirror ascent moves the weights π towards the least favourable
distribution over the grid, each step a Bayesian design, and stops when the
duality gap max_j Φ_j − Σ_j π_j Φ_j is small.  Every design ends with a local
refinement of the support's frequencies and weights.  The general equivalence
theorem (theorem 6.1) is the check: with the final π no frequency has a larger
directional derivative than the design's support.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize

from ..errors import ModelError
from ..scaled import RANK_TOLERANCE, ScaledInformation
from .criteria import parameter_points
from .frequency import frequency_information_grid, frequency_information_points

#: Multiplicative iterations per Bayesian sub-problem of the minimax design.
MINIMAX_INNER = 300
#: Outer (mirror ascent) iterations of the minimax design at most.
MINIMAX_OUTER = 400


@dataclass
class MultisineDesign:
    """An optimal input: sinusoids at ``frequencies`` (rad per time unit) with power ``weights``."""

    frequencies: np.ndarray
    weights: np.ndarray  # fractions of the total power, summing to 1
    value: float  # the criterion at the design (minimised): local, averaged or worst case
    criterion: str
    power: float
    max_derivative: float  # largest directional derivative over the frequency band
    support_derivative: float  # the design's own (equal at an optimum: equivalence theorem)
    information: pd.DataFrame  # per sample, of the design, at the assumed parameter values
    kind: str = "local"  # "local", "Bayesian" or "minimax"
    #: The parameter points the criterion was averaged or maximised over, with
    #: their weights π (for minimax the least favourable distribution found) and
    #: the criterion of the design at each; ``None`` for a local design.
    points: pd.DataFrame | None = None
    gap: float = 0.0  # minimax: worst value minus the π-average (0 at the saddle point)
    values: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def signal(self, times, offset: float = 0.0, phases="schroeder") -> np.ndarray:
        """The designed input's time series.

        Parameters
        ----------
        times : array_like
            The sample times.
        offset : float
            The signal's mean.
        phases : {"schroeder", "random"} or sequence of float
            The sinusoids' phases.

        Returns
        -------
        numpy.ndarray
            The signal (a sinusoid at frequency 0 is a constant of its power).
        """
        from ..simulate.signals import multisine

        times = np.asarray(times, dtype=np.float64)
        out = np.full(times.shape, float(offset))
        constant = self.frequencies <= 1e-12
        if np.any(constant):
            out += np.sqrt(self.power * self.weights[constant].sum())
        if np.any(~constant):
            share = self.weights[~constant]
            out += multisine(times, self.frequencies[~constant] / (2 * np.pi), power=share,
                             total_power=self.power * share.sum(), phases=phases)
        return out

    def table(self) -> pd.DataFrame:
        """The design as a table.

        Returns
        -------
        pandas.DataFrame
            ``frequency`` and ``weight`` (its share of the power), one row per sinusoid.
        """
        return pd.DataFrame({"frequency": self.frequencies, "weight": self.weights})


def _criterion_and_derivatives(M_s, Ms_s, kind, weight):
    """Value of the criterion at the scaled information M_s = S M S (without the scaling's offset of
    D) and the directional derivative towards each scaled S M_u(ω) S; ``weight`` is diag(S²), which
    takes A's trace of M⁻¹ = S M_s⁻¹ S back to the model's units.  +inf where M_s is singular.

    Batched: M_s (K, p, p), Ms_s (K, L, p, p), weight (K, p) give values (K,) and derivatives (K, L).
    """
    sign, logdet = np.linalg.slogdet(M_s)
    singular = (sign <= 0) | ~(np.linalg.cond(M_s) < 1.0 / RANK_TOLERANCE)
    M_s = np.where(singular[:, None, None], np.eye(M_s.shape[-1]), M_s)
    M_inv = np.linalg.inv(M_s)
    if kind == "D":
        values, towards = -logdet, M_inv
    else:
        values = np.einsum("ki,kii->k", weight, M_inv) / M_s.shape[-1]
        towards = M_inv @ (weight[:, :, None] * M_inv)
    derivatives = np.einsum("kij,klji->kl", towards, Ms_s)
    return np.where(singular, np.inf, values), np.where(singular[:, None], 0.0, derivatives)


class _Problem:
    """The information of every candidate frequency at every parameter point, scaled for the criterion.

    Each point's matrices are scaled to the unit diagonal of the uniform design's
    information, S M S (`greyid.scaled`): the same optimum in better
    conditioned numbers, whatever the parameters' units.  D's offset 2 Σ log S_ii
    and A's weights S_ii² give back each point's value in the model's units.
    """

    def __init__(self, model, points, input, tau, power, free, include_noise, omegas, criterion):
        self.model, self.points, self.input, self.tau = model, points, input, tau
        self.power, self.free, self.criterion = power, free, criterion
        M_u, M_c, self.names = frequency_information_points(model, points, omegas, input, tau, free)
        self.Ms = power * M_u  # (K, L, p, p)
        self.bases = M_c if include_noise else np.zeros_like(M_c)  # (K, p, p)
        total = self.Ms.mean(axis=1) + self.bases  # the uniform design's information at each point
        self.scales = []
        for point, M in zip(points, total):
            scaled = ScaledInformation.of(M, self.names)
            if scaled.singular:
                raise ModelError(f"sinusoids on '{input}' at every candidate frequency do not determine the "
                                 f"direction {scaled.describe()} (scaled parameters) at "
                                 f"{_point_text(point, self.names)}:"
                                 " no input design can; fix those parameters or choose free=")
            self.scales.append(scaled.scale)
        self.scales = np.array(self.scales)  # (K, p)
        self.weights = self.scales**2
        self.offsets = 2.0 * np.log(self.scales).sum(axis=1) if criterion == "D" else np.zeros(len(points))
        self.Ms_s = self._scaled(self.Ms)
        self.bases_s = np.einsum("ka,kab,kb->kab", self.scales, self.bases, self.scales)

    def _scaled(self, Ms):
        return np.einsum("ka,klab,kb->klab", self.scales, Ms, self.scales)

    def on_grid(self, alpha):
        """Each point's criterion and directional derivatives (K, L) of the grid design ``alpha``."""
        M = self.bases_s + np.einsum("l,klij->kij", alpha, self.Ms_s)
        values, derivatives = _criterion_and_derivatives(M, self.Ms_s, self.criterion, self.weights)
        return values + self.offsets, derivatives

    def support_information(self, freqs):
        """M_u at each point and each of ``freqs``, times the power: (K, k, p, p)."""
        M_u, _, _ = frequency_information_points(self.model, self.points, freqs, self.input, self.tau, self.free,
                                                 input_independent=False)
        return self.power * M_u

    def values(self, freqs, weights):
        """Each point's criterion of sinusoids at ``freqs`` with power fractions ``weights``."""
        M_f = self._scaled(self.support_information(freqs))
        M = self.bases_s + np.einsum("l,klij->kij", weights, M_f)
        return _criterion_and_derivatives(M, M_f, self.criterion, self.weights)[0] + self.offsets

    def at_design(self, freqs, weights):
        """Each point's criterion at a design, and its derivatives towards the grid and the support."""
        M_f = self._scaled(self.support_information(freqs))
        M = self.bases_s + np.einsum("l,klij->kij", weights, M_f)
        values, grid = _criterion_and_derivatives(M, self.Ms_s, self.criterion, self.weights)
        _, support = _criterion_and_derivatives(M, M_f, self.criterion, self.weights)
        return values + self.offsets, grid, support


def _point_text(point, names) -> str:
    return ", ".join(f"{n} = {point[n]:.4g}" for n in names)


def _multiplicative(problem, alpha, pi, iterations):
    """The multiplicative algorithm on the π-averaged criterion (a Fedorov–Wynn relative)."""
    for _ in range(iterations):
        _, derivatives = problem.on_grid(alpha)
        d = pi @ derivatives
        alpha = alpha * d / (alpha @ d)
    return alpha


def _minimax_on_grid(problem, alpha):
    """A minimax design on the frequency grid, as a start for the refinement.

    Active set: the minimax over the points that have been worst so far (one
    point: its local design), adding the point that is worst at that design.
    Over several active points, exponentiated-gradient ascent on π with
    decreasing steps (the points' values are the gradient of the dual), each
    step a Bayesian design; the design with the least worst value is kept.
    """
    K = len(problem.points)
    values, _ = problem.on_grid(alpha)
    active = [int(np.argmax(values))]
    best = (values.max(), alpha)
    while True:
        pi = np.zeros(K)
        pi[active] = 1.0 / len(active)
        alpha = _multiplicative(problem, alpha, pi, 5 * MINIMAX_INNER)
        values, _ = problem.on_grid(alpha)
        spread = max(values[active].max() - values[active].min(), 1e-12)
        for step in range(MINIMAX_OUTER if len(active) > 1 else 0):
            worst = values[active].max()
            if worst - pi @ values <= 1e-8 * max(1.0, abs(worst)):
                break
            pi[active] = pi[active] * np.exp((values[active] - worst) / (spread * np.sqrt(1.0 + step)))
            pi /= pi.sum()
            alpha = _multiplicative(problem, alpha, pi, MINIMAX_INNER // 10)
            values, _ = problem.on_grid(alpha)
            if values.max() < best[0]:
                best = (values.max(), alpha)
        if values.max() < best[0]:
            best = (values.max(), alpha)
        worst = int(np.argmax(values))
        if worst in active:
            return best[1]
        active.append(worst)


def _least_favourable(values, derivatives, support, weights, tolerance=1e-6):
    """Weights π on the worst points that make a minimax design satisfy the equivalence theorem.

    A design ξ is minimax-optimal when some distribution π on the points where
    its criterion is largest makes ξ optimal for the π-averaged criterion: no
    frequency's directional derivative Σ_j π_j d_j(ω) exceeds the support's
    Σ_j π_j s_j.  That is a linear programme in π (HiGHS through SciPy).
    """
    worst = values.max()
    active = np.flatnonzero(values >= worst - tolerance * max(1.0, abs(worst)) - 1e-9)
    excess = derivatives[active] - (support[active] @ weights)[:, None]  # (A, L)
    A = len(active)
    if A == 1:
        pi = np.zeros(len(values))
        pi[active] = 1.0
        return pi
    # minimise t subject to excessᵀπ ≤ t, Σπ = 1, π ≥ 0
    cost = np.r_[np.zeros(A), 1.0]
    upper = np.c_[excess.T, -np.ones(excess.shape[1])]
    solved = optimize.linprog(cost, A_ub=upper, b_ub=np.zeros(excess.shape[1]), A_eq=np.r_[np.ones(A), 0.0][None],
                              b_eq=[1.0], bounds=[(0, None)] * A + [(None, None)], method="highs")
    pi = np.zeros(len(values))
    pi[active] = solved.x[:A] if solved.success else 1.0 / A
    return pi / pi.sum()


def _peaks(omegas, alpha):
    """One sinusoid per peak of the grid weights, with its basin's weight summed.

    The algorithm leaves small weights spread around each support point, and
    merging all of them would average distinct peaks.
    """
    significant = alpha > 1e-3 * alpha.max()
    left = np.concatenate([[-np.inf], alpha[:-1]])
    right = np.concatenate([alpha[1:], [-np.inf]])
    peaks = np.flatnonzero(significant & (alpha >= left) & (alpha >= right))
    bounds = [0] + [int(p0 + np.argmin(alpha[p0:p1 + 1])) for p0, p1 in zip(peaks[:-1], peaks[1:])] + [len(alpha)]
    return omegas[peaks], np.array([alpha[lo:hi].sum() for lo, hi in zip(bounds[:-1], bounds[1:])])


def optimal_multisine(model, params, input: str, sampling_interval: float, criterion: str = "D",
                      power: float = 1.0, band=None, free=None, include_noise: bool = True,
                      grid: int = 400, iterations: int = 5000, prior=None, minimax=None, draws: int = 20,
                      seed: int = 0, levels: int = 2) -> MultisineDesign:
    """The input of a given power on one input that minimises a criterion per sample (6.3, 7.49).

    Candidate frequencies are 0 and a logarithmic grid up to the Nyquist frequency
    π/τ (or within ``band``); the information is M̄_c + power·Σ α_l M_u(ω_l).
    The result's ``max_derivative`` and ``support_derivative`` check the general
    equivalence theorem.

    Parameters
    ----------
    model : Model
        A linear time-invariant model.
    params : mapping of str to float
        The assumed parameter values (a local design).
    input : str
        The input to design.
    sampling_interval : float
        The time between samples, τ.
    criterion : {"D", "A"}
        The criterion minimised.
    power : float
        The input's variance.
    band : tuple of float, optional
        ``(low, high)`` angular frequencies the design may use.
    free : sequence of str, optional
        The parameters the information is taken for.
    include_noise : bool
        Include M̄_c, the information no input changes (False: the form of (7.50)).
    grid : int
        Candidate frequencies.
    iterations : int
        Steps of the design's weight iteration.
    prior : dict or pandas.DataFrame, optional
        Average the criterion over a prior (J₃, 6.36–6.38): a Gaussian
        ``{"mean", "sd", "corr"}`` (``draws`` seeded draws) or a DataFrame of points
        with an optional ``weight`` column.
    minimax : mapping or pandas.DataFrame, optional
        Minimise the worst value over a box ``{name: (low, high)}`` (a grid of
        ``levels`` values per parameter) or over a DataFrame's rows (6.39).
    draws : int
        Draws from a Gaussian prior.
    seed : int
        Their random seed.
    levels : int
        Grid values per parameter of a minimax box.

    Returns
    -------
    MultisineDesign
        ``frequencies``, ``weights`` (fractions of the power), ``value``,
        ``information``, the equivalence check, and for robust designs the ``points``
        with their weights (for minimax the least favourable distribution);
        ``signal(times)`` gives the input's time series.
    """
    if criterion not in ("D", "A"):
        raise ModelError(f"optimal_multisine supports criterion 'D' or 'A', not {criterion!r}")
    if not power > 0:
        raise ModelError(f"the input power must be positive, got {power!r}")
    tau = float(sampling_interval)
    nyquist = np.pi / tau
    low, high = (0.0, nyquist) if band is None else (float(band[0]), min(float(band[1]), nyquist))
    if not 0 <= low < high:
        raise ModelError(f"band must be (low, high) with 0 ≤ low < high ≤ π/τ = {nyquist:.4g}, got {band!r}")
    points, pi = parameter_points(model, params, prior, minimax, draws, seed, levels)
    kind = "local" if prior is None and minimax is None else ("Bayesian" if prior is not None else "minimax")
    start = max(low, high * 1e-4)
    omegas = np.unique(np.concatenate([[low], np.geomspace(start, high, grid)]))
    problem = _Problem(model, points, input, tau, float(power), free, include_noise, omegas, criterion)

    alpha = _multiplicative(problem, np.full(len(omegas), 1.0 / len(omegas)), pi, iterations)
    if kind == "minimax":
        alpha = _minimax_on_grid(problem, alpha)
    freq0, w0 = _peaks(omegas, alpha)

    def unpack(x):
        k = len(freq0)
        weights = np.exp(x[k:] - x[k:].max())
        return np.clip(x[:k], low, high), weights / weights.sum()

    def objective(x):
        values = problem.values(*unpack(x))
        return values.max() if kind == "minimax" else pi @ values

    x0 = np.concatenate([freq0, np.log(np.maximum(w0, 1e-12))])
    refined = optimize.minimize(objective, x0, method="Nelder-Mead",
                                options=dict(xatol=1e-8, fatol=1e-12, maxiter=4000))
    x = refined.x if refined.fun <= objective(x0) else x0
    freqs, weights = unpack(x)
    # Sinusoids the refinement drove to no power are dropped (the value changes by < 1e-8 relative).
    keep = weights > 1e-8
    order = np.argsort(freqs[keep])
    freqs, weights = freqs[keep][order], weights[keep][order] / weights[keep].sum()
    values, derivatives, support = problem.at_design(freqs, weights)
    value = values.max() if kind == "minimax" else pi @ values
    gap = 0.0
    if kind == "minimax":
        pi = _least_favourable(values, derivatives, support, weights)
        gap = float(values.max() - pi @ values)
    M_u, M_c, names = frequency_information_grid(model, params, freqs, input, tau, free)
    nominal = (M_c if include_noise else 0.0) + power * np.einsum("l,lij->ij", weights, M_u)
    table = None
    if kind != "local":
        given = prior if prior is not None else minimax
        varied = ([c for c in given.columns if c != "weight"] if isinstance(given, pd.DataFrame)
                  else list(given["mean"] if given is prior else given))
        table = pd.DataFrame(points)[varied].assign(weight=pi, value=values)
    return MultisineDesign(freqs, weights, float(value), criterion, float(power), float((pi @ derivatives).max()),
                           float(weights @ (pi @ support)), pd.DataFrame(nominal, index=names, columns=names),
                           kind=kind, points=table, gap=gap, values=values)

