"""A battery of bad inputs: each gives a named error (type, CLI exit code 2, the culprit in the message).

One line per case: model files, data, saved fits and command-line options.
"""

import contextlib
import io
import json

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import DataError, ModelError
from greyid.cli import main

MODEL = """
[model]
name = "ou"
inputs = ["u"]
system = ["dx = (-a*x + b*u)*dt + s*dw1"]
initial_covariance = [[0.1]]

[model.observations]
y = { equation = "x", variance = "r" }

[model.initial_state]
x = "x0"

[parameters]
a = { init = 0.5, lower = 0, upper = 10 }
b = 1.0
s = { init = 0.3, lower = 0 }
r = { init = 0.1, lower = 0 }
x0 = 0.0
"""


def replace(old, new):
    assert old in MODEL, old
    return MODEL.replace(old, new)


MODEL_FILE_CASES = [
    ("fixed not a boolean", replace("b = 1.0", 'b = { init = 1.0, fixed = "no" }'), "'fixed' must be true or false"),
    ("fixed a number", replace("b = 1.0", "b = { init = 1.0, fixed = 0 }"), "'fixed'"),
    ("unknown section", MODEL + "\n[solver]\nx = 1\n", "solver"),
    ("unknown model key", replace('name = "ou"', 'name = "ou"\nstates = ["x"]'), "states"),
    ("unknown parameter key", replace("b = 1.0", "b = { initial = 1.0 }"), "initial"),
    ("parameter not a number", replace("b = 1.0", 'b = "one"'), "'b'"),
    ("bounds crossed", replace("a = { init = 0.5, lower = 0, upper = 10 }",
                               "a = { init = 0.5, lower = 10, upper = 0 }"),
     "lower bound"),
    ("init outside bounds", replace("a = { init = 0.5,", "a = { init = 50.0,"), "outside its bounds"),
    ("init not a number", replace("a = { init = 0.5,", 'a = { init = "0.5",'), "init must be a number"),
    ("upper bound minus infinity", replace("s = { init = 0.3, lower = 0 }", "s = { init = 0.3, upper = -inf }"),
     "upper bound"),
    ("prior without sd", replace("b = 1.0", "b = { init = 1.0, prior = { mean = 1.0 } }"), "prior"),
    ("prior sd negative", replace("b = 1.0", "b = { init = 1.0, prior = { mean = 1.0, sd = -2 } }"), "prior"),
    ("observation not a table", replace('y = { equation = "x", variance = "r" }', 'y = "x"'), "observation 'y'"),
    ("observation without variance", replace('y = { equation = "x", variance = "r" }', 'y = { equation = "x" }'),
     "observation 'y'"),
    ("observation unknown key", replace('variance = "r" }', 'variance = "r", noise = 1 }'), "noise"),
    ("missing parenthesis", replace("(-a*x + b*u)*dt", "(-a*x + b*u*dt"), "dx"),
    ("equation without dt", replace("(-a*x + b*u)*dt + s*dw1", "-a*x + s*dw1"), "dx"),
    ("equation for no derivative", replace('system = ["dx =', 'system = ["x ='), "x ="),
    ("system not a list", replace('system = ["dx = (-a*x + b*u)*dt + s*dw1"]', "system = 3"), "system"),
    ("inputs not a list", replace('inputs = ["u"]', 'inputs = "u"'), "inputs"),
    ("duplicated input", replace('inputs = ["u"]', 'inputs = ["u", "u"]'), "'u'"),
    ("unknown covariance kind", replace("initial_covariance = [[0.1]]", 'initial_covariance = "huge"'), "huge"),
    ("unknown filter method", MODEL + '\n[filter]\nmethod = "pf"\n', "method"),
    ("unknown filter form", MODEL + '\n[filter]\nform = "qr"\n', "form"),
    ("substeps zero", MODEL + "\n[filter]\nsubsteps = 0\n", "substeps"),
    ("starts zero", MODEL + "\n[estimation]\nstarts = 0\n", "starts"),
    ("unknown criterion", MODEL + '\n[estimation]\ncriterion = "ls"\n', "criterion"),
    ("unknown covariance type", MODEL + '\n[estimation]\ncov_type = "robust"\n', "cov_type"),
    ("seed not an integer", MODEL + '\n[estimation]\nseed = "one"\n', "seed"),
    ("unknown hold", MODEL + '\n[data]\nhold = "cubic"\n', "hold"),
    ("columns not strings", MODEL + "\n[data.columns]\ny = 3\n", "columns"),
    ("prior correlation out of range", MODEL + '\n[estimation.prior_correlation]\n"a,b" = 1.5\n', "prior correlation"),
    ("invalid TOML", MODEL + "\n[parameters\n", "TOML"),
]


@pytest.mark.parametrize("text, culprit", [c[1:] for c in MODEL_FILE_CASES], ids=[c[0] for c in MODEL_FILE_CASES])
def test_model_file(text, culprit):
    with pytest.raises(ModelError, match=culprit):
        greyid.Model.from_toml(text).structure  # structure: equations are parsed when first needed


def data(n=40, seed=0):
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"t": np.arange(n) * 0.5, "u": rng.normal(size=n), "y": rng.normal(size=n)})


def with_value(column, row, value):
    frame = data().astype({column: object})
    frame.loc[row, column] = value
    return frame


DATA_CASES = [
    ("missing output column", data().drop(columns="y"), "'y'"),
    ("missing input column", data().drop(columns="u"), "'u'"),
    ("missing time column", data().drop(columns="t"), "'t'"),
    ("time going back", with_value("t", 5, 0.1), "row 5"),
    ("time repeated", with_value("t", 7, 3.0), "row 7"),
    ("time missing", with_value("t", 3, np.nan), "row 3"),
    ("time text", with_value("t", 4, "noon"), "row 4"),
    ("input missing", with_value("u", 6, np.nan), "row 6"),
    ("input text", with_value("u", 2, "high"), "'u'"),
    ("input infinite", with_value("u", 8, np.inf), "row 8"),
    ("output infinite", with_value("y", 9, np.inf), "row 9"),
    ("output text", with_value("y", 1, "warm"), "'y'"),
    ("empty data", data().iloc[:0], "no rows|empty"),
    ("too short for the parameters", data(4), "4 observed output value"),
    ("no observed output", data().assign(y=np.nan), "'y' has no observation"),
]


@pytest.fixture(scope="module")
def ou():
    return greyid.Model.from_toml(MODEL)


@pytest.mark.parametrize("frame, culprit", [c[1:] for c in DATA_CASES], ids=[c[0] for c in DATA_CASES])
def test_data(ou, frame, culprit):
    with pytest.raises(DataError, match=culprit):
        ou.fit(frame)


API_CASES = [
    ("starts zero", dict(starts=0), ModelError, "starts"),
    ("horizon zero", dict(horizon=0), ModelError, "horizon"),
    ("unknown criterion", dict(criterion="ls"), ModelError, "criterion"),
    ("map without prior", dict(criterion="map"), ModelError, "prior"),
    ("prior with ml", dict(prior={"mean": {"a": 1.0}, "sd": {"a": 1.0}}), ModelError, "criterion='map'"),
    ("prior on unknown parameter", dict(criterion="map", prior={"mean": {"q": 1.0}, "sd": {"q": 1.0}}),
     ModelError, "'q'"),
    ("init of unknown parameter", dict(init={"q": 1.0}), ModelError, "'q'"),
    ("init outside bounds", dict(init={"a": 20.0}), ModelError, "'a'"),
    ("robust norm unknown", dict(robust=("cauchy", 2.0)), ModelError, "robust"),
    ("robust threshold negative", dict(robust=("huber", -1.0)), ModelError, "threshold"),
    ("unknown covariance type", dict(cov_type="robust"), ModelError, "cov_type"),
    ("unknown filter method", dict(method="pf"), ModelError, "'pf'"),
    ("kalman on nonlinear", None, ModelError, "needs a linear model"),
    ("substeps zero", dict(substeps=0), ModelError, "substeps"),
    ("unknown filter option", dict(tolerance=1e-3), ModelError, "tolerance"),
    ("unknown hold", dict(hold="cubic"), (ModelError, DataError), "cubic"),
    ("unknown time column", dict(time="when"), DataError, "'when'"),
    ("init_from not a fit", dict(init_from=3.0), ModelError, "init_from"),
]


@pytest.mark.parametrize("options, error, culprit", [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_fit_options(ou, options, error, culprit):
    if options is None:  # the exact filter asked of a nonlinear model
        m = greyid.Model.from_toml(replace("(-a*x + b*u)*dt", "(-a*x*x + b*u)*dt"))
        with pytest.raises(error, match=culprit):
            m.fit(data(), method="kalman")
        return
    with pytest.raises(error, match=culprit):
        ou.fit(data(), **options)


STRUCTURE_CASES = [
    ("initial state of an unknown state", replace('x = "x0"', 'x = "x0"\nz = 1.0'), "'z'"),
    ("observation of an unknown state", replace('equation = "x"', 'equation = "z"'), "'z'.*state"),
    ("undeclared input", replace('inputs = ["u"]', "inputs = []"), "'u'.*input"),
    ("derived quantity of an unknown parameter", MODEL + '\n[derived]\nUA = "1/q"\n', "'q'"),
]


@pytest.mark.parametrize("text, culprit", [c[1:] for c in STRUCTURE_CASES], ids=[c[0] for c in STRUCTURE_CASES])
def test_model_structure(text, culprit):
    with pytest.raises(ModelError, match=culprit):  # when the file is read, or at the latest at the fit
        greyid.Model.from_toml(text).fit(data()).derived()


def test_function_model_without_initial_state():
    m = greyid.Model.from_functions(
        states=["x"], outputs=["y"], drift=lambda x, u, t, p: -p["a"] * x,
        diffusion=lambda x, u, t, p: np.ones((1, 1)) * p["s"], observation=lambda x, u, t, p: x,
        observation_variance=lambda x, u, t, p: np.ones(1) * p["r"], parameters=["a", "s", "r"])
    with pytest.raises(ModelError, match="set_initial_state"):
        m.loglik({"a": 1.0, "s": 1.0, "r": 0.1}, data().drop(columns="u"))


def test_undeclared_input_names_inputs(ou):
    m = greyid.Model.from_toml(replace('inputs = ["u"]', "inputs = []"))
    with pytest.raises(ModelError, match="'u' appears in the model's equations.*inputs"):
        m.fit(data())


def test_infinite_lower_bound_is_no_bound():
    m = greyid.Model.from_toml(replace("s = { init = 0.3, lower = 0 }", "s = { init = 0.3, lower = -inf }"))
    assert m.parameters["s"].lower is None


@pytest.fixture(scope="module")
def saved_fit(ou, tmp_path_factory):
    path = tmp_path_factory.mktemp("fit") / "fit.json"
    ou.fit(data()).save(path)
    return json.loads(path.read_text())


def _broken(spec, key, value):
    spec = json.loads(json.dumps(spec))
    if value is None:
        del spec[key]
    else:
        spec[key] = value
    return json.dumps(spec)


FIT_FILE_CASES = [
    ("not JSON", lambda spec: "{ not json", "not valid JSON"),
    ("a list", lambda spec: "[1, 2]", "not a greyid fit file"),
    ("wrong format", lambda spec: _broken(spec, "format", "other"), "not a greyid fit file"),
    ("no model", lambda spec: _broken(spec, "model", None), "'model'"),
    ("no parameters", lambda spec: _broken(spec, "params", None), "'params'"),
    ("no settings", lambda spec: _broken(spec, "settings", None), "'settings'"),
    ("parameter not a table", lambda spec: _broken(spec, "params", dict(spec["params"], a=3.0)), "'a'"),
    ("parameter without estimate", lambda spec: _broken(spec, "params", dict(spec["params"], a={"se": 1})), "'a'"),
]


@pytest.mark.parametrize("make, culprit", [c[1:] for c in FIT_FILE_CASES], ids=[c[0] for c in FIT_FILE_CASES])
def test_fit_file(saved_fit, tmp_path, make, culprit):
    path = tmp_path / "broken.json"
    path.write_text(make(saved_fit))
    with pytest.raises(ModelError, match=culprit):
        greyid.load_fit(path)
    code, message = run_cli(["validate", str(path)])
    assert code == 2 and "broken.json" in message, message


def test_fit_file_missing_or_folder(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        greyid.load_fit(tmp_path / "none.json")
    with pytest.raises(ModelError, match="is a folder"):
        greyid.load_fit(tmp_path)


def run_cli(args):
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        code = main(args)
    return code, printed.getvalue()


@pytest.fixture(scope="module")
def files(tmp_path_factory, saved_fit):
    folder = tmp_path_factory.mktemp("cli")
    (folder / "model.toml").write_text(MODEL)
    data().to_csv(folder / "data.csv", index=False)
    (folder / "fit.json").write_text(json.dumps(saved_fit))
    (folder / "existing.txt").write_text("x")
    (folder / "binary.csv").write_bytes(bytes(range(256)) * 4)
    (folder / "sub").mkdir()
    return folder


CLI_CASES = [
    ("unknown model", ["fit", "nonexistent_model"], "neither a model file"),
    ("data file missing", ["fit", "{f}/model.toml", "{f}/none.csv"], "not found"),
    ("data path a folder", ["fit", "{f}/model.toml", "{f}/sub"], "is a folder"),
    ("data not CSV", ["fit", "{f}/model.toml", "{f}/binary.csv"], "binary.csv"),
    ("fit --out a file", ["fit", "{f}/model.toml", "{f}/data.csv", "--out", "{f}/existing.txt"], "is a file"),
    ("fit --report without --out", ["fit", "{f}/model.toml", "{f}/data.csv", "--report"], "--out"),
    ("fit unknown method", ["fit", "{f}/model.toml", "{f}/data.csv", "--method", "pf"], "pf"),
    ("fit unknown hold", ["fit", "{f}/model.toml", "{f}/data.csv", "--hold", "cubic"], "cubic"),
    ("fit unknown time column", ["fit", "{f}/model.toml", "{f}/data.csv", "--time", "when"], "'when'"),
    ("report --out into a missing folder", ["report", "{f}/fit.json", "{f}/data.csv", "--out", "{f}/no/r.html"],
     "does not exist"),
    ("report --out a folder", ["report", "{f}/fit.json", "{f}/data.csv", "--out", "{f}/sub"], "is a folder"),
    ("validate not a fit file", ["validate", "{f}/model.toml"], "not a fit file"),
    ("validate missing fit", ["validate", "{f}/none.json"], "none.json' not found"),
    ("simulate deterministic paths", ["simulate", "{f}/model.toml", "{f}/data.csv", "--deterministic", "--paths",
                                      "10"], "--paths 10 would write 10 copies"),
    ("simulate --out into a missing folder", ["simulate", "{f}/model.toml", "{f}/data.csv", "--out", "{f}/no/s.csv"],
     "does not exist"),
    ("simulate unknown method", ["simulate", "{f}/model.toml", "{f}/data.csv", "--method", "rk4"], "rk4"),
    ("unknown library model", ["models", "NoSuchModel"], "NoSuchModel"),
]


@pytest.mark.parametrize("args, culprit", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_command_line(files, args, culprit):
    code, message = run_cli([a.format(f=files) for a in args])
    assert code == 2, message
    assert culprit in message, message
    assert "Traceback" not in message


def test_debug_shows_the_traceback(files):
    code, message = run_cli(["--debug", "validate", str(files / "model.toml")])
    assert code == 2 and "Traceback" in message


def test_version():
    code, message = run_cli(["--version"])
    assert code == 0 and message.strip() == f"greyid {greyid.__version__}"


def test_timestamps_in_a_data_file(files, tmp_path):
    """The CLI reads a time column of timestamps, says how it converted it, and names a bad row."""
    frame = data()
    frame["t"] = pd.Timestamp("2013-06-28 00:00:00") + pd.to_timedelta(frame["t"], unit="h")
    frame.to_csv(tmp_path / "stamped.csv", index=False)
    text = MODEL + '\n[data]\ntime_unit = "h"\n'
    (tmp_path / "model.toml").write_text(text)
    code, message = run_cli(["fit", str(tmp_path / "model.toml"), str(tmp_path / "stamped.csv"), "--quiet"])
    assert code in (0, 1), message
    assert "timestamps from 2013-06-28 00:00:00 read as elapsed time in 'h'" in message
    plain = greyid.Model.from_toml(text).fit(data())
    assert f"{plain.loglik:.6f}" in message  # the same fit as with hours as numbers
    frame = frame.astype({"t": str})
    frame.loc[5, "t"] = "noon"
    frame.to_csv(tmp_path / "bad.csv", index=False)
    code, message = run_cli(["fit", str(tmp_path / "model.toml"), str(tmp_path / "bad.csv"), "--quiet"])
    assert code == 2 and "row 5" in message and "'noon'" in message, message


def test_time_zone_makes_elapsed_time_cross_daylight_saving():
    from greyid.data.prepare import time_values
    from greyid.data.timestamps import parse_timestamps

    local = pd.DataFrame({"t": ["2026-03-29 00:30", "2026-03-29 01:30", "2026-03-29 03:30"]})  # clocks jump at 2:00
    parsed = parse_timestamps(local, "t", time_zone="Europe/Copenhagen")
    np.testing.assert_allclose(time_values(parsed, "t", "h"), [0.0, 1.0, 2.0])
    np.testing.assert_allclose(time_values(parse_timestamps(local, "t"), "t", "h"), [0.0, 1.0, 3.0])
    with pytest.raises(DataError, match="time zone 'Mars/Olympus'"):
        parse_timestamps(local, "t", time_zone="Mars/Olympus")


def test_setters_name_the_mistake_when_called():
    """A wrong state name or covariance shape is an error at set_initial_state, not at the first fit."""
    m = greyid.Model("setters")
    m.add_system("dx = -a*x*dt + s*dw1", "dz = (x - z)*b*dt + s*dw2")
    m.add_observation("y = z", variance="r")
    with pytest.raises(ModelError, match="initial state given for 'w', which is not a state"):
        m.set_initial_state(mean={"w": 0.0})
    with pytest.raises(ModelError, match="shape \\(3, 3\\), but the model has 2 states"):
        m.set_initial_state(mean={"x": 0.0, "z": 0.0}, covariance=np.eye(3))
    with pytest.raises(ModelError, match="ragged"):
        m.set_initial_state(mean={"x": 0.0, "z": 0.0}, covariance=[[1.0, 0.0], [0.0]])
    m.set_initial_state(mean={"x": 0.0, "z": 0.0}, covariance=[1.0, 2.0])  # variances
    m.set_initial_state(mean={"x": "x0", "z": 0.0}, covariance=[["p", 0.0], [0.0, 1.0]])
    with pytest.raises(ModelError, match="must be 1x1 \\(outputs \\['y'\\]\\)"):
        m.set_observation_covariance([["r", 0.0], [0.0, "r"]])
    # Before the states exist the setter cannot judge: the check comes when the model is built.
    early = greyid.Model("early").set_initial_state(mean={"w": 0.0})
    early.add_system("dx = -a*x*dt + s*dw1").add_observation("y = x", variance="r")
    with pytest.raises(ModelError, match="'w', which is not a state"):
        early.structure


# ---------------------------------------------------------------------- files one step off the path
def _csv(frame, **options):
    return frame.to_csv(index=False, **options)


def _battery_files(folder):
    """The malformed files of the battery, written into ``folder``: name → bytes."""
    good = data()
    text = _csv(good)
    lines = text.splitlines()
    files = {
        "latin1.toml": MODEL.replace('name = "ou"', 'name = "Zustände"').encode("latin-1"),
        "latin1.csv": (lines[0] + ",café\n" + "\n".join(line + ",1" for line in lines[1:])).encode("latin-1"),
        "empty.csv": b"",
        "blank.csv": b"\n\n  \n",
        "duplicate.csv": ("\n".join([lines[0] + ",y"] + [line + ",1.0" for line in lines[1:]])).encode(),
        "booleans.csv": _csv(good.assign(u=[bool(i % 2) for i in range(len(good))])).encode(),
        "columns.toml": (MODEL + '\n[data.columns]\nu = "heat"\n').encode(),
        "negative.toml": MODEL.replace("initial_covariance = [[0.1]]", "initial_covariance = [[-0.1]]").encode(),
        "complex.toml": MODEL.replace("s*dw1", "s*dw1 + sqrt(-1)*x*dt").encode(),
        "divide.toml": MODEL.replace("b*u)*dt", "b*u + 1/0)*dt").encode(),
        "pi.toml": MODEL.replace("b*u", "pi*u").replace("b = 1.0", "pi = 1.0").encode(),
        "input.toml": MODEL.replace("b = 1.0", "b = 1.0\nu = 2.0").encode(),
        "nostate.toml": MODEL.replace('equation = "x"', 'equation = "u"').encode(),
    }
    two = MODEL.replace('system = ["dx = (-a*x + b*u)*dt + s*dw1"]',
                        'system = ["dx = (-a*x + b*u)*dt + s*dw1", "dz = (x - z)*dt"]').replace(
        'x = "x0"', 'x = "x0"\nz = 0.0')
    for name, matrix in (("asymmetric", "[[0.1, 0.05], [0.0, 0.1]]"), ("indefinite", "[[0.1, 0.2], [0.2, 0.1]]")):
        files[f"{name}.toml"] = two.replace("initial_covariance = [[0.1]]", f"initial_covariance = {matrix}").encode()
    for name, blob in files.items():
        (folder / name).write_bytes(blob)
    (folder / "model.toml").write_text(MODEL)
    (folder / "data.csv").write_text(text)
    return folder


FILE_CASES = [
    ("model file not UTF-8", ["fit", "{f}/latin1.toml", "{f}/data.csv"], "not UTF-8"),
    ("data file not UTF-8", ["fit", "{f}/model.toml", "{f}/latin1.csv"], "not UTF-8"),
    ("empty data file", ["fit", "{f}/model.toml", "{f}/empty.csv"], "is empty"),
    ("blank data file", ["fit", "{f}/model.toml", "{f}/blank.csv"], "is empty"),
    ("duplicate column names", ["fit", "{f}/model.toml", "{f}/duplicate.csv"], "two columns named 'y'"),
    ("text booleans in a numeric column", ["fit", "{f}/model.toml", "{f}/booleans.csv"], "true/false"),
    ("column mapping to a missing column", ["fit", "{f}/columns.toml", "{f}/data.csv"], "'heat'"),
    ("negative initial variance", ["fit", "{f}/negative.toml", "{f}/data.csv"], "negative variance"),
    ("asymmetric initial covariance", ["fit", "{f}/asymmetric.toml", "{f}/data.csv"], "not symmetric"),
    ("indefinite initial covariance", ["fit", "{f}/indefinite.toml", "{f}/data.csv"], "positive semi-definite"),
    ("complex-valued equation", ["fit", "{f}/complex.toml", "{f}/data.csv"], "complex-valued"),
    ("division by zero", ["fit", "{f}/divide.toml", "{f}/data.csv"], "divides by zero"),
    ("a parameter named pi", ["fit", "{f}/pi.toml", "{f}/data.csv"], "the constant π"),
    ("a parameter named like an input", ["fit", "{f}/input.toml", "{f}/data.csv"], "is an input"),
    ("an observation of no state", ["fit", "{f}/nostate.toml", "{f}/data.csv"], "depends on no state"),
]


@pytest.fixture(scope="module")
def battery(tmp_path_factory):
    return _battery_files(tmp_path_factory.mktemp("battery"))


@pytest.mark.parametrize("args, culprit", [c[1:] for c in FILE_CASES], ids=[c[0] for c in FILE_CASES])
def test_malformed_files_are_named(battery, args, culprit):
    code, message = run_cli([a.format(f=battery) for a in args])
    assert code == 2, message
    assert culprit in message, message
    assert "Traceback" not in message and "site-packages" not in message, message


def test_comma_decimals_with_semicolons_read_as_numbers(battery, ou):
    """'1,5;2,25' (a European spreadsheet's CSV): decimal commas, not text."""
    from greyid.data.files import read_csv_file

    path = battery / "comma.csv"
    path.write_text(_csv(data(), sep=";", decimal=","))
    frame = read_csv_file(path)
    pd.testing.assert_frame_equal(frame, data(), check_exact=False, rtol=1e-12)
    assert ou.loglik(ou.initial_values(), frame) == pytest.approx(ou.loglik(ou.initial_values(), data()), rel=1e-12)


def test_timestamps_with_two_utc_offsets_are_read_as_instants(tmp_path):
    """A daylight-saving change inside the data: +01:00 then +02:00.  The elapsed times are exact (10 min
    steps across the change), and no pandas warning is printed."""
    from greyid.data.timestamps import parse_timestamps

    utc = pd.date_range("2024-03-31T00:00:00Z", periods=12, freq="10min")
    frame = pd.DataFrame({"t": [ts.isoformat() for ts in utc.tz_convert("Europe/Copenhagen")]})
    assert frame["t"].str.endswith("+01:00").any() and frame["t"].str.endswith("+02:00").any()
    parsed = parse_timestamps(frame, "t")
    steps = parsed["t"].diff().dropna().dt.total_seconds().to_numpy()
    np.testing.assert_array_equal(steps, 600.0)


def test_a_fit_file_edited_by_hand_is_checked_against_its_schema(saved_fit, tmp_path):
    cases = {
        "a string for a boolean": (dict(saved_fit, converged="yes"), "'converged'"),
        "a string for a number": (dict(saved_fit, loglik="high"), "'loglik'"),
        "a covariance of the wrong shape": (dict(saved_fit, cov=dict(saved_fit["cov"], matrix=[1.0, 2.0])), "'cov'"),
        "an estimate that is text": (dict(saved_fit, params=dict(saved_fit["params"], a=dict(
            saved_fit["params"]["a"], estimate="x"))), "'estimate' of parameter 'a'"),
        "a negative count": (dict(saved_fit, n_obs=-3), "'n_obs'"),
    }
    for label, (spec, culprit) in cases.items():
        path = tmp_path / "edited.json"
        path.write_text(json.dumps(spec))
        with pytest.raises(ModelError, match=culprit):
            greyid.load_fit(path)
        code, message = run_cli(["validate", str(path)])
        assert code == 2 and culprit in message and "Traceback" not in message, (label, message)


def test_a_fit_whose_data_file_is_gone_says_so(saved_fit, tmp_path):
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(dict(saved_fit, data_file=str(tmp_path / "moved.csv"))))
    code, message = run_cli(["validate", str(path)])
    assert code == 2 and "moved.csv" in message and "does not exist" in message, message


def test_data_that_determine_no_parameter_get_no_finite_standard_error(ou):
    """An input that is always 0 says nothing of its gain b: b's standard error is infinite (t = 0,
    p = 1), not finite with p = 0."""
    flat = data().assign(u=0.0)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = ou.fit(flat)
    undetermined = {n for d in fit.ill_determined for n in d["direction"]}
    assert undetermined
    for name in undetermined:
        row = fit.params.loc[name]
        assert not np.isfinite(row["std_error"]) and not row["reliable"], fit.params
        assert not (row["p_value"] < 0.05)


def test_a_bad_time_deep_in_a_long_file_is_named_at_its_row(tmp_path):
    """A long file of numeric times with one bad entry: the error names that row and that value (not a
    row that a date parser happened to trip on)."""
    n = 200_000
    frame = pd.DataFrame({"t": np.arange(n) / 6.0, "u": 0.0, "y": 0.0}).astype({"t": object})
    frame.loc[150_000, "t"] = "abc"
    path = tmp_path / "long.csv"
    frame.to_csv(path, index=False)
    (tmp_path / "model.toml").write_text(MODEL)
    code, message = run_cli(["fit", str(tmp_path / "model.toml"), str(path)])
    assert code == 2 and "row 150000" in message and "'abc'" in message, message


def test_an_initial_covariance_of_parameters_is_checked_at_their_values():
    """A matrix of expressions passes when the file is read; at the parameters' values it must be symmetric
    and positive semi-definite, or the fit stops with the element named."""
    two = MODEL.replace('system = ["dx = (-a*x + b*u)*dt + s*dw1"]',
                        'system = ["dx = (-a*x + b*u)*dt + s*dw1", "dz = (x - z)*dt"]').replace(
        'x = "x0"', 'x = "x0"\nz = 0.0')
    frame = data()
    for matrix, culprit in (('[["p", "q"], ["0", "p"]]', "not symmetric"),
                            ('[["p", "q"], ["q", "p"]]', "positive semi-definite")):
        text = two.replace("initial_covariance = [[0.1]]", f"initial_covariance = {matrix}").replace(
            "x0 = 0.0", "x0 = 0.0\np = 0.1\nq = 0.5")
        model = greyid.Model.from_toml(text)
        with pytest.raises(ModelError, match=culprit):
            model.loglik(model.initial_values(), frame)
