"""The [`Model`][greyid.model.model.Model]: a stochastic state-space model written as equations.

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

from .. import _jax  # noqa: F401  (64-bit JAX before any JAX work)

from typing import Callable, Mapping, Sequence

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
from .files import model_from_dict, model_to_dict, read_model, write_model
from .options import DATA_KEYS, ESTIMATION_KEYS, FILTER_KEYS, check_options, rename_columns, resolve
from .parameters import Parameter
from .structure import LTI, LTV, NONLINEAR, Structure

_COVARIANCE_KINDS = ("process", "stationary")


class Model:
    """A continuous–discrete stochastic state-space model written as equations (4.1)–(4.2).

    ``dx = f(x, u, t, θ) dt + G(x, u, t, θ) dω`` with discrete observations
    ``y_k = h(x_k, u_k, t_k, θ) + e_k``, ``e_k ~ N(0, S)``.  Build it with the
    ``add_*`` and ``set_*`` methods (each returns the model, so calls chain), read
    it from a model file ([`from_toml()`][greyid.model.model.Model.from_toml]) or
    write it as Python functions ([`from_functions()`][greyid.model.model.Model.from_functions]).

    Parameters
    ----------
    name : str
        The model's name, shown in summaries and reports.
    description : str
        A sentence on what the model is (units, what the states stand for).

    Examples
    --------
    >>> import greyid
    >>> m = greyid.Model("TiTe")
    >>> m = (m.add_inputs("Ta", "Ph")
    ...       .add_system("dTi = (1/(Ci*Rie)*(Te - Ti) + Ph/Ci)*dt + exp(p1)*dw1",
    ...                   "dTe = (1/(Ce*Rie)*(Ti - Te) + 1/(Ce*Rea)*(Ta - Te))*dt + exp(p2)*dw2")
    ...       .add_observation("yTi = Ti", variance="exp(e1)")
    ...       .set_initial_state({"Ti": "Ti0", "Te": "Te0"}))
    >>> m.state_names
    ('Ti', 'Te')
    """

    def __init__(self, name: str = "model", description: str = ""):
        self.name = name
        self.description = description
        self._system: list = []
        self._inputs: list[str] = []
        self._observations: list[tuple] = []
        self._observation_covariance = None  # a full matrix of expressions (set_observation_covariance)
        self._algebraics: list = []
        self._parameters: dict[str, Parameter] = {}
        self._initial_mean: dict[str, object] | None = None
        self._initial_covariance: object = "process"
        self._initial_scale: float = 1.0
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

    def add_system(self, *equations: str) -> "Model":
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

    def add_inputs(self, *names: str) -> "Model":
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

    def add_observation(self, equation: str, variance: str | float) -> "Model":
        """Add an observation ``y = h(x, u, t, θ)`` measured with Gaussian noise.

        Parameters
        ----------
        equation : str
            ``"<output> = <expression>"``; the output's name is its data column.
        variance : str or float
            The noise variance S, a number or an expression of the parameters (and of
            the inputs and time), e.g. ``"exp(e11)"`` or ``"sigv^2"``.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            An output defined twice, or an equation holding ``dt`` or ``dw`` terms.
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
        var = self._expression(variance, f"variance of observation '{eq.lhs}'")
        self._observations.append((eq, var, variance))
        self._changed()
        return self

    def add_algebraic(self, equation: str) -> "Model":
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
    ) -> "Model":
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

    def fix_parameter(self, name: str, value: float) -> "Model":
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

    def set_options(self, **options) -> "Model":
        """Set the model's default settings for data, filter and estimation calls.

        A setting given to [`fit()`][greyid.model.model.Model.fit],
        [`loglik()`][greyid.model.model.Model.loglik] and the other calls overrides the
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

    def set_observation_covariance(self, matrix) -> "Model":
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

    def set_nested_start(self, rule) -> "Model":
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

    def add_derived(self, name: str, expression: str) -> "Model":
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

    def set_population(self, random=None, effects=None, omega=None, covariates=None, omega_init=None) -> "Model":
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

    def set_units(self, units: Mapping[str, str]) -> "Model":
        """Give the units of the model's names, the time column's included, as Pint reads them.

        Every equation is then checked for dimensional consistency before a fit
        ([`check_units()`][greyid.model.model.Model.check_units]); names without a unit
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
    ) -> "Model":
        """Set the initial state, x(t0) ~ N(mean, covariance).

        Parameters
        ----------
        mean : mapping of str to float or str
            Every state's mean: a number, or a parameter name or expression (then estimated).
        covariance : {"process", "stationary"} or array_like
            A matrix (numbers or expressions), a vector of variances, ``"process"``
            (the process noise integrated over the first sampling interval, times
            ``scale``, as in CTSM) or ``"stationary"`` (the stationary covariance of a
            stable linear model).
        scale : float
            The factor of the ``"process"`` covariance.

        Returns
        -------
        Model
            The model itself.

        Raises
        ------
        ModelError
            A name that is not a state, a covariance of the wrong shape or not a
            covariance (negative variance, not symmetric, not positive semi-definite).
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
        self._initial_mean = dict(mean)
        self._initial_covariance = covariance
        self._initial_scale = float(scale)
        self._changed()
        return self

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
    ) -> "Model":
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
        """The parameter vector θ in [`parameter_names`][greyid.model.model.Model.parameter_names] order.

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
            What [`from_dict()`][greyid.model.model.Model.from_dict] reads (and a saved fit keeps).
        """
        return model_to_dict(self)

    @classmethod
    def from_dict(cls, spec: Mapping) -> "Model":
        """Rebuild a model written by [`to_dict()`][greyid.model.model.Model.to_dict].

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
    def from_toml(cls, source) -> "Model":
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
    def _call_settings(self, data, given: dict, keys):
        """The data renamed to model names and this call's settings (given, else the model's)."""
        settings = resolve(self._options, given, keys)
        columns = settings.pop("columns", None)
        data = rename_columns(data, columns)
        # How text in the time column is read: used here, where the data meet the model, not by the filter.
        time_format, time_zone = settings.pop("time_format", None), settings.pop("time_zone", None)
        return _read_times(data, settings.get("time", "t"), time_format, time_zone), settings

    def fit(self, data, time: str | None = None, hold: str | None = None, method: str | None = None,
            criterion: str | None = None, prior=None, robust=None, horizon: int | None = None,
            starts: int | None = None, seed: int | None = None, init=None, init_from=None, progress=False,
            **options):
        """Estimate the free parameters by maximum likelihood or MAP (chapter 3).

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame
            The time column, one column per input and per output (NaN: not observed);
            a list of frames is independent experiments whose log-likelihoods add.
        time : str, optional
            The name of the time column (default ``"t"``).
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples: zero-order hold (the default) or
            first-order hold (linear interpolation, eq. 4.37).
        method : str, optional
            The filter: ``"kalman"``, ``"ekf"``, ``"iekf"``, ``"ekf2"``, ``"ukf"``, ``"gaussian2"``
            or ``"truncated2"`` (default: the exact Kalman filter for linear models, the EKF otherwise).
        criterion : {"ml", "map"}, optional
            Maximum likelihood (default) or maximum a posteriori with ``prior``.
        prior : dict, optional
            ``{"mean": {...}, "sd": {...}, "corr": {...}}`` by parameter name (3.46);
            with ``criterion="map"`` and no ``prior``, the priors declared with
            ``set_parameter(..., prior=(mean, sd))``.
        robust : tuple, optional
            ``("huber", c)`` or ``("tukey", c)``: a robust criterion (3.57–3.58).
        horizon : int, optional
            Greater than 1: k-step prediction errors (section 7.2).
        starts : int, optional
            Starting points: the initial values, then points of a space-filling design
            inside the bounds (where the ``"auto"`` optimizer takes scoring steps, the
            first of them repeats the initial values with Newton steps only).  They run
            side by side; the best optimum is the fit.
        seed : int, optional
            Seed of the space-filling starts (non-negative).
        init : mapping of str to float, optional
            Starting values by name, in place of the declared initial values.
        init_from : FitResult, optional
            The fit of a smaller model this one extends: adds a start at its estimates,
            with the new parameters where this model reduces to it
            ([`set_nested_start()`][greyid.model.model.Model.set_nested_start]).
        progress : bool or callable
            True prints the optimiser's iterations; a callable receives one dict per iteration.
        **options
            Other settings by name (as [`set_options()`][greyid.model.model.Model.set_options]):
            ``cov_type`` (``"hessian"``, the default for ML and MAP; ``"sandwich"``
            H⁻¹JH⁻¹, the default for k-step and robust criteria; ``"opg"``),
            ``optimizer`` (``"auto"``: Fisher scoring far from the optimum where a
            Hessian is costly, then exact Newton steps; ``"scoring"``; ``"newton"``;
            ``"quasi-newton"``: L-BFGS steps on the value and exact gradient, then
            Newton steps, the same optimum, faster compiled fits of small models, one
            program more to compile), ``steady_state`` (True: a regular series of 128
            rows or more of a linear time-invariant model is filtered in the filter's
            steady state once it has settled; later fits take about half the time, the
            first one compiles 2–3 times as long), ``maxiter``, ``time_unit``,
            ``time_format``, ``time_zone``, ``columns`` and the filter's ``form``,
            ``substeps``, ``iterations``, ``alpha``, ``beta``, ``kappa``.

        Returns
        -------
        FitResult
            Estimates, standard errors, the log-likelihood, convergence and warnings.
            ``converged`` is True only at a minimum where every free parameter is
            determined by the data.

        Raises
        ------
        DataError
            Data that do not fit the model (names the column and row).
        ModelError
            Bad settings, or a criterion not finite at the start (names the equation
            and row where it can tell).

        See Also
        --------
        greyid.estimate.results.FitResult : what a fit holds and what it can do next.
        greyid.model.model.Model.likelihood : the criterion as a function, for other optimisers and samplers.

        Examples
        --------
        >>> import greyid
        >>> from greyid.datasets import building_model, load_building_data
        >>> fit = building_model().fit(load_building_data().iloc[:300])
        >>> fit.converged
        True
        >>> print(fit.summary())  # doctest: +SKIP
        """
        from ..estimate.estimation import fit

        given = dict(time=time, hold=hold, method=method, criterion=criterion, robust=robust, horizon=horizon,
                     starts=starts, seed=seed, **options)
        data, settings = self._call_settings(data, given, DATA_KEYS + FILTER_KEYS + ESTIMATION_KEYS)
        settings.pop("prior_correlation", None)
        if self._units:
            self.check_units(time=settings.get("time"))
        if prior is None and settings.get("criterion") == "map":
            prior = self.prior()
        return fit(self, data, prior=prior, init=init, init_from=init_from, progress=progress, **settings)

    def likelihood(self, data, time: str | None = None, hold: str | None = None, method: str | None = None,
                   criterion: str | None = None, prior=None, robust=None, horizon: int | None = None, **options):
        """The negative log-likelihood as a function of the free parameters.

        Or the criterion ``fit`` would minimise: MAP, robust, k-step.  Its single
        evaluations of a regular series of a linear model switch to the filter's
        steady state where it has settled.

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame
            As for [`fit()`][greyid.model.model.Model.fit].
        time : str, optional
            The name of the time column.
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples.
        method : str, optional
            The filter.
        criterion : {"ml", "map"}, optional
            With ``"map"``, the negative log-posterior.
        prior : dict, optional
            The prior of ``criterion="map"`` (else the declared priors).
        robust : tuple, optional
            ``("huber", c)`` or ``("tukey", c)``.
        horizon : int, optional
            k-step prediction errors.
        **options
            Other settings; ``steady_state=False`` steps through every row.

        Returns
        -------
        Likelihood
            ``.names``, ``.value(x)``, ``.value_and_grad(x)``, ``.hessian(x)`` (``x`` in
            the parameters' own units, one vector or one row per vector;
            ``unconstrained=True`` for the optimiser's z) and ``.function()``, the pure
            JAX function for ``jax.grad``, ``vmap``, samplers and optimisers.

        Examples
        --------
        >>> from greyid.datasets import building_model, load_building_data
        >>> model = building_model()
        >>> L = model.likelihood(load_building_data().iloc[:100])
        >>> x = [model.initial_values()[n] for n in L.names]
        >>> value, gradient = L.value_and_grad(x)
        """
        from ..estimate.likelihood import Likelihood

        given = dict(time=time, hold=hold, method=method, criterion=criterion, robust=robust, horizon=horizon,
                     **options)
        data, settings = self._call_settings(data, given, DATA_KEYS + FILTER_KEYS + ESTIMATION_KEYS)
        for key in ("prior_correlation", "starts", "seed", "maxiter", "cov_type", "optimizer"):
            settings.pop(key, None)
        if prior is None and settings.get("criterion") == "map":
            prior = self.prior()
        return Likelihood(self, data, prior=prior, **settings)

    def predict(self, params, data, steps: int = 1, time: str | None = None, hold: str | None = None,
                method: str | None = None, states: bool = False, **options):
        """Output predictions ``steps`` samples ahead, with standard deviations.

        Parameters
        ----------
        params : mapping of str to float
            The parameters' values by name.
        data : pandas.DataFrame
            Times, inputs and (where known) outputs.  Rows with missing outputs are
            predicted too: append future inputs to forecast past the data.
        steps : int
            The prediction horizon in samples.
        time : str, optional
            The name of the time column.
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples.
        method : str, optional
            The filter.
        states : bool
            Also the states' predictions.
        **options
            Other data and filter settings.

        Returns
        -------
        pandas.DataFrame
            The time column, each output and ``<output>_sd`` and, with
            ``states=True``, each state and ``<state>_sd``.
        """
        from ..filters.api import predict_data

        data, settings = self._call_settings(data, dict(time=time, hold=hold, method=method, **options),
                                             DATA_KEYS + FILTER_KEYS)
        return predict_data(self, params, data, steps=steps, states=states, **settings)

    def loglik(self, params, data, time: str | None = None, hold: str | None = None, method: str | None = None,
               **options) -> float:
        """The Gaussian log-likelihood (3.18) of the data at given parameters.

        Parameters
        ----------
        params : mapping of str to float
            The parameters' values by name.
        data : pandas.DataFrame or list of pandas.DataFrame
            A list holds independent experiments; their log-likelihoods add.
        time : str, optional
            The name of the time column.
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples.
        method : str, optional
            The filter (default: the exact Kalman filter for linear models, the EKF otherwise).
        **options
            ``form``, ``substeps``, ``iterations`` (IEKF), ``time_unit`` and
            ``robust=("huber", c)`` or ``("tukey", c)`` for the robust criterion
            (3.57–3.58) instead of the Gaussian one.

        Returns
        -------
        float
            The log-likelihood.

        Raises
        ------
        DataError
            Data that do not fit the model.
        ModelError
            Parameter values that make a variance negative or the initial covariance invalid.
        """
        from ..estimate.criteria import loglik

        data, settings = self._call_settings(data, dict(time=time, hold=hold, method=method, **options),
                                             DATA_KEYS + FILTER_KEYS)
        return loglik(self, params, data, **settings)

    def filter(self, params, data, time: str | None = None, hold: str | None = None, method: str | None = None,
               **options):
        """Run the filter through the data.

        Parameters
        ----------
        params : mapping of str to float
            The parameters' values by name.
        data : pandas.DataFrame
            Times, inputs and outputs.
        time : str, optional
            The name of the time column.
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples.
        method : str, optional
            The filter.
        **options
            Other data and filter settings.

        Returns
        -------
        FilterResult
            Predicted and filtered means and covariances, innovations and their
            covariances, per row.
        """
        from ..filters.api import filter_data

        data, settings = self._call_settings(data, dict(time=time, hold=hold, method=method, **options),
                                             DATA_KEYS + FILTER_KEYS)
        return filter_data(self, params, data, **settings)

    def smooth(self, params, data, time: str | None = None, hold: str | None = None, method: str | None = None,
               **options):
        """Rauch–Tung–Striebel smoothed states (linear models and the EKF).

        Parameters
        ----------
        params : mapping of str to float
            The parameters' values by name.
        data : pandas.DataFrame
            Times, inputs and outputs.
        time : str, optional
            The name of the time column.
        hold : {"zoh", "foh"}, optional
            How inputs are held between samples.
        method : str, optional
            The filter.
        **options
            Other data and filter settings.

        Returns
        -------
        SmootherResult
            Smoothed means and covariances of the states at the sample times.
        """
        from ..filters.api import smooth_data

        data, settings = self._call_settings(data, dict(time=time, hold=hold, method=method, **options),
                                             DATA_KEYS + FILTER_KEYS)
        return smooth_data(self, params, data, **settings)

    def simulate(self, params, data_or_times, n_paths: int = 1, method: str = "euler", seed: int = 0, **options):
        """Sample paths of the states and noisy observations (section 2.5).

        Parameters
        ----------
        params : mapping of str to float
            The parameters' values by name.
        data_or_times : pandas.DataFrame or array_like
            The times and the inputs (a frame), or the times alone for a model without inputs.
        n_paths : int
            The number of paths.
        method : {"euler", "milstein", "heun", "exact"}
            The integration scheme (``"exact"``: the exact discretisation of a linear model).
        seed : int
            The random seed.
        **options
            ``time``, ``hold``, ``time_unit``, ``columns``, ``substeps`` (integration
            steps per sampling interval, default 10), ``calculus`` (``"ito"`` or
            ``"stratonovich"``) and ``noise`` (False: the noise-free solution).

        Returns
        -------
        Simulation
            ``.frame(i)`` the i-th path, ``.to_frame()`` all of them.
        """
        from ..simulate.simulate import simulate

        data_or_times, settings = self._call_settings(data_or_times, options, ("time", "hold", "time_unit", "columns"))
        return simulate(self, params, data_or_times, n_paths=n_paths, method=method, seed=seed, **settings)


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
