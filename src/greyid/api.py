"""What users hold: ``greyid.Model`` and ``greyid.FitResult``, with every method that reaches past the
specification and the numbers.

A [`Model`][greyid.api.Model] is its specification ([`ModelSpec`][greyid.model.model.ModelSpec]: equations,
parameters, units, options, model files) and the calls that run on it — filtering, estimation,
prediction, simulation.  A [`FitResult`][greyid.api.FitResult] is the numbers of a fit
([`Estimates`][greyid.estimate.results.Estimates]: estimates, covariance, summary, saving) and what the
layers above the estimator make of them: profile likelihoods, posterior sampling, prediction and
simulation intervals with the parameters' uncertainty, validation and the report.  These classes
sit above uncertainty, validation, design and report and below fleets and populations, so every
import points down.
"""

from __future__ import annotations

import dataclasses

import pandas as pd

from .estimate.calls import filter_at, loglik_at, predict_at, simulate_at, smooth_at
from .estimate.estimation import fit_model
from .estimate.likelihood import likelihood_of
from .estimate.results import Estimates, estimates_from_dict, read_fit_file
from .errors import ModelError
from .model.model import ModelSpec
from .outputs import write_atomic

# The layers past the estimator load SciPy's statistics and matplotlib: they are imported by the
# methods that use them, so that a model and its fit do not wait for them.

__all__ = ["Model", "FitResult", "load_fit", "fit_from_dict"]


class Model(ModelSpec):
    """A continuous–discrete stochastic state-space model written as equations (4.1)–(4.2).

    ``dx = f(x, u, t, θ) dt + G(x, u, t, θ) dω`` with discrete observations
    ``y_k = h(x_k, u_k, t_k, θ) + e_k``, ``e_k ~ N(0, S)``.  Build it with the
    ``add_*`` and ``set_*`` methods (each returns the model, so calls chain), read
    it from a model file ([`from_toml()`][greyid.api.Model.from_toml]) or
    write it as Python functions ([`from_functions()`][greyid.api.Model.from_functions]).

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
            ([`set_nested_start()`][greyid.api.Model.set_nested_start]).
        progress : bool or callable
            True prints the optimiser's iterations; a callable receives one dict per iteration.
        **options
            Other settings by name (as [`set_options()`][greyid.api.Model.set_options]):
            ``cov_type`` (``"hessian"``, the default for ML and MAP; ``"sandwich"``
            H⁻¹JH⁻¹, the default for k-step and robust criteria; ``"opg"``),
            ``optimizer`` (``"auto"``: Fisher scoring far from the optimum where a
            Hessian is costly, the quasi-Newton start where a Hessian of one block
            carries many states, then exact Newton steps; for the Laplace method
            ``"lbfgs"``, as ctsmTMB fits; ``"scoring"``; ``"newton"``;
            ``"quasi-newton"``: L-BFGS steps on the value and exact gradient, then
            Newton steps, the same optimum, faster compiled fits of small models, one
            program more to compile; ``"lbfgs"``: L-BFGS to the optimum and the Hessian
            there by central differences of the exact gradient, as TMB's ``sdreport``:
            no Hessian program to compile, so a first fit by the Laplace method takes
            about 0.6 of Newton's time, standard errors to about 1e-6 relative; single
            fits only), ``steady_state`` (True: a regular series of 128
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
        greyid.api.FitResult : what a fit holds and what it can do next.
        greyid.api.Model.likelihood : the criterion as a function, for other optimisers and samplers.

        Examples
        --------
        >>> import greyid
        >>> from greyid.datasets import building_model, load_building_data
        >>> fit = building_model().fit(load_building_data().iloc[:300])
        >>> fit.converged
        True
        >>> print(fit.summary())  # doctest: +SKIP
        """
        given = dict(time=time, hold=hold, method=method, criterion=criterion, robust=robust, horizon=horizon,
                     starts=starts, seed=seed, **options)
        return FitResult.of(fit_model(self, data, prior=prior, init=init, init_from=init_from, progress=progress,
                                      **given))

    def likelihood(self, data, time: str | None = None, hold: str | None = None, method: str | None = None,
                   criterion: str | None = None, prior=None, robust=None, horizon: int | None = None, **options):
        """The negative log-likelihood as a function of the free parameters.

        Or the criterion ``fit`` would minimise: MAP, robust, k-step.  Its single
        evaluations of a regular series of a linear model switch to the filter's
        steady state where it has settled.

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame
            As for [`fit()`][greyid.api.Model.fit].
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
        given = dict(time=time, hold=hold, method=method, criterion=criterion, robust=robust, horizon=horizon,
                     **options)
        return likelihood_of(self, data, prior=prior, **given)

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
        return predict_at(self, params, data, steps=steps, states=states, time=time, hold=hold, method=method,
                          **options)

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
        return loglik_at(self, params, data, time=time, hold=hold, method=method, **options)

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
        return filter_at(self, params, data, time=time, hold=hold, method=method, **options)

    def smooth(self, params, data, time: str | None = None, hold: str | None = None, method: str | None = None,
               **options):
        """Smoothed states: Rauch–Tung–Striebel after a Gaussian filter; with ``method="laplace"`` the mode of the
        states given all the data and the Laplace approximation's marginal covariances.

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
            The filter, or ``"laplace"``.
        **options
            Other data and filter settings.

        Returns
        -------
        SmootherResult
            Smoothed means and covariances of the states at the sample times.
        """
        return smooth_at(self, params, data, time=time, hold=hold, method=method, **options)

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
        return simulate_at(self, params, data_or_times, n_paths=n_paths, method=method, seed=seed, **options)


class FitResult(Estimates):
    """Estimates and their uncertainty for one model fitted to one or more data sets.

    Made by [`Model.fit()`][greyid.api.Model.fit] and [`load_fit()`][greyid.api.load_fit]; its names
    follow statsmodels' results (``params``, ``bse``, ``llf``, ``aic``, ``conf_int()``, ``summary()``).

    Attributes
    ----------
    model : Model
        The fitted model.
    params : pandas.DataFrame
        One row per parameter: ``estimate``, ``std_error``, ``t_value``,
        ``p_value``, ``lower_bound``, ``upper_bound``, ``fixed``, ``at_bound``,
        ``reliable``, ``gradient`` (and ``unit`` where the model has units).
    cov : pandas.DataFrame
        The covariance of the free parameters' estimates (``cov_type``).
    loglik : float
        The Gaussian log-likelihood at the estimates.
    criterion_value : float
        The value of the criterion maximised (the log-posterior for MAP, the
        robust or k-step criterion), equal to ``loglik`` for plain ML.
    n_obs : int
        The number of observed output values.
    converged : bool
        True only at a minimum: the optimiser stopped, the Hessian is positive
        definite in the parameters not at a bound, and every free parameter
        affects the likelihood.
    message : str
        Why the optimiser stopped, or why the fit is not converged.
    iterations : int
        The optimiser's steps.
    settings : FitSettings
        The settings the fit used (time, hold, method, criterion, ...), typed
        ([`FitSettings`][greyid.estimate.settings.FitSettings]) and read as a mapping too
        (``fit.settings["method"]``).
    warnings : list of str
        What the summary's warnings say (a bound, a flat direction, ...).
    data : list of pandas.DataFrame or None
        The data fitted; None for a loaded fit until
        [`attach_stored_data()`][greyid.api.FitResult.attach_stored_data]
        or [`with_data()`][greyid.api.FitResult.with_data].
    starts : list of dict
        One per start: its label, criterion, convergence, iterations and message.
    data_file : str or None
        Where the data came from: a file's path or ``dataset:NAME``.
    """

    @classmethod
    def of(cls, estimates: Estimates) -> "FitResult":
        """The fit whose numbers are ``estimates`` (what the estimator returns).

        Parameters
        ----------
        estimates : Estimates
            The numbers of a fit.

        Returns
        -------
        FitResult
            The same numbers, with the methods of this class.
        """
        if isinstance(estimates, cls):
            return estimates
        return cls(**{f.name: getattr(estimates, f.name) for f in dataclasses.fields(Estimates)})

    def conf_int(self, level: float = 0.95, method: str = "wald"):
        """Confidence intervals of the parameters.

        Parameters
        ----------
        level : float
            The confidence level, between 0 and 1.
        method : {"wald", "profile"}
            ``"wald"``: estimate ± the Student-t quantile (N − k degrees of freedom) ×
            the standard error (NaN where there is none: fixed parameters, estimates at
            a bound).  ``"profile"``: the likelihood-ratio interval from the profile of
            each free parameter, which follows a skewed likelihood; an end that runs
            into a bound is that bound, with a warning.

        Returns
        -------
        pandas.DataFrame
            Columns ``lower`` and ``upper``, one row per parameter.

        Raises
        ------
        ModelError
            An unknown method or a level outside (0, 1).
        """
        if method == "profile" and 0 < level < 1:
            from .uncertainty.profile import profile_intervals

            return profile_intervals(self, level)
        return super().conf_int(level, method)

    def predict(self, data=None, steps: int = 1, states: bool = False, interval: float | None = None,
                parameter_uncertainty: bool = False, draws: int = 200, seed: int = 0, posterior=None):
        """Output (and state) predictions ``steps`` samples ahead, with standard deviations.

        As [`Model.predict()`][greyid.api.Model.predict] at the estimates (for a Laplace fit by the particle
        filter, as ``filter()``); append rows of future inputs with missing outputs to ``data`` to forecast past
        its end.

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Other data (default: the fit's).
        steps : int
            The horizon in samples.
        states : bool
            Also the states' predictions.
        interval : float, optional
            A level such as 0.95: adds ``<y>_lower`` and ``<y>_upper`` columns.
        parameter_uncertainty : bool
            Also carry the parameters' uncertainty: ``draws`` parameter vectors from the
            Laplace approximation (or from ``posterior``), the predictive mixture's mean,
            total ``<y>_sd`` and quantiles.
        draws : int
            The parameter draws of ``parameter_uncertainty``.
        seed : int
            Their random seed.
        posterior : Posterior, optional
            Draws from [`sample()`][greyid.api.FitResult.sample] to use instead.

        Returns
        -------
        pandas.DataFrame or list of pandas.DataFrame
            The time column, each output and ``<output>_sd`` (and the interval's columns).

        Raises
        ------
        ModelError
            ``states=True`` with ``parameter_uncertainty=True``, or a level outside (0, 1).
        """
        if parameter_uncertainty:
            if states:
                raise ModelError("states=True is not available with parameter_uncertainty=True")
            from .uncertainty.intervals import predict as predict_with_uncertainty

            return predict_with_uncertainty(self, data, steps=steps, interval=0.95 if interval is None else interval,
                                            draws=draws, seed=seed, posterior=posterior)
        return super().predict(data, steps=steps, states=states, interval=interval)

    def simulate(self, data=None, n_paths: int | None = None, seed: int = 0, method: str = "euler",
                 interval: float | None = None, parameter_uncertainty: bool = False, posterior=None, **options):
        """Sample paths of the fitted model driven by the data's inputs.

        Parameters
        ----------
        data : pandas.DataFrame, optional
            Times and inputs (default: the fit's data).
        n_paths : int, optional
            The number of paths (default 1; 200 with ``interval`` or ``parameter_uncertainty``).
        seed : int
            The random seed.
        method : {"euler", "milstein", "heun", "exact"}
            The integration scheme.
        interval : float, optional
            A level such as 0.95: the paths' mean and central interval per output instead of the paths.
        parameter_uncertainty : bool
            Each path with its own parameter draw (Laplace, or ``posterior``).
        posterior : Posterior, optional
            Draws from [`sample()`][greyid.api.FitResult.sample].
        **options
            ``substeps``, ``calculus``, ``noise`` (see [`Model.simulate()`][greyid.api.Model.simulate]).

        Returns
        -------
        Simulation or pandas.DataFrame
            The paths, or (with ``interval`` or ``parameter_uncertainty``) their summary; see
            [`greyid.uncertainty.intervals.simulate()`][greyid.uncertainty.intervals.simulate].
        """
        if interval is not None or parameter_uncertainty:
            from .uncertainty.intervals import simulate as simulate_with_uncertainty

            return simulate_with_uncertainty(self, data, n_paths=200 if n_paths is None else n_paths,
                                             interval=0.95 if interval is None else interval, seed=seed,
                                             posterior=posterior, parameter_uncertainty=parameter_uncertainty,
                                             method=method, **options)
        return super().simulate(data, n_paths=n_paths, seed=seed, method=method, **options)

    def profile(self, name: str, values=None, n: int = 21, span: float = 3.0, expression: str | None = None
                ) -> pd.DataFrame:
        """The profile likelihood of a parameter or derived quantity.

        Parameters
        ----------
        name : str
            A parameter, or a derived quantity declared on the model.
        values : array_like, optional
            Where to hold it (default: ``n`` points over the estimate ± ``span``
            standard errors, within the bounds).
        n : int
            The number of points.
        span : float
            The half-width of the default grid, in standard errors.
        expression : str, optional
            A derived quantity given as an expression in the parameters.

        Returns
        -------
        pandas.DataFrame
            The quantity, ``loglik`` (``criterion`` for MAP, robust or k-step fits),
            the re-estimated parameters, ``converged`` and ``deviance``; ``attrs`` holds
            the estimate, the maximum and the 95 % χ² threshold.  See
            `greyid.uncertainty.profile()`.
        """
        from .uncertainty.profile import profile

        return profile(self, name, values=values, n=n, span=span, expression=expression)

    def sample(self, draws: int = 1000, chains: int = 4, seed: int = 0, warmup: int = 500,
               target_accept: float = 0.8, sampler: str = "auto", particles: int | None = None,
               proposal: str | None = None):
        """Draws from the posterior of the fit's criterion: NUTS (BlackJAX) on an exact likelihood, particle
        marginal Metropolis–Hastings on a particle filter's estimate.

        Parameters
        ----------
        draws : int
            Draws kept per chain.
        chains : int
            Chains run in parallel, each started from a draw of the Laplace approximation.
        seed : int
            The random seed.
        warmup : int
            Adaptation steps before the kept draws.
        target_accept : float
            NUTS: the step-size adaptation's target acceptance rate.
        sampler : str
            ``"nuts"``, ``"pmmh"`` or ``"auto"`` (PMMH for a particle fit, NUTS otherwise).
        particles : int, optional
            PMMH: the particle filter's particles (default: the fit's, or 1000).
        proposal : str, optional
            PMMH: the particle filter's proposal (default: the fit's, or ``"bootstrap"``).

        Returns
        -------
        Posterior
            Draws, R-hat, effective sample sizes, the acceptance rate, and divergences (NUTS) or the
            log-likelihood estimate's spread (PMMH); ArviZ's ``InferenceData`` through
            ``to_inference_data()``.  See [`greyid.uncertainty.sample()`][greyid.uncertainty.sampling.sample]
            and [`sample_pmmh()`][greyid.uncertainty.pmmh.sample_pmmh].

        Raises
        ------
        ModelError
            An unknown sampler, NUTS asked for a particle fit, PMMH settings for NUTS, or BlackJAX or
            ArviZ not installed (``pip install "greyid[sampling]"``).
        """
        if sampler not in ("auto", "nuts", "pmmh"):
            raise ModelError(f"unknown sampler '{sampler}'; use 'auto', 'nuts' or 'pmmh'")
        particle_fit = self.settings["method"] == "particle"
        if sampler == "pmmh" or (sampler == "auto" and particle_fit):
            from .uncertainty.pmmh import sample_pmmh

            return sample_pmmh(self, draws=draws, chains=chains, seed=seed, warmup=warmup, particles=particles,
                               proposal=proposal)
        if particle_fit:
            raise ModelError("NUTS needs an exact gradient; a particle fit's is a Monte Carlo estimate: use "
                             "sampler='pmmh'")
        if particles is not None or proposal is not None:
            raise ModelError("particles and proposal are settings of sampler='pmmh'")
        from .uncertainty.sampling import sample

        return sample(self, draws=draws, chains=chains, seed=seed, warmup=warmup, target_accept=target_accept)

    def plot_profile(self, name: str, ax=None, **options):
        """Plot the profile of ``name``: deviance, χ² threshold and the Wald parabola.

        Parameters
        ----------
        name : str
            A parameter or derived quantity.
        ax : matplotlib.axes.Axes, optional
            Where to draw (default: a new figure).
        **options
            Passed to [`profile()`][greyid.api.FitResult.profile]
            (``values``, ``n``, ``span``, ``expression``).

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from .uncertainty.profile import plot_profile

        table = self.profile(name, **options)
        se = float(self.params.loc[name, "std_error"]) if name in self.params.index else None
        return plot_profile(table, ax=ax, wald_se=se)

    def validate(self, level: float = 0.05, lags: int | None = None, m: int | None = None):
        """The residual tests of chapter 5 on every output.

        Parameters
        ----------
        level : float
            The significance level of the tests.
        lags : int, optional
            Lags of the autocorrelation tests (default: from the series' length).
        m : int, optional
            The smoothing of the spectral estimates (default: from the series' length).

        Returns
        -------
        Validation
            Its ``tests`` DataFrame has columns ``test, output, statistic, df, p_value,
            reject``; ``plot()``, ``plot_coherency()``, ``plot_simulation()``,
            ``plot_bootstrap()`` and ``plot_prediction()`` return matplotlib figures.
        """
        from .validation.validate import validate

        return validate(self, level=level, lags=lags, m=m)

    def compare_methods(self, data=None, methods=None, particles: int = 1000, seed: int = 0,
                        replicates: int = 8):
        """Each method's log-likelihood at the estimates beside the particle filter's estimate: whether
        this fit's approximation (an EKF's, a UKF's, the Laplace method's) is trustworthy.

        Parameters
        ----------
        data : pandas.DataFrame or list of pandas.DataFrame, optional
            The data (default: the fit's own).
        methods : sequence of str, optional
            The methods to compare (default: every Gaussian filter and the Laplace method, or the Laplace
            method alone for non-Gaussian observations).
        particles : int
            Particles of each run of the particle filter.
        seed : int
            The seed its runs' random numbers are split from.
        replicates : int
            Its independent runs (the Monte Carlo standard error needs at least 2).

        Returns
        -------
        pandas.DataFrame
            One row per method: ``loglik``, ``std_error``, ``difference`` from the particle estimate and
            ``agrees`` (within 3 standard errors, and 0.1 at least).

        Raises
        ------
        ModelError
            An unknown method, or a fit without data.

        Examples
        --------
        >>> fit.compare_methods(methods=["ekf", "ukf"])  # doctest: +SKIP
        """
        from .estimate.approximations import compare_methods

        where = {k: v for k, v in self._filter_settings().items() if k in ("time", "hold", "time_unit")}
        return compare_methods(self.model, self.values, self._data(data), methods, particles, seed, replicates,
                               **where)

    def report(self, path=None, **options) -> str:
        """The self-contained HTML report of this fit.

        Parameters
        ----------
        path : str or pathlib.Path, optional
            Where to write it (atomically); without it, nothing is written.
        **options
            ``level`` (the tests' significance level), ``steps`` (the prediction
            horizon shown), ``n_paths`` (the Monte Carlo band), ``seed``, ``title``,
            ``profile`` (False leaves the profile-likelihood intervals out of the
            parameter table).

        Returns
        -------
        str
            The HTML document.

        Raises
        ------
        ModelError
            A fit that carries no data (a loaded fit whose data file is gone).
        """
        from .report import html_report

        text = html_report(self, **options)
        if path is not None:
            write_atomic(path, text)
        return text


def fit_from_dict(spec: dict, where: str = "the fit", model=None) -> FitResult:
    """A [`FitResult`][greyid.api.FitResult] from [`to_dict()`][greyid.api.FitResult.to_dict]'s form; errors
    name ``where`` it came from.

    Parameters
    ----------
    spec : dict
        What ``to_dict()`` gave (a saved fit's JSON).
    where : str
        What to call its origin in errors.
    model : Model, optional
        The model to attach instead of a new one built from the stored model (the same
        model: a fleet's fits share the caller's compiled one).

    Returns
    -------
    FitResult
        The fit.
    """
    return FitResult.of(estimates_from_dict(spec, Model, where, model))


def load_fit(path) -> FitResult:
    """Read a fit written by [`FitResult.save()`][greyid.api.FitResult.save] (or ``greyid fit --out``).

    Parameters
    ----------
    path : str or pathlib.Path
        The JSON file.

    Returns
    -------
    FitResult
        The fit; its ``model`` reproduces the log-likelihood, and its data are read
        from ``data_file`` when first needed.

    Raises
    ------
    ModelError
        A file that is missing, a folder, not JSON, or not a greyid fit (names the key).
    """
    return fit_from_dict(read_fit_file(path), f"fit file '{path}'")
