"""Observation distributions: how an output y_k is distributed given the states.

The thesis' model (4.2) measures y_k = h(x_k, u_k, t_k, θ) + e_k with Gaussian
e_k.  An observation may instead be declared with another distribution whose
location is the equation's value m = h(x_k, u_k, t_k, θ):

========================  ===============================  ====================  ===================
family                    y given m                        ``variance`` S        shape parameter a
========================  ===============================  ====================  ===================
``normal``                N(m, S)                          required              —
``student_t``             m + √S·t_ν (heavy tails)         S = scale²            ``df`` ν
``lognormal``             log y ~ N(log m, S): m median    S of log y            —
``poisson``               Poisson(m): m the mean count     not given             —
``negative_binomial``     mean m, variance m + m²/r        not given             ``size`` r
``binomial``              Binomial(n, m): m probability    not given             ``trials`` n
========================  ===============================  ====================  ===================

The shape parameter is an expression of the parameters, inputs and time (a
number of trials is usually an input column).  Only the methods that evaluate the
observation density itself take a family other than ``normal`` (``NON_GAUSSIAN_METHODS``:
the particle filter and the Laplace method); the Gaussian filters refuse them by name.
The functions below are JAX functions of one output's y, m, S and a, used by those
methods and by the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammaln

from ..errors import DataError, ModelError

NORMAL, STUDENT_T, LOGNORMAL = "normal", "student_t", "lognormal"
POISSON, NEGATIVE_BINOMIAL, BINOMIAL = "poisson", "negative_binomial", "binomial"
#: Each family and the name of its shape parameter (None: it has none).
SHAPES: dict[str, str | None] = {NORMAL: None, STUDENT_T: "df", LOGNORMAL: None, POISSON: None,
                                 NEGATIVE_BINOMIAL: "size", BINOMIAL: "trials"}
#: Families whose equation's value is scaled by a variance expression.
WITH_VARIANCE = (NORMAL, STUDENT_T, LOGNORMAL)
#: Families of counts (y a non-negative integer).
COUNTS = (POISSON, NEGATIVE_BINOMIAL, BINOMIAL)
#: The filter methods that evaluate an observation's density, so take any family.
NON_GAUSSIAN_METHODS = ("particle", "laplace")


@dataclass(frozen=True)
class Distribution:
    """An output's distribution: the family and its shape parameter's expression (see the module doc).

    Parameters
    ----------
    family : str
        One of ``normal``, ``student_t``, ``lognormal``, ``poisson``, ``negative_binomial``,
        ``binomial``.
    shape : str or float, optional
        The family's shape parameter (``df``, ``size`` or ``trials``) as an expression or a number;
        required for the families that have one, refused for the others.

    Examples
    --------
    >>> from greyid.model.distributions import Distribution
    >>> Distribution("student_t", "nu").shape_name
    'df'
    """

    family: str
    shape: str | float | None = None

    def __post_init__(self):
        if self.family not in SHAPES:
            raise ModelError(f"unknown observation distribution '{self.family}'; use one of {list(SHAPES)}")
        name = SHAPES[self.family]
        if name is not None and self.shape is None:
            raise ModelError(f"the {self.family} distribution needs its {name}: give "
                             f"distribution={{'family': '{self.family}', '{name}': ...}}")
        if name is None and self.shape is not None:
            raise ModelError(f"the {self.family} distribution has no shape parameter (got {self.shape!r})")

    @property
    def shape_name(self) -> str | None:
        """``df``, ``size`` or ``trials``, or None."""
        return SHAPES[self.family]

    @property
    def gaussian(self) -> bool:
        return self.family == NORMAL

    def to_dict(self) -> dict | str:
        """The form model files and saved fits hold: the family's name, or a table with the shape."""
        if self.shape_name is None:
            return self.family
        return {"family": self.family, self.shape_name: self.shape}


def distribution_of(value, where: str) -> Distribution:
    """A [`Distribution`][greyid.model.distributions.Distribution] from what a user wrote: None (normal), a
    family's name, a table ``{family = ..., df|size|trials = ...}`` or a Distribution."""
    if value is None:
        return Distribution(NORMAL)
    if isinstance(value, Distribution):
        return value
    if isinstance(value, str):
        try:
            return Distribution(value)
        except ModelError as error:
            raise ModelError(f"{where}: {error}") from None
    if isinstance(value, Mapping):
        family = value.get("family")
        if not isinstance(family, str):
            raise ModelError(f"{where}: a distribution table needs 'family' (one of {list(SHAPES)})")
        allowed = {"family"} | ({SHAPES[family]} if SHAPES.get(family) else set())
        unknown = sorted(set(value) - allowed)
        if unknown:
            raise ModelError(f"{where}: unknown key '{unknown[0]}' for the {family} distribution; allowed keys are "
                             f"{sorted(allowed)}")
        try:
            return Distribution(family, value.get(SHAPES.get(family) or "", None))
        except ModelError as error:
            raise ModelError(f"{where}: {error}") from None
    raise ModelError(f"{where}: a distribution is a name such as 'poisson' or a table "
                     f"{{family = ..., ...}}, got {value!r}")


def check_method(families, outputs, method: str) -> None:
    """Refuse a Gaussian filter for outputs whose distribution is not normal, naming them and the
    methods that can."""
    if method in NON_GAUSSIAN_METHODS:
        return
    able = " or ".join(repr(m) for m in NON_GAUSSIAN_METHODS)
    for family, output in zip(families, outputs):
        if family != NORMAL:
            raise ModelError(f"observation '{output}' has the {family} distribution, which the Gaussian filter "
                             f"'{method}' cannot evaluate; use method={able}")


def check_observed(family: str, output: str, values: np.ndarray, times: np.ndarray, time_name: str) -> None:
    """Refuse data a family cannot have produced: a count that is negative or not whole, a log-normal
    output that is not positive (missing values are allowed)."""
    observed = ~np.isnan(values)
    if family in COUNTS:
        bad = observed & ((values < 0) | (values != np.round(values)))
        what = "a non-negative whole number (a count)"
    elif family == LOGNORMAL:
        bad = observed & ~(values > 0)
        what = "positive (it is log-normal)"
    else:
        return
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(f"column '{output}' has {values[row]:g} at row {row} ({time_name} = {times[row]:g}); "
                        f"its observation has the {family} distribution, so each value must be {what}")


def _positive(a):
    """a where positive, 1 elsewhere: logarithms that stay finite (and their derivatives too) where a
    density is set to −∞ instead."""
    return jnp.where(a > 0, a, 1.0)


def log_density(family: str, y, m, variance, shape):
    """log p(y | m, S, a) of one output (−∞ where m or a is outside the family's range)."""
    if family == NORMAL:
        return -0.5 * (jnp.log(2 * jnp.pi * variance) + (y - m) ** 2 / variance)
    if family == STUDENT_T:
        nu = _positive(shape)
        z2 = (y - m) ** 2 / (nu * variance)
        value = (gammaln((nu + 1) / 2) - gammaln(nu / 2) - 0.5 * jnp.log(nu * jnp.pi * variance)
                 - (nu + 1) / 2 * jnp.log1p(z2))
        return jnp.where(shape > 0, value, -jnp.inf)
    if family == LOGNORMAL:
        safe_y, safe_m = _positive(y), _positive(m)
        value = -jnp.log(safe_y) - 0.5 * (jnp.log(2 * jnp.pi * variance)
                                          + (jnp.log(safe_y) - jnp.log(safe_m)) ** 2 / variance)
        return jnp.where((m > 0) & (y > 0), value, -jnp.inf)
    if family == POISSON:
        safe_m = _positive(m)
        value = y * jnp.log(safe_m) - m - gammaln(y + 1)
        return jnp.where(m > 0, value, jnp.where((m == 0) & (y == 0), 0.0, -jnp.inf))
    if family == NEGATIVE_BINOMIAL:
        r, safe_m = _positive(shape), _positive(m)
        value = (gammaln(y + r) - gammaln(r) - gammaln(y + 1) + r * (jnp.log(r) - jnp.log(r + safe_m))
                 + y * (jnp.log(safe_m) - jnp.log(r + safe_m)))
        return jnp.where((m > 0) & (shape > 0), value, -jnp.inf)
    if family == BINOMIAL:
        n = shape
        p = jnp.clip(m, 0.0, 1.0)
        inside = (m > 0) & (m < 1)
        safe_p = jnp.where(inside, p, 0.5)
        value = (gammaln(n + 1) - gammaln(y + 1) - gammaln(n - y + 1) + y * jnp.log(safe_p)
                 + (n - y) * jnp.log1p(-safe_p))
        edge = jnp.where(((m <= 0) & (y == 0)) | ((m >= 1) & (y == n)), 0.0, -jnp.inf)
        return jnp.where(y <= n, jnp.where(inside, value, edge), -jnp.inf)
    raise ModelError(f"unknown observation distribution '{family}'")


def moments(family: str, m, variance, shape):
    """The mean and variance of y given m, S and a."""
    if family == NORMAL:
        return m, variance
    if family == STUDENT_T:
        return m, jnp.where(shape > 2, variance * shape / _positive(shape - 2), jnp.inf)
    if family == LOGNORMAL:
        return m * jnp.exp(variance / 2), m**2 * jnp.exp(variance) * jnp.expm1(variance)
    if family == POISSON:
        return m, m
    if family == NEGATIVE_BINOMIAL:
        return m, m + m**2 / shape
    if family == BINOMIAL:
        return shape * m, shape * m * (1 - m)
    raise ModelError(f"unknown observation distribution '{family}'")


def sample(family: str, key, m, variance, shape):
    """One draw of y given m, S and a."""
    if family == NORMAL:
        return m + jnp.sqrt(variance) * jax.random.normal(key, jnp.shape(m))
    if family == STUDENT_T:
        return m + jnp.sqrt(variance) * jax.random.t(key, shape, jnp.shape(m))
    if family == LOGNORMAL:
        return m * jnp.exp(jnp.sqrt(variance) * jax.random.normal(key, jnp.shape(m)))
    if family == POISSON:
        return jax.random.poisson(key, m, jnp.shape(m)).astype(jnp.float64)
    if family == NEGATIVE_BINOMIAL:
        rate_key, count_key = jax.random.split(key)
        rate = jax.random.gamma(rate_key, shape, jnp.shape(m)) * m / shape  # gamma–Poisson mixture
        return jax.random.poisson(count_key, rate, jnp.shape(m)).astype(jnp.float64)
    if family == BINOMIAL:
        return jax.random.binomial(key, shape, jnp.clip(m, 0.0, 1.0), jnp.shape(m))
    raise ModelError(f"unknown observation distribution '{family}'")


def cdf(family: str, y, m, variance, shape):
    """P(Y ≤ y | m, S, a) of one output (for counts, of the whole number y; 0 below 0)."""
    from jax.scipy.special import betainc, gammaincc
    from jax.scipy.stats import norm

    if family == NORMAL:
        return norm.cdf((y - m) / jnp.sqrt(variance))
    if family == STUDENT_T:
        nu = _positive(shape)
        t = (y - m) / jnp.sqrt(variance)
        tail = 0.5 * betainc(nu / 2, 0.5, nu / (nu + t**2))
        return jnp.where(t > 0, 1 - tail, tail)
    if family == LOGNORMAL:
        return jnp.where(y > 0, norm.cdf((jnp.log(_positive(y)) - jnp.log(_positive(m))) / jnp.sqrt(variance)), 0.0)
    k = jnp.floor(y)
    safe_k = jnp.maximum(k, 0.0)
    if family == POISSON:
        value = gammaincc(safe_k + 1, _positive(m))
        return jnp.where(k < 0, 0.0, jnp.where(m > 0, value, 1.0))
    if family == NEGATIVE_BINOMIAL:
        r = _positive(shape)
        return jnp.where(k < 0, 0.0, betainc(r, safe_k + 1, r / (r + _positive(m))))
    if family == BINOMIAL:
        n = shape
        p = jnp.clip(m, 0.0, 1.0)
        inside = betainc(jnp.maximum(n - safe_k, 1e-300), safe_k + 1, 1 - p)
        return jnp.where(k < 0, 0.0, jnp.where(k >= n, 1.0, inside))
    raise ModelError(f"unknown observation distribution '{family}'")


def probability_integral_transform(family: str, y, m, variance, shape, uniform):
    """u = P(Y < y) + V·P(Y = y) (V the ``uniform`` number) for counts, P(Y ≤ y) otherwise: uniform on (0, 1)
    when y comes from the distribution (randomized for counts, Dunn & Smyth 1996)."""
    upper = cdf(family, y, m, variance, shape)
    if family not in COUNTS:
        return upper
    return cdf(family, y - 1, m, variance, shape) * (1 - uniform) + upper * uniform


def observations_log_density(families, y, mask, m, variance, shape):
    """Σ_i mask_i · log p(y_i | m_i, S_i, a_i) over one row's outputs (unobserved ones add nothing)."""
    total = 0.0
    for i, family in enumerate(families):
        term = log_density(family, y[i], m[i], variance[i], shape[i])
        total = total + jnp.where(mask[i] > 0, term, 0.0)
    return total


__all__ = ["Distribution", "distribution_of", "log_density", "moments", "sample", "cdf",
           "probability_integral_transform", "check_method", "check_observed",
           "observations_log_density", "SHAPES", "NON_GAUSSIAN_METHODS"]
