"""Estimation criteria built on the filters' per-step terms (chapter 3).

* maximum likelihood: the Gaussian log-likelihood (3.17)–(3.18);
* robust norms (3.57)–(3.58): in (3.18) a squared normalised innovation r² is
  replaced by ρ(r) — Huber's 2c|r| − c² for |r| ≥ c (CTSM's convention) or
  Tukey's bisquare (c²/3)(1 − (1 − (r/c)²)³), capped at c²/3 for |r| ≥ c; both
  equal r² for small r — and log det R by κ log det R, κ = E[Zρ'(Z)]/2 (see
  [`scale_consistency()`][greyid.estimate.criteria.scale_consistency]), so that variances estimated with the other
  parameters are consistent on Gaussian data (the default); ``(norm, c, "ctsm")``
  keeps log det R unweighted, CTSM-R's convention, to reproduce its numbers;
* MAP (3.46): the log-likelihood plus the log-density of a multivariate
  Gaussian prior on the parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp
import numpy as np

from ..errors import ModelError
from ..filters.api import _prepare, accurate_options, compiled_filter
from ..filters.updates import LOG_2PI, DensityTerms

ROBUST_NORMS = ("huber", "tukey")


#: Conventions for log det R under a robust norm: "consistent" weights it by κ (the default),
#: "ctsm" leaves it unweighted, as CTSM-R does (its printed criterion values).
ROBUST_CONVENTIONS = ("consistent", "ctsm")


def check_robust(robust) -> tuple | None:
    """``None``, ``(norm, c)`` or ``(norm, c, "ctsm")``: the robust setting in its normal form."""
    if robust is None:
        return None
    if not (isinstance(robust, (tuple, list)) and len(robust) in (2, 3) and robust[0] in ROBUST_NORMS
            and (len(robust) == 2 or robust[2] in ROBUST_CONVENTIONS)):
        raise ModelError(f"robust must be None, ('huber', c) or ('tukey', c), optionally with the convention "
                         f"'consistent' (default) or 'ctsm' as a third element; got {robust!r}")
    try:
        c = float(robust[1])
    except (TypeError, ValueError):
        raise ModelError(f"the robust threshold c must be a positive number, got {robust[1]!r}") from None
    if not c > 0:
        raise ModelError(f"the robust threshold c must be positive, got {robust[1]!r}")
    if len(robust) == 3 and robust[2] == "ctsm":
        return robust[0], c, "ctsm"
    return robust[0], c


def squared_norm(r, robust: tuple[str, float] | None):
    """r² or its robust replacement ρ(r), element-wise."""
    if robust is None:
        return r**2
    kind, c = robust[:2]
    if kind == "huber":
        a = jnp.abs(r)
        return jnp.where(a < c, r**2, 2.0 * c * a - c**2)
    u = jnp.minimum((r / c) ** 2, 1.0)
    return (c**2 / 3.0) * (1.0 - (1.0 - u) ** 3)


def scale_consistency(robust) -> float:
    """κ = E[Z ρ'(Z)]/2 for Z ~ N(0, 1): 1 for the Gaussian norm, 2Φ(c) − 1 for Huber's,
    E[Z²(1 − Z²/c²)²; |Z| < c] for Tukey's.

    With κ log det R in place of log det R the robust criterion is stationary at
    the true innovation variance when the data are Gaussian, so variances
    estimated jointly are not shrunk: without it Tukey's norm, whose ρ is capped,
    rewards shrinking R until many residuals count as outliers (0.012 against a
    true 0.041 in the issue's example).
    """
    if robust is None or (len(robust) == 3 and robust[2] == "ctsm"):
        return 1.0  # the Gaussian norm; CTSM-R's convention leaves log det R unweighted
    from scipy import integrate, special, stats

    kind, c = robust[:2]
    if kind == "huber":
        return float(special.erf(c / np.sqrt(2.0)))  # 2Φ(c) − 1
    def integrand(z):
        return z**2 * (1 - (z / c) ** 2) ** 2 * stats.norm.pdf(z)
    return float(2 * integrate.quad(integrand, 0.0, c, epsabs=1e-13)[0])


def step_criterion(terms, robust=None, kappa: float = 1.0):
    """−½(s_k log 2π + κ log det R_k + Σ_i ρ(r_ki)) for each step k: the summands of
    [`log_criterion()`][greyid.estimate.criteria.log_criterion].

    κ is [`scale_consistency()`][greyid.estimate.criteria.scale_consistency] of the norm (1 for the Gaussian
    log-likelihood).  A filter that evaluates the observations' density (the particle filter) gives
    each step's log-likelihood itself ([`DensityTerms`][greyid.filters.updates.DensityTerms]), which has no
    innovation for a robust norm to weigh.
    """
    if isinstance(terms, DensityTerms):
        if robust is not None:
            raise ModelError("a robust criterion weighs Gaussian innovations; the particle filter has none "
                             "(fit it by maximum likelihood)")
        return terms.loglik
    return -0.5 * (terms.n_obs * LOG_2PI + kappa * terms.logdet
                   + jnp.sum(squared_norm(terms.whitened, robust), -1))


def log_criterion(terms, robust=None):
    """Σ_k −½(s_k log 2π + κ log det R_k + Σ_i ρ(r_ki)): (3.18), robust if asked (κ = 1 for ML)."""
    return jnp.sum(step_criterion(terms, robust, scale_consistency(robust)))


@dataclass(frozen=True)
class GaussianPrior:
    """A multivariate Gaussian prior on some parameters (3.46)."""

    names: tuple[str, ...]
    mean: np.ndarray
    covariance: np.ndarray

    @classmethod
    def from_spec(cls, spec: Mapping, parameter_names) -> "GaussianPrior":
        """``{"mean": {...}, "sd": {...}, "corr": {(a, b): ρ} or matrix}``."""
        if not isinstance(spec, Mapping) or "mean" not in spec or "sd" not in spec:
            raise ModelError("prior must be a dict with 'mean' and 'sd' (and optionally 'corr') by parameter name")
        names = tuple(spec["mean"])
        if set(spec["sd"]) != set(names):
            raise ModelError("prior 'mean' and 'sd' must name the same parameters")
        for n in names:
            if n not in parameter_names:
                raise ModelError(f"prior given for '{n}', which is not a parameter of the model")
        mean = np.array([float(spec["mean"][n]) for n in names])
        sd = np.array([float(spec["sd"][n]) for n in names])
        if np.any(~(sd > 0)):
            raise ModelError("prior standard deviations must be positive")
        corr = np.eye(len(names))
        given = spec.get("corr")
        if isinstance(given, Mapping):
            from ..schema import prior_correlation

            for (a, b), rho in prior_correlation(given).items():
                missing = [n for n in (a, b) if n not in names]
                if missing:
                    raise ModelError(f"prior correlation names '{missing[0]}', which has no prior mean and sd")
                i, j = names.index(a), names.index(b)
                corr[i, j] = corr[j, i] = float(rho)
        elif given is not None:
            corr = np.asarray(given, dtype=np.float64)
            if corr.shape != (len(names), len(names)):
                raise ModelError(f"prior correlation matrix must be {len(names)}x{len(names)}")
        cov = corr * np.outer(sd, sd)
        if np.min(np.linalg.eigvalsh(cov)) <= 0:
            raise ModelError("the prior covariance (sd and corr) is not positive definite")
        return cls(names, mean, cov)


def loglik(model, params, data, time="t", hold="zoh", method=None, time_unit=None, robust=None, **options) -> float:
    """Sum over data sets of the Gaussian log-likelihood (3.18), or its robust version.

    With ``robust=("huber", c)`` or ``("tukey", c)`` the squared normalised
    innovations are replaced as in [`greyid.estimate.criteria`][greyid.estimate.criteria] (CTSM's
    convention for Huber).
    """
    robust = check_robust(robust)
    structure, theta, prepared = _prepare(model, params, data, time, hold, time_unit)
    run = compiled_filter(structure, accurate_options(structure, theta, prepared, method, **options)[0],
                          keep_outputs=False)
    return float(sum(log_criterion(run(jnp.asarray(theta), inputs)[0], robust) for _, inputs in prepared))
