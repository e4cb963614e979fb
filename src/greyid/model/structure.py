"""From a model specification to compiled JAX functions.

A [`Structure`][greyid.model.structure.Structure] holds everything the filters need: names, the drift f, the
diffusion G, the observation function h and the observation variances S as
jitted-traceable functions of ``(x, u, t, theta)`` (model (4.1)–(4.2)), the initial
state, and the model class (linear time-invariant, linear time-varying or
nonlinear) that decides which filter is exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
import sympy as sp
from sympy.utilities.lambdify import lambdify

from ..errors import ModelError
from .kernels import scaled_besseli
from .symbols import TIME

Array = jnp.ndarray
ModelFunction = Callable[[Array, Array, Array, Array], Array]

LTI = "lti"
LTV = "ltv"
NONLINEAR = "nonlinear"


@dataclass(frozen=True)
class InitialCovariance:
    """How the initial state covariance P0 is formed.

    kind is ``"matrix"`` (``matrix(theta)`` gives P0), ``"process"`` (the process
    noise integrated over the first sampling interval, times ``scale``, as CTSM
    does) or ``"stationary"`` (the solution of A P + P A' + G G' = 0).
    """

    kind: str
    scale: float = 1.0
    matrix: Callable[[Array], Array] | None = None
    #: Latent forces' states, from ``latent_start`` on: θ → their stationary covariance P∞, their block of P0
    #: whatever ``kind`` gives the model's own states (with "process" and "stationary").
    latent: Callable[[Array], Array] | None = None
    latent_start: int = 0
    #: The states started exactly diffuse (their indices): their rows and columns of P0 are zero, their
    #: unknown part is the filter's P∞ ([`diffuse`][greyid.filters.diffuse]).
    diffuse: tuple[int, ...] = ()
    #: For each diffuse state, the outputs that depend on it (directly or through the states it drives); empty
    #: where unknown (models of Python functions: every output).
    seen_by: tuple[tuple[int, ...], ...] = ()


@dataclass(frozen=True)
class Structure:
    """A compiled model structure; functions take ``(x, u, t, theta)``."""

    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    parameter_names: tuple[str, ...]
    noise_names: tuple[str, ...]
    kind: str
    drift: ModelFunction
    diffusion: ModelFunction
    observation: ModelFunction
    observation_variance: ModelFunction
    initial_mean: Callable[[Array], Array]
    initial_covariance: InitialCovariance
    equations: dict = field(default_factory=dict)
    #: (x, u, t, θ) → the outputs' full noise covariance, where they are correlated (else None).
    observation_covariance: ModelFunction | None = None
    #: The model's ``delay(u, tau)`` terms ([`DelayedInput`][greyid.model.delays.DelayedInput]), each an
    #: extra input of the functions above, after the data's inputs.
    delays: tuple = ()
    #: Whether ∂h/∂x and the outputs' noise depend on neither inputs nor time (a linear
    #: model's filter then has a steady state at a constant sampling interval).
    constant_observation: bool = False
    #: For a linear time-invariant model, θ → (A, B, c) with f(x, u, t) = A x + B u + c, from
    #: the equations' symbolic derivatives (else None): the exact filter's drift terms without
    #: differentiating or evaluating f in every step.
    linear_drift: Callable[[Array], tuple] | None = None
    #: A hash of everything the functions above compute (the equations as lambdified, names,
    #: settings), for programs kept on disk ([`greyid.runtime.store`][greyid.runtime.store]); None for models of Python
    #: functions, whose programs are never kept.
    fingerprint: str | None = field(default=None, compare=False)
    #: Where the drift and diffusion alone are linear and time-invariant (whatever the observations), θ →
    #: (A, B, c) as ``linear_drift``: the particle filter samples their exact transition.
    linear_dynamics: Callable[[Array], tuple] | None = None
    #: Each output's distribution family ([`distributions`][greyid.model.distributions]); empty where all
    #: are normal, as the Gaussian filters need.
    distributions: tuple[str, ...] = ()
    #: (x, u, t, θ) → each output's shape parameter (df, size, trials; 1 where it has none), or None where
    #: all outputs are normal.
    observation_shape: ModelFunction | None = None
    #: The states the functions above see through a Lamperti transform
    #: ([`StateTransform`][greyid.model.transforms.StateTransform]); results report them in the user's coordinates.
    state_transforms: tuple = ()
    #: Where states are transformed, the drift of the noise-free model dx = f dt in their coordinates (the drift
    #: above less Itô's term): the simulator's deterministic path.  None otherwise (it is ``drift``).
    ode_drift: ModelFunction | None = None
    #: The latent forces ([`LatentForce`][greyid.model.latent.LatentForce]): each a weighted sum of the states
    #: its kernel appended.
    latent_forces: tuple = ()
    #: Compiled filters and simulators for this structure, keyed by their settings.
    cache: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    @property
    def n_inputs(self) -> int:
        return len(self.input_names)

    @property
    def n_outputs(self) -> int:
        return len(self.output_names)

    @property
    def is_linear(self) -> bool:
        return self.kind in (LTI, LTV)

    @property
    def output_families(self) -> tuple[str, ...]:
        """Each output's distribution family ("normal" where none was declared)."""
        return self.distributions or ("normal",) * self.n_outputs

    def observation_law(self, x, u, t, theta) -> tuple:
        """(m, S, a): each output's location h(x, u, t, θ), variance and shape parameter (1 where its family
        has none), as the [`distributions`][greyid.model.distributions] functions take them."""
        shape = jnp.ones(self.n_outputs) if self.observation_shape is None else self.observation_shape(x, u, t, theta)
        return self.observation(x, u, t, theta), self.observation_variance(x, u, t, theta), shape


def _vector_function(exprs: list[sp.Expr], args: list, shape: tuple[int, ...]) -> ModelFunction:
    """Lambdify a list of expressions into a JAX function returning ``shape``.

    ``args`` lists the function's arguments: a list of symbols for a vector, a
    symbol for a scalar.  Only the elements the expressions use are taken out
    of the vectors: the model functions are called many times in a filter, and
    each element taken out is an operation to trace and differentiate.
    """
    used = set().union(*(sp.sympify(e).free_symbols for e in exprs))
    picks = []  # (argument position, element index or None for a scalar, symbol)
    for position, arg in enumerate(args):
        if isinstance(arg, (list, tuple)):
            picks += [(position, i, sym) for i, sym in enumerate(arg) if sym in used]
        elif arg in used:
            picks.append((position, None, arg))
    raw = lambdify([sym for _, _, sym in picks], exprs, modules=[_ELEMENTWISE, "jax"])

    def function(*values):
        out = raw(*(values[p] if i is None else values[p][i] for p, i, _ in picks))
        return jnp.reshape(jnp.stack([jnp.asarray(v, dtype=jnp.float64) for v in out]), shape)

    return function


def classify(drift: sp.Matrix, diffusion: sp.Matrix, observation: sp.Matrix, variance: sp.Matrix,
             states: list[sp.Symbol], inputs: list[sp.Symbol]) -> str:
    """Linear time-invariant, linear time-varying or nonlinear (section 4.1.4).

    Linear means f affine in x, G and S free of x, and h affine in x.  Time
    invariant means additionally that A and G depend on neither u nor t and that
    f(0, u) is affine in u with constant coefficients, so that the discretization
    (4.36)–(4.39) is exact for both hold orders.
    """
    xs, us = set(states), set(inputs)
    if not states:
        raise ModelError("the model has no states")
    a = drift.jacobian(sp.Matrix(states))
    c = observation.jacobian(sp.Matrix(states))
    if any(e.free_symbols & xs for e in [*a, *diffusion, *c, *variance]):
        return NONLINEAR
    varying = us | {TIME}
    if any(e.free_symbols & varying for e in [*a, *diffusion]):
        return LTV
    offset = drift.subs({x: 0 for x in states})
    if inputs:
        b = offset.jacobian(sp.Matrix(inputs))
        if any(e.free_symbols & varying for e in b):
            return LTV
        constant = sp.simplify(offset - b * sp.Matrix(inputs))
    else:
        constant = offset
    if any(e.free_symbols & varying for e in constant):
        return LTV
    return LTI


def observation_is_constant(observation: sp.Matrix, variances: list, states, inputs) -> bool:
    """Whether ∂h/∂x and the noise variances (or covariances) are free of states, inputs and time."""
    varying = set(states) | set(inputs) | {TIME}
    c = observation.jacobian(sp.Matrix(states))
    return not any(sp.sympify(e).free_symbols & varying for e in [*c, *variances])


def _extreme(reduce):
    """SymPy before 1.13 prints Max(a, b) as amax((a, b), axis=0), a tuple JAX's reductions refuse."""
    def extreme(values, axis=0):
        return reduce(jnp.stack(jnp.broadcast_arrays(*values)), axis=axis)

    return extreme


#: Names SymPy's JAX printer may use, as functions of element-wise arguments.
_ELEMENTWISE = {"amax": _extreme(jnp.max), "amin": _extreme(jnp.min), "ScaledBesselI": scaled_besseli}


def lambdify_model(exprs, states, inputs, parameters, shape) -> ModelFunction:
    """A JAX function of ``(x, u, t, theta)`` from SymPy expressions."""
    args = [list(states), list(inputs), TIME, list(parameters)]
    fn = _vector_function(list(exprs), args, shape)

    def model_function(x, u, t, theta):
        return fn(x, u, t, theta)

    return model_function


def linear_drift_function(drift: sp.Matrix, states, inputs, parameters) -> Callable[[Array], tuple]:
    """θ → (A, B, c) of a drift f = A x + B u + c that is affine in x and u with coefficients
    free of x, u and t (a linear time-invariant model, see [`classify()`][greyid.model.structure.classify])."""
    n, p = len(states), len(inputs)
    A = drift.jacobian(sp.Matrix(states))
    offset = drift.subs({x: 0 for x in states})
    B = offset.jacobian(sp.Matrix(inputs)) if p else sp.zeros(n, 0)
    c = offset.subs({u: 0 for u in inputs})
    fn = _vector_function([*A, *B, *c], [list(parameters)], (n * (n + p + 1),))

    def linear_drift(theta):
        flat = fn(theta)
        return flat[:n * n].reshape(n, n), flat[n * n:n * (n + p)].reshape(n, p), flat[n * (n + p):]

    return linear_drift


def lambdify_parameters(exprs, parameters, shape) -> Callable[[Array], Array]:
    """A JAX function of ``theta`` alone (initial state)."""
    fn = _vector_function(list(exprs), [list(parameters)], shape)
    return lambda theta: fn(theta)
