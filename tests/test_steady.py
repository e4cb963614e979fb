"""The steady-state form of the exact Kalman filter on regular series (filters/steady.py).

References: the Riccati recursion iterated to convergence, the mean recursion
step by step, and the ordinary filter (steady form switched off) on the same
series — with missing values, an irregular interval, both holds, both covariance
forms and correlated output noise.  Long series are made long relative to
chunks made short for the tests; shorter ones (one switch after their first
rows) are a few hundred rows, as the public likelihood takes them.
"""

import collections
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from conftest import random_linear_model_spec, random_linear_parameters
from greyid.estimate.criteria import step_criterion
from greyid.filters import steady
from greyid.filters.api import filter_options, prepare_datasets, sampling_intervals
from greyid.filters.driver import make_filter, make_summed_filter
from test_correlated_noise import TRUE as CORRELATED_TRUE, correlated_model

N_ROWS = 1400


class SteadyCounts(collections.Counter):
    """``["steady"]``: the calls of the steady-state form that ran (not only traced), counted by a host
    callback in the programs traced until `stop()`; ``["traced"]``: the calls traced, always."""

    counting = True

    def stop(self):
        """Trace no callback from now on, and forget the programs traced with one: JAX's cache of compiled
        programs keeps no program with a host callback, so a derivative program traced with one would be
        compiled again on every run of the tests.  Where the steady form runs is decided on the filter's
        values, the same in a derivative's program as in the value's, so a test counts it on the value and
        checks that its derivatives' programs trace the steady form (``["traced"]``)."""
        self.counting = False
        jax.clear_caches()


def count_steady_rows(monkeypatch):
    """A [`SteadyCounts`] of the steady-state form's calls."""
    counts = SteadyCounts()
    means = steady.steady_means  # what steady_rows and a sum of the rest both run

    def counted(*args, **kwargs):
        counts.update(["traced"])
        if counts.counting:
            jax.debug.callback(lambda: counts.update(["steady"]))
        return means(*args, **kwargs)

    monkeypatch.setattr(steady, "steady_means", counted)
    return counts


@pytest.fixture
def short_chunks(monkeypatch):
    """Chunks of 64 rows from 512 rows on; counts the chunks run in the steady state."""
    monkeypatch.setattr(steady, "MIN_ROWS", 512)
    monkeypatch.setattr(steady, "CHUNK", 64)
    return count_steady_rows(monkeypatch)


def step_by_step(monkeypatch):
    monkeypatch.setattr(steady, "MIN_ROWS", 10**12)


def test_riccati_solution_is_the_recursion_s_limit():
    rng = np.random.default_rng(0)
    n, m = 3, 2
    Phi = rng.normal(size=(n, n))
    Phi *= 0.97 / np.max(np.abs(np.linalg.eigvals(Phi)))
    G = rng.normal(size=(n, n))
    Q, C = G @ G.T * 0.1, rng.normal(size=(m, n))
    W = rng.normal(size=(m, m))
    S = W @ W.T * 0.05 + 0.01 * np.eye(m)
    P = Q.copy()
    for _ in range(20000):
        P = Phi @ P @ Phi.T - Phi @ P @ C.T @ np.linalg.solve(C @ P @ C.T + S, C @ P @ Phi.T) + Q
    solution = np.asarray(steady.riccati_solution(*map(jnp.asarray, (Phi, Q, C, S))))
    np.testing.assert_allclose(solution, P, rtol=1e-11, atol=1e-14)


def test_riccati_step_tangent_is_the_step_s_derivative():
    """The written-out derivative of the Riccati step in Φ, Λ, C and S (P held) equals JAX's derivative of
    the step written with a solve, and F is the closed loop Φ(I − KC)."""
    rng = np.random.default_rng(4)
    n, m = 3, 2

    def spd(k, scale):
        G = rng.normal(size=(k, k))
        return jnp.asarray(G @ G.T * scale + 0.01 * np.eye(k))

    P, Lam, S = spd(n, 1.0), spd(n, 0.1), spd(m, 0.05)
    Phi, C = jnp.asarray(rng.normal(size=(n, n)) * 0.5), jnp.asarray(rng.normal(size=(m, n)))
    tangents = (jnp.asarray(rng.normal(size=(n, n))), spd(n, 0.3), jnp.asarray(rng.normal(size=(m, n))),
                spd(m, 0.2))

    def step(Phi, Lam, C, S):
        return Phi @ P @ Phi.T - Phi @ P @ C.T @ jnp.linalg.solve(C @ P @ C.T + S, C @ P @ Phi.T) + Lam

    _, expected = jax.jvp(step, (Phi, Lam, C, S), tangents)
    tangent, F = steady.riccati_step_tangent(P, Phi, C, S, *tangents)
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(expected), rtol=1e-11, atol=1e-12)
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + S)
    np.testing.assert_allclose(np.asarray(F), np.asarray(Phi @ (np.eye(n) - K @ C)), rtol=1e-12, atol=1e-13)


def test_smith_sum_solves_the_stein_equation():
    """The doubling sum Σ F^k X (F^k)ᵀ over 2^SMITH_DOUBLINGS terms (a loop of doublings) is the solution of
    Y = F Y Fᵀ + X by the Kronecker form where F's powers vanish, with F^(2^d) beside it; and its derivatives of
    first and second order and in reverse mode are the Kronecker solution's."""
    rng = np.random.default_rng(3)
    n = 3
    F0 = rng.normal(size=(n, n))
    F0 *= 0.8 / np.max(np.abs(np.linalg.eigvals(F0)))
    G = rng.normal(size=(n, n))
    X0, W = G @ G.T, rng.normal(size=(n, n))

    def kronecker(F, X):
        return jnp.linalg.solve(jnp.eye(n * n) - jnp.kron(F, F), X.reshape(-1)).reshape(n, n)

    Y, power = steady.smith_sum(jnp.asarray(X0), jnp.asarray(F0))
    np.testing.assert_allclose(np.asarray(Y), np.asarray(kronecker(jnp.asarray(F0), jnp.asarray(X0))),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(power), np.linalg.matrix_power(F0, 2 ** steady.SMITH_DOUBLINGS),
                               atol=1e-14)

    def summary(solve, a):  # F and X both depend on a
        F, X = jnp.asarray(F0) * (1 + a[0]) + a[1] * jnp.eye(n) * 0.1, jnp.asarray(X0) * a[2] + a[0]
        return jnp.sum(jnp.asarray(W) * solve(F, X))

    a = jnp.asarray([0.02, 0.3, 1.5])
    for symmetric in (True, False):
        def fast(a, symmetric=symmetric):
            return summary(lambda F, X: steady.smith_sum(X, F, symmetric)[0], a)

        def slow(a):
            return summary(kronecker, a)

        for derivative in (jax.jacfwd, jax.grad, lambda f: jax.jacfwd(jax.jacfwd(f))):
            np.testing.assert_allclose(jax.jit(derivative(fast))(a), jax.jit(derivative(slow))(a), rtol=1e-9)


def loop_recursion(F, v, start):
    """x_r = F x_{r−1} + v_r one row after the other (a scan: a Python loop over 1280 rows took
    100 s under the derivatives)."""
    def step(x, v_r):
        x = F @ x + v_r
        return x, x

    return jax.lax.scan(step, start, v)[1]


RECURSIONS = {"blocks": lambda F, v, start: steady.linear_recursion(steady.recursion(F), v, start),
              "short": steady.short_recursion, "doubling": steady.doubling_recursion}


@pytest.mark.parametrize("kind, rows", [("blocks", 5 * steady.BLOCK), ("blocks", 3 * steady.BLOCK - 7),
                                        ("blocks", 40 * steady.BLOCK), ("short", 5 * steady.BLOCK),
                                        ("short", 3 * steady.BLOCK - 7), ("short", 1),
                                        ("doubling", 5 * steady.BLOCK), ("doubling", 3 * steady.BLOCK - 7),
                                        ("doubling", 1), ("doubling", 2)])
def test_mean_recursions_are_the_loop(kind, rows):
    """Blocks carried by powers of F^BLOCK (up to a chunk's blocks) or by a scan (more), or by two
    triangular solves (short), or by doubling, a partial last block; and the derivatives of first and second order (the
    recursions' own rules) and in reverse mode (the rules transposed) equal the loop's."""
    recursion = RECURSIONS[kind]
    rng = np.random.default_rng(1)
    n = 3
    F = jnp.asarray(rng.normal(size=(n, n)) * 0.4)
    v, start = jnp.asarray(rng.normal(size=(rows, n))), jnp.asarray(rng.normal(size=n))
    np.testing.assert_allclose(np.asarray(recursion(F, v, start)), np.asarray(loop_recursion(F, v, start)),
                               rtol=1e-12, atol=1e-12)
    weights = jnp.asarray(rng.normal(size=(rows, n)))

    def summary(recursion, a):  # F, v and start all depend on a
        return jnp.sum(weights * recursion(F * (1 + a[0]) + a[1], v * a[2] + a[0], start * a[1]) ** 2)

    a = jnp.asarray([0.1, 0.05, 1.2])
    def fast(a):
        return summary(recursion, a)
    def slow(a):
        return summary(loop_recursion, a)
    for derivative, rtol in ((jax.jacfwd, 1e-10), (jax.grad, 1e-10), (lambda f: jax.jacfwd(jax.jacfwd(f)), 1e-9)):
        # Compiled: op by op, the derivatives of the recursions' rules took seconds each.
        np.testing.assert_allclose(jax.jit(derivative(fast))(a), jax.jit(derivative(slow))(a), rtol=rtol)


def linear_series(seed=2, missing=True, gap=True):
    """A regular series of the random linear model, with a stretch of missing outputs and a gap."""
    rng = np.random.default_rng(seed)
    model = random_linear_model_spec()
    params, _ = random_linear_parameters(rng)
    t = np.arange(N_ROWS) * 0.5
    if gap:
        t[900:] += 0.25  # one interval of 0.75
    frame = pd.DataFrame({"t": t, "u1": rng.normal(size=N_ROWS), "u2": np.sin(t / 7)})
    simulated = model.simulate(params, frame, method="exact", seed=seed).outputs[0]
    frame["y1"], frame["y2"] = simulated[:, 0], simulated[:, 1]
    if missing:
        frame.loc[700:705, "y1"] = np.nan
        frame.loc[650, "y2"] = np.nan
    return params, frame


@pytest.mark.parametrize("hold, form", [("zoh", "sqrt"), ("foh", "plain")])
def test_steady_state_filter_equals_the_ordinary_filter(monkeypatch, short_chunks, hold, form):
    params, frame = linear_series()
    fast = random_linear_model_spec().filter(params, frame, hold=hold, form=form)
    assert short_chunks["steady"] >= 10  # most chunks ran in the steady state
    step_by_step(monkeypatch)
    exact = random_linear_model_spec().filter(params, frame, hold=hold, form=form)
    assert np.isclose(fast.loglik_terms.sum(), exact.loglik_terms.sum(), rtol=0, atol=1e-8)
    np.testing.assert_allclose(fast.loglik_terms, exact.loglik_terms, atol=1e-10)
    np.testing.assert_allclose(fast.filtered, exact.filtered, atol=1e-9)
    np.testing.assert_allclose(fast.predicted, exact.predicted, atol=1e-9)
    np.testing.assert_allclose(fast.filtered_cov, exact.filtered_cov, atol=1e-12)
    np.testing.assert_allclose(fast.innovation_cov, exact.innovation_cov, atol=1e-12)
    np.testing.assert_allclose(fast.innovations.fillna(0), exact.innovations.fillna(0), atol=1e-9)


def summed_criterion(model, params, frame, robust=None):
    structure = model.structure
    theta = model.parameter_vector(params)
    (_, inputs), = prepare_datasets(structure, theta, frame, "t", "zoh", None)
    run = make_summed_filter(structure, filter_options(structure, None),
                             lambda terms: step_criterion(terms, robust))
    return jnp.asarray(theta), lambda th: run(th, inputs)


@pytest.mark.slow
def test_steady_state_derivatives_equal_the_ordinary_filter_s(monkeypatch, short_chunks):
    params, frame = linear_series(seed=4)
    theta, fast = summed_criterion(random_linear_model_spec(), params, frame)
    fast(theta)
    assert short_chunks["steady"] >= 10
    short_chunks.stop()
    traced = short_chunks["traced"]
    fast_value, fast_gradient = jax.jit(jax.value_and_grad(fast))(theta)
    fast_forward = jax.jit(jax.jacfwd(fast))(theta)
    assert short_chunks["traced"] > traced
    step_by_step(monkeypatch)
    _, exact = summed_criterion(random_linear_model_spec(), params, frame)
    value, gradient = jax.jit(jax.value_and_grad(exact))(theta)
    assert abs(float(fast_value - value)) < 1e-8
    scale = np.max(np.abs(gradient))
    np.testing.assert_allclose(fast_gradient, gradient, atol=1e-8 * scale)
    np.testing.assert_allclose(fast_forward, gradient, atol=1e-8 * scale)


def test_steady_state_hessian_equals_the_ordinary_filter_s(monkeypatch, short_chunks):
    """Forward over forward, as a long fit's final Hessian (chunks that the blocks do not divide, a shorter
    last chunk of padding rows only)."""
    monkeypatch.setattr(steady, "CHUNK", 100)
    params, frame = linear_series(seed=7)
    theta, fast = summed_criterion(random_linear_model_spec(), params, frame)
    directions = jnp.asarray(np.random.default_rng(7).normal(size=(2, len(theta))))

    def hessian_rows(f):  # rows u·H, forward over forward
        return jax.jit(jax.vmap(lambda u: jax.jvp(jax.jacfwd(f), (theta,), (u,))[1]))(directions)

    fast(theta)
    assert short_chunks["steady"] >= 5
    short_chunks.stop()
    traced = short_chunks["traced"]
    rows = hessian_rows(fast)
    assert short_chunks["traced"] > traced
    step_by_step(monkeypatch)
    _, exact = summed_criterion(random_linear_model_spec(), params, frame)
    expected = hessian_rows(exact)
    np.testing.assert_allclose(rows, expected, atol=1e-8 * np.max(np.abs(expected)))


def test_chunks_with_a_tail_and_padding_rows(monkeypatch, short_chunks):
    """Chunks of 100 rows: partial blocks in each, a last chunk of 8 rows (the length bucket's padding)."""
    monkeypatch.setattr(steady, "CHUNK", 100)
    params, frame = linear_series(seed=8)
    fast = random_linear_model_spec().filter(params, frame)
    assert short_chunks["steady"] >= 5
    step_by_step(monkeypatch)
    exact = random_linear_model_spec().filter(params, frame)
    np.testing.assert_allclose(fast.loglik_terms, exact.loglik_terms, atol=1e-10)
    np.testing.assert_allclose(fast.filtered, exact.filtered, atol=1e-9)
    np.testing.assert_allclose(fast.innovations.fillna(0), exact.innovations.fillna(0), atol=1e-9)


def test_correlated_noise_and_robust_criterion(monkeypatch, short_chunks):
    rng = np.random.default_rng(5)
    t = np.arange(N_ROWS) * 0.4
    frame = pd.DataFrame({"t": t, "u": rng.normal(size=N_ROWS)})
    simulated = correlated_model().simulate(CORRELATED_TRUE, frame, method="exact", seed=5).outputs[0]
    frame["y1"], frame["y2"] = simulated[:, 0], simulated[:, 1]
    results = []
    for robust in (None, ("huber", 1.5)):
        theta, fast = summed_criterion(correlated_model(), CORRELATED_TRUE, frame, robust)
        results.append(float(fast(theta)))
    assert short_chunks["steady"] >= 20
    step_by_step(monkeypatch)
    for robust, value in zip((None, ("huber", 1.5)), results):
        theta, exact = summed_criterion(correlated_model(), CORRELATED_TRUE, frame, robust)
        assert abs(value - float(exact(theta))) < 1e-8


def test_no_steady_state_without_one(monkeypatch, short_chunks):
    """A random walk nobody observes has no steady state: every chunk runs step by step."""
    import greyid

    model = greyid.Model("unobserved_walk")
    model.add_system("dx1 = -a*x1*dt + s*dw1", "dx2 = 0*dt + s*dw2")
    model.add_observation("y = x1", variance="r")
    model.set_initial_state(mean={"x1": 0.0, "x2": 0.0}, covariance=[[1.0, 0.0], [0.0, 1.0]])
    params = dict(a=0.5, s=0.3, r=0.1)
    frame = pd.DataFrame({"t": np.arange(N_ROWS) * 0.5,
                          "y": np.random.default_rng(6).normal(size=N_ROWS)})
    value = model.loglik(params, frame)
    assert short_chunks["steady"] == 0
    step_by_step(monkeypatch)
    other = greyid.Model.from_dict(model.to_dict())
    assert other.loglik(params, frame) == pytest.approx(value, abs=1e-9)


def shorter_series(seed, rows=400, missing_at=None):
    """A regular series of the random linear model, a few hundred rows (a shorter series)."""
    rng = np.random.default_rng(seed)
    model = random_linear_model_spec()
    params, _ = random_linear_parameters(rng)
    t = np.arange(rows) * 0.5
    frame = pd.DataFrame({"t": t, "u1": rng.normal(size=rows), "u2": np.sin(t / 7)})
    simulated = model.simulate(params, frame, method="exact", seed=seed).outputs[0]
    frame["y1"], frame["y2"] = simulated[:, 0], simulated[:, 1]
    if missing_at is not None:
        frame.loc[missing_at, "y1"] = np.nan
    return model, params, frame


@pytest.fixture
def counted_steady(monkeypatch):
    return count_steady_rows(monkeypatch)


def shorter_filters(model, params, frame, hold="zoh", form="sqrt"):
    """The filter with and without the switch after the first rows, at θ, keeping every output."""
    structure = model.structure
    theta = jnp.asarray(model.parameter_vector(params))
    (_, inputs), = prepare_datasets(structure, np.asarray(theta), frame, "t", hold, None)
    options = filter_options(structure, None, form=form)
    switching = dataclasses.replace(options, steady_state=True)
    return (lambda th: make_filter(structure, switching, True)(th, inputs),
            lambda th: make_filter(structure, options, True)(th, inputs), theta)


@pytest.mark.parametrize("hold, form", [("zoh", "sqrt"), ("foh", "plain")])
def test_shorter_series_switch_after_their_first_rows(counted_steady, hold, form):
    """A few hundred regular rows: the rows after HEAD at once in the steady state, every output as the
    ordinary filter's — per-row terms, states, covariances — and the log-likelihood to 1e-9."""
    model, params, frame = shorter_series(seed=21)
    fast, exact, theta = shorter_filters(model, params, frame, hold, form)
    (fast_terms, fast_out), (terms, out) = fast(theta), exact(theta)
    assert counted_steady["steady"] == 1
    assert abs(float(fast_terms.loglik.sum() - terms.loglik.sum())) < 1e-9
    np.testing.assert_allclose(fast_terms.loglik, terms.loglik, atol=1e-10)
    rows = len(frame)  # the rows padding the series to its length bucket carry nothing used
    for name in ("filtered_mean", "output_prediction", "innovation"):
        np.testing.assert_allclose(getattr(fast_out, name)[:rows], getattr(out, name)[:rows], atol=1e-9)
    for name in ("predicted_cov", "filtered_cov", "innovation_cov"):
        np.testing.assert_allclose(getattr(fast_out, name)[:rows], getattr(out, name)[:rows], atol=1e-10)


@pytest.mark.slow
def test_shorter_series_derivatives_equal_the_ordinary_filter_s(counted_steady):
    """Forward and reverse mode through the switch: the gradient of the ordinary filter to 1e-8 of its
    scale (the carried covariance's derivatives stand for P∞'s), the Hessian to 1e-6."""
    model, params, frame = shorter_series(seed=24)
    fast, exact, theta = shorter_filters(model, params, frame)

    def total(run):
        return lambda th: -jnp.sum(run(th)[0].loglik)

    directions = jnp.asarray(np.random.default_rng(24).normal(size=(2, len(theta))))
    total(fast)(theta)
    assert counted_steady["steady"] == 1
    counted_steady.stop()
    traced = counted_steady["traced"]
    # The forward gradient comes with the Hessian's rows (forward over forward): one program, not two.
    forward, rows = jax.jit(jax.vmap(lambda u: jax.jvp(jax.jacfwd(total(fast)), (theta,), (u,))))(directions)
    assert counted_steady["traced"] > traced
    traced = counted_steady["traced"]
    reverse, expected = jax.jit(jax.grad(total(fast)))(theta), jax.jit(jax.grad(total(exact)))(theta)
    assert counted_steady["traced"] > traced
    scale = np.max(np.abs(expected))
    np.testing.assert_allclose(forward[0], expected, atol=1e-8 * scale)
    np.testing.assert_allclose(reverse, expected, atol=1e-8 * scale)
    _, expected_rows = jax.jit(jax.vmap(lambda u: jax.jvp(jax.jacfwd(total(exact)), (theta,), (u,))))(directions)
    np.testing.assert_allclose(rows, expected_rows, atol=1e-6 * np.max(np.abs(expected_rows)))


def test_shorter_series_with_a_missing_value_or_no_steady_state_step_through(counted_steady):
    """A missing output after the first rows, or a filter with no steady state: every row step by step,
    the same values as the ordinary filter's exactly."""
    model, params, frame = shorter_series(seed=23, missing_at=200)
    fast, exact, theta = shorter_filters(model, params, frame)
    assert float(fast(theta)[0].loglik.sum()) == float(exact(theta)[0].loglik.sum())
    assert counted_steady["steady"] == 0

    fast, exact, theta = shorter_filters(*unobserved_walk())
    assert float(fast(theta)[0].loglik.sum()) == float(exact(theta)[0].loglik.sum())
    assert counted_steady["steady"] == 0


def unobserved_walk():
    """A model without a steady state (a random walk nothing observes), its parameters and 300 rows."""
    import greyid

    walk = greyid.Model("unobserved_walk")
    walk.add_system("dx1 = -a*x1*dt + s*dw1", "dx2 = 0*dt + s*dw2")
    walk.add_observation("y = x1", variance="r")
    walk.set_initial_state(mean={"x1": 0.0, "x2": 0.0}, covariance=[[1.0, 0.0], [0.0, 1.0]])
    frame = pd.DataFrame({"t": np.arange(300) * 0.5, "y": np.random.default_rng(6).normal(size=300)})
    return walk, dict(a=0.5, s=0.3, r=0.1), frame


def forward_sums(model, params, frame):
    """The summed log-likelihood of a shorter series with the steady state, differentiated forward only (a
    fit's Hessian program: the loop that tests until its filter settles), and the ordinary filter's."""
    structure = model.structure
    theta = model.parameter_vector(params)
    (_, inputs), = prepare_datasets(structure, theta, frame, "t", "zoh", None)
    options = filter_options(structure, None)
    switching = make_summed_filter(structure, dataclasses.replace(options, steady_state=True),
                                   lambda terms: step_criterion(terms, None), forward_only=True)
    ordinary = make_summed_filter(structure, options, lambda terms: step_criterion(terms, None))
    return jnp.asarray(theta), lambda th: switching(th, inputs), lambda th: ordinary(th, inputs)


@pytest.mark.parametrize("missing_at", [None, 200])
@pytest.mark.slow
def test_forward_sums_switch_where_the_filter_settles(counted_steady, missing_at):
    """The loop stops where the filter has settled and the later rows are regular and observed — after
    a missing value at row 200, at the next test after it, where the single test after HEAD rows steps
    through every row — and the sum equals the ordinary filter's to 1e-9, its forward gradient to 1e-8
    of its scale and rows of its Hessian (forward over forward, as a fit's) to 1e-6."""
    model, params, frame = shorter_series(seed=25, missing_at=missing_at)
    theta, fast, exact = forward_sums(model, params, frame)
    value, expected = float(fast(theta)), float(exact(theta))
    assert counted_steady["steady"] == 1
    assert abs(value - expected) < 1e-9
    counted_steady.stop()
    traced = counted_steady["traced"]
    directions = jnp.asarray(np.random.default_rng(25).normal(size=(2, len(theta))))

    def gradient_and_rows(f):  # the forward gradient comes with the Hessian's rows: one program
        gradients, rows = jax.jit(jax.vmap(lambda u: jax.jvp(jax.jacfwd(f), (theta,), (u,))))(directions)
        return gradients[0], rows

    (gradient, rows), (expected_gradient, expected_rows) = gradient_and_rows(fast), gradient_and_rows(exact)
    assert counted_steady["traced"] > traced
    scale = np.max(np.abs(expected_gradient))
    np.testing.assert_allclose(gradient, expected_gradient, atol=1e-8 * scale)
    np.testing.assert_allclose(rows, expected_rows, atol=1e-6 * np.max(np.abs(expected_rows)))


def test_forward_sums_without_a_steady_state_step_through(counted_steady):
    """A filter that never settles (a mode neither stable nor observed): every row step by step, the
    ordinary filter's value exactly."""
    theta, fast, exact = forward_sums(*unobserved_walk())
    assert float(fast(theta)) == float(exact(theta))
    assert counted_steady["steady"] == 0


def test_sampling_intervals_merge_rounding_only():
    t = np.arange(300_000) / 3.0
    dt = np.concatenate([[0.0], np.diff(t)])
    assert len(np.unique(np.diff(t))) > 1  # the stored times differ in their last digits
    merged = sampling_intervals(dt, t)
    assert set(np.unique(merged)) == {0.0, np.unique(merged)[1]}
    assert abs(np.unique(merged)[1] - 1 / 3) < 1e-10
    steadily = np.cumsum(np.linspace(1.0, 1.0 + 1e-6, 1000))  # intervals that really vary
    dt2 = np.concatenate([[0.0], np.diff(steadily)])
    assert len(np.unique(sampling_intervals(dt2, steadily))) > 500
