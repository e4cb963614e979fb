"""Convergence orders of the simulation schemes, exact sampling and reproducibility."""

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.simulate import make_integrator

MU, SIGMA, X0, T = 1.0, 0.5, 1.0, 1.0


@pytest.fixture(scope="module")
def gbm():
    m = greyid.Model("gbm")
    m.add_system("dx = mu*x*dt + sigma*x*dw1")
    m.add_observation("y = x", variance="0.01")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[1e-6]])
    return m


def errors(model, method, calculus, exact, paths=4000, fine=2**9, levels=(3, 4, 5, 6, 7)):
    """Strong and weak errors at T against the exact solution on the same Brownian paths."""
    s = model.structure
    theta = jnp.asarray(model.parameter_vector({"mu": MU, "sigma": SIGMA}))
    key = jax.random.PRNGKey(0)
    dW = jax.random.normal(key, (paths, fine, 1)) * jnp.sqrt(T / fine)
    W_T = np.asarray(dW.sum(axis=(1, 2)))
    x_exact = exact(W_T)
    integ = jax.jit(jax.vmap(make_integrator(s.drift, s.diffusion, method, calculus), in_axes=(None, 0, None, None, 0)))
    hs, strong, weak = [], [], []
    for level in levels:
        steps = 2**level
        coarse = dW.reshape(paths, steps, fine // steps, 1).sum(axis=2)
        times = jnp.linspace(0, T, steps + 1)
        x = np.asarray(integ(theta, jnp.full((paths, 1), X0), times, jnp.zeros((steps + 1, 0)), coarse))[:, -1, 0]
        hs.append(T / steps)
        strong.append(np.mean(np.abs(x - x_exact)))
        weak.append(abs(np.mean(x - x_exact)))
    def slope(e):
        return np.polyfit(np.log(hs), np.log(e), 1)[0]
    return slope(strong), slope(weak), strong, weak


def ito_solution(W):
    return X0 * np.exp((MU - 0.5 * SIGMA**2) * T + SIGMA * W)


def stratonovich_solution(W):
    return X0 * np.exp(MU * T + SIGMA * W)


def test_euler_strong_order_half_weak_order_one(gbm):
    strong, weak, *_ = errors(gbm, "euler", "ito", ito_solution)
    assert 0.35 < strong < 0.7
    assert 0.8 < weak < 1.25


def test_milstein_strong_order_one(gbm):
    strong, *_ = errors(gbm, "milstein", "ito", ito_solution)
    assert 0.85 < strong < 1.2


def test_heun_converges_to_stratonovich_solution(gbm):
    strong, _, err, _ = errors(gbm, "heun", "stratonovich", stratonovich_solution)
    assert strong > 0.8 and err[-1] < 0.01
    # Read as an Itô equation, the Heun scheme gets the corrected drift (2.48) and
    # converges to the Itô solution instead.
    strong_ito, _, err_ito, _ = errors(gbm, "heun", "ito", ito_solution)
    assert strong_ito > 0.8 and err_ito[-1] < 0.01
    # ... and plain Euler on the Stratonovich reading converges to its solution too.
    _, _, err_e, _ = errors(gbm, "euler", "stratonovich", stratonovich_solution)
    assert err_e[-1] < 0.1


@pytest.fixture(scope="module")
def ou():
    m = greyid.Model("ou_input")
    m.add_system("dx = (-a*x + b*u)*dt + s*dw1")
    m.add_inputs("u")
    m.add_observation("y = x", variance="r")
    m.set_initial_state(mean={"x": 1.0}, covariance=[[0.0001]])
    return m


@pytest.mark.parametrize("method", ["exact", "euler", "milstein", "heun"])
def test_simulated_moments_match_the_discretized_distribution(ou, method):
    params = dict(a=1.5, b=2.0, s=0.8, r=0.04)
    df = pd.DataFrame({"t": [0.0, 0.5, 1.0], "u": [1.0, 1.0, 1.0]})
    sim = ou.simulate(params, df, n_paths=20000, method=method, seed=4, substeps=50)
    a, b, s = 1.5, 2.0, 0.8
    tau = 1.0
    mean = np.exp(-a * tau) * 1.0 + b / a * (1 - np.exp(-a * tau))
    var = np.exp(-2 * a * tau) * 1e-4 + s**2 / (2 * a) * (1 - np.exp(-2 * a * tau))
    x = sim.states[:, -1, 0]
    se = np.sqrt(var / len(x))
    assert abs(x.mean() - mean) < 4 * se + (0.01 if method != "exact" else 0)
    assert x.var() == pytest.approx(var, rel=0.05)
    y = sim.outputs[:, -1, 0]
    assert y.var() == pytest.approx(var + 0.04, rel=0.05)


def test_simulation_is_seeded_and_reproducible(ou):
    params = dict(a=1.5, b=2.0, s=0.8, r=0.04)
    df = pd.DataFrame({"t": np.arange(10.0), "u": np.ones(10)})
    a = ou.simulate(params, df, n_paths=3, seed=1)
    b = ou.simulate(params, df, n_paths=3, seed=1)
    c = ou.simulate(params, df, n_paths=3, seed=2)
    np.testing.assert_array_equal(a.states, b.states)
    assert not np.allclose(a.states, c.states)
    frame = a.frame(2)
    assert list(frame.columns) == ["t", "u", "x", "y"]
    assert len(a.to_frame()) == 30


def test_simulated_data_have_white_innovations(building):
    model, params, data = building
    sim = model.simulate(params, data, n_paths=1, method="exact", seed=11)
    res = model.filter(params, sim.frame(0))
    z = res.standardized_innovations["yTi"].to_numpy()
    assert abs(z.mean()) < 0.1 and abs(z.std() - 1) < 0.08
    assert abs(np.corrcoef(z[1:], z[:-1])[0, 1]) < 0.1


def test_a_simulation_too_large_for_memory_is_refused_before_any_work():
    """10⁹ paths would abort the process inside XLA; greyid refuses them with the memory they need."""
    import subprocess
    import sys
    import time
    from pathlib import Path

    from greyid.simulate.simulate import check_memory

    with pytest.raises(greyid.ModelError, match="GB"):
        check_memory(10**9, 10_000, 4, 1_000, 6)
    check_memory(10, 100, 4, 100, 6)  # small: fine
    model = Path(__file__).resolve().parents[1] / "src" / "greyid" / "datasets" / "building.toml"
    started = time.time()
    result = subprocess.run([sys.executable, "-m", "greyid", "simulate", str(model), "--paths", "1000000000"],
                            capture_output=True, text=True)
    assert result.returncode == 2 and "GB" in result.stderr and "Traceback" not in result.stderr, result.stderr
    assert time.time() - started < 60
