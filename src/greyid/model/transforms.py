"""Lamperti transforms of states: a state with state-dependent noise rewritten in a coordinate whose noise is
additive, so that the Gaussian filters' linearisation and the Laplace method's Gaussian transitions fit it.

A state x with one noise term, ``dx = f dt + g(x) dw``, and a transform z = ψ(x) with inverse x = φ(z) give by
Itô's formula

    dz = [f / φ'(z) − ½ φ''(z) g² / φ'(z)³] dt + g / φ'(z) dw,    f, g at x = φ(z),

(ψ' = 1/φ', ψ'' = −φ''/φ'³).  The transform is the Lamperti transform of the state where g / φ'(z) is free of
the states: the noise of z is then additive.  Every other equation (drifts, diffusions, observations) has x
replaced by φ(z); the filters, the Laplace method and the simulators then work in z, under the state's own name,
and [`to_original`][greyid.model.transforms.to_original] reports their states in the user's coordinates.

Named transforms, each for the diffusion it makes additive (any positive factor of it):

| name | z = ψ(x) | x = φ(z) | diffusion |
|---|---|---|---|
| ``log`` | log x | exp z | ∝ x |
| ``logit`` | log(x / (1 − x)) | 1 / (1 + exp(−z)) | ∝ x (1 − x) |
| ``sqrt`` | √x | z² | ∝ √x |
| ``arcsine`` | arcsin √x | sin² z | ∝ √(x (1 − x)) |

Any other transform is written as an expression of the state, e.g. ``"log(x - c)"``, with a unique inverse that
SymPy can solve for.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import sympy as sp

from ..errors import ModelError
from .equations import parse_expression

#: The named transforms: ψ(x), φ(z) and the diffusion each makes additive, as text.
TRANSFORMS: dict[str, tuple[Callable, Callable, str]] = {
    "log": (sp.log, sp.exp, "proportional to the state (e.g. s*{x})"),
    "logit": (lambda x: sp.log(x / (1 - x)), lambda z: 1 / (1 + sp.exp(-z)),
              "proportional to {x}*(1 - {x})"),
    "sqrt": (sp.sqrt, lambda z: z ** 2, "proportional to sqrt({x})"),
    "arcsine": (lambda x: sp.asin(sp.sqrt(x)), lambda z: sp.sin(z) ** 2, "proportional to sqrt({x}*(1 - {x}))"),
}


@dataclass(frozen=True)
class StateTransform:
    """A transformed state: its index, the transform's name (or expression) and x = φ(z), dx/dz = φ'(z) as
    vectorised NumPy functions of z and the parameter vector θ."""

    index: int
    state: str
    kind: str
    inverse: Callable[[np.ndarray, np.ndarray], np.ndarray]
    slope: Callable[[np.ndarray, np.ndarray], np.ndarray]


def forward_and_inverse(state: str, kind: str) -> tuple[Callable, Callable]:
    """ψ and φ as functions of a SymPy expression, for a named transform or one written as an expression of
    ``state``."""
    if kind in TRANSFORMS:
        psi, phi, _ = TRANSFORMS[kind]
        return psi, phi
    x = sp.Symbol(state, real=True)
    try:
        psi_x = parse_expression(kind, f"the transform of state '{state}'")
    except ModelError as err:
        raise ModelError(f"{err}; a transform is one of {', '.join(sorted(TRANSFORMS))} or an expression of "
                         f"'{state}'") from None
    if x not in psi_x.free_symbols:
        raise ModelError(f"the transform of state '{state}' is neither one of {', '.join(sorted(TRANSFORMS))} nor "
                         f"an expression of '{state}' (got {kind!r})")
    z = sp.Dummy("z", real=True)
    solutions = sp.solve(sp.Eq(psi_x, z), x)
    if len(solutions) != 1:
        raise ModelError(f"the transform '{kind}' of state '{state}' has {len(solutions) or 'no'} inverse(s) that "
                         "SymPy can find; give a transform with one inverse (or a named one: "
                         f"{', '.join(sorted(TRANSFORMS))})")
    inverse = solutions[0]
    return (lambda e: psi_x.xreplace({x: e})), (lambda e: inverse.xreplace({z: e}))


def lamperti(states: list[str], transforms: dict[str, str], drift: list, diffusion: list[list],
             others: list[list], noise_names: list[str]):
    """The drift, diffusion and other expressions (observations, variances, ...) in the transformed states'
    coordinates, each transform's ψ and φ as functions of SymPy expressions (module docstring), and the drift of
    the noise-free model dx = f dt in those coordinates (f / φ'(z), without Itô's term).

    Raises
    ------
    ModelError
        A transformed state without noise or with more than one noise term, or a transform whose noise is not
        additive (it does not match the state's diffusion).
    """
    state_symbols = {name: sp.Symbol(name, real=True) for name in states}
    dummies = {name: sp.Dummy(name, real=True) for name in transforms}
    maps = {name: forward_and_inverse(name, kind) for name, kind in transforms.items()}
    # x → φ(z) everywhere at once, z a stand-in renamed to x at the end (the user's name for the new coordinate).
    into = {state_symbols[name]: maps[name][1](dummies[name]) for name in transforms}
    back = {dummies[name]: state_symbols[name] for name in transforms}
    drift = list(drift)
    diffusion = [list(row) for row in diffusion]
    for name, kind in transforms.items():
        i = states.index(name)
        terms = [(j, g) for j, g in enumerate(diffusion[i]) if g != 0]
        label = f"{kind} transform" if kind in TRANSFORMS else f"transform '{kind}'"
        if not terms:
            raise ModelError(f"the {label} of state '{name}' is a Lamperti transform, which makes a state's noise "
                             f"additive; '{name}' has no noise term (d{name} = ... has no dw): nothing to transform")
        if len(terms) > 1:
            raise ModelError(f"state '{name}' has {len(terms)} noise terms ("
                             + ", ".join(noise_names[j] for j, _ in terms)
                             + "): a Lamperti transform makes one noise term additive, not several")

    def substitute(e):
        e = e.xreplace(into)
        # √(φ(z)) with φ = z² or sin² z is |z| or |sin z| to SymPy; z ≥ 0 and 0 ≤ z ≤ π/2 are those transforms'
        # ranges, where both are positive (and so is cos z).
        for name in transforms:
            z = dummies[name]
            e = e.xreplace({sp.Abs(z): z, sp.Abs(sp.sin(z)): sp.sin(z), sp.Abs(sp.cos(z)): sp.cos(z)})
        return e

    out_drift, out_diffusion, ode_drift = [], [], []
    for i, name in enumerate(states):
        f = substitute(drift[i])
        row = [substitute(g) for g in diffusion[i]]
        ode = f
        if name in transforms:
            z = dummies[name]
            phi = maps[name][1](z)
            d1, d2 = sp.diff(phi, z), sp.diff(phi, z, 2)
            g2 = sum((g ** 2 for g in row), sp.Integer(0))
            ode = substitute(sp.simplify(substitute(f / d1)))
            f = substitute(sp.simplify(substitute(f / d1 - d2 * g2 / (2 * d1 ** 3))))
            row = [substitute(sp.simplify(substitute(g / d1))) for g in row]
            left = set().union(*(g.free_symbols for g in row)) & (set(dummies.values()) | set(state_symbols.values()))
            if left:
                kind = transforms[name]
                hint = (f"; the {kind} transform makes a diffusion {TRANSFORMS[kind][2].format(x=name)} additive"
                        if kind in TRANSFORMS else "")
                shown = [g.xreplace(back) for g in row if g != 0][0]
                raise ModelError(f"the {kind if kind in TRANSFORMS else repr(kind)} transform does not match the "
                                 f"diffusion of state '{name}': its noise becomes {shown}, which still depends on "
                                 f"the states{hint}")
        out_drift.append(f.xreplace(back))
        ode_drift.append(ode.xreplace(back))
        out_diffusion.append([g.xreplace(back) for g in row])
    out_others = [[sp.simplify(substitute(e)).xreplace(back) if e.has(*into) else e for e in part]
                  for part in others]
    return out_drift, out_diffusion, out_others, maps, ode_drift


def initial_mean_and_covariance(states: list[str], transforms: dict[str, str], maps: dict, mean: list, cov):
    """The initial mean in the transformed coordinates, z0 = ψ(x0), and a given covariance matrix by the delta
    method, J P Jᵀ with J = diag(ψ'(x0)) ("process" and "stationary" covariances are formed from the
    transformed model and stay as they are)."""
    mean = list(mean)
    slopes = [sp.Integer(1)] * len(states)
    for name in transforms:
        i = states.index(name)
        psi = maps[name][0]
        x = sp.Dummy("x", real=True)
        slopes[i] = sp.diff(psi(x), x).xreplace({x: mean[i]})
        mean[i] = psi(mean[i])
    if isinstance(cov, list):
        cov = [[slopes[i] * cov[i][j] * slopes[j] for j in range(len(states))] for i in range(len(states))]
    return mean, cov


def state_transforms(states: list[str], transforms: dict[str, str], maps: dict,
                     parameters: list[str]) -> tuple[StateTransform, ...]:
    """The [`StateTransform`][greyid.model.transforms.StateTransform]s a structure keeps for reporting (φ may hold
    parameters: ``log(x - c)``)."""
    out = []
    symbols = [sp.Symbol(p, real=True) for p in parameters]
    for name, kind in transforms.items():
        z = sp.Dummy("z", real=True)
        phi = maps[name][1](z)
        inverse = sp.lambdify([z, *symbols], phi, "numpy")
        slope = sp.lambdify([z, *symbols], sp.diff(phi, z), "numpy")
        out.append(StateTransform(states.index(name), name, kind,
                                  lambda v, theta, f=inverse: np.broadcast_to(f(v, *theta), np.shape(v)).astype(float),
                                  lambda v, theta, f=slope: np.broadcast_to(f(v, *theta), np.shape(v)).astype(float)))
    return tuple(out)


def to_original(transforms: tuple[StateTransform, ...], theta, mean: np.ndarray, cov: np.ndarray | None = None):
    """States (…, n) and covariances (…, n, n) in the user's coordinates at the parameters θ: x = φ(z) for the
    mean (the median of x where z is Gaussian) and J P Jᵀ, J = diag(φ'(z)), for the covariance (the delta
    method).  Unchanged where no state is transformed."""
    if not transforms:
        return mean, cov
    theta = np.asarray(theta, dtype=float)
    mean = np.array(mean, dtype=float)
    z = mean.copy()
    slopes = np.ones(mean.shape)
    for t in transforms:
        mean[..., t.index] = t.inverse(z[..., t.index], theta)
        slopes[..., t.index] = t.slope(z[..., t.index], theta)
    if cov is not None:
        cov = np.asarray(cov, dtype=float) * slopes[..., :, None] * slopes[..., None, :]
    return mean, cov


def paths_to_original(transforms: tuple[StateTransform, ...], theta, states: np.ndarray) -> np.ndarray:
    """Simulated states (…, n) in the user's coordinates, x = φ(z) along each path (exact)."""
    return to_original(transforms, theta, states)[0]
