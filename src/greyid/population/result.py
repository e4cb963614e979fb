"""The result of a population fit, in statsmodels' manner: ``params``, ``loglik``, ``aic``, ``summary()``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.special import ndtri

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp

from ..data.files import read_source
from ..errors import DataError
from ..api import FitResult, Model
from ..estimate.results import Estimates, parameter_table
from ..estimate.settings import FitSettings, filter_settings
from ..estimate.transforms import Transform
from ..filters.api import filter_options
from ..outputs import write_atomic
from ..runtime.jit import structure_program
from ..scaled import ScaledInformation, scaled_inverse
from .laplace import MemberPrograms, Modes, conditional_modes, laplace_values
from .members import Members, population_programs, prepare_members
from .saved import FORMAT, population_to_dict
from .spec import PopulationSpec

#: Two-sided 95 % intervals.
Z95 = float(ndtri(0.975))  # scipy.stats.norm.ppf's value; scipy.stats is imported only where it is used


def _reporting(spec: PopulationSpec):
    """``(ρ(φ, s), m)``: per reported quantity a coordinate ρ_k in which its Wald interval is taken and the
    monotone map m_k(ρ_k) to the reported value (the bound transform of a typical value, exp for a
    lognormal typical value or for ω, tanh for a correlation, identity for a covariate effect); ``s`` the
    covariates' standard deviations of the effects (a covariate effect per unit of its covariate)."""
    free_kind = spec.transform.kind

    def rho(phi, covariate_sd):
        s = spec.slices
        L = spec.cholesky(phi)
        omega_sq = jnp.sum(L ** 2, axis=1)
        parts = [phi[s["typical"]], phi[s["beta"]] / covariate_sd, 0.5 * jnp.log(omega_sq)]
        if spec.full:
            cov = L @ L.T
            corr = [cov[a, b] / jnp.sqrt(omega_sq[a] * omega_sq[b]) for a, b in spec.pairs()]
            parts.append(jnp.arctanh(jnp.stack(corr)))
        return jnp.concatenate(parts)

    def value(r):

        n = len(spec.free)
        # An interval's end far out on the log scale (ω → 0, its standard error large) is +inf or 0
        # on the natural scale: the intended value, so no overflow warning.
        with np.errstate(over="ignore", under="ignore"):
            typical = Transform(free_kind, spec.transform.lower, spec.transform.upper).to_theta(r[:n], np)
            typical = np.where(spec.log_scale, np.exp(np.where(spec.log_scale, r[:n], 0.0)), typical)
            a, b = n + len(spec.effects), n + len(spec.effects) + spec.n_random
            return np.concatenate([typical, r[n:a], np.exp(r[a:b]), np.tanh(r[b:])])

    return rho, value


def _effects_sd(spec: PopulationSpec) -> np.ndarray:
    """The standard deviation of each covariate effect's covariate (``_reporting``'s ``s``)."""
    return np.asarray(spec.covariate_sd, dtype=float)[[c for _, c in spec.effects]].reshape(len(spec.effects))


def _summaries(structure, spec: PopulationSpec):
    """One program for what a result reports at φ: ``(ρ, ∂ρ/∂φ, L, θ_i)`` from ``(φ, s, U, X, base)`` (ρ and s
    as in ``_reporting``, L Ω's Cholesky factor, θ_i every member's parameters at its random effects U_i
    and covariates X_i).  Kept with the layout's other programs: run op by op, these small operations
    would each compile a program of their own, in every process."""
    rho_of, _ = _reporting(spec)

    def summaries(phi, covariate_sd, u, x, base):
        theta = jax.vmap(spec.theta, in_axes=(None, 0, 0, None))(phi, u, x, base)
        return rho_of(phi, covariate_sd), jax.jacfwd(rho_of)(phi, covariate_sd), spec.cholesky(phi), theta

    return structure_program(structure, ("population", "result", spec.key()), lambda: summaries)


class PopulationResult:
    """A population fit: its parameters with their uncertainty, each member's random effects, its statistics.

    Made by [`fit_population()`][greyid.population.fit.fit_population] and
    [`load_population()`][greyid.population.result.load_population].

    Attributes
    ----------
    params : pandas.DataFrame
        One row per population parameter: the typical values of the free
        parameters (for a lognormal parameter, its median over the population; with
        covariates, at their mean), ``beta_<parameter>_<covariate>`` (per unit of
        the covariate, on the parameter's scale: log for lognormal),
        ``omega_<parameter>`` (the standard deviation of η; for a lognormal
        parameter about its coefficient of variation) and ``corr_<a>_<b>``; with
        standard errors from the Hessian of the Laplace marginal likelihood (the
        members' second derivatives by differences, or the exact one: ``call["hessian"]``)
        and 95 % intervals taken where each quantity is unbounded, then mapped back.
    random_effects : pandas.DataFrame
        One row per member: each random parameter at the conditional mode of η,
        its conditional standard error (given the population parameters) and η.
    individual : pandas.DataFrame
        One row per member: every parameter's value.
    loglik : float
        The Laplace approximation of the marginal log-likelihood.
    converged : bool
        Whether the outer search converged.
    left_out : dict
        The data sets that could not be prepared, with the reason.
    """

    def __init__(self, model, spec, members, phi, hessian, modes, call, converged, message, iterations):
        self.model, self.spec, self.call = model, spec, call
        self.names = list(members.names)
        self.frames = dict(zip(members.names, members.frames))
        self.sources = {}  # name -> CSV path, for the members read from files
        self.covariates = None  # the covariates table given to the fit, its members' rows
        self.left_out = dict(members.left_out)
        self.n_obs = int(np.sum(members.n_obs))
        self.n_members = len(members.names)
        self.phi = np.asarray(phi, dtype=float)
        self.hessian = np.asarray(hessian, dtype=float)
        self.converged, self.message, self.iterations = bool(converged), message, int(iterations)
        self._modes = modes
        self._members = members
        self.loglik = float(call["loglik"])
        self._at_estimates = self._summarised(modes.u, members.x)
        self._build_params()
        self._build_random_effects()

    @classmethod
    def _at_optimum(cls, model, spec, members, optimum, modes, call):
        """The result at the outer search's optimum, with the members' modes (for fit_population)."""
        call = dict(call, loglik=-float(np.sum(laplace_values(modes))))
        return cls(model, spec, members, optimum.z, optimum.hessian, modes, call, optimum.converged,
                   optimum.message, optimum.iterations)

    def _summarised(self, u, x) -> tuple:
        """``(ρ, ∂ρ/∂φ, L, θ_i)`` at the estimates for members at random effects ``u`` with covariates ``x``
        (see ``_summaries``), as NumPy arrays."""
        spec = self.spec
        program = _summaries(self.model.structure, spec)
        return tuple(np.asarray(a) for a in program(self.phi, _effects_sd(spec), np.asarray(u, dtype=float),
                                                    np.asarray(x, dtype=float), spec.base()))

    # ------------------------------------------------------------------ tables
    def _build_params(self):
        spec = self.spec
        names = spec.phi_names()
        information = ScaledInformation.of(self.hessian, names)
        singular = information.singular
        self.cov_phi = scaled_inverse(self.hessian, pseudo=bool(singular))
        _, value_of = _reporting(spec)
        rho, J = self._at_estimates[:2]
        cov_rho = J @ self.cov_phi @ J.T
        se_rho = np.sqrt(np.where(np.diag(cov_rho) >= 0, np.diag(cov_rho), np.nan))
        estimate = value_of(rho)
        h = 1e-6 * np.maximum(np.abs(rho), 1.0)
        slope = (value_of(rho + h) - value_of(rho - h)) / (2 * h)  # element-wise monotone maps
        with np.errstate(invalid="ignore"):
            lower, upper = value_of(rho - Z95 * se_rho), value_of(rho + Z95 * se_rho)
        self.params = pd.DataFrame(dict(estimate=estimate, std_error=np.abs(slope) * se_rho,
                                        ci_lower=np.minimum(lower, upper), ci_upper=np.maximum(lower, upper)),
                                   index=pd.Index(names, name=None))
        self.params["kind"] = self._kinds()
        self.cov = pd.DataFrame((slope[:, None] * cov_rho * slope[None, :]), index=names, columns=names)
        self.undetermined = information.directions() if singular else []

    def _kinds(self) -> list[str]:
        spec = self.spec
        out = []
        for i in spec.free:
            if i in spec.random:
                out.append(f"typical ({spec.kinds[spec.random.index(i)]})")
            else:
                out.append("shared")
        out += ["covariate effect"] * len(spec.effects)
        out += ["sd of random effect"] * spec.n_random
        out += ["correlation"] * spec.n_correlations
        return out

    def _build_random_effects(self):
        spec = self.spec
        L, thetas = self._at_estimates[2:]
        rows, self.individual_params = [], []
        for k, _name in enumerate(self.names):
            u = self._modes.u[k]
            theta = thetas[k]
            self.individual_params.append(theta)
            H = self._modes.hessian[k]
            cov_eta = L @ np.linalg.inv(0.5 * (H + H.T)) @ L.T
            eta = L @ u
            row = {}
            for r, i in enumerate(spec.random):
                scale = theta[i] if spec.kinds[r] == "lognormal" else 1.0  # dθ/dη
                row[spec.names[i]] = theta[i]
                row[f"{spec.names[i]}_se"] = abs(scale) * np.sqrt(cov_eta[r, r])
                row[f"eta_{spec.names[i]}"] = eta[r]
            rows.append(row)
        self.random_effects = pd.DataFrame(rows, index=pd.Index(self.names, name="dataset"))
        self.individual = pd.DataFrame(np.array(self.individual_params), index=pd.Index(self.names, name="dataset"),
                                       columns=list(spec.names))

    # ------------------------------------------------------------------ statistics
    @property
    def n_params(self) -> int:
        """The number of population parameters estimated."""
        return self.spec.size

    @property
    def aic(self) -> float:
        """Akaike's information criterion, −2 log L + 2k."""
        return -2 * self.loglik + 2 * self.n_params

    @property
    def bic(self) -> float:
        """The Bayesian information criterion, −2 log L + k log n (n: observed output values, as nlme)."""
        return -2 * self.loglik + self.n_params * np.log(self.n_obs)

    @property
    def omega(self) -> pd.DataFrame:
        """Ω, the random effects' covariance (on each parameter's scale: log for lognormal)."""
        L = self._at_estimates[2]
        names = [self.spec.names[i] for i in self.spec.random]
        return pd.DataFrame(L @ L.T, index=names, columns=names)

    @property
    def shrinkage(self) -> pd.Series:
        """η-shrinkage per random effect, 1 − sd(η̂_i)/ω (0: the data determine each member's η; 1: none)."""
        out = {}
        for i in self.spec.random:
            name = self.spec.names[i]
            eta = self.random_effects[f"eta_{name}"].to_numpy()
            omega = self.params.loc[f"omega_{name}", "estimate"]
            out[name] = 1.0 - np.std(eta, ddof=1) / omega if len(eta) > 1 else np.nan
        return pd.Series(out, name="shrinkage")

    def member(self, name):
        """One member's fit at its individual parameters.

        Parameters
        ----------
        name : str
            The member's name.

        Returns
        -------
        FitResult
            The random parameters at their conditional modes (standard errors
            conditional on the population parameters), the others at the population
            estimates (their population standard errors); residual tests, predictions
            and plots work on it as on any fit.  Its ``loglik`` is the member's own
            log-likelihood at these parameters.

        Raises
        ------
        KeyError
            A name that is not a member (or was left out: the reason), or a member of a
            loaded fit whose data are not at hand.
        """

        if name not in self.frames:
            known = ", ".join(map(str, self.names[:10]))
            why = f" (left out: {self.left_out[name]})" if name in self.left_out else ""
            raise KeyError(f"'{name}' is not a member of this population fit{why}; members: {known}"
                           + (" ..." if len(self.names) > 10 else ""))
        k = self.names.index(name)
        frames = self.frames[name]
        if frames is None and name in self.sources:

            frames = self.frames[name] = [read_source(self.sources[name])]
        if frames is None:
            raise KeyError(f"the data of member '{name}' are not in the saved fit; "
                           "load_population(path, data={name: DataFrame, ...}) gives them")
        theta = self.individual.loc[name].to_numpy(dtype=float)
        se = {self.spec.names[i]: float(self.random_effects.loc[name, f"{self.spec.names[i]}_se"])
              for i in self.spec.random}
        return self._fit_at(name, theta, se, frames, int(self._members.n_obs[k]), "member")

    def _fit_at(self, name, theta, random_se: dict, frames, n_obs: int, what: str):
        """A FitResult at individual parameters θ: random parameters with their conditional SEs, the
        other free ones with their population SEs."""
        spec = self.spec
        # The member's own filter settings; its estimates come from the population (optimizer).
        settings = FitSettings(**{"time_unit": None, **filter_settings(self.call)}, optimizer="population")
        loglik = self.model.loglik(dict(zip(spec.names, theta)), frames[0], **settings.filter_kwargs())
        free_names = [spec.names[i] for i in spec.free]
        se = np.array([random_se[name] if name in random_se
                       else float(self.params.loc[name, "std_error"]) if name in self.params.index else np.nan
                       for name in free_names], dtype=float)
        params = parameter_table(self.model, np.asarray(theta, dtype=float), spec.free, se)
        cov = pd.DataFrame(np.diag(se ** 2), index=free_names, columns=free_names)
        return FitResult.of(Estimates(model=self.model, params=params, cov=cov, loglik=float(loglik),
                                      criterion_value=float(loglik), n_obs=n_obs, converged=self.converged,
                                      message=f"{what} '{name}' of a population fit ({self.message})",
                                      iterations=self.iterations, settings=settings, data=frames))

    def predict(self, new_data, covariates=None, name: str = "new"):
        """A data set not in the fit, with the population as its prior (MAP).

        Its random effects' conditional mode given its data and the population estimates.

        Parameters
        ----------
        new_data : pandas.DataFrame
            The new data set.
        covariates : mapping or pandas.DataFrame, optional
            The covariates the population's effects use (a mapping or a one-row table);
            needed where the population has covariate effects.
        name : str
            The name the result carries.

        Returns
        -------
        FitResult
            A fit at its parameters (``.predict()``, ``.residuals``, ``.validate()`` on it).

        Raises
        ------
        DataError
            Covariates missing where the population has covariate effects, or data that
            do not fit the model.
        """
        spec = self.spec
        if spec.covariates:
            if covariates is None:
                raise DataError(f"the population has covariate effects; give covariates= with "
                                 f"{', '.join(spec.covariates)}")
            row = covariates if isinstance(covariates, pd.DataFrame) else pd.DataFrame([dict(covariates)])
            missing = [c for c in spec.covariates if c not in row.columns]
            if missing:
                raise DataError(f"covariates= lacks '{missing[0]}'")
            raw = row[list(spec.covariates)].to_numpy(dtype=float)[:1]
        else:
            raw = np.zeros((1, 0))
        settings = self.call
        members = prepare_members(self.model, [name], [new_data], spec, raw, settings["time"], settings["hold"],
                                   settings.get("time_unit"), None, minimum=1)
        options = filter_options(self.model.structure, settings["method"], form=settings["form"],
                                 substeps=settings["substeps"], iterations=settings["iterations"])
        programs = MemberPrograms(population_programs(self.model.structure, spec, options), members.x,
                                  spec.base(), members.data, 1)
        try:
            modes = conditional_modes(programs, self.phi, np.zeros((1, spec.n_random)))
        finally:
            programs.close()
        _, _, L, thetas = self._summarised(modes.u, members.x)
        theta = thetas[0]
        cov_eta = L @ np.linalg.inv(0.5 * (modes.hessian[0] + modes.hessian[0].T)) @ L.T
        random_se = {}
        for r, i in enumerate(spec.random):
            scale = theta[i] if spec.kinds[r] == "lognormal" else 1.0
            random_se[spec.names[i]] = float(abs(scale) * np.sqrt(cov_eta[r, r]))
        return self._fit_at(name, theta, random_se, members.frames[0], int(members.n_obs[0]), "new data set")

    def report(self, path=None, level: float = 0.05, title: str | None = None, members: bool = True) -> str:
        """The self-contained HTML report of this population fit.

        Parameters
        ----------
        path : str or pathlib.Path, optional
            Where to write it (atomically); without it, nothing is written.
        level : float
            The significance level of the members' residual tests.
        title : str, optional
            The report's title.
        members : bool
            False leaves out the members' residual tests.

        Returns
        -------
        str
            The HTML document.
        """
        from ..report.population import population_report  # matplotlib: imported where a report is asked for

        text = population_report(self, level=level, title=title, members=members)
        if path is not None:
            write_atomic(path, text)
        return text

    def save(self, path) -> None:
        """Write the fit as JSON, atomically.

        Parameters
        ----------
        path : str or pathlib.Path
            The file; [`load_population()`][greyid.population.result.load_population] reads it.
        """
        write_atomic(path, json.dumps(population_to_dict(self), indent=1))

    def summary(self) -> str:
        """A readable table of the population fit.

        Returns
        -------
        str
            The log-likelihood, information criteria, convergence, the random effects'
            kinds, the population parameters with standard errors and intervals, the
            shrinkage and the data sets left out.
        """
        spec = self.spec
        lines = [f"Population fit of model {self.model.name}: {self.n_members} data sets, {self.n_obs} observations",
                 f"log-likelihood (Laplace) {self.loglik:.6f}   AIC {self.aic:.4f}   BIC {self.bic:.4f}   "
                 f"{self.n_params} population parameters",
                 f"converged: {self.converged} ({self.message}), {self.iterations} iterations",
                 f"filter: {self.call['method']}, {self.call['substeps']} sub-step(s) per sampling interval; "
                 + ("standard errors from the Hessian with the members' second derivatives by differences"
                    if self.call.get("hessian") == "differences" else "standard errors from the exact Hessian"),
                 "random effects: " + ", ".join(f"{spec.names[i]} {k}" for i, k in zip(spec.random, spec.kinds))
                 + f"; Ω {'full' if spec.full else 'diagonal'}"]
        if spec.covariates:
            means = ", ".join(f"{c} = {m:.6g}" for c, m in zip(spec.covariates, spec.covariate_mean))
            lines.append(f"typical values at the covariates' mean ({means})")
        table = self.params.copy()
        fmt = {c: (lambda v: f"{v:.6g}") for c in ("estimate", "std_error", "ci_lower", "ci_upper")}
        lines.append(table.to_string(formatters=fmt))
        lines.append("")
        lines.append("shrinkage: " + ", ".join(f"{k} {v:.3f}" for k, v in self.shrinkage.items()))
        for name, why in self.left_out.items():
            lines.append(f"left out: data set '{name}': {why}")
        for direction in self.undetermined:
            lines.append(f"undetermined direction of the population parameters: {direction}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()


class LikelihoodRatio:
    """A likelihood-ratio test between nested population models
    ([`likelihood_ratio()`][greyid.population.result.likelihood_ratio])."""

    def __init__(self, statistic, df, p_value, variances, note):
        self.statistic, self.df, self.p_value, self.variances, self.note = statistic, df, p_value, variances, note

    def __repr__(self) -> str:
        return (f"likelihood ratio {self.statistic:.4f} on {self.df} parameter(s), p = {self.p_value:.4g}"
                + (f"\n{self.note}" if self.note else ""))


def likelihood_ratio(restricted: PopulationResult, general: PopulationResult) -> LikelihoodRatio:
    """Test a population model against a larger one that nests it.

    LR = 2(ℓ_general − ℓ_restricted).  Where the general model adds k variances
    (random effects) that the restricted one holds at 0, a value on the boundary
    of their range, LR is not χ²_df but the mixture Σ_j C(k, j)/2^k χ²_{df−k+j}
    (Self & Liang 1987; for one variance ½χ²_{df−1} + ½χ²_df).

    Parameters
    ----------
    restricted : PopulationResult
        The smaller model's fit.
    general : PopulationResult
        The larger model's fit (more random effects, correlations or covariate
        effects), to the same data sets.

    Returns
    -------
    LikelihoodRatio
        ``statistic``, ``df``, ``p_value``, ``variances`` (the k variances added)
        and ``note`` (which distribution the p-value used).

    Raises
    ------
    ValueError
        Fits of different data sets, or models that are not nested.
    """
    from scipy import stats  # here: scipy.stats costs half a second to import, and a fit needs none
    from scipy.special import comb

    small, large = restricted.spec.phi_names(), general.spec.phi_names()
    extra = [n for n in large if n not in small]
    if [n for n in small if n not in large] or not extra:
        raise ValueError("the general model must hold every population parameter of the restricted one and more "
                         f"(restricted: {small}; general: {large})")
    if restricted.names != general.names or restricted.n_obs != general.n_obs:
        raise ValueError("the two population models were not fitted to the same data sets")
    statistic = max(2.0 * (general.loglik - restricted.loglik), 0.0)
    df = len(extra)
    k = sum(1 for n in extra if n.startswith("omega_"))
    if k == 0:
        return LikelihoodRatio(statistic, df, float(stats.chi2.sf(statistic, df)), 0, "")
    p = 0.0
    for j in range(k + 1):
        degrees = df - k + j
        tail = (1.0 if statistic <= 0 else 0.0) if degrees == 0 else float(stats.chi2.sf(statistic, degrees))
        p += comb(k, j) / 2 ** k * tail
    note = (f"{k} variance(s) tested at 0, on the boundary of their range: p from the mixture "
            f"{' + '.join(f'{comb(k, j) / 2 ** k:g}·χ²_{df - k + j}' for j in range(k + 1))} (Self & Liang 1987)")
    return LikelihoodRatio(statistic, df, p, k, note)


def load_population(path, data=None):
    """Read a population fit written by [`PopulationResult.save()`][greyid.population.result.PopulationResult.save].

    Parameters
    ----------
    path : str or pathlib.Path
        The JSON file.
    data : mapping of str to pandas.DataFrame, optional
        The members' data sets that were not CSV files (``member()`` needs them).

    Returns
    -------
    PopulationResult
        The fit.

    Raises
    ------
    DataError
        A file that is missing, not JSON, not a saved population fit, or damaged.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"population fit file '{path}' not found")
    try:
        saved = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataError(f"'{path}' is not a population fit file ({error})") from None
    if not isinstance(saved, dict) or saved.get("format") != FORMAT:
        raise DataError(f"'{path}' is not a population fit file (written by PopulationResult.save)")
    try:
        model = Model.from_dict(saved["model"])
        s = saved["spec"]
        spec = PopulationSpec(tuple(s["names"]), np.array(s["theta0"], dtype=float), tuple(s["free"]),
                              tuple(bool(v) for v in s["log_scale"]),
                              Transform(np.array(s["kind"], dtype=int), np.array(s["lower"], dtype=float),
                                        np.array(s["upper"], dtype=float)),
                              tuple(s["random"]), tuple(s["kinds"]), tuple(s["covariates"]),
                              tuple(tuple(e) for e in s["effects"]), np.array(s["covariate_mean"], dtype=float),
                              np.array(s["covariate_sd"], dtype=float), bool(s["full"]),
                              np.array(s["omega0"], dtype=float))
        m = saved["members"]
        names = list(m["names"])
        q = len(spec.random)
        members = Members(names, [None] * len(names), None, np.array(m["x"], dtype=float).reshape(len(names), -1),
                          np.array(m["raw"], dtype=float).reshape(len(names), -1),
                          np.array(m["n_obs"], dtype=int), dict(m["left_out"]))
        md = saved["modes"]
        modes = Modes(np.array(md["u"], dtype=float).reshape(len(names), q), np.array(md["value"], dtype=float),
                      np.array(md["hessian"], dtype=float).reshape(len(names), q, q),
                      np.ones(len(names), dtype=bool), np.ones(len(names), dtype=bool))
        result = PopulationResult(model, spec, members, np.array(saved["phi"], dtype=float),
                                  np.array(saved["hessian"], dtype=float), modes, dict(saved["call"]),
                                  saved["converged"], saved["message"], saved["iterations"])
    except (KeyError, TypeError, ValueError) as error:
        raise DataError(f"'{path}' is a damaged population fit file ({type(error).__name__}: {error})") from None
    result.sources = {n: src for n, src in zip(names, m.get("sources", [None] * len(names))) if src}
    if saved.get("covariates") is not None:
        table = saved["covariates"]
        result.covariates = pd.DataFrame(table["data"], index=[str(i) for i in table["index"]],
                                         columns=table["columns"])
    result.frames = {n: None for n in names}
    for name in names:
        if data is not None and name in data:
            result.frames[name] = [data[name]]
    return result
