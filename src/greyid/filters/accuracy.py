"""How many sub-steps a filter takes per sampling interval, chosen for accuracy.

The exact Kalman filter of a time-invariant linear model, and the EKF and UKF
on such a model, discretize each interval exactly.  Every other case
approximates the moment equations (4.19)–(4.20) between samples: the Kalman
filter of a time-varying linear model freezes A(t) and G(t) at the midpoint of
each sub-step (second order), the EKF and UKF linearize at the start of each
sub-step (first order).  With ``substeps`` left unset, greyid doubles the number
of sub-steps from one until the log-likelihood changes by less than
``LOGLIK_TOLERANCE`` when it is doubled once more (step doubling, the usual
error estimate of an integrator); a fit also requires that the estimates would
move by less than a tenth of a standard error (see
[`greyid.estimate.estimation.fit()`][greyid.estimate.estimation.fit]).  A value given by the user is taken as
it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..model.structure import LTI
from .protocol import STOCHASTIC

#: Largest number of sub-steps the automatic choice tries.
MAX_SUBSTEPS = 64
#: Change of the log-likelihood on doubling the sub-steps that is accepted.
LOGLIK_TOLERANCE = 0.01


def needs_substeps(structure) -> bool:
    """Whether sub-steps change the filter at all (everything but time-invariant linear models)."""
    return structure.kind != LTI


def chooses_substeps(structure, method: str | None, scheme: str | None = None) -> bool:
    """Whether step doubling chooses the sub-steps where none are given: wherever they change the filter,
    except for the particle and ensemble filters (whose Monte Carlo noise would swamp the comparison; they
    take a fixed number, ``filters.api.PARTICLE_SUBSTEPS``) and ctsmTMB's Laplace convention (one step
    per interval)."""
    return needs_substeps(structure) and method not in STOCHASTIC and scheme != "ctsmtmb"


@dataclass(frozen=True)
class SubstepChoice:
    """The sub-steps chosen and the change of the log-likelihood when they are doubled."""

    substeps: int
    change: float
    accurate: bool  # False where MAX_SUBSTEPS was reached without meeting the tolerance

    def describe(self) -> str:
        if self.accurate:
            note = f"the log-likelihood changes by {self.change:.2g} with {2 * self.substeps}"
        else:
            note = (f"the log-likelihood still changed by {self.change:.2g} from {self.substeps // 2}: "
                    "set substeps higher or sample more often")
        return f"{self.substeps} sub-steps per interval (automatic; {note})"


def choose_substeps(loglik_at: Callable[[int], float], start: int = 1,
                    tolerance: float = LOGLIK_TOLERANCE) -> SubstepChoice:
    """The fewest sub-steps m ≥ ``start`` (doubling) with |ℓ(2m) − ℓ(m)| ≤ ``tolerance``.

    Stops at MAX_SUBSTEPS, returning it with ``accurate=False``.
    """
    m, value = start, loglik_at(start)
    while True:
        finer = loglik_at(2 * m)
        change = abs(finer - value)
        if change <= tolerance:
            return SubstepChoice(m, float(change), True)
        if 2 * m >= MAX_SUBSTEPS:
            return SubstepChoice(2 * m, float(change), False)
        m, value = 2 * m, finer
