"""Delayed inputs, ``delay(u, tau)`` (chapter 8): exact against shifted columns and fine-step solutions."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.errors import DataError, ModelError


def first_order(drift_input: str, name: str = "delayed") -> greyid.Model:
    m = greyid.Model(name)
    m.add_system(f"dx = (-x/T + {drift_input})*dt + exp(ls)*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="exp(le)")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1e-12]])
    return m


def simulated_delay(tau, step, n, clock, input_seed, noise_seed):
    """The one-delay first-order model, its true parameters, and a series simulated from them
    (a random ±1 input held for ``clock`` samples)."""
    rng = np.random.default_rng(input_seed)
    m = first_order("k*delay(u, tau)")
    m.set_initial_state(mean={"x": 0.0}, covariance=[[0.01]])
    truth = dict(T=2.0, k=1.0, tau=tau, ls=-2.0, le=-4.0)
    data = pd.DataFrame({"t": np.arange(n) * step, "u": np.repeat(rng.choice([-1.0, 1.0], n // clock), clock)})
    data["y"] = m.simulate(truth, data, method="exact", seed=noise_seed).outputs[0, :, 0]
    return m, truth, data


@pytest.fixture(scope="module")
def two_delays():
    return first_order("k*delay(u, tau) + c*delay(u, tau2)", "two_delays")


def exact_reference(t, u, T, gains, taus, hold):
    """x' = −x/T + Σ g·u(t − τ), x(0) = 0, solved exactly on a grid holding every switching instant.

    Between consecutive instants of the grid (the sampling times, the delayed
    sampling times and 2000 points in between) the delayed inputs are constant
    (zoh) or linear (foh), so each step has a closed form.
    """
    cuts = np.concatenate([t] + [t + tau for tau in taus])
    grid = np.unique(np.concatenate([cuts[cuts <= t[-1]], np.linspace(t[0], t[-1], 2001)]))

    def signal(s):
        if hold == "zoh":
            return u[np.clip(np.searchsorted(t, s, side="right") - 1, 0, len(t) - 1)]
        return np.interp(s, t, u)

    x = np.zeros(len(grid))
    for i in range(len(grid) - 1):
        h = grid[i + 1] - grid[i]
        a = np.exp(-h / T)
        if hold == "zoh":
            mid = 0.5 * (grid[i] + grid[i + 1])
            b = sum(g * signal(mid - tau) for g, tau in zip(gains, taus))
            x[i + 1] = a * x[i] + (1 - a) * T * b
        else:  # b linear over the step: exact integral of e^{-(h-s)/T}(b0 + (b1-b0)s/h)
            b0 = sum(g * signal(grid[i] - tau) for g, tau in zip(gains, taus))
            b1 = sum(g * signal(grid[i + 1] - tau) for g, tau in zip(gains, taus))
            ramp = T * h - T * T * (1 - a)
            x[i + 1] = a * x[i] + (1 - a) * T * b0 + (b1 - b0) / h * ramp
    return x[np.searchsorted(grid, t)]


def test_whole_sample_delay_equals_the_shifted_column():
    rng = np.random.default_rng(0)
    n = 120
    t = np.arange(n) * 0.5
    u = np.repeat(rng.normal(size=n // 4), 4)
    y = np.sin(t / 3) + 0.1 * rng.normal(size=n)
    delayed, plain = first_order("k*delay(u, tau)"), first_order("k*u", "plain")
    p = dict(T=2.0, k=1.5, ls=-1.0, le=-2.0)
    data = pd.DataFrame({"t": t, "u": u, "y": y})
    shifted = data.assign(u=np.concatenate([np.full(3, u[0]), u[:-3]]))  # the first value before the start
    for hold in ("zoh", "foh"):
        for method in ("kalman", "ekf", "ukf"):
            assert delayed.loglik({**p, "tau": 1.5}, data, hold=hold, method=method) == pytest.approx(
                plain.loglik(p, shifted, hold=hold, method=method), abs=1e-8), (hold, method)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_fractional_delays_on_irregular_times_match_the_exact_solution(two_delays, hold):
    rng = np.random.default_rng(1)
    n = 50
    t = np.cumsum(np.r_[0.0, rng.uniform(0.3, 1.7, n - 1)])  # irregular sampling: several cuts per interval
    u = rng.normal(size=n)
    p = dict(T=2.0, k=1.0, c=0.5, tau=2.37, tau2=0.81, ls=-20.0, le=0.0)
    reference = exact_reference(t, u, 2.0, (1.0, 0.5), (2.37, 0.81), hold)
    data = pd.DataFrame({"t": t, "u": u, "y": np.zeros(n)})
    for method in ("kalman", "ekf"):
        predicted = two_delays.predict(p, data, steps=1, hold=hold, method=method)["y"].to_numpy()
        np.testing.assert_allclose(predicted, reference, atol=1e-9, err_msg=method)
    simulated = two_delays.simulate(p, data, method="exact", noise=False, hold=hold)
    np.testing.assert_allclose(simulated.states[0, :, 0], reference, atol=1e-9)
    regular = pd.DataFrame({"t": np.arange(n) * 0.7, "u": u, "y": np.zeros(n)})
    reference = exact_reference(regular["t"].to_numpy(), u, 2.0, (1.0, 0.5), (2.37, 0.81), hold)
    predicted = two_delays.predict(p, regular, steps=1, hold=hold)["y"].to_numpy()
    np.testing.assert_allclose(predicted, reference, atol=1e-9)


def test_the_gradient_in_the_delay_matches_differences(two_delays):
    import jax
    import jax.numpy as jnp
    from greyid.data import prepare_series
    from greyid.filters.api import compiled_filter, filter_inputs, filter_options

    rng = np.random.default_rng(2)
    n = 80
    s = two_delays.structure
    p = dict(T=2.0, k=1.0, c=0.5, tau=2.37, tau2=0.81, ls=-1.0, le=-2.0)
    theta = jnp.asarray(two_delays.parameter_vector(p))
    for times in (np.arange(n) * 0.6, np.cumsum(np.r_[0.0, rng.uniform(0.3, 1.1, n - 1)])):
        data = pd.DataFrame({"t": times, "u": np.repeat(rng.normal(size=n // 4), 4), "y": rng.normal(size=n)})
        for hold in ("zoh", "foh"):
            inputs = filter_inputs(prepare_series(data, s.input_names, s.output_names), hold)
            for method in ("kalman", "ekf"):
                run = compiled_filter(s, filter_options(s, method), keep_outputs=False)
                f = lambda th: run(th, inputs)[0].loglik.sum()  # noqa: E731
                g = np.asarray(jax.grad(f)(theta))
                for name in ("tau", "tau2"):
                    i = s.parameter_names.index(name)
                    eps = 1e-6
                    fd = (f(theta.at[i].add(eps)) - f(theta.at[i].add(-eps))) / (2 * eps)
                    assert g[i] == pytest.approx(float(fd), rel=1e-5, abs=1e-6), (hold, method, name)


def test_a_delay_is_estimated_with_its_standard_error():
    m, truth, data = simulated_delay(2.37, 1.0, 400, 5, 3, 3)
    for name, (init, lower, upper) in dict(T=(1.0, 0.1, 10), k=(0.5, 0, 5), tau=(1.5, 0, 5), ls=(-1, -10, 2),
                                           le=(-1, -10, 2)).items():
        m.set_parameter(name, init=init, lower=lower, upper=upper)
    fit = m.fit(data)
    assert fit.converged
    est, se = fit.params.loc["tau", ["estimate", "std_error"]]
    assert abs(est - 2.37) < 3 * se and se < 0.1
    assert fit.loglik >= m.loglik(truth, data) - 1e-6


def test_delay_errors_name_the_problem():
    with pytest.raises(ModelError, match="negative"):
        first_order("k*delay(u, -1)").structure
    with pytest.raises(ModelError, match="must be an input"):
        first_order("k*delay(x, 1)").structure
    with pytest.raises(ModelError, match="parameters only"):
        first_order("k*delay(u, x)").structure
    m = first_order("k*delay(u, tau)")
    data = pd.DataFrame({"t": np.arange(10.0), "u": np.ones(10), "y": np.zeros(10)})
    p = dict(T=1.0, k=1.0, ls=0.0, le=0.0)
    with pytest.raises(DataError, match="longer than the series"):
        m.loglik({**p, "tau": 20.0}, data)
    with pytest.raises(ModelError, match="must be ≥ 0"):
        m.loglik({**p, "tau": -0.5}, data)
    with pytest.raises(DataError, match="longer than the series"):
        m.simulate({**p, "tau": 20.0}, data)
    m.set_parameter("tau", init=1.0, lower=-1.0, upper=5.0)
    with pytest.raises(ModelError, match="'tau' is the delay of delay\\(u, tau\\); give it a lower bound of 0"):
        m.fit(data.assign(y=np.sin(np.arange(10.0))), init=p)
    bad = greyid.Model("initial")
    bad.add_system("dx = (-x + delay(u, 1))*dt + dw1")
    bad.add_inputs("u")
    bad.add_observation("y = x", variance=1.0)
    bad.set_initial_state(mean={"x": "delay(u, 1)"})
    with pytest.raises(ModelError):
        bad.structure


def test_delays_in_model_files_and_units(tmp_path):
    m = first_order("k*delay(u, tau)")
    m.set_units({"t": "s", "x": "K", "u": "W", "T": "s", "k": "K/J", "tau": "s", "ls": "K/s^0.5",
                 "le": "K^2", "y": "K"})
    assert any("delay(u, tau)" in line and "✓" in line for line in m.check_units())
    path = tmp_path / "delayed.toml"
    m.to_toml(path)
    again = greyid.Model.from_toml(path)
    assert again.structure.delays[0].name == "delay(u, tau)"
    p = dict(T=2.0, k=1.0, tau=0.7, ls=-1.0, le=-1.0)
    data = pd.DataFrame({"t": np.arange(20.0), "u": np.sin(np.arange(20.0)), "y": np.cos(np.arange(20.0))})
    assert again.loglik(p, data) == pytest.approx(m.loglik(p, data), abs=1e-10)
    m.set_units({"t": "h", "x": "K", "u": "W", "T": "h", "k": "K/(W*h)", "tau": "s", "ls": "K/h^0.5",
                 "le": "K^2", "y": "K"})
    with pytest.raises(ModelError, match="time unit"):
        m.check_units()


def test_a_held_inputs_delay_is_searched_in_the_neighbouring_sampling_intervals():
    """The likelihood in τ has a kink at every whole number of sampling intervals (here 2.4) and a local
    optimum on each side; from a start in the wrong interval the fit (and a fleet's member) still ends
    at the better one, found from the middle of the next interval."""
    m, truth, data = simulated_delay(2.37, 0.8, 250, 5, 5, 2)
    for name, (init, lower, upper) in dict(T=(1.0, 0.1, 10), k=(0.5, 0, 5), tau=(3.0, 0, 5), ls=(-1, -10, 2),
                                           le=(-1, -10, 2)).items():
        m.set_parameter(name, init=init, lower=lower, upper=upper)
    good = m.fit(data, init={"tau": 2.0})
    fit = m.fit(data)
    starts = {s["start"]: s["criterion"] for s in fit.starts}
    assert starts["initial values"] < good.loglik - 1.0  # the start's own interval holds the worse optimum
    assert fit.loglik == pytest.approx(good.loglik, abs=1e-6) and fit.values["tau"] == pytest.approx(2.365, abs=1e-3)
    assert starts["tau in the next sampling interval, shorter"] == pytest.approx(good.loglik, abs=1e-6)
    fleet = greyid.fit_many(m, {"a": data, "b": data.iloc[:200]})
    assert fleet.table.loc["a", "loglik"] == pytest.approx(good.loglik, abs=1e-6)


def test_a_delayed_model_gets_its_report_and_uncertainty_bands(tmp_path):
    m, truth, data = simulated_delay(1.3, 0.5, 120, 4, 7, 7)
    m.set_parameter("tau", init=1.0, lower=0.0, upper=5.0)
    fit = m.fit(data, init=truth)
    bands = fit.predict(steps=3, parameter_uncertainty=True, draws=20)
    assert np.all(bands["y_upper"] > bands["y_lower"])
    text = fit.report(tmp_path / "report.html", profile=False)
    section = text[text.find('<section id="identifiability">'):text.find('<section id="validation">')]
    assert "delayed inputs" in section and "plan=" in section


@pytest.mark.parametrize("method", ["kalman", "ekf", "ukf"])
def test_the_gradient_at_a_whole_number_of_sampling_intervals(method):
    """τ = 2 and 1 sampling intervals exactly: the interval is cut into a piece of length 0, whose
    derivative in τ must not be dropped.  With a held input the log-likelihood has a kink there (the
    switch passes an observation): the gradient is the right-sided one; with a ramped (foh) input it
    is smooth, and the gradient is the central difference.  Beside the whole multiples both agree."""
    import jax
    import jax.numpy as jnp
    from greyid.data import prepare_series
    from greyid.filters.api import compiled_filter, filter_inputs, filter_options

    rng = np.random.default_rng(4)
    n, step = 60, 0.6
    # A proper initial covariance: the sigma points' square root of a near-zero P has no usable derivative.
    two_delays = first_order("k*delay(u, tau) + c*delay(u, tau2)", "two_delays_p0")
    two_delays.set_initial_state(mean={"x": 0.0}, covariance=[[0.01]])
    s = two_delays.structure
    data = pd.DataFrame({"t": np.arange(n) * step, "u": np.repeat(rng.normal(size=n // 4), 4),
                         "y": rng.normal(size=n)})
    run = compiled_filter(s, filter_options(s, method), keep_outputs=False)
    for hold in ("zoh", "foh"):
        inputs = filter_inputs(prepare_series(data, s.input_names, s.output_names), hold)
        f = lambda th: run(th, inputs)[0].loglik.sum()  # noqa: E731
        # (Two delays at the same offset within the interval at once are a tie of their cuts, whose
        # order as one of them grows the sort cannot know: not covered.)
        for taus in ((2 * step, step - 0.23), (2 * step + 0.17, step), (2 * step + 0.17, step - 0.23)):
            p = dict(T=2.0, k=1.0, c=0.5, tau=taus[0], tau2=taus[1], ls=-1.0, le=-2.0)
            theta = jnp.asarray(two_delays.parameter_vector(p))
            g = np.asarray(jax.grad(f)(theta))
            whole = taus[0] == 2 * step or taus[1] == step
            for name in ("tau", "tau2"):
                i = s.parameter_names.index(name)
                if hold == "zoh" and whole:
                    eps = 1e-7
                    fd = (f(theta.at[i].add(eps)) - f(theta)) / eps
                    assert g[i] == pytest.approx(float(fd), rel=1e-4, abs=1e-5), (hold, name, taus)
                else:
                    eps = 1e-6
                    fd = (f(theta.at[i].add(eps)) - f(theta.at[i].add(-eps))) / (2 * eps)
                    assert g[i] == pytest.approx(float(fd), rel=1e-5, abs=1e-6), (hold, name, taus)


def test_the_information_of_a_delay_is_continuous_across_whole_sampling_intervals(two_delays):
    """With ramped inputs the likelihood is smooth in τ: its information at τ = 2 intervals is the limit
    of the information just beside it (no jump from a dropped piece derivative)."""
    from greyid import design

    rng = np.random.default_rng(6)
    n, step = 60, 0.6
    plan = pd.DataFrame({"t": np.arange(n) * step, "u": np.repeat(rng.normal(size=n // 4), 4)})
    base = dict(T=2.0, k=1.0, c=0.5, tau2=0.3, ls=-1.0, le=-2.0)
    free = ["T", "k", "tau"]
    at = [design.fisher_information(two_delays, dict(base, tau=2 * step + d), plan, hold="foh", free=free)
          .to_numpy() for d in (-1e-6, 0.0, 1e-6)]
    np.testing.assert_allclose(at[1], 0.5 * (at[0] + at[2]), rtol=1e-4)
    np.testing.assert_allclose(at[0], at[2], rtol=1e-4)


@pytest.fixture(scope="module")
def delayed_series():
    """The one-delay model with bounds, on its regular series and on the same values at irregular times."""
    m, truth, data = simulated_delay(0.37, 0.25, 120, 6, 1, 2)
    for name, value in truth.items():
        m.set_parameter(name, init=value, lower=0.0 if name == "tau" else None, upper=5.0 if name == "tau" else None)
    irregular = data.assign(t=np.cumsum(np.random.default_rng(0).uniform(0.1, 0.4, len(data))))
    return m, truth, {"regular": data, "irregular": irregular}


@pytest.mark.parametrize("sampling", ["regular", "irregular"])
def test_laplace_method_with_delays_is_the_kalman_filter(delayed_series, sampling):
    """Exact transitions cut where the delayed input switches: the Laplace value and its gradient (the delay's
    included) are the Kalman filter's; Euler–Maruyama transitions converge to it as the sub-steps grow."""
    m, truth, sets = delayed_series
    data = sets[sampling]
    exact, laplace = m.likelihood(data), m.likelihood(data, method="laplace")
    x = np.array([truth[n] for n in exact.names])
    (value, gradient), (l_value, l_gradient) = exact.value_and_grad(x), laplace.value_and_grad(x)
    assert l_value == pytest.approx(value, rel=1e-11)
    np.testing.assert_allclose(l_gradient, gradient, rtol=1e-8, atol=1e-8)
    errors = [abs(m.loglik(truth, data, method="laplace", scheme="euler", substeps=s) + value) for s in (2, 8, 32)]
    assert errors[0] > 3 * errors[1] and errors[1] > 3 * errors[2]  # first order: a quarter per 4× the sub-steps
    with pytest.raises(ModelError, match="ctsmtmb.*does not take delay"):
        m.loglik(truth, data, method="laplace", scheme="ctsmtmb")


@pytest.mark.parametrize("sampling", ["regular", "irregular"])
def test_particle_and_ensemble_filters_with_delays(delayed_series, sampling):
    from greyid.estimate.approximations import particle_loglik

    m, truth, sets = delayed_series
    data = sets[sampling]
    reference = m.loglik(truth, data)
    estimate = particle_loglik(m, truth, data, particles=2000, seed=3)
    assert abs(estimate.loglik - reference) < 3 * estimate.std_error
    # Without the delay's cuts (τ = 0 is another model) the value is another.
    assert abs(particle_loglik(m, dict(truth, tau=0.0), data, particles=2000, seed=3).loglik - reference) > 2.0
    ensemble = np.mean([m.loglik(truth, data, method="enkf", particles=5000, seed=s) for s in range(3)])
    assert ensemble == pytest.approx(reference, abs=0.3)


def test_particle_filter_sub_steps_with_delays():
    """A model that is not linear (a negligible cubic term) takes Euler–Maruyama sub-steps, each cut where the
    delayed input switches: the particle estimate is within its error of the Laplace value of the same Euler
    chain (exact for it, the chain being linear and Gaussian up to the cubic term), and both near the exact
    filter of the linear model."""
    from greyid.estimate.approximations import particle_loglik

    m, truth, data = simulated_delay(0.37, 0.25, 84, 6, 1, 2)
    cubic = first_order("k*delay(u, tau) - q*x**3")
    cubic.set_initial_state(mean={"x": 0.0}, covariance=[[0.01]])
    params = dict(truth, q=1e-9)
    chain = cubic.loglik(params, data, method="laplace", scheme="euler", substeps=16)
    estimate = particle_loglik(cubic, params, data, particles=2000, seed=1, substeps=16, proposal="ekf")
    assert abs(estimate.loglik - chain) < 3 * estimate.std_error + 1e-3
    assert abs(chain - m.loglik(truth, data)) < 0.2
