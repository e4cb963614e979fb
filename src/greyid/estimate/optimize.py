"""What every optimiser of greyid shares: the kinds of evaluation a search asks for, the answer it
gets, the optimum it returns, and the loop that runs one search alone.

A search is explicit state.  A strategy supplies ``init() -> state`` and
``step(state, answer) -> state``; ``state.request`` is the evaluation it asks for next
(a kind and a point z in unbounded coordinates), ``state.optimum`` is set once it has
ended.  [`run_alone()`][greyid.estimate.optimize.run_alone] answers one search's requests
with one program per kind; [`drive()`][greyid.estimate.batch.drive] answers many searches'
requests together by batched programs.  The strategies:
[`greyid.estimate.trust_region`][greyid.estimate.trust_region] (Fisher scoring, Newton's
method on the exact Hessian, or BFGS, in a trust region) and
[`greyid.estimate.lbfgs`][greyid.estimate.lbfgs] (SciPy's L-BFGS, to move a start closer).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ModelError


class NotFiniteError(ModelError):
    """The criterion or its derivatives are not finite where the search starts."""


@dataclass
class Optimum:
    """Where a search ended: the point z, the criterion's value, gradient and Hessian there, its
    accepted steps and evaluations, whether it converged and why it stopped."""

    z: np.ndarray
    value: float
    gradient: np.ndarray
    hessian: np.ndarray
    iterations: int
    evaluations: int
    converged: bool
    message: str


def _no_report(iteration: int, stage: str, f: float, g: np.ndarray) -> None:
    pass


#: Kinds of evaluation a search asks for: (f, g, H) exact, (f, g, F) scoring, (f,) value.
EXACT, SCORING, VALUE, GRADIENT = "exact", "scoring", "value", "gradient"


def settle(outputs) -> tuple[tuple, bool]:
    """An evaluation's outputs as float arrays, and whether all of them are finite."""
    out = tuple(np.asarray(a, dtype=float) for a in outputs)
    return out, all(np.all(np.isfinite(a)) for a in out)


def run_alone(search, programs: dict[str, Callable]) -> Optimum:
    """Run one search (``init``/``step``, e.g. a [`Search`][greyid.estimate.trust_region.Search]) to its
    optimum, evaluating each request with ``programs[kind](z)``."""
    state = search.init()
    while state.optimum is None:
        kind, z = state.request
        state = search.step(state, settle(programs[kind](z)))
    return state.optimum
