"""What a filter family supplies and what the driver hands it.

A family (the exact Kalman filter, the extended filters, the unscented filter, …)
is a module with one function, ``prepare(structure, options)``, that returns
``steps(theta, data) -> FilterSteps``: the filter's state at t₀ before its first
update, the rows to scan, and two pure functions of an explicit state,

* ``predict(state, row) -> (state, transition)`` — from t_{k-1} to t_k (row 0
  "predicts" over an interval of length 0);
* ``update(state, row, mask=None) -> (update, y_pred)`` — with the observed
  elements of y_k; ``update.state`` is the state carried on and ``update.terms``
  what the step adds to the criterion (3.18).

The state is any pytree of arrays: a mean and a covariance for the Gaussian
filters ([`GaussianState`][greyid.filters.updates.GaussianState]), particles, weights and a key
for a particle filter.  [`greyid.filters.driver`][greyid.filters.driver] runs any family over
the rows; delays, missing values, the steady-state switch and k-step predictions are
written once, there and in [`series_rows()`][greyid.filters.protocol.series_rows].
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Protocol

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..model.structure import Structure
from .delays import Delays, Pieces, delays_at, interval_pieces, regular_offsets, with_delayed_inputs
from .proposals import PROPOSALS
from .updates import FORMS

KALMAN, EKF, IEKF, UKF, EKF2 = "kalman", "ekf", "iekf", "ukf", "ekf2"
#: The modified truncated and Gaussian second-order filters (section 4.2.2).
TRUNCATED2, GAUSSIAN2 = "truncated2", "gaussian2"
SECOND_ORDER = (TRUNCATED2, GAUSSIAN2)
#: The bootstrap particle filter ([`particle`][greyid.filters.particle]).
PARTICLE = "particle"
#: The stochastic ensemble Kalman filter ([`ensemble`][greyid.filters.ensemble]).
ENKF = "enkf"
#: The Laplace method over the states on a time grid ([`laplace`][greyid.filters.laplace]).
LAPLACE = "laplace"
GAUSSIAN_METHODS = (KALMAN, EKF, IEKF, UKF, EKF2, TRUNCATED2, GAUSSIAN2)
METHODS = (*GAUSSIAN_METHODS, ENKF, PARTICLE, LAPLACE)
#: Methods whose random numbers ``seed`` fixes.
STOCHASTIC = (ENKF, PARTICLE)
#: The Laplace method's transitions: "auto" (exact for linear time-invariant dynamics, else Euler–Maruyama),
#: "euler" (Euler–Maruyama always) or "ctsmtmb" (ctsmTMB's: Euler–Maruyama with G Gᵀ + 10⁻⁸ I, inputs
#: interpolated linearly, one step per interval unless given).
SCHEMES = ("auto", "euler", "ctsmtmb")


@dataclass(frozen=True)
class FilterOptions:
    """Static settings of a filter; each distinct value compiles once."""

    method: str
    form: str = "sqrt"
    substeps: int = 1
    iterations: int = 5
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0
    #: Shorter regular series (steady.SHORT_ROWS rows or more) of a time-invariant linear model
    #: filtered exactly switch to the steady state too, after their first rows where the filter
    #: has settled ([`steady`][greyid.filters.steady]); long ones (steady.MIN_ROWS or more) always do.
    #: Its programs hold both forms: a fit's first call compiles longer and its later evaluations
    #: run faster (docs/performance.md).  The public likelihood turns it on for its single
    #: evaluations ([`greyid.estimate.likelihood`][greyid.estimate.likelihood]); programs vectorised
    #: over series or parameter vectors (fleets, populations, a fit's starts) would run both forms
    #: for every member and do not take it.
    steady_state: bool = False
    #: The particle filter's number of particles (the ensemble Kalman filter's members), the seed of
    #: their random numbers, the fraction of the particles below which the effective sample size
    #: makes the particle filter resample, and the ensemble's inflation of its predicted spread.
    particles: int = 1000
    seed: int = 0
    resample: float = 0.5
    inflation: float = 1.0
    scheme: str = "auto"
    #: The particle filter's proposal: "bootstrap" (the dynamics alone), "ekf" or "ukf" (guided by a Gaussian
    #: filter's update, [`proposals`][greyid.filters.proposals]).
    proposal: str = "bootstrap"

    def __post_init__(self):
        if self.method not in METHODS:
            raise ModelError(f"unknown filter method '{self.method}'; use one of {list(METHODS)}")
        if self.form not in FORMS:
            raise ModelError(f"unknown covariance form '{self.form}'; use 'sqrt' or 'plain'")
        if not isinstance(self.substeps, int) or self.substeps < 1:
            raise ModelError(f"substeps must be a positive integer, got {self.substeps!r}")
        if not isinstance(self.iterations, int) or self.iterations < 1:
            raise ModelError(f"iterations must be a positive integer, got {self.iterations!r}")
        if not isinstance(self.particles, (int, np.integer)) or isinstance(self.particles, bool) or self.particles < 1:
            raise ModelError(f"particles must be a positive integer, got {self.particles!r}")
        if not isinstance(self.seed, (int, np.integer)) or isinstance(self.seed, bool) or self.seed < 0:
            raise ModelError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not (isinstance(self.resample, (int, float)) and 0 < self.resample <= 1):
            raise ModelError(f"resample must be a fraction in (0, 1] of the particles, got {self.resample!r}")
        if not (isinstance(self.inflation, (int, float)) and self.inflation >= 1):
            raise ModelError(f"inflation must be a number of at least 1, got {self.inflation!r}")
        if self.proposal not in PROPOSALS:
            raise ModelError(f"unknown proposal '{self.proposal}'; use one of {list(PROPOSALS)}")
        if self.proposal != "bootstrap" and self.method != PARTICLE:
            raise ModelError(f"proposal='{self.proposal}' is a setting of the particle filter (method='particle'), "
                             f"not of method='{self.method}'")
        if self.scheme not in SCHEMES:
            raise ModelError(f"unknown scheme '{self.scheme}'; use one of {list(SCHEMES)}")
        if not isinstance(self.steady_state, (bool, np.bool_)):
            raise ModelError(f"steady_state must be True or False, got {self.steady_state!r}")


class FilterInputs(NamedTuple):
    """Arrays of one (padded) series; row k describes the interval ending at t_k."""

    t: jnp.ndarray  # (N,)
    t_prev: jnp.ndarray  # (N,)
    dt: jnp.ndarray  # (N,), 0 at row 0 and on padding
    u_prev: jnp.ndarray  # (N, nu)
    u_cur: jnp.ndarray  # (N, nu)
    y: jnp.ndarray  # (N, ny), 0 where unobserved
    mask: jnp.ndarray  # (N, ny), 1.0 observed / 0.0 not
    dt_index: jnp.ndarray  # (N,) into unique_dt
    unique_dt: jnp.ndarray  # (M,)
    first_interval: jnp.ndarray  # t_1 − t_0
    foh: jnp.ndarray  # 0.0 (zoh) or 1.0 (foh)
    delay_slots: jnp.ndarray  # (W,) zeros: W cuts per delay fit in one interval; (0,): regular sampling
    #: (D,) zeros: the first D rows hold the diffuse period of a diffuse initial state
    #: ([`diffuse`][greyid.filters.diffuse]); (0,) without diffuse states.
    diffuse_rows: jnp.ndarray


class Row(NamedTuple):
    """What one step needs of its row; the filter scans over these (leading axis N)."""

    t: jnp.ndarray
    t_prev: jnp.ndarray
    dt: jnp.ndarray
    u_prev: jnp.ndarray
    u_cur: jnp.ndarray
    y: jnp.ndarray
    mask: jnp.ndarray
    dt_index: jnp.ndarray
    pieces: Pieces | None = None  # with delayed inputs: the interval's pieces (see .delays)


class FilterSteps(NamedTuple):
    """A family's filter for one parameter vector and data set (see the module's docstring)."""

    initial: Any  # the state at t₀ before its update
    rows: Row  # per-row inputs, leading axis N
    predict: Callable  # (state, row) -> (state_{k|k-1}, transition)
    update: Callable  # (state_{k|k-1}, row, mask=None) -> (update with .state and .terms, ŷ_{k|k-1})
    #: A time-invariant linear model's pieces for the steady-state form ([`steady`][greyid.filters.steady]),
    #: or None where the driver steps through every row.
    steady: Any = None
    #: The exact diffuse start ([`DiffuseStart`][greyid.filters.diffuse.DiffuseStart]) whose rows the driver filters
    #: first, or None.
    diffuse: Any = None


class Family(Protocol):
    """A filter family: ``prepare(structure, options)(theta, data) -> FilterSteps``."""

    def __call__(self, structure: Structure, options: FilterOptions) -> Callable[[Any, FilterInputs], FilterSteps]:
        ...


class SeriesRows(NamedTuple):
    """A series' rows as every family's steps read them, for one parameter vector."""

    data: FilterInputs  # with the delayed inputs appended to u_prev and u_cur
    rows: Row
    delays: Delays | None  # the delays at θ, or None without any
    offsets: jnp.ndarray | None  # regular sampling with delays: the cuts' offsets inside each interval


def series_rows(structure: Structure, theta, data: FilterInputs) -> SeriesRows:
    """The rows of ``data`` at θ: inputs extended by their delayed values, intervals cut where they switch."""
    delays = delays_at(structure, theta, data.t, data.u_cur, data.foh) if structure.delays else None
    data = with_delayed_inputs(structure, theta, data, delays)
    pieces = offsets = None
    if delays is not None:
        regular = data.delay_slots.shape[0] == 0
        offsets = regular_offsets(delays.taus, jnp.max(data.unique_dt)) if regular else None
        pieces = interval_pieces(delays, data, structure.n_inputs, offsets)
    rows = Row(data.t, data.t_prev, data.dt, data.u_prev, data.u_cur, data.y, data.mask, data.dt_index, pieces)
    return SeriesRows(data, rows, delays, offsets)
