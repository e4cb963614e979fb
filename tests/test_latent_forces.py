"""Latent forces: Gaussian-process kernels as linear SDEs, against dense Gaussian-process likelihoods computed
here from the kernels' closed forms on irregular samples."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.special import ive
from scipy.stats import multivariate_normal

import greyid
from greyid.cli import main
from greyid.model.kernels import Named, periodic_truncation_error

RNG = np.random.default_rng(0)
TIMES = np.sort(RNG.uniform(0.0, 20.0, 40))  # irregular sampling
VALUES = np.sin(TIMES) + 0.1 * RNG.normal(size=40)
DATA = pd.DataFrame({"t": TIMES, "y": VALUES})
LAG = TIMES[:, None] - TIMES[None, :]


def matern(nu, s, length, lag=LAG):
    a = np.abs(lag)
    if nu == "12":
        return s**2 * np.exp(-a / length)
    if nu == "32":
        r = np.sqrt(3) * a / length
        return s**2 * (1 + r) * np.exp(-r)
    r = np.sqrt(5) * a / length
    return s**2 * (1 + r + r**2 / 3) * np.exp(-r)


def periodic(s, period, w, order=None, lag=LAG):
    """The exact kernel σ² exp(−2 sin²(πτ/p)/w²), or its cosine series to ``order`` (SciPy's Bessel functions)."""
    if order is None:
        return s**2 * np.exp(-2 * np.sin(np.pi * lag / period) ** 2 / w**2)
    x = w**-2.0
    weights = [ive(0, x)] + [2 * ive(j, x) for j in range(1, order + 1)]
    return s**2 * sum(q * np.cos(j * 2 * np.pi / period * lag) for j, q in enumerate(weights))


def dense(kernel_matrix, noise=0.01):
    return multivariate_normal(np.zeros(len(TIMES)), kernel_matrix + noise * np.eye(len(TIMES))).logpdf(VALUES)


def gp_model(kernel, **hyper):
    m = greyid.Model("gp").add_latent_force("f", kernel=kernel, **hyper)
    m.add_observation("y = f", variance="r")
    used = {value for _, value in m._latent_forces["f"].hyperparameters()}
    for name in ("lf", "pf", "wf", "l2"):
        if name in used:
            m.set_parameter(name, init=1.0, lower=0.01, upper=100.0)
    return m


@pytest.mark.parametrize("nu", ["12", "32", "52"])
def test_matern_forces_give_the_dense_gaussian_process_likelihood(nu):
    """A Matérn force observed with noise on an irregular grid: the Kalman filter of its SDE equals the dense
    GP likelihood with the kernel's covariance matrix to 1e-10 relative (the state-space form is exact)."""
    m = gp_model(f"matern{nu}", scale="sf", lengthscale="lf")
    assert m.structure.kind == "lti"
    params = dict(sf=0.8, lf=1.7, r=0.01)
    assert m.loglik(params, DATA) == pytest.approx(dense(matern(nu, 0.8, 1.7)), rel=1e-10)


def test_the_periodic_force_is_its_cosine_series_and_within_its_truncation_error_of_the_kernel():
    """Order J: equal to the dense GP of the J-term cosine series to 1e-9 relative; the series differs from
    the exact kernel by at most σ² · periodic_truncation_error(w, J) anywhere; the likelihood approaches the
    exact kernel's as J grows."""
    params = dict(sf=0.8, pf=6.3, wf=1.0, r=0.01)
    gaps = []
    for order in (2, 4, 8):
        m = gp_model(greyid.model.kernels.Named("periodic", ("sf", "pf", "wf"), order))
        assert len(m.state_names) == 2 * order + 1
        value = m.loglik(params, DATA)
        assert value == pytest.approx(dense(periodic(0.8, 6.3, 1.0, order)), rel=1e-9)
        lags = np.linspace(-10, 10, 2001)
        kernel_gap = np.max(np.abs(periodic(0.8, 6.3, 1.0, order, lags) - periodic(0.8, 6.3, 1.0, None, lags)))
        assert kernel_gap <= 0.8**2 * periodic_truncation_error(1.0, order) * (1 + 1e-9) + 1e-15
        gaps.append(abs(value - dense(periodic(0.8, 6.3, 1.0))))
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[2] < 1e-4  # the kernel's error 4e-9 σ², through (K + R)⁻¹


def test_quasiperiodic_sums_and_products_of_kernels():
    """The quasi-periodic kernel is periodic × Matérn-3/2; sums stack the state spaces, products take Kronecker
    products: each equals its dense GP (series kernels) to 1e-9 relative."""
    params = dict(sf=0.8, pf=6.3, wf=1.0, lf=10.0, r=0.01)
    quasi = gp_model("quasiperiodic", scale="sf", lengthscale="lf", period="pf", smoothness="wf")
    assert quasi.loglik(params, DATA) == pytest.approx(
        dense(periodic(0.8, 6.3, 1.0, 6) * matern("32", 1.0, 10.0)), rel=1e-9)
    both = Named("matern12", ("s1", "l2")) + Named("periodic", ("sf", "pf", "wf"), 4)
    summed = gp_model(both)
    values = dict(s1=0.3, l2=2.5, sf=0.8, pf=6.3, wf=1.0, r=0.01)
    assert summed.loglik(values, DATA) == pytest.approx(
        dense(matern("12", 0.3, 2.5) + periodic(0.8, 6.3, 1.0, 4)), rel=1e-9)
    product = gp_model({"kernel": "product", "parts": [{"kernel": "matern32", "scale": "sf", "lengthscale": "lf"},
                                                       {"kernel": "matern12", "scale": 1.0, "lengthscale": "l2"}]})
    values = dict(sf=0.8, lf=3.0, l2=5.0, r=0.01)
    assert product.loglik(values, DATA) == pytest.approx(
        dense(matern("32", 0.8, 3.0) * matern("12", 1.0, 5.0)), rel=1e-9)


def rc_with_force(kernel="matern32"):
    """A one-state RC model whose heat input is partly unmeasured: Q enters like an input."""
    m = greyid.Model("rc")
    m.add_inputs("Ta", "Ph")
    m.add_system("dTi = ((Ta - Ti)/(R*C) + Ph/C + Q/C)*dt + s*dw1")
    m.add_observation("y = Ti", variance="r")
    m.add_latent_force("Q", kernel=kernel, scale="sQ", lengthscale="lQ")
    m.set_initial_state(mean={"Ti": 20.0}, covariance=[[0.5]])
    for name, value, lower in (("R", 2.0, 0.1), ("C", 3.0, 0.1), ("s", 0.1, 1e-4), ("r", 0.01, 1e-5),
                               ("sQ", 0.5, 1e-3), ("lQ", 4.0, 0.1)):
        m.set_parameter(name, init=value, lower=lower, upper=100)
    return m


def test_a_force_in_an_rc_model_is_estimated_and_its_smoothed_path_follows_the_hidden_input():
    """Simulate the RC model with a hidden heat input, fit with a Matérn-3/2 force: the fit converges, its
    log-likelihood beats the model without the force, and the smoothed force follows the hidden input."""
    times = np.arange(0.0, 48.0, 0.25)
    hidden = 1.0 * np.sin(2 * np.pi * times / 24.0)
    rng = np.random.default_rng(4)
    Ta, Ph = 5.0 + 0 * times, np.where((times % 24) < 12, 6.0, 2.0)
    Ti, ys = 20.0, []
    for k in range(len(times)):
        ys.append(Ti + 0.1 * rng.normal())
        for _ in range(25):
            Ti += 0.01 * ((Ta[k] - Ti) / 6.0 + Ph[k] / 3.0 + np.sin(2 * np.pi * (times[k]) / 24.0) / 3.0) \
                + 0.1 * np.sqrt(0.01) * rng.normal()
    data = pd.DataFrame({"t": times, "Ta": Ta, "Ph": Ph, "y": ys})
    m = rc_with_force()
    assert m.state_names == ("Ti", "Q", "Q_d1")
    fit = m.fit(data)
    assert fit.converged
    smooth = fit.smooth()
    force = smooth.latent_forces
    assert list(force.columns) == ["Q", "Q_sd"]
    np.testing.assert_allclose(force["Q"], smooth.smoothed["Q"])
    inside = np.abs(force["Q"] - hidden) < 3 * force["Q_sd"] + 0.3
    assert inside.mean() > 0.9
    assert np.corrcoef(force["Q"], hidden)[0, 1] > 0.8
    plain = greyid.Model.from_dict({**m.to_dict(), "latent_forces": {}, "system": [
        "dTi = ((Ta - Ti)/(R*C) + Ph/C)*dt + s*dw1"]})
    for name in ("sQ", "lQ"):
        plain._parameters.pop(name)
    assert fit.loglik > plain.fit(data).loglik + 10
    filtered = fit.filter()
    assert filtered.latent_forces is not None and len(filtered.latent_forces) == len(data)
    simulated = m.simulate(fit.values, data, n_paths=2, seed=1).frame(0)
    assert {"Q", "Q_d1", "Ti", "y"} <= set(simulated.columns)
    html = fit.report(profile=False)
    assert '<section id="forces"><h2>Latent forces</h2>' in html and 'href="#forces"' in html


def test_simulated_forces_have_the_kernels_covariance():
    """Paths of a force alone (exact scheme) have the kernel's variance and lag covariance."""
    m = gp_model("matern32", scale="sf", lengthscale="lf")
    paths = m.simulate(dict(sf=0.8, lf=1.7, r=0.01), np.array([0.0, 0.5, 2.0]), n_paths=20000, method="exact",
                       seed=2).states[:, :, 0]
    assert paths[:, 0].var() == pytest.approx(0.64, rel=0.04)
    for k, lag in ((1, 0.5), (2, 2.0)):
        cov = np.mean(paths[:, 0] * paths[:, k])
        assert cov == pytest.approx(matern("32", 0.8, 1.7, lag), abs=0.03)


def test_forces_round_trip_through_model_files(tmp_path):
    m = rc_with_force("matern52")
    text = m.to_toml()
    assert "[model.latent_forces]" in text
    again = greyid.Model.from_toml(text)
    assert again.state_names == m.state_names
    assert again.structure.fingerprint == m.structure.fingerprint
    alone = gp_model("quasiperiodic", scale="sf", lengthscale="lf", period="pf", smoothness="wf")
    assert greyid.Model.from_toml(alone.to_toml()).structure.fingerprint == alone.structure.fingerprint


@pytest.mark.parametrize("kernel, hyper, culprit", [
    ("rbf", dict(scale="sf", lengthscale="lf"), "unknown kernel 'rbf'"),
    ("matern32", dict(scale="sf"), "needs its lengthscale"),
    ("matern32", dict(scale="sf", lengthscale="lf", period="pf"), "unknown key 'period'"),
    ("periodic", dict(scale="sf", period="pf", smoothness="wf", order=0), "order must be a positive whole number"),
    ("matern32", dict(scale="sf", lengthscale=-1.0), "its lengthscale must be positive, got -1.0"),
    ("matern32", dict(scale="sf", lengthscale="free"), "its lengthscale 'free' may be zero or negative"),
    ("periodic", dict(scale="sf", period="free", smoothness=1.0), "its period 'free' may be zero or negative"),
])
def test_bad_kernels_are_refused_by_name(kernel, hyper, culprit):
    with pytest.raises(greyid.ModelError, match=culprit):
        m = greyid.Model().add_latent_force("f", kernel=kernel, **hyper).add_observation("y = f", variance="r")
        m.set_parameter("free", init=1.0)
        m.structure  # noqa: B018  (built here)


def test_a_force_used_in_no_equation_and_taken_names_are_refused():
    m = greyid.Model().add_system("dx = -a*x*dt + s*dw1").add_observation("y = x", variance="r")
    m.add_latent_force("Q", kernel="matern12", scale="sQ", lengthscale=2.0)
    m.set_initial_state(mean={"x": 0.0}, covariance=[[1.0]])
    with pytest.raises(greyid.ModelError, match="latent force 'Q' is used in no equation"):
        m.structure  # noqa: B018
    with pytest.raises(greyid.ModelError, match="already a latent force, state or input"):
        m.add_latent_force("x", kernel="matern12", scale="sQ", lengthscale=2.0)
    with pytest.raises(greyid.ModelError, match="not a valid name"):
        m.add_latent_force("dw3", kernel="matern12", scale="sQ", lengthscale=2.0)
    fixed = greyid.Model().add_latent_force("f", kernel="periodic", scale="sf", period="p", smoothness=1.0)
    fixed.add_observation("y = f", variance="r").set_parameter("p", init=24.0, fixed=True)
    assert set(fixed.parameter_names) == {"p", "sf", "r"}  # built: a fixed positive period needs no bounds
    fixed.set_parameter("p", init=-24.0, fixed=True)
    with pytest.raises(greyid.ModelError, match="its period 'p' is fixed at -24.0; it must be positive"):
        fixed.structure  # noqa: B018
    with pytest.raises(greyid.ModelError, match="'Q' is a latent force: it starts in its kernel's stationary"):
        m.set_initial_state(mean={"x": 0.0, "Q": 1.0})


def test_a_model_file_with_a_bad_kernel_exits_2(tmp_path, capsys):
    (tmp_path / "data.csv").write_text("t,y\n0,1\n1,1.1\n2,1.2\n")
    (tmp_path / "model.toml").write_text(
        '[model]\n[model.latent_forces]\nf = { kernel = "matern33", scale = "sf", lengthscale = "lf" }\n'
        '[model.observations]\ny = { equation = "f", variance = "r" }\n')
    assert main(["fit", str(tmp_path / "model.toml"), str(tmp_path / "data.csv")]) == 2
    err = capsys.readouterr().err
    assert "unknown kernel 'matern33'" in err and "Traceback" not in err


def test_a_forces_hyperparameters_are_checked_for_units():
    """The scale is in the force's unit, the lengthscale in the time unit: checked like any equation's terms."""
    m = rc_with_force()
    units = {"t": "h", "Ti": "degC", "Ta": "degC", "Ph": "kW", "Q": "kW", "y": "degC", "R": "K/kW", "C": "kWh/K",
             "s": "K/h^0.5", "r": "K^2", "sQ": "kW", "lQ": "h"}
    m.set_units(units)
    lines = m.check_units()
    assert any("scale of latent force Q" in line for line in lines)
    assert any("lengthscale of latent force Q" in line for line in lines)
    m.set_units({**units, "lQ": "kW"})
    with pytest.raises(greyid.ModelError, match="not dimensionally consistent:\n  in lengthscale of latent force Q"):
        m.check_units()


def test_the_default_optimizer_starts_the_library_matern_house_by_quasi_newton_steps():
    """"auto" takes L-BFGS steps first where an exact Hessian of one block is large (rows × free² × states²
    from QUASI_WORK on): the Armadillo house with a Matérn-3/2 force (233 rows, 9 free parameters, 4 states)
    does, and reaches the optimum of Newton steps throughout; the plain house (7 parameters, 2 states), a
    Hessian above SPLIT_WORK, scoring, and optimizer="newton" keep Newton steps."""
    from greyid import library
    from greyid.estimate.estimation import QUASI_WORK, SPLIT_WORK, uses_quasi_start

    assert uses_quasi_start("auto", False, 233, 9, 4)
    assert not uses_quasi_start("auto", False, 233, 7, 2)
    assert not uses_quasi_start("auto", False, 1512, 9, 4)  # 1.2e5 ≥ SPLIT_WORK: Hessian split over threads
    assert not uses_quasi_start("auto", True, 233, 9, 4)  # scoring steps first
    assert not uses_quasi_start("newton", False, 233, 9, 4) and uses_quasi_start("quasi-newton", False, 233, 7, 2)
    assert 233 * 7 ** 2 * 2 ** 2 < QUASI_WORK <= 233 * 9 ** 2 * 4 ** 2 and 233 * 9 ** 2 < SPLIT_WORK

    model = library.load_model("armadillo_matern32")
    data = greyid.datasets.fetch("armadillo")
    events = []
    auto = model.fit(data, progress=events.append)
    stages = [e["stage"] for e in events if "iteration" in e]
    assert stages[0] == "quasi-newton" and stages[-1] == "newton"
    newton = model.fit(data, optimizer="newton")
    assert auto.converged and newton.converged
    assert auto.loglik == pytest.approx(newton.loglik, abs=1e-8)
    shift = (auto.params["estimate"] - newton.params["estimate"]) / newton.params["std_error"]
    assert np.max(np.abs(shift)) < 1e-3
    np.testing.assert_allclose(auto.cov.to_numpy(), newton.cov.to_numpy(), rtol=1e-4)
