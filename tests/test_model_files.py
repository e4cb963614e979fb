"""Model files (TOML): round trip, settings used by the calls, priors, column mapping, errors."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import DataError, ModelError, library
from greyid.datasets import TRUE_PARAMETERS, building_model, load_building_data
from greyid.data.files import read_data

OU_TOML = """
[model]
name = "ou"
description = "Ornstein-Uhlenbeck process with an input"
inputs = ["u"]
system = ["dx = theta*(mu*u - x)*dt + exp(logsx)*dw1"]
initial_covariance = [0.5]

[model.observations]
y = { equation = "x", variance = "exp(2*logsy)" }

[model.initial_state]
x = "x0"

[parameters]
theta = { init = 1.0, lower = 0.01, upper = 20 }
mu = { init = 1.0 }
logsx = { init = -1.0, lower = -10, upper = 3 }
logsy = { init = -1.0, lower = -10, upper = 3 }
x0 = { init = 0.5, fixed = true }

[derived]
"time constant" = "1/theta"

[data]
time = "time"
hold = "foh"
[data.columns]
y = "measured"
u = "input"
"""


def ou_frame(n=120, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.25
    u = np.sign(np.sin(t / 2.0)) + 1.5
    x = np.empty(n)
    x[0] = 0.5
    for k in range(1, n):  # exact AR(1) discretisation of the OU process at θ = 2, μ = 1.2
        a = np.exp(-2.0 * 0.25)
        x[k] = a * x[k - 1] + (1 - a) * 1.2 * u[k - 1] + rng.normal(0, 0.2 * np.sqrt((1 - a**2) / 4.0))
    return pd.DataFrame({"time": t, "input": u, "measured": x + rng.normal(0, 0.05, n)})


def test_round_trip_keeps_everything():
    m = greyid.Model.from_toml(OU_TOML)
    assert m.description.startswith("Ornstein")
    assert m.options == {"time": "time", "hold": "foh", "columns": {"y": "measured", "u": "input"}}
    assert m.derived == {"time constant": "1/theta"}
    again = greyid.Model.from_toml(m.to_toml())
    assert again.to_dict() == m.to_dict()
    assert again.to_toml() == m.to_toml()


def test_every_library_model_round_trips():
    for name in library.names():
        m = library.load_model(name)
        again = greyid.Model.from_toml(m.to_toml())
        assert again.to_dict() == m.to_dict(), name
        assert again.kind == m.kind


def test_settings_and_column_mapping_apply_to_calls():
    m = greyid.Model.from_toml(OU_TOML)
    raw = ou_frame()
    renamed = raw.rename(columns={"time": "t", "measured": "y", "input": "u"})
    params = {"theta": 2.0, "mu": 1.2, "logsx": np.log(0.2), "logsy": np.log(0.05)}
    plain = greyid.Model.from_toml(OU_TOML.split("[data]")[0])  # the same model without settings
    expected = plain.loglik(params, renamed, time="t", hold="foh")
    assert m.loglik(params, raw) == pytest.approx(expected, rel=1e-12)
    # An argument given in the call wins over the file's setting.
    assert m.loglik(params, raw, hold="zoh") == pytest.approx(plain.loglik(params, renamed, time="t"), rel=1e-12)
    fit = m.fit(raw)
    assert fit.settings["hold"] == "foh" and fit.settings["time"] == "time"
    assert fit.converged
    derived = fit.derived()
    assert derived.loc["time constant", "estimate"] == pytest.approx(1 / fit.values["theta"])
    # the fit keeps the renamed data, so filtering it again works
    assert fit.filter().loglik == pytest.approx(fit.loglik, rel=1e-9)


def test_missing_mapped_column_is_named():
    m = greyid.Model.from_toml(OU_TOML)
    with pytest.raises(DataError, match="'measured' \\(for 'y'\\)"):
        m.loglik({"theta": 1, "mu": 1, "logsx": 0, "logsy": 0}, ou_frame().drop(columns="measured"))


def test_priors_from_the_file_give_map():
    text = OU_TOML.replace('mu = { init = 1.0 }', 'mu = { init = 1.0, prior = { mean = 0.6, sd = 0.01 } }')
    text += '\n[estimation]\ncriterion = "map"\n'
    m = greyid.Model.from_toml(text)
    assert m.prior() == {"mean": {"mu": 0.6}, "sd": {"mu": 0.01}}
    fit = m.fit(ou_frame())
    assert fit.settings["criterion"] == "map"
    ml = m.fit(ou_frame(), criterion="ml", prior=None)
    # a tight prior at 0.6 pulls μ away from its ML value (about 1.2)
    assert abs(fit.values["mu"] - 0.6) < 0.05 and ml.values["mu"] > 1.0


def test_data_file_relative_to_model_file(tmp_path):
    (tmp_path / "sub").mkdir()
    ou_frame().to_csv(tmp_path / "sub" / "ou.csv", sep=";", index=False)
    path = tmp_path / "sub" / "ou.toml"
    path.write_text(OU_TOML.replace('[data]\n', '[data]\nfile = "ou.csv"\n'))
    m = greyid.Model.from_toml(path)
    frame = read_data(m)
    assert list(frame.columns) == ["time", "input", "measured"] and len(frame) == 120


def test_bundled_model_file_gives_the_demo_model():
    m = building_model()
    assert m.options["file"] == "building.csv"
    data = read_data(m)
    pd.testing.assert_frame_equal(data, load_building_data())
    assert np.isfinite(m.loglik(TRUE_PARAMETERS, data))


@pytest.mark.parametrize("text, message", [
    ("[model]\nname = 'x'", "needs system"),
    ("[model]\nsystem = ['dx = -x*dt + dw1']", "no \\[model.observations\\]"),
    ("[model]\nsytem = []", "unknown key 'sytem' in \\[model\\]"),
    ("[modle]\n", "unknown key 'modle' in the model file"),
    ("[model]\nsystem = ['dx = -a*x*dt + dw1']\n[model.observations]\ny = 'x'", "observation 'y' must be a table"),
    ("[model]\nsystem = ['dx = -a*x*dt + dw1']\n[model.observations]\ny = { equation = 'x', variance = 1 }\n"
     "[parameters]\na = { init = 1, lowr = 0 }", "unknown key 'lowr' in \\[parameters\\] a"),
    ("[model]\nsystem = ['dx = -a*x*dt + dw1']\n[model.observations]\ny = { equation = 'x', variance = 1 }\n"
     "[data]\nhold = 'cubic'", "'hold' must be 'zoh' or 'foh'"),
    ("[model]\nsystem = ['dx = -a*x*dt + dw1'\n", "not valid TOML"),
    ("[model]\nsystem = ['dx = -a*x*dt + dw1']\n[model.observations]\ny = { equation = 'x', variance = 1 }\n"
     "[parameters]\na = { init = 1, prior = { mean = 1 } }", "prior of parameter 'a'"),
])
def test_bad_model_files_are_named(text, message):
    with pytest.raises(ModelError, match=message):
        greyid.Model.from_toml(text)


def test_missing_model_file_is_named(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        greyid.Model.from_toml(tmp_path / "nothing.toml")
