"""Structural identifiability before any data (thesis section 6.1).

For a linear time-invariant model, what the data can reveal is the transfer
function from the inputs to the outputs, G(p) = C(pI − A)⁻¹B + D (6.15), the
noise model H(p) = C(pI − A)⁻¹K + I with the stationary Kalman gain K, and the
innovations' covariance Σ (6.16, 6.18).  [`identifiability()`][greyid.design.identifiability.identifiability] writes
G(p)
with SymPy (each element a ratio of polynomials in p, the denominator monic:
its coefficients are what the data determine, (6.17)) and decides:

* **local** identifiability of every parameter from the rank of the Jacobian
  of (G, H, Σ) with respect to θ at generic random points (G and H evaluated at
  random complex p, K and Σ from the stationary Riccati equation);
* **global** identifiability of the parameters of G by solving
  coefficients(θ) = coefficients(θ*) with SymPy at a random rational θ*: one
  solution is global, several local (when SymPy answers in time);
* the combinations that are identifiable where single parameters are not, from
  the null space of the Jacobian in log-parameters (e.g. "a*b" where only the
  product enters).

For other models the local rank of the Fisher information of a plan
(Monte Carlo, [`fisher_information()`][greyid.design.information.fisher_information]) at random points
inside the bounds decides, on the information scaled to unit diagonal: the
``plan=`` given, or a generic rich one ([`generic_plan()`][greyid.design.identifiability.generic_plan], said in the
result's notes).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from fractions import Fraction

import numpy as np
import pandas as pd
import scipy.linalg as sl

from ..scaled import ScaledInformation, loadings

#: Singular values of the scaled Jacobian below this, relative to the largest, are zero.
RANK_TOLERANCE = 1e-7
#: Generic points at which the rank is taken.
POINTS = 3
#: Largest number of parameters of G for which a global (symbolic) answer is attempted.
GLOBAL_MAX = 6


@dataclass
class Identifiability:
    """What the data of any experiment can determine (see the module doc)."""

    identifiable: dict  # parameter → bool (locally, at generic points)
    status: dict  # parameter → "global", "local" or "not identifiable"
    combinations: list  # identifiable combinations of parameters that are not identifiable alone
    directions: list  # each a mapping parameter → loading of a direction the data cannot see
    transfer_function: object = None  # SymPy matrix G(p), for linear models
    method: str = ""
    notes: list = field(default_factory=list)

    def summary(self) -> str:
        lines = [f"structural identifiability ({self.method})"]
        if self.transfer_function is not None:
            lines.append(f"G(p) = {self.transfer_function}")
        width = max(len(n) for n in self.status)
        for name, status in self.status.items():
            lines.append(f"  {name:{width}s}  {status}")
        for combination in self.combinations:
            lines.append(f"identifiable combination: {combination}")
        for direction in self.directions:
            desc = ", ".join(f"{v:+.3f}·{n}" for n, v in direction.items())
            lines.append(f"not determined: the direction {desc} (log-parameters)")
        lines.extend(self.notes)
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()


def _points(model, params, names, seed):
    """Generic parameter values: around ``params`` (or the declared initial values), inside the bounds."""
    rng = np.random.default_rng(seed)
    declared = model.parameters
    base = {n: (float(params[n]) if params is not None and n in params else
                (declared[n].init if n in declared and declared[n].init is not None else 1.0)) for n in names}
    points = []
    for _ in range(POINTS):
        point = {}
        for n in names:
            value = base[n] * float(np.exp(rng.uniform(-0.3, 0.3))) if base[n] != 0 else rng.uniform(0.1, 1.0)
            p = declared.get(n)
            if p is not None and p.lower is not None and p.upper is not None:
                margin = 1e-3 * (p.upper - p.lower)
                value = float(np.clip(value, p.lower + margin, p.upper - margin))
            point[n] = value
        points.append(point)
    return points


def _linear_parts(model):
    """SymPy A, B, C, D (with the affine terms as a constant input), Σ₁ = GGᵀ, Σ₂."""
    import sympy as sp

    s = model.structure
    eq = s.equations
    x = [sp.Symbol(n, real=True) for n in s.state_names]
    u = [sp.Symbol(n, real=True) for n in s.input_names]
    f, g, h, v = eq["drift"], eq["diffusion"], eq["observation"], eq["variance"]
    zero = {sym: 0 for sym in x + u}
    A, C = f.jacobian(x), h.jacobian(x)
    B = (f.jacobian(u) if u else sp.zeros(len(x), 0)).row_join(f.subs(zero))
    D = (h.jacobian(u) if u else sp.zeros(len(h), 0)).row_join(h.subs(zero))
    return A, B, C, D, g * g.T, sp.diag(*v)


def _rates(A) -> np.ndarray:
    """The system's rates: |eigenvalues of A| that are not zero (none for pure integrators)."""
    rates = np.abs(np.linalg.eigvals(A)) if A.size and np.all(np.isfinite(A)) else np.zeros(0)
    return rates[rates > 1e-12 * max(rates.max(initial=0.0), 1e-300)]


def _time_scale(A) -> float:
    """The system's own rate: the geometric mean of its rates (of A's entries for integrators)."""
    rates = _rates(A)
    if not rates.size:
        rates = np.abs(A[A != 0]) if np.any(A != 0) else np.ones(1)
    return float(np.exp(np.mean(np.log(rates))))


def _frequencies(A, draws) -> np.ndarray:
    """Complex points p spread over the system's own rates (one decade beyond each end), from the
    unit-free ``draws`` (k × 2 uniform numbers): in seconds or hours, the same points of G(p)."""
    rates = _rates(A)
    if rates.size:
        low, high = np.log(rates.min()) - 2.3, np.log(rates.max()) + 2.3
        magnitudes = np.exp(low + draws[:, 0] * (high - low))
    else:
        magnitudes = _time_scale(A) * np.exp(draws[:, 0])
    return magnitudes * np.exp(1j * (draws[:, 1] - 0.5) * 2.0)  # right half-plane, away from the axis


def _observables(A, B, C, D, Q, R, points_p, rate):
    """G and H at the complex points p, and Σ, for numeric matrices (the stationary Kalman filter):
    one row per element of G, H and R, one column per point.

    The measurement variance R enters the continuous Riccati equation as a spectral density R/rate
    over the system's own time scale, so that a change of the time unit leaves K and H unchanged.
    """
    n = A.shape[0]
    try:
        Rc = R / rate
        P = sl.solve_continuous_are(A.T, C.T, Q, Rc)
        K = P @ C.T @ np.linalg.inv(Rc)
    except (np.linalg.LinAlgError, ValueError):
        K = np.zeros((n, C.shape[0]))
    G, H = [], []
    for p in points_p:
        resolvent = np.linalg.solve(p * np.eye(n) - A, np.eye(n))
        G.append((C @ resolvent @ B + D).ravel())
        H.append((C @ resolvent @ K).ravel())
    per_point = np.concatenate([np.array(G).T, np.array(H).T])
    return np.concatenate([per_point, np.repeat(R.reshape(-1, 1).astype(complex), len(points_p), axis=1)])


def _relative_jacobian(observed, z, h: float = 1e-6) -> np.ndarray:
    """∂(observables)/∂(log θ) by central differences, each element of G, H and R relative to its
    largest magnitude over the points (its units cancel); real and imaginary parts as rows.
    Elements that are zero at every point (a structural zero) carry no information and are left out."""
    value = observed(z)
    columns = [(observed(z + h * e) - observed(z - h * e)) / (2 * h) for e in np.eye(len(z))]
    dJ = np.stack(columns, axis=-1)  # (elements, points, parameters)
    magnitude = np.abs(value).max(axis=1)
    keep = magnitude > 1e-300
    rel = dJ[keep] / magnitude[keep, None, None]
    rows = rel.reshape(-1, len(z))
    return np.concatenate([rows.real, rows.imag])


def _directions(null, names) -> list[dict]:
    """Each undetermined direction (a column of ``null``, log-parameters) as {parameter: loading},
    the largest loading ±1, loadings under 0.05 left out."""
    return [loadings(column, names) for column in null.T]


def _combinations(null, names):
    """Monomials θ^k identifiable although their factors are not: k ⟂ every null direction (in
    log-parameters), small integer powers, fewest factors first."""
    from itertools import product

    involved = np.flatnonzero(np.any(np.abs(null) > 1e-6, axis=1))
    if len(involved) == 0 or len(involved) > 6:
        return []
    sub = null[involved]
    wanted = len(involved) - np.linalg.matrix_rank(sub, tol=1e-6)
    candidates = [np.array(k) for k in product(range(-2, 3), repeat=len(involved)) if any(k)]
    candidates = [k for k in candidates if np.all(np.abs(k @ sub) < 1e-5 * np.linalg.norm(k))]
    # Fewest factors, then smallest powers, then the first factor positive (one sign of each).
    candidates.sort(key=lambda k: (np.count_nonzero(k), np.abs(k).sum(), int(np.sum(k < 0))))
    chosen: list = []
    for k in candidates:
        if k[np.flatnonzero(k)[0]] < 0:
            continue
        if np.linalg.matrix_rank(np.array(chosen + [k]), tol=1e-9) > len(chosen):
            chosen.append(k)
        if len(chosen) == wanted:
            break
    out = []
    for k in chosen:
        terms = [names[i] if power == 1 else f"{names[i]}**{power}" for power, i in zip(k, involved) if power]
        out.append("*".join(terms))
    return out


def identifiability(model, params=None, plan=None, seed: int = 0, free=None) -> Identifiability:
    """Which parameters of a model any experiment can determine (section 6.1).

    Linear time-invariant models are judged from their transfer function, noise
    model and innovations' covariance (6.15–6.18), with no data and no plan; other
    models from the rank of the Fisher information of a plan at generic points.

    Parameters
    ----------
    model : Model
        The model.
    params : mapping of str to float, optional
        The centre of the generic points (default: the declared initial values).
    plan : pandas.DataFrame, optional
        For a model that is not linear time-invariant, the experiment judged
        (times and inputs); without it, a generic rich plan whose inputs span the
        model file's data where it names some (see
        [`generic_plan()`][greyid.design.identifiability.generic_plan]).
    seed : int
        The seed of the generic points and plan.
    free : sequence of str, optional
        The parameters judged (default: the non-fixed ones).

    Returns
    -------
    Identifiability
        ``identifiable`` (parameter → bool), ``status`` ("global", "local" or "not
        identifiable"), ``combinations`` that are identifiable where single
        parameters are not, the undetermined ``directions``, the
        ``transfer_function`` of a linear model, and ``summary()``.

    Raises
    ------
    ModelError
        A generic plan whose inputs make an equation not finite (names it: give a plan).

    Examples
    --------
    >>> from greyid import design, library
    >>> result = design.identifiability(library.load_model("Ti"))
    >>> all(result.identifiable.values())
    True
    """
    from ..model.parameters import in_dynamics
    from .information import _free_names

    structure = model.structure
    all_names = list(structure.parameter_names)
    # Parameters of the initial state only are seen in an experiment's transient, not in
    # the stationary G, H and Σ: they are left out of the judgement (and say so).
    judged = _free_names(model, free)
    names = in_dynamics(structure, judged)
    initial_only = [n for n in judged if n not in names]
    points = _points(model, params, all_names, seed)
    if structure.kind != "lti" or structure.delays:  # a delay's e^{-sτ} is not rational in s
        return _by_information(model, judged, points, plan, seed)
    import sympy as sp

    A, B, C, D, Q, R = _linear_parts(model)
    syms = {n: sp.Symbol(n, real=True) for n in all_names}
    p = sp.Symbol("p")
    G = (C * (p * sp.eye(A.shape[0]) - A).inv() * B + D).applyfunc(sp.cancel)
    numeric = sp.lambdify([syms[n] for n in all_names], [A, B, C, D, Q, R], "numpy")
    draws = np.random.default_rng(seed + 1).uniform(size=(A.shape[0] + 2, 2))
    free_index = [all_names.index(n) for n in names]
    ranks, nulls = [], []
    for point in points:
        values = np.array([point[n] for n in all_names], dtype=float)
        at = [np.asarray(M, dtype=float) for M in numeric(*values)]
        rate = _time_scale(at[0])
        at_p = _frequencies(at[0], draws)

        def observed(log_free, values=values, at_p=at_p, rate=rate):
            v = values.copy()
            v[free_index] = np.exp(log_free)
            return _observables(*[np.asarray(M, dtype=float) for M in numeric(*v)], at_p, rate)

        # Log-parameters (columns) and relative observables (rows): no unit enters the rank.
        J = _relative_jacobian(observed, np.log(np.abs(values[free_index])))
        norms = np.maximum(np.linalg.norm(J, axis=0), 1e-300)
        U, sv, Vt = np.linalg.svd(J / norms, full_matrices=True)
        rank = int(np.sum(sv > RANK_TOLERANCE * sv.max()))
        ranks.append(rank)
        # Back from the scaled columns to log-parameters, orthonormalised.
        null_log = Vt[rank:].T / norms[:, None]
        nulls.append(sl.orth(null_log) if null_log.size else null_log)
    null = nulls[int(np.argmax(ranks))]
    unseen = np.any(np.abs(null) > 1e-4, axis=1) if null.size else np.zeros(len(names), dtype=bool)
    identifiable = {n: not bool(unseen[i]) for i, n in enumerate(names)}
    status = {n: ("local" if identifiable[n] else "not identifiable") for n in names}
    notes = []
    in_G = sorted({s.name for s in G.free_symbols} - {"p"} & set(names))
    if all(identifiable[n] for n in in_G) and 0 < len(in_G) <= GLOBAL_MAX:
        answer = _global(G, p, in_G, syms, points[0], model.parameters)
        if answer is None:
            notes.append("global identifiability of G's parameters not decided (SymPy found no closed form)")
        else:
            for n in in_G:
                status[n] = "global" if answer == 1 else "local"
            if answer > 1:
                notes.append(f"G's parameters: {answer} solutions reproduce the same G(p) (locally identifiable)")
    if initial_only:
        notes.append(f"not judged: {', '.join(initial_only)} (initial state only, seen in an experiment's "
                     "transient, not in G, H or Σ)")
    return Identifiability(identifiable, status, _combinations(null, names) if null.size else [],
                           _directions(null, names), G,
                           "transfer functions G, H and Σ of the innovations form (6.15–6.18)", notes)


def _rational(value: float):
    """A small rational near ``value`` with two significant digits, whatever its magnitude
    (0.005 K/W stays 1/200, not 0)."""
    import sympy as sp

    if value == 0:
        return sp.Integer(0)
    exponent = int(np.floor(np.log10(abs(value))))
    mantissa = Fraction(value / 10.0**exponent).limit_denominator(8)
    return sp.Rational(mantissa) * sp.Integer(10) ** exponent


def _global(G, p, names, syms, point, declared):
    """The number of parameter vectors within the declared bounds giving the G(p) of a random rational θ*
    (None if undecided)."""
    import sympy as sp

    # θ*: a generic point inside the bounds, as small rationals (exact arithmetic for SymPy).
    star = {syms[n]: _rational(point[n]) for n in names}
    equations = []
    for element in G:
        num, den = sp.fraction(sp.cancel(sp.together(element)))
        num, den = sp.Poly(num, p), sp.Poly(den, p)
        lead = den.LC()
        for c in num.all_coeffs() + den.all_coeffs()[1:]:
            expr = sp.cancel(c / lead)
            equations.append(sp.numer(sp.together(expr - expr.subs(star))))
    unknowns = [syms[n] for n in names]
    equations = [e for e in equations if e != 0 and e.free_symbols & set(unknowns)]
    try:
        solutions = sp.solve(equations, unknowns, dict=True)
    except (NotImplementedError, ValueError):
        return None
    def inside(symbol, value):
        p_ = declared.get(symbol.name)
        v = complex(value)
        if abs(v.imag) > 1e-12 * max(1.0, abs(v)):
            return False
        lo = None if p_ is None else p_.lower
        hi = None if p_ is None else p_.upper
        return (lo is None or v.real > lo) and (hi is None or v.real < hi)

    real = [s for s in solutions if len(s) == len(unknowns)
            and all(not v.free_symbols and inside(k, v) for k, v in s.items())]
    return len(real) if real else None


#: Rows of the generic plan used for models other than LTI when no plan is given.
GENERIC_ROWS = 240
#: Levels of each input in the generic plan.
GENERIC_LEVELS = 16


def input_ranges(model) -> dict:
    """``{input: (low, high)}`` from the data the model file names (``[data] file`` or ``dataset``), or
    ``{}`` where it names none or they cannot be read."""
    from ..errors import DataError, ModelError
    from ..data.files import read_data
    from ..model.options import rename_columns

    options = getattr(model, "options", {}) or {}
    if not (options.get("file") or options.get("dataset")):
        return {}
    try:
        frame = rename_columns(read_data(model), options.get("columns"))
    except (DataError, ModelError, OSError, ImportError):
        return {}
    ranges = {}
    for name in model.structure.input_names:
        if name in frame.columns:
            values = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=float)
            values = values[np.isfinite(values)]
            if len(values):
                ranges[name] = (float(values.min()), float(values.max()))
    return ranges


def generic_plan(model, point, seed: int = 0, ranges: dict | None = None) -> tuple[pd.DataFrame, str]:
    """A rich experiment for a model that no transfer function describes, and its description.

    The drift linearised at the initial state (inputs at their ranges' middle, else 1)
    gives the model's rates; the plan covers five of the slowest time constants,
    sampled at least four times per fastest one (at most [`GENERIC_ROWS`][greyid.design.identifiability.GENERIC_ROWS]
    rows),
    with each input held at [`GENERIC_LEVELS`][greyid.design.identifiability.GENERIC_LEVELS] random levels (seeded)
    within
    ``ranges[input]`` (the model file's data: [`input_ranges()`][greyid.design.identifiability.input_ranges]), else in
    [0.5, 1.5].
    """
    import jax
    import jax.numpy as jnp

    s = model.structure
    ranges = {name: ranges[name] for name in s.input_names if name in (ranges or {})}
    bounds = [ranges.get(name, (0.5, 1.5)) for name in s.input_names]
    theta = jnp.asarray(model.parameter_vector(point), dtype=jnp.float64)
    x0 = s.initial_mean(theta)
    middle = jnp.asarray([0.5 * (lo + hi) if name in ranges else 1.0
                          for name, (lo, hi) in zip(s.input_names, bounds)], dtype=jnp.float64)
    A = np.asarray(jax.jacfwd(s.drift, argnums=0)(x0, middle, jnp.asarray(0.0), theta), dtype=float)
    rates = _rates(A)
    slow, fast = (rates.min(), rates.max()) if rates.size else (1.0, 1.0)
    span = 5.0 / slow
    step = max(span / (GENERIC_ROWS - 1), 0.25 / fast) if fast > slow else span / (GENERIC_ROWS - 1)
    rows = int(min(GENERIC_ROWS, np.floor(span / step) + 1))
    rng = np.random.default_rng(seed)
    plan = {"t": np.arange(rows) * step}
    hold = max(1, rows // GENERIC_LEVELS)
    for name, (lo, hi) in zip(s.input_names, bounds):
        levels = rng.uniform(lo, hi, -(-rows // hold))
        plan[name] = np.repeat(levels, hold)[:rows]
    where = ("within the ranges of the model file's data" if ranges and len(ranges) == s.n_inputs else
             "within the ranges of the model file's data where it has the input, else in [0.5, 1.5]" if ranges
             else "in [0.5, 1.5]")
    text = (f"{rows} samples every {step:.4g} time units (five of the slowest time constants), "
            + (f"inputs held at {GENERIC_LEVELS} random levels {where}" if s.n_inputs else "no inputs"))
    return pd.DataFrame(plan), text


def _check_plan_finite(model, point, plan: pd.DataFrame, text: str) -> None:
    """Name the equation a plan's inputs make not finite at the initial state, before simulating it
    ([`check_equations_finite()`][greyid.filters.api.check_equations_finite] on the plan)."""
    from ..errors import ModelError
    from ..filters.api import check_equations_finite, prepare_datasets

    structure = model.structure
    theta = model.parameter_vector(point)
    observed = plan.assign(**{o: 0.0 for o in model.output_names})  # the outputs' values are not used
    for series, inputs in prepare_datasets(structure, theta, observed, "t", "zoh", None, check=False):
        try:
            check_equations_finite(structure, theta, series, inputs)
        except ModelError as error:
            raise ModelError(f"{text}: {error}; give a plan with the inputs of a real experiment "
                             "(plan=DataFrame of times and inputs, or --plan FILE.csv on the command line)") from None


def _by_information(model, names, points, plan, seed):
    """Local rank of the Fisher information of ``plan`` (or of
    [`generic_plan()`][greyid.design.identifiability.generic_plan]) at generic points
    (models other than LTI), decided on the scaled information; combinations from its null space."""
    from .information import fisher_information

    notes = ["a rank judged on one plan: another experiment may determine more"]
    if plan is None:
        plan, text = generic_plan(model, points[0], seed, input_ranges(model))
        _check_plan_finite(model, points[0], plan, f"the generic plan ({text})")
        notes = [f"no plan given: judged on a generic plan, {text}; another experiment may determine more"]
    best = None
    for k, point in enumerate(points):
        info = fisher_information(model, point, plan, free=names, method="montecarlo", n_paths=20, seed=seed + k)
        scaled = ScaledInformation.of(info.to_numpy(), names, tolerance=1e-8)
        if best is None or scaled.rank > best[0].rank:
            best = (scaled, point)
    scaled, point = best
    # The undetermined directions in log-parameters (δ log θ = S v / θ), for the combinations.
    theta = np.array([abs(point[n]) for n in names])
    null = scaled.null_directions() * (scaled.scale / np.where(theta > 0, theta, 1.0))[:, None]
    null = sl.orth(null) if null.size else null
    unseen = np.any(np.abs(null) > 1e-4, axis=1) if null.size else np.zeros(len(names), dtype=bool)
    identifiable = {n: not bool(unseen[i]) for i, n in enumerate(names)}
    status = {n: ("local" if identifiable[n] else "not identifiable") for n in names}
    return Identifiability(identifiable, status, _combinations(null, names) if null.size else [],
                           _directions(null, names), None,
                           "rank of the Fisher information of a plan at generic points (Monte Carlo)", notes)


__all__ = ["identifiability", "Identifiability"]
