"""The [`ModelSpec`][greyid.model.model.ModelSpec]: a stochastic state-space model written as equations.

    m = Model("TiTw")
    m.add_system("dTi = (1/(Ci*Riw)*(Tw-Ti) + Aw/Ci*Gv + Qi/Ci)*dt + exp(p11)*dw1")
    m.add_system("dTw = (1/(Cw*Riw)*(Ti-Tw) + 1/(Cw*Rwe)*(Te-Tw))*dt + exp(p22)*dw2")
    m.add_inputs("Te", "Gv", "Qi")
    m.add_observation("yTi = Ti", variance="exp(e11)")
    m.set_initial_state(mean={"Ti": "Ti0", "Tw": 31.0}, covariance="process")

The equations are the model (4.1)–(4.2) of the thesis: dx = f(x,u,t,θ)dt +
G(x,u,t,θ)dω and y_k = h(x_k,u_k,t_k,θ) + e_k with e_k ~ N(0, S).
"""

from __future__ import annotations

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)

from typing import Callable, Mapping, Self, Sequence

import numpy as np
import pandas as pd
import sympy as sp

from ..errors import ModelError
from .equations import (
    is_wiener_name,
    parse_equation,
    parse_expression,
    parse_system_equation,
)
from .distributions import WITH_VARIANCE, Distribution, distribution_of
from .kernels import kernel_of
from .files import model_from_dict, model_to_dict, read_model, write_model
from .options import check_options, rename_columns, resolve
from .parameters import Parameter
from .structure import LTI, LTV, NONLINEAR, Structure

_COVARIANCE_KINDS = ("process", "stationary")


class ModelSpec:
    """The specification of a continuous–discrete stochastic state-space model (4.1)–(4.2).

    Equations, inputs, observations, parameters, the initial state, units, derived
    quantities, options and their model-file form: what a [`Model`][greyid.api.Model] is
    before any filter or estimator runs on it.  Users build a
    [`greyid.Model`][greyid.api.Model], which adds those calls.
    """

    def __init__(self, name: str = "model", description: str = ""):
        self.name = name
        self.description = description
        self._system: list = []
        self._inputs: list[str] = []
        self._observations: list[tuple] = []
        self._distributions: dict[str, Distribution] = {}  # by output; normal where not non-Gaussian
        self._observation_covariance = None  # a full matrix of expressions (set_observation_covariance)
        self._algebraics: list = []
        self._transforms: dict[str, str] = {}  # state → Lamperti transform (transform_state)
        self._latent_forces: dict = {}  # name → kernels.Kernel (add_latent_force)
        self._parameters: dict[str, Parameter] = {}
        self._initial_mean: dict[str, object] | None = None
        self._initial_covariance: object = "process"
        self._initial_scale: float = 1.0
        self._diffuse: tuple[str, ...] = ()  # states started exactly diffuse (set_initial_state)
        self._functions: dict | None = None
        self._structure: Structure | None = None
        self._options: dict = {}
        self._derived: dict[str, str] = {}
        self._units: dict[str, str] = {}
        self.nested_start = None  # rule for starting from a smaller model's fit (set_nested_start)
        self.source = None  # the model file this model was read from, if any
        self.population: dict = {}  # fit_population's defaults (set_population, a model file's [population])

    # ------------------------------------------------------------------ building
    def _changed(self) -> None:
        self._structure = None

    def add_system(self, *equations: str) -> Self:
        """Add state equations.

        Parameters
        ----------
        *equations : str
            One equation per state, ``"d<state> = <drift>*dt + <g1>*dw1 + ..."``: the
            drift f and the diffusion terms G dω (the Wiener processes ``dw1``,
            ``dw2``, ... may be shared between states).

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An equation that cannot be read (names the equation and the problem), a
            state defined twice, or a model defined by Python functions.

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model().add_system("dx = -a*x*dt + s*dw1")
        """
        if self._functions is not None:
            raise ModelError("this model is defined by Python functions; equations cannot be added")
        for text in equations:
            eq = parse_system_equation(text)
            if any(e.state == eq.state for e in self._system):
                raise ModelError(f"state '{eq.state}' is defined twice (again in '{text}')")
            self._system.append(eq)
        self._changed()
        return self

    def add_inputs(self, *names: str) -> Self:
        """Declare the inputs: known external signals u, one data column each.

        Parameters
        ----------
        *names : str
            The inputs' names (the data's column names, or names mapped to them by the
            ``columns`` setting).

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A name that is not an identifier, declared twice, or reserved (``t``,
            ``dt``, ``dw1``, ...).
        """
        for name in names:
            if not isinstance(name, str) or not name.isidentifier():
                raise ModelError(f"input name {name!r} is not a valid name")
            if name in self._inputs:
                raise ModelError(f"input '{name}' is declared twice")
            if name in ("t", "dt") or is_wiener_name(name):
                raise ModelError(f"'{name}' is reserved and cannot be an input")
            self._inputs.append(name)
        self._changed()
        return self

    def add_observation(self, equation: str, variance: str | float | None = None, distribution=None) -> Self:
        """Add an observation ``y = h(x, u, t, θ)``, measured with Gaussian noise or with another
        distribution whose location is the equation's value.

        Parameters
        ----------
        equation : str
            ``"<output> = <expression>"``; the output's name is its data column.
        variance : str or float, optional
            The noise variance S, a number or an expression of the parameters (and of
            the inputs and time), e.g. ``"exp(e11)"`` or ``"sigv^2"``.  Required for the
            normal, Student-t (S = scale²) and log-normal (S of log y) distributions; not
            given for counts.
        distribution : str, dict or Distribution, optional
            ``"normal"`` (the default), ``"poisson"``, ``"lognormal"``, or a table with a
            shape parameter: ``{"family": "student_t", "df": "nu"}``,
            ``{"family": "negative_binomial", "size": "r"}``, ``{"family": "binomial",
            "trials": "n"}`` (see [`distributions`][greyid.model.distributions]).  Only
            ``method="particle"`` fits a distribution other than the normal.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An output defined twice, an equation holding ``dt`` or ``dw`` terms, an unknown
            distribution, a variance missing where the distribution needs one or given where
            it has none.

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model("counts")
        >>> _ = m.add_system("dlogr = -a*(logr - mu)*dt + s*dw1")
        >>> _ = m.add_observation("cases = exp(logr)", distribution="poisson")
        >>> _ = m.set_initial_state(mean={"logr": "mu"})
        >>> m.structure.distributions
        ('poisson',)
        """
        eq = parse_equation(equation, "observation equation")
        if any(o[0].lhs == eq.lhs for o in self._observations):
            raise ModelError(f"observation '{eq.lhs}' is defined twice")
        noise = [s.name for s in eq.rhs.free_symbols if is_wiener_name(s.name) or s.name == "dt"]
        if noise:
            raise ModelError(
                f"observation equation '{equation}' contains '{noise[0]}'; observations cannot hold dt or dw "
                "terms (give the measurement noise as variance=...)"
            )
        law = distribution_of(distribution, f"observation '{eq.lhs}'")
        if law.family in WITH_VARIANCE and variance is None:
            raise ModelError(f"observation '{eq.lhs}' ({law.family}) needs its variance: give variance=...")
        if law.family not in WITH_VARIANCE and variance is not None:
            raise ModelError(f"observation '{eq.lhs}' has the {law.family} distribution, whose variance follows from "
                             f"its mean; leave variance out (got {variance!r})")
        # The variance slot of a count is 1: the Gaussian filters, which alone read it, refuse counts.
        var = self._expression(1.0 if variance is None else variance, f"variance of observation '{eq.lhs}'")
        if law.shape_name is not None:
            self._expression(law.shape, f"{law.shape_name} of observation '{eq.lhs}'")  # checked here
        self._observations.append((eq, var, variance))
        self._distributions[eq.lhs] = law
        self._changed()
        return self

    def add_latent_force(self, name: str, kernel="matern32", **hyperparameters) -> Self:
        """Add an unmeasured input modelled as a Gaussian process written as a linear SDE (a latent force).

        The force's name is then used in the equations like an input (``+ Q/Ci``); its kernel's states are
        appended to the model's, start in their stationary law and are estimated with it (see
        [`kernels`][greyid.model.kernels] for the kernels and their state-space forms).  Filters and smoothers
        give the force's path with its uncertainty (``result.latent_forces``).

        Parameters
        ----------
        name : str
            The force's name, as the equations use it.
        kernel : str, dict or greyid.model.kernels.Kernel
            ``"matern12"``, ``"matern32"``, ``"matern52"``, ``"periodic"`` or ``"quasiperiodic"`` with the
            hyperparameters as keywords; or a table ``{"kernel": "sum" | "product", "parts": [...]}``; or kernel
            objects combined with ``+`` and ``*`` (``Named("matern32", ("s1", "l1")) + ...``).
        **hyperparameters : str or float
            ``scale`` (a standard deviation in the force's unit), ``lengthscale`` and ``period`` (in the time
            unit), ``smoothness`` (the periodic kernel's own, dimensionless lengthscale) and ``order`` (the
            periodic kernels' number of harmonics, default 6): parameter names, expressions or numbers.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An unknown kernel or hyperparameter, a name that is not an identifier or is taken; when the model is
            built: a force used in no equation, or a lengthscale, period or smoothness that may be zero or
            negative (a number ≤ 0, or a parameter without a lower bound above 0).

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model("gp")
        >>> _ = m.add_latent_force("f", kernel="matern32", scale="sf", lengthscale="lf")
        >>> _ = m.add_observation("y = f", variance="r")
        >>> _ = m.set_parameter("lf", init=1.0, lower=0.01, upper=100)
        >>> m.state_names
        ('f', 'f_d1')
        """
        if not isinstance(name, str) or not name.isidentifier() or is_wiener_name(name) or name in ("t", "dt"):
            raise ModelError(f"latent force name {name!r} is not a valid name")
        if name in self._latent_forces or name in self._declared_states() or name in self._inputs:
            raise ModelError(f"latent force '{name}': the name is already a latent force, state or input")
        if isinstance(kernel, str):
            spec = {"kernel": kernel, **hyperparameters}
        else:
            if hyperparameters:
                raise ModelError(f"latent force '{name}': give the hyperparameters in the kernel, not as keywords")
            spec = kernel
        self._latent_forces[name] = kernel_of(spec, f"latent force '{name}'")
        self._changed()
        return self

    def transform_state(self, state: str, transform: str) -> Self:
        """Work with a state in a coordinate where its noise is additive (a Lamperti transform).

        A state with state-dependent noise (``s*x*dw1``, ``s*sqrt(x)*dw1``) is rewritten as z = ψ(x) by Itô's
        formula (see [`transforms`][greyid.model.transforms]): the Gaussian filters linearise it better and the
        Laplace method's transitions are Gaussian in it.  The equations stay as written, in the state's own name;
        filtered, smoothed, predicted and simulated states are reported in the original coordinate (x = φ(z) of
        the transformed mean, the median where z is Gaussian, with the delta method's covariance).

        Parameters
        ----------
        state : str
            The state, with exactly one noise term.
        transform : str
            ``"log"`` (noise ∝ x), ``"logit"`` (∝ x(1−x)), ``"sqrt"`` (∝ √x), ``"arcsine"`` (∝ √(x(1−x))), or
            an expression of the state with one inverse, e.g. ``"log(x - c)"``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A state that does not exist, a transform given twice, a transform that is not a string; when the
            model is built: a state without noise or with several noise terms, or a transform that leaves the
            noise state-dependent (it does not match the diffusion).

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model("gbm").add_system("dx = mu*x*dt + s*x*dw1")
        >>> _ = m.add_observation("y = log(x)", variance="r")
        >>> _ = m.set_initial_state(mean={"x": 1.0}, covariance=[[0.01]])
        >>> _ = m.transform_state("x", "log")
        >>> m.structure.kind   # linear in z = log x
        'lti'
        """
        if self._functions is not None:
            raise ModelError("transform_state() rewrites equations; this model is defined by Python functions")
        if not isinstance(state, str) or not isinstance(transform, str) or not transform.strip():
            raise ModelError(f"transform_state(state, transform) takes two strings, got {state!r} and {transform!r}")
        states = self._declared_states()
        if state not in states:
            raise ModelError(f"transform_state: '{state}' is not a state (states: {states}); add its equation "
                             "first")
        if state in self._transforms:
            raise ModelError(f"state '{state}' is already transformed ({self._transforms[state]!r})")
        self._transforms[state] = transform.strip()
        self._changed()
        return self

    def add_algebraic(self, equation: str) -> Self:
        """Define a name by an expression, usable in every equation.

        Parameters
        ----------
        equation : str
            ``"<name> = <expression>"``, e.g. ``"theta = exp(logtheta)"``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A name defined twice (a cycle of definitions is refused when the model is built).
        """
        eq = parse_equation(equation, "algebraic equation")
        if any(a.lhs == eq.lhs for a in self._algebraics):
            raise ModelError(f"algebraic name '{eq.lhs}' is defined twice")
        self._algebraics.append(eq)
        self._changed()
        return self

    def set_parameter(
        self,
        name: str,
        init: float | None = None,
        lower: float | None = None,
        upper: float | None = None,
        fixed: bool = False,
        prior: tuple[float, float] | None = None,
    ) -> Self:
        """Declare a parameter's initial value and bounds, or fix it.

        Parameters
        ----------
        name : str
            The parameter, as the equations name it.
        init : float, optional
            The starting value of the estimation (the value, where ``fixed``).
        lower, upper : float, optional
            Bounds; the optimiser works in a transformed coordinate that keeps the
            estimate inside them.
        fixed : bool
            Not estimated: held at ``init``.
        prior : tuple of float, optional
            ``(mean, sd)`` of a Gaussian prior, used with ``criterion="map"`` (3.46).

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A name that is not an identifier, bounds that cross, or ``init`` outside them.
        """
        if not isinstance(name, str) or not name.isidentifier():
            raise ModelError(f"parameter name {name!r} is not a valid name")
        self._parameters[name] = Parameter(name, init, lower, upper, fixed, prior)
        self._changed()
        return self

    def fix_parameter(self, name: str, value: float) -> Self:
        """Fix a parameter at a value (it is then not estimated).

        Parameters
        ----------
        name : str
            The parameter.
        value : float
            Its value.

        Returns
        -------
        Model
            The model itself.
        """
        return self.set_parameter(name, init=value, fixed=True)

    def set_options(self, **options) -> Self:
        """Set the model's default settings for data, filter and estimation calls.

        A setting given to [`fit()`][greyid.api.Model.fit],
        [`loglik()`][greyid.api.Model.loglik] and the other calls overrides the
        default set here.  A model file's ``[data]``, ``[filter]`` and ``[estimation]``
        tables set the same names.

        Parameters
        ----------
        **options
            Data: ``time`` (the time column), ``hold`` (``"zoh"``/``"foh"``),
            ``time_unit`` (the unit of elapsed time for timestamps: ``"s"``, ``"min"``,
            ``"h"``, ``"d"``), ``time_format`` (a ``strftime`` format for dates written as
            text), ``time_zone`` (an IANA zone for naive timestamps), ``columns``
            (model name → data column).  Filter: ``method``, ``form`` (``"sqrt"`` or
            ``"plain"``), ``substeps``, ``iterations`` (IEKF), ``alpha``, ``beta``,
            ``kappa`` (UKF), ``steady_state``.  Estimation: ``criterion``, ``robust``,
            ``horizon``, ``starts``, ``seed``, ``maxiter``, ``prior_correlation``,
            ``cov_type``, ``optimizer``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An unknown setting or a value of the wrong kind (names the setting).
        """
        self._options.update(check_options(options))
        return self

    @property
    def options(self) -> dict:
        """The model's default settings (see `set_options()`)."""
        return dict(self._options)

    def set_observation_covariance(self, matrix) -> Self:
        """Declare correlated measurement noise: the full covariance of the outputs.

        Missing outputs are handled element by element (the observed subset is
        decorrelated by its Cholesky factor before the updates).

        Parameters
        ----------
        matrix : sequence of sequences or numpy.ndarray
            Square, in the outputs' order, numbers or expressions of the parameters;
            its diagonal must repeat the outputs' variances, and it must be symmetric
            and free of the states.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A matrix that is not square or not of the outputs' size.
        """
        if isinstance(matrix, np.ndarray):
            matrix = matrix.tolist()
        if not (isinstance(matrix, (list, tuple)) and matrix and all(isinstance(r, (list, tuple)) for r in matrix)):
            raise ModelError("the observation covariance must be a square matrix (a list of rows)")
        outputs = [o[0].lhs for o in self._observations]
        if outputs and (len(matrix) != len(outputs) or any(len(r) != len(outputs) for r in matrix)):
            raise ModelError(f"the observation covariance must be {len(outputs)}x{len(outputs)} "
                             f"(outputs {outputs}), got {len(matrix)} rows of lengths {[len(r) for r in matrix]}")
        self._observation_covariance = [list(r) for r in matrix]
        self._changed()
        return self

    def set_nested_start(self, rule) -> Self:
        """Declare where this model reduces to a smaller one it extends.

        Used by ``fit(..., init_from=smaller_fit)`` and by forward selection
        ([`select_forward()`][greyid.validation.selection.select_forward]).

        Parameters
        ----------
        rule : callable
            ``rule(values) -> {parameter: initial value}``: given the smaller model's
            estimates by name, the starting values of the parameters this model adds
            (and of any it changes), e.g. a sensor state's
            ``{"Ris": 0.01, "Cs": 0.001, "Ts0": values["Ti0"]}``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            ``rule`` is not callable.
        """
        if not callable(rule):
            raise ModelError("set_nested_start takes a function of the smaller model's estimates")
        self.nested_start = rule
        return self

    def add_derived(self, name: str, expression: str) -> Self:
        """Name a physical quantity computed from the parameters.

        ``fit.derived()`` reports it with a delta-method standard error (6.35).

        Parameters
        ----------
        name : str
            The quantity's name, e.g. ``"UA [kW/K]"``.
        expression : str
            Its expression in the parameters, e.g. ``"1/(Ri + Ro)"``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An empty name or an expression that cannot be read.
        """
        if not isinstance(name, str) or not name.strip():
            raise ModelError(f"derived quantity name {name!r} must be a non-empty string")
        parse_expression(expression, f"derived quantity '{name}'")
        self._derived[name] = expression
        return self

    def set_population(self, random=None, effects=None, omega=None, covariates=None, omega_init=None) -> Self:
        """Set the defaults of [`fit_population()`][greyid.population.fit.fit_population] for this model.

        A model file's ``[population]`` table sets the same names.

        Parameters
        ----------
        random : dict, optional
            ``{parameter: "normal" | "lognormal"}``: the parameters with a random effect.
        effects : dict, optional
            ``{parameter: [covariate, ...]}``: covariate effects on the parameters' means.
        omega : {"diagonal", "full"}, optional
            Independent or correlated random effects.
        covariates : str, optional
            A CSV file with a row per data set (first column: the data sets' names),
            relative to the model file.
        omega_init : dict, optional
            ``{parameter: sd}``: starting standard deviations of the random effects.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A value of the wrong kind (names the key).
        """
        from ..errors import ModelError

        given = dict(random=random, effects=effects, omega=omega, covariates=covariates, omega_init=omega_init)
        checks = dict(random=Mapping, effects=Mapping, omega=str, covariates=str, omega_init=Mapping)
        for key, value in given.items():
            if value is not None and not isinstance(value, checks[key]):
                kind = "a table" if checks[key] is Mapping else "a string"
                raise ModelError(f"[population] {key} must be {kind}, got {value!r}")
        self.population.update({k: (dict(v) if isinstance(v, Mapping) else v) for k, v in given.items()
                                if v is not None})
        return self

    def set_units(self, units: Mapping[str, str]) -> Self:
        """Give the units of the model's names, the time column's included, as Pint reads them.

        Every equation is then checked for dimensional consistency before a fit
        ([`check_units()`][greyid.api.Model.check_units]); names without a unit
        count as dimensionless.

        Parameters
        ----------
        units : mapping of str to str
            E.g. ``{"t": "h", "Ti": "degC", "Ci": "kWh/K", "s1": "K/h^0.5"}``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A unit Pint does not know.
        """
        from .units import parse_units

        parse_units(units)  # an unknown unit is an error now, not at the fit
        self._units.update(units)
        return self

    @property
    def units(self) -> dict[str, str]:
        """The units given with `set_units()` (a copy)."""
        return dict(self._units)

    def unit_report(self, time: str | None = None) -> pd.DataFrame:
        """Every term of every equation with its unit, the expected unit and whether they agree.

        Parameters
        ----------
        time : str, optional
            The time column's name (default: the model's ``time`` setting, else ``"t"``).

        Returns
        -------
        pandas.DataFrame
            Columns ``equation``, ``term``, ``unit``, ``expected``, ``ok``, ``note``.
        """
        from .units import check_model_units

        terms = check_model_units(self, self._units, time or self._options.get("time", "t"))
        return pd.DataFrame([dict(equation=t.equation, term=t.term, unit=t.unit, expected=t.expected, ok=t.ok,
                                  note=t.note.lstrip(" :")) for t in terms])

    def check_units(self, time: str | None = None) -> list[str]:
        """Check the equations' dimensions.

        Parameters
        ----------
        time : str, optional
            The time column's name (default: the model's ``time`` setting, else ``"t"``).

        Returns
        -------
        list of str
            The report's lines, one per term.

        Raises
        ------
        ModelError
            Names every term whose unit is not the expected one.
        """
        from .units import check_model_units

        terms = check_model_units(self, self._units, time or self._options.get("time", "t"))
        bad = [t.line() for t in terms if not t.ok]
        if bad:
            raise ModelError(f"the equations of model '{self.name}' are not dimensionally consistent:\n  "
                             + "\n  ".join(bad))
        return [t.line() for t in terms]

    @property
    def derived(self) -> dict[str, str]:
        """Derived physical quantities by name (expressions in the parameters)."""
        return dict(self._derived)

    def prior(self) -> dict | None:
        """The Gaussian prior declared on the free parameters (3.46).

        Returns
        -------
        dict or None
            ``{"mean": {...}, "sd": {...}}`` (and ``"corr"`` where the
            ``prior_correlation`` setting gives one), or None where no parameter has a prior.
        """
        with_prior = {n: p.prior for n, p in self._parameters.items() if p.prior is not None and not p.fixed}
        if not with_prior:
            return None
        spec = {"mean": {n: v[0] for n, v in with_prior.items()}, "sd": {n: v[1] for n, v in with_prior.items()}}
        corr = self._options.get("prior_correlation")
        if corr:
            spec["corr"] = dict(corr)
        return spec

    def set_initial_state(
        self,
        mean: Mapping[str, float | str],
        covariance: str | Sequence | np.ndarray = "process",
        scale: float = 1.0,
        diffuse: Sequence[str] = (),
    ) -> Self:
        """Set the initial state, x(t0) ~ N(mean, covariance), some states possibly diffuse.

        Parameters
        ----------
        mean : mapping of str to float or str
            Every state's mean: a number, or a parameter name or expression (then estimated).
            A diffuse state's mean may be left out (it does not change any result).
        covariance : {"process", "stationary"} or array_like
            A matrix (numbers or expressions), a vector of variances, ``"process"``
            (the process noise integrated over the first sampling interval, times
            ``scale``, as in CTSM) or ``"stationary"`` (the stationary covariance of a
            stable linear model; with diffuse states, of the other states' own block).
            A matrix gives the diffuse states' rows and columns as zeros.
        scale : float
            The factor of the ``"process"`` covariance.
        diffuse : sequence of str
            States whose initial value is unknown, x0 = a + δ with δ ~ N(0, κ I), κ → ∞: the
            exact diffuse initialisation of Koopman and Durbin, for linear models, by the Kalman
            filter ([`diffuse`][greyid.filters.diffuse]) and the Laplace method (a flat prior).
            Their observations' log-likelihood terms are −½(log 2π + log F∞), statsmodels'
            convention.  Simulation starts a diffuse state at its mean.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A name that is not a state, a covariance of the wrong shape or not a
            covariance (negative variance, not symmetric, not positive semi-definite), a
            diffuse state given a variance or an estimated mean.

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model().add_system("dx = 0*dt + sig*dw").add_observation("y = x", variance="s2")
        >>> m = m.set_initial_state(mean={}, covariance="process", diffuse=["x"])
        """
        if not isinstance(mean, Mapping):
            raise ModelError("initial state mean must be a mapping from state name to value")
        if isinstance(covariance, str) and covariance not in _COVARIANCE_KINDS:
            raise ModelError(
                f"unknown initial covariance '{covariance}'; use a matrix, 'process' or 'stationary'"
            )
        if not isinstance(scale, (int, float)) or not scale > 0:
            raise ModelError(f"initial covariance scale must be a positive number, got {scale!r}")
        states = self._declared_states()
        forced = [k for k in mean if k in self._latent_forces]
        if forced:
            raise ModelError(f"'{forced[0]}' is a latent force: it starts in its kernel's stationary distribution; "
                             "give the initial state of the model's own states only")
        if states:  # the states are known: a wrong name or shape is an error here, not at the first fit
            unknown = [k for k in mean if k not in states]
            if unknown:
                raise ModelError(f"initial state given for '{unknown[0]}', which is not a state (states: {states})")
            if not isinstance(covariance, str):
                shape = np.shape(np.asarray(covariance, dtype=object)) if _rectangular(covariance) else None
                n = len(states)
                if shape not in ((n,), (n, n)):
                    raise ModelError(f"initial covariance has shape {shape if shape else 'ragged'}, but the model "
                                     f"has {n} states {states}: it must be {n}x{n} (or a vector of {n} variances)")
        if not isinstance(covariance, str):
            check_constant_covariance(covariance)
        diffuse = self._checked_diffuse(diffuse, mean, covariance, states)
        self._initial_mean = dict(mean)
        self._diffuse = diffuse
        self._initial_covariance = covariance
        self._initial_scale = float(scale)
        self._changed()
        return self

    def _checked_diffuse(self, diffuse, mean, covariance, states) -> tuple[str, ...]:
        """The diffuse states, checked: states, once each, with neither a variance nor an estimated mean."""
        if isinstance(diffuse, str) or not all(isinstance(d, str) for d in diffuse):
            raise ModelError(f"diffuse must be a list of state names, got {diffuse!r}")
        diffuse = tuple(diffuse)
        for name in diffuse:
            if diffuse.count(name) > 1:
                raise ModelError(f"diffuse state '{name}' is named twice")
            if name in self._latent_forces:
                raise ModelError(f"'{name}' is a latent force: it starts in its kernel's stationary distribution "
                                 "and cannot be diffuse")
            if states and name not in states:
                raise ModelError(f"diffuse state '{name}' is not a state (states: {states})")
            value = mean.get(name, 0.0)
            if not isinstance(value, (int, float, np.integer, np.floating)) or isinstance(value, bool):
                raise ModelError(f"diffuse state '{name}' has the mean {value!r}: a diffuse state's mean does not "
                                 "change the likelihood, so it cannot be estimated; give a number or leave it out")
        if diffuse and not isinstance(covariance, str) and states:
            arr = np.asarray(covariance, dtype=object)
            for name in diffuse:
                i = states.index(name)
                entries = [arr[i]] if arr.ndim == 1 else [*arr[i], *arr[:, i]]
                given = [e for e in entries if not (isinstance(e, (int, float, np.integer, np.floating))
                                                    and float(e) == 0.0)]
                if given:
                    raise ModelError(f"state '{name}' is diffuse but the initial covariance gives it "
                                     f"{given[0]!r}: its rows and columns must be zero (its variance is infinite)")
        return diffuse

    def _declared_states(self) -> list[str]:
        if self._functions is not None:
            return list(self._functions["states"])
        return [e.state for e in self._system]

    @classmethod
    def from_functions(
        cls,
        states: Sequence[str],
        outputs: Sequence[str],
        drift: Callable,
        diffusion: Callable,
        observation: Callable,
        observation_variance: Callable,
        parameters: Sequence[str],
        inputs: Sequence[str] = (),
        kind: str = NONLINEAR,
        name: str = "model",
    ) -> Self:
        """A model from JAX-traceable Python functions of ``(x, u, t, p)``.

        Parameters
        ----------
        states, outputs : sequence of str
            The states' and outputs' names.
        drift : callable
            ``f(x, u, t, p)`` of shape (n,); ``p`` maps parameter names to scalars.
        diffusion : callable
            ``G(x, u, t, p)`` of shape (n, m).
        observation : callable
            ``h(x, u, t, p)`` of shape (s,).
        observation_variance : callable
            The outputs' noise variances, shape (s,).
        parameters : sequence of str
            The parameters' names.
        inputs : sequence of str
            The inputs' names.
        kind : {"lti", "ltv", "nonlinear"}
            The model's class, which opaque functions cannot reveal: it chooses the
            default filter (exact for linear models).
        name : str
            The model's name.

        Returns
        -------
        Model
            A model whose programs are never kept on disk (functions have no stable key).

        Raises
        ------
        ModelError
            An unknown ``kind``.
        """
        if kind not in (LTI, LTV, NONLINEAR):
            raise ModelError(f"unknown model kind '{kind}'; use 'lti', 'ltv' or 'nonlinear'")
        model = cls(name)
        model._functions = dict(
            states=tuple(states), outputs=tuple(outputs), inputs=tuple(inputs), parameters=tuple(parameters),
            drift=drift, diffusion=diffusion, observation=observation,
            observation_variance=observation_variance, kind=kind,
        )
        model._inputs = list(inputs)
        return model

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _expression(value, where: str) -> sp.Expr:
        if isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool):
            if not np.isfinite(value):
                raise ModelError(f"{where} must be finite, got {value}")
            return sp.Float(float(value))
        if isinstance(value, str):
            return parse_expression(value, where)
        raise ModelError(f"{where} must be a number or an expression, got {value!r}")

    @property
    def parameters(self) -> dict[str, Parameter]:
        """Declared parameters (bounds, initial and fixed values), by name."""
        return dict(self._parameters)

    @property
    def structure(self) -> Structure:
        """The compiled structure (built on first use, then reused)."""
        if self._structure is None:
            self._structure = self._build()
        return self._structure

    @property
    def state_names(self) -> tuple[str, ...]:
        """The states' names, in the order of the state vector."""
        return self.structure.state_names

    @property
    def input_names(self) -> tuple[str, ...]:
        """The inputs' names, in the order of the input vector."""
        return self.structure.input_names

    @property
    def output_names(self) -> tuple[str, ...]:
        """The outputs' names (their data columns), in the order of the observation vector."""
        return self.structure.output_names

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """The parameters' names, in the order of θ (fixed ones included)."""
        return self.structure.parameter_names

    @property
    def kind(self) -> str:
        """``"lti"``, ``"ltv"`` or ``"nonlinear"``: which filter is exact."""
        return self.structure.kind

    def __repr__(self) -> str:
        try:
            s = self.structure
            return (
                f"Model({self.name!r}, kind={s.kind!r}, states={list(s.state_names)}, "
                f"inputs={list(s.input_names)}, outputs={list(s.output_names)}, "
                f"parameters={list(s.parameter_names)})"
            )
        except ModelError as err:
            return f"Model({self.name!r}, incomplete: {err})"

    # ------------------------------------------------------------------ compile
    def _substitute_algebraics(self, expr: sp.Expr) -> sp.Expr:
        defs = {sp.Symbol(a.lhs, real=True): a.rhs for a in self._algebraics}
        for _ in range(len(defs) + 1):
            new = expr.xreplace(defs)
            if new == expr:
                return new
            expr = new
        raise ModelError("algebraic equations refer to each other in a cycle: "
                         + ", ".join(a.text for a in self._algebraics))

    def _build(self) -> Structure:
        if self._functions is not None:
            from .functions import build_from_functions

            return build_from_functions(self)
        from .build import build_structure

        return build_structure(self)

    # ------------------------------------------------------------------ parameters
    def parameter_vector(self, params: Mapping[str, float] | None = None) -> np.ndarray:
        """The parameter vector θ in [`parameter_names`][greyid.api.Model.parameter_names] order.

        Parameters
        ----------
        params : mapping of str to float, optional
            Values by name; parameters not named take their fixed value.

        Returns
        -------
        numpy.ndarray
            θ, float64.

        Raises
        ------
        ModelError
            A name that is not a parameter, a parameter with no value, or a value that
            is not a finite number.
        """
        names = self.parameter_names
        params = {} if params is None else dict(params)
        unknown = [k for k in params if k not in names]
        if unknown:
            raise ModelError(f"'{unknown[0]}' is not a parameter of the model (parameters: {list(names)})")
        values = []
        for name in names:
            if name in params:
                value = params[name]
            elif name in self._parameters and self._parameters[name].fixed:
                value = self._parameters[name].init
            else:
                raise ModelError(f"parameter '{name}' is used in the model but given no value")
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ModelError(f"parameter '{name}' must be a number, got {value!r}") from None
            if not np.isfinite(value):
                raise ModelError(f"parameter '{name}' must be finite, got {value}")
            values.append(value)
        return np.asarray(values, dtype=np.float64)

    def initial_values(self) -> dict[str, float]:
        """The declared initial (or fixed) value of every parameter that has one.

        Returns
        -------
        dict
            ``{parameter: value}``.
        """
        return {n: p.init for n, p in self._parameters.items() if p.init is not None}

    # ------------------------------------------------------------------ saving
    def to_dict(self) -> dict:
        """Everything needed to rebuild this model, equations as text.

        Returns
        -------
        dict
            What [`from_dict()`][greyid.api.Model.from_dict] reads (and a saved fit keeps).
        """
        return model_to_dict(self)

    @classmethod
    def from_dict(cls, spec: Mapping) -> Self:
        """Rebuild a model written by [`to_dict()`][greyid.api.Model.to_dict].

        Parameters
        ----------
        spec : mapping
            The dictionary.

        Returns
        -------
        Model
            The model.

        Raises
        ------
        ModelError
            A dictionary that does not describe a model (names the key).
        """
        return model_from_dict(spec, cls)

    @classmethod
    def from_toml(cls, source) -> Self:
        """Read a model file.

        Parameters
        ----------
        source : str or pathlib.Path
            The file's path, or the TOML text itself.

        Returns
        -------
        Model
            The model, with its settings, units, derived quantities and data source
            (``model.source`` is the file's path).

        Raises
        ------
        ModelError
            A file that cannot be read as a model: names the file, section, key or equation.

        Examples
        --------
        >>> import greyid
        >>> m = greyid.Model.from_toml("examples/armadillo.toml")  # doctest: +SKIP
        """
        return read_model(source, cls)

    def to_toml(self, path=None) -> str:
        """The model as a TOML model file.

        Parameters
        ----------
        path : str or pathlib.Path, optional
            Where to write it (atomically); without it, nothing is written.

        Returns
        -------
        str
            The file's text.
        """
        return write_model(self, path)

    # ------------------------------------------------------------------ public calls
    def call_settings(self, data, given: dict, keys):
        """The data renamed to the model's names and a call's settings.

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame
            The data as given (columns named as in the file; text times allowed).
        given : dict
            The call's settings; None where not given.
        keys : sequence of str
            The names of the settings the call takes.

        Returns
        -------
        tuple
            The data (columns renamed by ``[data.columns]``, times read) and the settings: those
            given, else the model's (from its file or [`set_options()`][greyid.api.Model.set_options]).
        """
        settings = resolve(self._options, given, keys)
        columns = settings.pop("columns", None)
        data = rename_columns(data, columns)
        # How text in the time column is read: used here, where the data meet the model, not by the filter.
        time_format, time_zone = settings.pop("time_format", None), settings.pop("time_zone", None)
        return _read_times(data, settings.get("time", "t"), time_format, time_zone), settings


def check_constant_covariance(covariance) -> None:
    """An initial covariance of numbers must be one: variances ≥ 0, symmetric, positive semi-definite
    (a matrix with expressions is checked where its parameters have values)."""
    try:
        M = np.asarray(covariance, dtype=np.float64)
    except (TypeError, ValueError):
        return  # expressions of parameters
    if M.ndim == 1:
        negative = np.flatnonzero(~(M >= 0))
        if len(negative):
            raise ModelError(f"initial variance {negative[0] + 1} is {float(M[negative[0]]):g}; a variance must be ≥ 0")
        return
    if M.ndim != 2 or M.shape[0] != M.shape[1] or not np.all(np.isfinite(M)):
        raise ModelError(f"initial covariance must be a square matrix of finite numbers, got {covariance!r}")
    scale = max(float(np.abs(M).max()), 1e-300)
    bad = np.flatnonzero(np.diag(M) < 0)
    if len(bad):
        raise ModelError(f"initial covariance has the negative variance {float(M[bad[0], bad[0]]):g} on its diagonal "
                         f"(element {bad[0] + 1}); a variance must be ≥ 0")
    i, j = np.unravel_index(np.argmax(np.abs(M - M.T)), M.shape)
    if abs(M[i, j] - M[j, i]) > 1e-12 * scale:
        raise ModelError(f"initial covariance is not symmetric: element ({i + 1}, {j + 1}) is {float(M[i, j]):g} but "
                         f"({j + 1}, {i + 1}) is {float(M[j, i]):g}")
    lowest = float(np.linalg.eigvalsh(M).min())
    if lowest < -1e-12 * scale:
        raise ModelError(f"initial covariance is not positive semi-definite (an eigenvalue is {lowest:.4g}): no "
                         "distribution has it; its correlations must lie in [-1, 1]")


def _rectangular(value) -> bool:
    """A vector, or a list of rows of equal length (NumPy would make a ragged one an array of lists)."""
    if isinstance(value, np.ndarray):
        return True
    if not isinstance(value, (list, tuple)):
        return False
    rows = [r for r in value if isinstance(r, (list, tuple, np.ndarray))]
    return not rows or (len(rows) == len(value) and len({len(r) for r in rows}) == 1)


def _read_times(data, time: str, time_format, time_zone):
    """Text in the time column of ``data`` (a frame or a list of frames) read as timestamps."""
    import pandas as pd

    from ..data.timestamps import parse_timestamps

    if isinstance(data, (list, tuple)):
        return [_read_times(d, time, time_format, time_zone) for d in data]
    if not isinstance(data, pd.DataFrame):
        return data
    return parse_timestamps(data, time, time_format, time_zone)
