"""The negative log-likelihood of a model on data as a public object (``model.likelihood(data)``).

What ``model.fit`` minimises — the negative log-likelihood (3.18) through the
model's filter, or the chosen criterion (MAP, robust, k-step) — as functions of
the free parameters, as ctsmTMB's ``likelihood()`` and statsmodels'
``loglike``/``score`` give it:

    nll = model.likelihood(data, time="t", hold="zoh")
    nll.names                        # the free parameters, in order
    nll.value(x)                     # x in the parameters' own units
    nll.value_and_grad(x)            # exact gradient (forward mode)
    nll.hessian(x)
    nll.value(X)                     # a 2-D X: one row per parameter vector
    f = nll.function()               # the pure JAX function x ↦ value: jax.grad, vmap, BlackJAX, optax

With ``unconstrained=True`` x is the optimiser's coordinate z, in which every
bound is gone (θ = l + e^z and the like, [`transforms`][greyid.estimate.transforms]).

Single evaluations of a shorter regular series of a linear model switch to the
filter's steady state after its first rows ([`greyid.filters.steady`][greyid.filters.steady]) and
sum the criterion in the filter's scan; the Hessian and batches of parameter
vectors step through every row.  ``steady_state=False`` steps through every
row for single evaluations too.
"""

from __future__ import annotations

import hashlib
import weakref
from dataclasses import replace

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np

from ..runtime.jit import jit, kept_key
from ..data.prepare import as_frames
from ..errors import ModelError
from ..filters.api import prepare_datasets
from ..model.options import DATA_KEYS, ESTIMATION_KEYS, FILTER_KEYS
from . import objective
from .estimation import check_observed, check_settings, free_parameters, make_problem
from .transforms import Transform


def data_digest(arrays) -> str:
    """A hash of a tree of arrays: its structure, and each array's shape, type and values."""
    leaves, tree = jax.tree_util.tree_flatten(arrays)
    digest = hashlib.sha256(str(tree).encode())
    for leaf in leaves:
        leaf = np.ascontiguousarray(leaf)
        digest.update(repr((leaf.shape, leaf.dtype.str)).encode())
        digest.update(leaf.tobytes())
    return digest.hexdigest()


def likelihood_of(model, data, prior=None, **given) -> "Likelihood":
    """[`Model.likelihood()`][greyid.api.Model.likelihood]: the settings resolved as the model's methods
    resolve them (given, else the model's), then the [`Likelihood`][greyid.estimate.likelihood.Likelihood]."""
    data, settings = model.call_settings(data, given, DATA_KEYS + FILTER_KEYS + ESTIMATION_KEYS)
    for key in ("prior_correlation", "starts", "seed", "maxiter", "cov_type", "optimizer"):
        settings.pop(key, None)
    if prior is None and settings.get("criterion") == "map":
        prior = model.prior()
    return Likelihood(model, data, prior=prior, **settings)


class Likelihood:
    """The negative log-likelihood (or the criterion a fit minimises) as a function of the free parameters.

    Made by [`Model.likelihood()`][greyid.api.Model.likelihood], whose
    arguments it takes.  Parameters not free in the model (fixed ones) keep their
    values; the free ones are ``names``, in order.  Compiled once, and kept in greyid's cache folder
    under the model, the settings and the data for a later process; single
    evaluations of a regular series of a linear model switch to the filter's
    steady state where it has settled (``steady_state=False`` steps through every row).

    Attributes
    ----------
    names : list of str
        The free parameters, in the order of ``x``.
    n_obs : int
        The observed output values.

    Examples
    --------
    >>> from scipy.optimize import minimize
    >>> from greyid.datasets import building_model, load_building_data
    >>> nll = building_model().likelihood(load_building_data().iloc[:200])
    >>> result = minimize(lambda z: nll.value_and_grad(z, unconstrained=True),
    ...                   nll.to_unconstrained(nll.start()), jac=True, method="BFGS")
    >>> estimates = dict(zip(nll.names, nll.from_unconstrained(result.x)))
    """

    def __init__(self, model, data, time: str = "t", hold: str = "zoh", method=None, criterion: str = "ml",
                 prior=None, robust=None, horizon: int = 1, time_unit=None, steady_state: bool = True,
                 **filter_settings):
        structure = model.structure
        robust, _ = check_settings(criterion, prior, robust, horizon, None, "auto", 1)
        parameters = free_parameters(model)
        problem = make_problem(structure, parameters, method, (robust, horizon, prior),
                               dict(filter_settings, steady_state=steady_state))
        prepared = prepare_datasets(structure, parameters.theta0, as_frames(data), time, hold, time_unit,
                                    check=False)
        check_observed(prepared, len(parameters.free))
        if sum(series.n_rows for series, _ in prepared) > objective.LONG_SERIES:
            problem = replace(problem, long_series=True)
        self.model, self.problem = model, problem
        self.names = [parameters.names[i] for i in parameters.free]
        self.n_obs = sum(int(np.sum(~np.isnan(series.outputs))) for series, _ in prepared)
        self._transform = parameters.transform
        self._start = parameters.theta0[list(parameters.free)]
        base, lower, upper, prior_mean, prior_chol = problem.arguments(parameters.theta0)
        datasets = [inputs for _, inputs in prepared]
        kinds = problem.transform.kind

        def functions(problem):
            _, negative = objective.criterion_functions(structure, problem)

            def at_x(x):
                return negative(problem.assemble(x, base, jnp), prior_mean, prior_chol, datasets)

            def at_z(z):
                theta = problem.theta(z, base, Transform(kinds, lower, upper), jnp)
                return negative(theta, prior_mean, prior_chol, datasets)

            return {False: at_x, True: at_z}

        # A short series' switch to the steady state after its first rows (greyid.filters.steady)
        # for single values and gradients; Hessians and evaluations vectorised over parameter
        # vectors (one decision per row of x would run both forms) step through every row.
        # By whether every row steps through: the problem and its functions.
        every_row = replace(problem, options=replace(problem.options, steady_state=False))
        self._forms = {every: (p, functions(p)) for every, p in ((False, problem), (True, every_row))}
        self._programs: dict = {}
        self._ready = weakref.WeakValueDictionary()
        # The data are constants of the programs (XLA folds what depends on them alone: a fifth of the
        # Armadillo value's time), so a program kept in the cache folder is named by them too.
        self._data_digest = data_digest((base, lower, upper, prior_mean, prior_chol, datasets))

    # ------------------------------------------------------------------ the functions
    def function(self, unconstrained: bool = False):
        """The pure JAX function of one parameter vector, for ``jax.grad``, ``jax.vmap``, samplers and optimisers.

        Parameters
        ----------
        unconstrained : bool
            A function of z, the optimiser's coordinates, instead of the parameters' values.

        Returns
        -------
        callable
            x ↦ the negative log-likelihood (a JAX scalar).
        """
        return self._forms[False][1][bool(unconstrained)]

    def _program(self, kind: str, unconstrained: bool, batched: bool):
        key = (kind, bool(unconstrained), batched)
        if key not in self._programs:
            every_row = batched or kind == "hessian"
            problem, functions = self._forms[every_row]
            fun = functions[bool(unconstrained)]
            if kind == "value_and_grad":
                fun = objective.forward_value_and_grad(fun)
            elif kind == "hessian":
                fun = jax.jacfwd(jax.jacfwd(fun))
            name = ("likelihood", *key, problem.key(), problem.prior_index, self._data_digest)
            self._programs[key] = jit(jax.vmap(fun) if batched else fun, key=kept_key(self.model.structure, name))
        return self._programs[key]

    def _call(self, kind: str, x, unconstrained: bool):
        x = np.asarray(x, dtype=float)
        if x.ndim not in (1, 2) or x.shape[-1] != len(self.names):
            raise ModelError(f"x must hold the {len(self.names)} free parameters {self.names} (a vector, or one row "
                             f"per parameter vector), got shape {x.shape}")
        # NumPy in and out directly (the compiled program's own fast path): a jnp.asarray and
        # a tree_map around each call cost a third of the Armadillo model's value and gradient.
        run = self._ready.get((kind, bool(unconstrained), x.shape))
        if run is None:
            # Fetched once per shape: the program's own call would look it up by its arguments' tree
            # and types at every evaluation.  Held weakly, so that release_compiled() frees it.
            program = self._program(kind, unconstrained, x.ndim == 2)
            run = self._ready[(kind, bool(unconstrained), x.shape)] = program.executable(x)
        out = run(x)
        return tuple(np.asarray(a) for a in out) if isinstance(out, tuple) else np.asarray(out)

    def value(self, x, unconstrained: bool = False):
        """The negative log-likelihood at x.

        Parameters
        ----------
        x : array_like
            The free parameters' values in ``names``' order: one vector, or a 2-D array
            with one vector per row (evaluated together).
        unconstrained : bool
            ``x`` is in the optimiser's coordinates z (bounds removed) instead.

        Returns
        -------
        float or numpy.ndarray
            One value, or one per row of ``x``.
        """
        return self._call("value", x, unconstrained)

    def __call__(self, x, unconstrained: bool = False):
        return self.value(x, unconstrained)

    def value_and_grad(self, x, unconstrained: bool = False):
        """The value and its exact gradient at x (forward mode, one tangent per parameter).

        Parameters
        ----------
        x : array_like
            The free parameters' values in ``names``' order: one vector, or a 2-D array
            with one vector per row (evaluated together).
        unconstrained : bool
            ``x`` is in the optimiser's coordinates z (bounds removed) instead.

        Returns
        -------
        tuple
            ``(value, gradient)``; with one row per vector, one of each per row.
        """
        return self._call("value_and_grad", x, unconstrained)

    def hessian(self, x, unconstrained: bool = False):
        """The exact Hessian at x (forward over forward).

        Parameters
        ----------
        x : array_like
            The free parameters' values in ``names``' order: one vector, or a 2-D array
            with one vector per row (evaluated together).
        unconstrained : bool
            ``x`` is in the optimiser's coordinates z (bounds removed) instead.

        Returns
        -------
        numpy.ndarray
            (n, n), or (rows, n, n).
        """
        return self._call("hessian", x, unconstrained)

    # ------------------------------------------------------------------ coordinates
    def to_unconstrained(self, x) -> np.ndarray:
        """The optimiser's coordinates z of parameter values x (bounds removed by log and logit transforms).

        Parameters
        ----------
        x : array_like
            The free parameters' values in ``names``' order.

        Returns
        -------
        numpy.ndarray
            z.
        """
        return self._transform.to_z(np.asarray(x, dtype=float))

    def from_unconstrained(self, z) -> np.ndarray:
        """The parameter values x at the optimiser's coordinates z.

        Parameters
        ----------
        z : array_like
            The coordinates.

        Returns
        -------
        numpy.ndarray
            x, in ``names``' order.
        """
        return np.asarray(self._transform.to_theta(jnp.asarray(z, dtype=float)))

    def start(self) -> np.ndarray:
        """The free parameters' initial values.

        Returns
        -------
        numpy.ndarray
            In ``names``' order.
        """
        return self._start.copy()

    def __repr__(self) -> str:
        return (f"<negative log-likelihood of '{self.model.name}' on {self.n_obs} observed values; "
                f"free parameters {self.names}>")
