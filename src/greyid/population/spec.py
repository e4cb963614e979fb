"""What a population model estimates: typical values, covariate effects and the random effects' spread.

A member i's parameters are (the parameter's *scale* ψ is θ itself for a
``"normal"`` random effect and for parameters without one, log θ for a
``"lognormal"`` one)

    ψ_i = ψ_typical + Σ_c β_c x_ic + η_i,    η_i = L u_i,  u_i ~ N(0, I),  Ω = L Lᵀ,

with x_ic the covariates standardised over the data sets (so β and the
optimiser's steps do not depend on the covariates' units; β is reported per
unit of the covariate) and u_i the standardised random effects the inner
optimisation works in (so its steps do not depend on the parameters' units).
L = diag(ω)·C with C the Cholesky factor of the random effects' correlation
matrix (identity for a diagonal Ω), its rows unit vectors of free
lower-triangular elements: every Ω this gives is positive definite.

The population parameters φ the outer optimisation works in are, in order:
one coordinate per free model parameter (its bound transform's z for the
typical value, log θ for a lognormal one), the covariate effects β (per
standard deviation of the covariate), log ω per random effect and, with a full
Ω, the off-diagonal elements of C's unnormalised rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import pandas as pd

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax.numpy as jnp

from ..errors import DataError, ModelError
from ..estimate.transforms import NONE, Transform

KINDS = ("normal", "lognormal")
OMEGAS = ("diagonal", "full")
#: Default standard deviation of a lognormal random effect at the start (about a 30 % spread).
OMEGA_START = 0.3


def _random_spec(random, names, declared) -> tuple[list[str], list[str]]:
    if isinstance(random, str) or not isinstance(random, Mapping) or not random:
        raise ModelError("random must map parameter names to 'normal' or 'lognormal', e.g. {'Ci': 'lognormal'}")
    params, kinds = [], []
    for name, kind in random.items():
        if name not in names:
            raise ModelError(f"a random effect on '{name}', which is not a parameter of the model "
                             f"(parameters: {', '.join(names)})")
        p = declared.get(name)
        if p is not None and p.fixed:
            raise ModelError(f"a random effect on '{name}', which is fixed; free it (set_parameter('{name}', "
                             "fixed=False)) or leave its random effect out")
        if kind not in KINDS:
            raise ModelError(f"the random effect of '{name}' is '{kind}'; use 'normal' (θ_i = θ + η_i) or "
                             "'lognormal' (θ_i = θ·exp(η_i))")
        if kind == "lognormal" and p is not None and p.lower is not None and p.lower < 0:
            raise ModelError(f"'{name}' has a lognormal random effect but may be negative (lower bound {p.lower}); "
                             "a lognormal parameter is positive: use 'normal', or a lower bound of 0")
        params.append(name)
        kinds.append(kind)
    return params, kinds


@dataclass(frozen=True)
class PopulationSpec:
    """The layout of φ and the map (φ, u_i, x_i) → θ_i (see the module's docstring)."""

    names: tuple[str, ...]  # every model parameter, in θ's order
    theta0: np.ndarray  # fixed parameters' values, free ones' starting typical values
    free: tuple[int, ...]  # positions in θ of the free parameters
    log_scale: tuple[bool, ...]  # per free parameter: ψ = log θ (a lognormal random effect)
    transform: Transform  # per free parameter: z → typical ψ (identity where log_scale)
    random: tuple[int, ...]  # positions in θ of the random effects' parameters
    kinds: tuple[str, ...]
    covariates: tuple[str, ...]
    effects: tuple[tuple[int, int], ...]  # (position in θ, covariate column)
    covariate_mean: np.ndarray
    covariate_sd: np.ndarray
    full: bool  # Ω with correlations
    omega0: np.ndarray  # starting standard deviations of η
    correlation0: np.ndarray | None = None  # starting correlation elements of C (full Ω), pairs' order

    # ------------------------------------------------------------------ layout
    @property
    def n_random(self) -> int:
        return len(self.random)

    @property
    def n_correlations(self) -> int:
        q = self.n_random
        return q * (q - 1) // 2 if self.full else 0

    @property
    def slices(self) -> dict[str, slice]:
        """Where each block sits in φ."""
        a, b, c = len(self.free), len(self.effects), self.n_random
        return dict(typical=slice(0, a), beta=slice(a, a + b), log_omega=slice(a + b, a + b + c),
                    correlation=slice(a + b + c, a + b + c + self.n_correlations))

    @property
    def size(self) -> int:
        return len(self.free) + len(self.effects) + self.n_random + self.n_correlations

    def phi_names(self) -> list[str]:
        """The population parameters' names, in φ's order."""
        free = [self.names[i] for i in self.free]
        beta = [f"beta_{self.names[i]}_{self.covariates[c]}" for i, c in self.effects]
        omega = [f"omega_{self.names[i]}" for i in self.random]
        corr = [f"corr_{self.names[self.random[a]]}_{self.names[self.random[b]]}" for a, b in self.pairs()]
        return free + beta + omega + corr

    def pairs(self) -> list[tuple[int, int]]:
        """(row, column) of C's off-diagonal elements, row by row."""
        if not self.full:
            return []
        return [(a, b) for a in range(self.n_random) for b in range(a)]

    def phi0(self) -> np.ndarray:
        """φ at the model's initial values, no covariate effect, ω at ``omega0``, the correlations at
        ``correlation0`` (none where not given)."""
        theta_free = self.theta0[list(self.free)]
        typical = np.where(self.log_scale, np.log(np.where(self.log_scale, theta_free, 1.0)),
                           self.transform.to_z(theta_free))
        correlation = np.zeros(self.n_correlations) if self.correlation0 is None else self.correlation0
        return np.concatenate([typical, np.zeros(len(self.effects)), np.log(self.omega0), correlation])

    # ------------------------------------------------------------------ maps
    def cholesky(self, phi, xp=jnp):
        """L with Ω = L Lᵀ (q × q)."""
        s = self.slices
        omega = xp.exp(phi[s["log_omega"]])
        q = self.n_random
        if not self.full:
            return xp.diag(omega)
        rows = []
        elements = dict(zip(self.pairs(), [phi[s["correlation"]][k] for k in range(self.n_correlations)]))
        for a in range(q):
            row = xp.stack([elements[(a, b)] if b < a else (xp.ones(()) if b == a else xp.zeros(()))
                            for b in range(q)])
            rows.append(row / xp.sqrt(xp.sum(row ** 2)))
        return omega[:, None] * xp.stack(rows)

    def base(self) -> tuple:
        """The arrays `theta()` takes besides φ, u and x: θ's fixed values, the bounds of the free ones
        (arguments of the compiled programs, so that new values do not compile anew)."""
        return (self.theta0, self.transform.lower, self.transform.upper)

    def typical_scale(self, phi, base, xp=jnp):
        """ψ of the typical member (covariates at their mean), per free parameter."""
        z = phi[self.slices["typical"]]
        natural = Transform(self.transform.kind, base[1], base[2]).to_theta(z, xp)
        return xp.where(np.array(self.log_scale), z, natural)

    def key(self) -> tuple:
        """Everything `theta()` closes over (the key of the compiled programs)."""
        return (self.names, self.free, self.log_scale, tuple(self.transform.kind.tolist()), self.random,
                self.effects, self.full)

    def scale_key(self) -> tuple:
        """Everything `theta_at_scale()` and `random_in_scale` close over: the key of the programs that take
        the members' scales ψ (the same for nested layouts: a diagonal or a full Ω, covariate effects or none)."""
        return (self.names, self.free, self.log_scale, self.random_in_scale)

    def scale(self, phi, u, x, base, xp=jnp):
        """ψ_i, the free parameters' scales of member i (log θ for a lognormal random effect, θ otherwise),
        at the standardised random effects ``u`` and standardised covariates ``x``."""
        psi = self.typical_scale(phi, base, xp)
        beta = phi[self.slices["beta"]]
        eta = self.cholesky(phi, xp) @ u if self.n_random else None
        shifts: dict[int, list] = {}
        for k, (i, c) in enumerate(self.effects):
            shifts.setdefault(i, []).append(beta[k] * x[c])
        for r, i in enumerate(self.random):
            shifts.setdefault(i, []).append(eta[r])
        return xp.stack([psi[j] + sum(shifts.get(i, [])) for j, i in enumerate(self.free)])

    def theta_at_scale(self, scale, base, xp=jnp):
        """θ of a member from its free parameters' ``scale`` (see `scale()`) and the fixed values in ``base``."""
        position = {index: j for j, index in enumerate(self.free)}
        out = []
        for i in range(len(self.names)):
            if i not in position:
                out.append(base[0][i])
                continue
            j = position[i]
            out.append(xp.exp(scale[j]) if self.log_scale[j] else scale[j])
        return xp.stack(out)

    def theta(self, phi, u, x, base, xp=jnp):
        """θ_i at the standardised random effects ``u`` and standardised covariates ``x``."""
        return self.theta_at_scale(self.scale(phi, u, x, base, xp), base, xp)

    @property
    def random_in_scale(self) -> tuple[int, ...]:
        """Where the random effects' parameters sit in `scale()`'s vector (ψ_i moves with u_i there alone)."""
        return tuple(self.free.index(i) for i in self.random)

    def standardise(self, table: pd.DataFrame | None) -> np.ndarray:
        """Covariates of data sets (rows of ``table``) standardised as in the fit."""
        if not self.covariates:
            return np.zeros((0 if table is None else len(table), 0))
        values = table[list(self.covariates)].to_numpy(dtype=float)
        return (values - self.covariate_mean) / self.covariate_sd


def make_spec(model, random, covariates, effects, omega, names_of_datasets, init=None,
              omega_init=None) -> tuple[PopulationSpec, np.ndarray]:
    """The [`PopulationSpec`][greyid.population.spec.PopulationSpec] of these settings, and the data sets' covariate
    rows (raw)."""
    from ..estimate.estimation import free_parameters

    parameters = free_parameters(model, init)
    names = list(parameters.names)
    declared = model.parameters
    random_names, kinds = _random_spec(random, names, declared)
    if omega not in OMEGAS:
        raise ModelError(f"omega is '{omega}'; use 'diagonal' or 'full'")
    free = list(parameters.free)
    log_scale = [names[i] in random_names and kinds[random_names.index(names[i])] == "lognormal" for i in free]
    for j, i in enumerate(free):
        if log_scale[j] and not parameters.theta0[i] > 0:
            raise ModelError(f"'{names[i]}' has a lognormal random effect but its initial value is "
                             f"{parameters.theta0[i]}; give a positive initial value")
    kind = np.where(log_scale, NONE, parameters.transform.kind)
    transform = Transform(kind.astype(int), parameters.transform.lower, parameters.transform.upper)

    effects = {} if effects is None else dict(effects)
    if effects and covariates is None:
        raise DataError("effects name covariates, but no covariates table was given: a CSV file with a row per "
                        "data set (--covariates FILE.csv on the command line, covariates = \"FILE.csv\" in the "
                        "model file's [population] table) or covariates=DataFrame in Python")
    columns: list[str] = []
    pairs = []
    for name, listed in effects.items():
        if name not in names:
            raise ModelError(f"a covariate effect on '{name}', which is not a parameter of the model")
        if name not in [names[i] for i in free]:
            raise ModelError(f"a covariate effect on '{name}', which is fixed")
        for column in [listed] if isinstance(listed, str) else list(listed):
            if column not in covariates.columns:
                raise DataError(f"covariate '{column}' (an effect on '{name}') is not a column of the covariates "
                                f"table ({', '.join(map(str, covariates.columns))})")
            if column not in columns:
                columns.append(column)
            pairs.append((names.index(name), columns.index(column)))
    raw = np.zeros((len(names_of_datasets), len(columns)))
    mean, sd = np.zeros(len(columns)), np.ones(len(columns))
    if columns:
        index = [str(i) for i in covariates.index]
        missing = [n for n in names_of_datasets if str(n) not in index]
        if missing:
            raise DataError(f"the covariates table has no row for data set '{missing[0]}' (its index must be the "
                            "data sets' names)")
        for n in names_of_datasets:  # a member's covariates must be one row, not the first of several
            places = [k for k, i in enumerate(index) if i == str(n)]
            if len(places) > 1:
                raise DataError(f"the covariates table has {len(places)} rows for data set '{n}' (rows "
                                f"{', '.join(str(k + 1) for k in places)} below the header); keep one")
        rows = [index.index(str(n)) for n in names_of_datasets]
        table = covariates.iloc[rows][columns]
        for column in columns:
            values = pd.to_numeric(table[column], errors="coerce")
            bad = values.isna() | ~np.isfinite(values.to_numpy(dtype=float, na_value=np.nan))
            if bad.any():
                raise DataError(f"covariate '{column}' is missing or not a number for data set "
                                f"'{names_of_datasets[int(np.flatnonzero(bad.to_numpy())[0])]}'")
        raw = table.to_numpy(dtype=float)
        mean, sd = raw.mean(axis=0), raw.std(axis=0)
        constant = [c for c, s in zip(columns, sd) if not s > 0]
        if constant:
            raise DataError(f"covariate '{constant[0]}' has the same value for every data set; its effect cannot "
                            "be estimated")

    omega_init, correlation0 = _omega_start(omega_init, random_names, omega == "full")
    unknown = [n for n in omega_init if n not in random_names]
    if unknown:
        raise ModelError(f"omega_init given for '{unknown[0]}', which has no random effect")
    omega0 = []
    for name, kind in zip(random_names, kinds):
        if name in omega_init:
            value = float(omega_init[name])
            if not value > 0:
                raise ModelError(f"omega_init of '{name}' is {value}; a standard deviation must be positive")
        elif kind == "lognormal":
            value = OMEGA_START
        else:
            start = abs(parameters.theta0[names.index(name)])
            value = OMEGA_START * start if start > 0 else 1.0
        omega0.append(value)
    spec = PopulationSpec(tuple(names), parameters.theta0.copy(), tuple(free), tuple(log_scale), transform,
                          tuple(names.index(n) for n in random_names), tuple(kinds), tuple(columns),
                          tuple(pairs), mean, sd, omega == "full", np.array(omega0), correlation0)
    return spec, raw


def _omega_start(omega_init, random_names: list[str], full: bool) -> tuple[dict, np.ndarray | None]:
    """``omega_init`` as (standard deviations by name, C's starting elements or None): a mapping of
    standard deviations, or Ω itself as a square DataFrame labelled by the random parameters."""
    if not isinstance(omega_init, pd.DataFrame):
        return dict(omega_init or {}), None
    labels = [str(c) for c in omega_init.columns]
    if [str(i) for i in omega_init.index] != labels or sorted(labels) != sorted(random_names):
        raise ModelError(f"omega_init as a matrix must be square with rows and columns named by the random "
                         f"effects' parameters ({', '.join(random_names)}); it has rows "
                         f"{list(omega_init.index)} and columns {list(omega_init.columns)}")
    try:
        matrix = omega_init.loc[random_names, random_names].to_numpy(dtype=float)
    except (TypeError, ValueError):
        raise ModelError("omega_init holds a value that is not a number") from None
    if not np.all(np.isfinite(matrix)) or not np.allclose(matrix, matrix.T, rtol=1e-10, atol=0.0):
        raise ModelError("omega_init is not a symmetric matrix of numbers; Ω is a covariance matrix")
    eigenvalues = np.linalg.eigvalsh(matrix)
    if not eigenvalues.min() > 0:
        raise ModelError(f"omega_init is not positive definite (smallest eigenvalue {eigenvalues.min():.6g}); "
                         "Ω is the covariance of the random effects")
    sd = np.sqrt(np.diag(matrix))
    correlation = matrix / np.outer(sd, sd)
    if not full:
        if np.any(np.abs(correlation - np.eye(len(sd))) > 1e-12):
            raise ModelError("omega_init has correlations but omega is 'diagonal'; use omega='full'")
        return dict(zip(random_names, sd)), None
    L = np.linalg.cholesky(correlation)
    q = len(sd)
    elements = np.array([L[a, b] / L[a, a] for a in range(q) for b in range(a)])  # C's rows, normalised
    return dict(zip(random_names, sd)), elements
