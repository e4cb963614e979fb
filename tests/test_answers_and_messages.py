"""What a user meets in the second hour: dates, covariates, singular equations, parameters the data do not
determine, design at a zero parameter, seeds, the cache folder, warnings and help that read as meant."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid import DataError, ModelError
from greyid.data.timestamps import READ_AS, parse_timestamps
from greyid.datasets import load_building_data
from greyid.datasets.building import model_file
from test_bad_input import MODEL, run_cli

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------- dates
def _stamped(start: str, rows: int, form: str) -> pd.DataFrame:
    times = pd.Timestamp(start) + pd.to_timedelta(np.arange(rows) * 10, unit="min")
    return pd.DataFrame({"t": times.strftime(form), "y": np.arange(rows, dtype=float)})


def test_ambiguous_day_first_dates_are_refused_with_the_setting_that_decides():
    frame = _stamped("2024-01-03", 300, "%d.%m.%Y %H:%M")  # days 3 to 5 of January: every day ≤ 12
    with pytest.raises(DataError, match=r"ambiguous: row 0 \('03.01.2024 00:00'\) is 03 January 2024 read "
                                        r"day-first and 01 March 2024 read month-first") as refused:
        parse_timestamps(frame, "t")
    assert 'time_format = "%d.%m.%Y %H:%M" (day-first)' in str(refused.value)
    parsed = parse_timestamps(frame, "t", time_format="%d.%m.%Y %H:%M")
    assert parsed["t"].iloc[-1] == pd.Timestamp("2024-01-05 01:50")
    assert np.all(np.diff(parsed["t"].to_numpy()) == np.timedelta64(10, "m"))  # no gap of a month


def test_the_one_order_that_fits_every_row_is_taken_and_said():
    day_first = parse_timestamps(_stamped("2024-01-12", 300, "%d.%m.%Y %H:%M"), "t")  # the 13th settles it
    assert day_first.attrs[READ_AS] == "day-first"
    assert day_first["t"].iloc[0] == pd.Timestamp("2024-01-12")
    month_first = parse_timestamps(_stamped("2024-01-12", 300, "%m/%d/%Y %H:%M"), "t")
    assert month_first.attrs[READ_AS] == "month-first"
    assert month_first["t"].iloc[-1] == pd.Timestamp("2024-01-14 01:50")
    iso = parse_timestamps(_stamped("2024-01-03", 10, "%Y-%m-%d %H:%M"), "t")  # year first: never ambiguous
    assert iso["t"].iloc[0] == pd.Timestamp("2024-01-03")


def test_a_model_files_time_format_and_time_zone_are_used_by_the_command_line(tmp_path):
    frame = load_building_data().iloc[:200]
    stamped = frame.assign(t=(pd.Timestamp("2024-01-03") + pd.to_timedelta(frame["t"], unit="h"))
                           .dt.strftime("%d.%m.%Y %H:%M:%S.%f"))
    stamped.to_csv(tmp_path / "data.csv", index=False)
    text = model_file().read_text().replace('file = "building.csv"', 'file = "data.csv"\ntime_unit = "h"\n'
                                            'time_format = "%d.%m.%Y %H:%M:%S.%f"\ntime_zone = "UTC"')
    (tmp_path / "model.toml").write_text(text)
    code, message = run_cli(["fit", str(tmp_path / "model.toml"), "--quiet"])
    assert code in (0, 1), message
    assert "timestamps from 2024-01-03 00:00:00+00:00" in message and "unknown" not in message
    plain = greyid.Model.from_toml(model_file()).fit(frame)
    assert f"log-likelihood: {plain.loglik:.6f}" in message  # the same data as hours written as numbers
    (tmp_path / "model.toml").write_text(text.replace('time_format = "%d.%m.%Y %H:%M:%S.%f"\n', ""))
    code, message = run_cli(["fit", str(tmp_path / "model.toml"), "--quiet"])
    assert code == 2 and "ambiguous" in message and "Traceback" not in message


# ---------------------------------------------------------------------- population covariates
def _population_model():
    model = greyid.Model.from_toml(MODEL)
    model.set_parameter("b", init=1.0, lower=-10, upper=10)
    return model


def test_covariates_keep_members_names_as_written_and_refuse_a_member_twice(tmp_path):
    from greyid.data.files import read_covariates
    from greyid.population.spec import make_spec

    (tmp_path / "covariates.csv").write_text("house,area\n001,120\n002,80\n")
    table = read_covariates(tmp_path / "covariates.csv")
    assert list(table.index) == ["001", "002"]
    model = _population_model()
    _, raw = make_spec(model, {"a": "lognormal"}, table, {"b": ["area"]}, "diagonal", ["002", "001"])
    np.testing.assert_allclose(raw[:, 0], [80.0, 120.0])
    (tmp_path / "twice.csv").write_text("house,area\n001,120\n002,80\n001,95\n")
    with pytest.raises(DataError, match=r"2 rows for data set '001' \(rows 1, 3 below the header\)"):
        make_spec(model, {"a": "lognormal"}, read_covariates(tmp_path / "twice.csv"), {"b": ["area"]}, "diagonal",
                  ["001", "002"])


# ---------------------------------------------------------------------- equations and data
def _time_singular_model(term: str):
    m = greyid.Model("singular")
    m.add_system(f"dx = (-a*x + b*{term})*dt + s*dw1")
    m.add_observation("y = x", variance="e")
    m.set_initial_state({"x": 0.0}, covariance=[1.0])
    for name, value in dict(a=1.0, b=0.1, s=0.1, e=0.01).items():
        m.set_parameter(name, init=value, lower=1e-4, upper=10)
    return m


@pytest.mark.parametrize("term", ["log(t)", "1/t"])
def test_an_equation_infinite_at_the_first_time_is_named_with_its_row(term):
    rng = np.random.default_rng(0)
    frame = pd.DataFrame({"t": np.arange(30.0), "y": rng.normal(size=30)})
    with pytest.raises(ModelError) as refused:
        _time_singular_model(term).fit(frame)
    message = str(refused.value)
    assert "the drift of 'dx'" in message and "row 0" in message and "t = 0" in message
    assert "whatever the parameters' values" in message and "initial parameter values" not in message


def _flat_model():
    m = greyid.Model("flat")
    m.add_inputs("u")
    m.add_system("dx = (-a*x + b*u)*dt + s*dw1")
    m.add_observation("y = x", variance="e^2")
    m.set_initial_state({"x": "x0"}, covariance=[1.0])
    for name, value, low, high in [("a", 1.0, 0.01, 10), ("b", 1.0, 0.0, 10), ("s", 0.3, 1e-3, 10),
                                   ("e", 0.1, 1e-3, 1), ("x0", 0.0, -5, 5)]:
        m.set_parameter(name, init=value, lower=low, upper=high)
    return m


@pytest.fixture(scope="module")
def undetermined_fit():
    """A parameter that multiplies an input which is 0 in every row, in data far below the noise bounds:
    the likelihood does not depend on it and it runs to a bound."""
    rng = np.random.default_rng(1)
    frame = pd.DataFrame({"t": np.arange(200) * 0.1, "u": 0.0, "y": 1e-6 * rng.normal(size=200)})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = _flat_model().fit(frame)
    return fit, caught


def test_a_parameter_run_so_far_to_its_bound_that_its_derivatives_vanish_is_judged_by_the_equations():
    """Data simulated from the model with u = 0, scaled far below the noise bounds: b runs to its bound so far
    that dθ/dz underflows and every derivative in z is 0; the equations (u constant 0) still tell."""
    model = _flat_model()
    times = pd.DataFrame({"t": np.arange(200) * 0.1, "u": 0.0})
    simulated = model.simulate({"a": 1.0, "b": 1.0, "s": 0.3, "e": 0.1, "x0": 0.0}, times, seed=1).frame(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = model.fit(simulated[["t", "u", "y"]].assign(y=simulated["y"] * 1e-6))
    assert fit.params.loc["b", "at_bound"] and not fit.converged
    assert "the data do not determine 'b'" in fit.message


def test_a_parameter_the_likelihood_does_not_depend_on_is_named_wherever_the_search_leaves_it():
    """Data of ordinary size, u = 0 in every row: b's slope and curvature are exactly 0, and the search leaves it
    inside its bounds or at one (where depends on the rounding of the other parameters' steps, so on the CPU):
    either way the fit names b as what the data do not determine, once, and the other estimates stand."""
    model = _flat_model()
    times = pd.DataFrame({"t": np.arange(200) * 0.1, "u": 0.0})
    simulated = model.simulate({"a": 1.0, "b": 1.0, "s": 0.3, "e": 0.1, "x0": 0.0}, times, seed=1).frame(0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fit = model.fit(simulated[["t", "u", "y"]])
    assert not fit.converged
    assert fit.message == "the data do not determine 'b' (the likelihood does not depend on it)"
    said = [str(w.message) for w in caught]
    assert sum("the likelihood does not depend on 'b'" in w for w in said) == 1
    assert not any("the Hessian is singular" in w for w in said)
    assert fit.params.loc["b", "std_error"] == np.inf and not fit.params.loc["b", "reliable"]
    assert fit.params.loc[["a", "s", "e"], "reliable"].all()


def test_a_parameter_the_likelihood_does_not_depend_on_is_no_converged_estimate(undetermined_fit):
    fit, _ = undetermined_fit
    assert not fit.converged
    assert "the data do not determine 'b'" in fit.message
    said = " ".join(fit.warnings)
    assert "the likelihood does not depend on 'b'" in said
    assert "the constant input 'u' (0 in every row)" in said
    assert not fit.params.loc["b", "reliable"]


def test_a_fits_warnings_point_at_the_users_line(undetermined_fit):
    _, caught = undetermined_fit
    ours = [w for w in caught if issubclass(w.category, greyid.FitWarning)]
    assert ours and all(Path(w.filename).name == "test_answers_and_messages.py" for w in ours), \
        [(w.filename, w.lineno) for w in ours]


def test_one_row_of_data_is_refused_by_what_it_lacks(tmp_path):
    load_building_data().iloc[:1].to_csv(tmp_path / "one.csv", index=False)
    code, message = run_cli(["fit", str(model_file()), str(tmp_path / "one.csv"), "--quiet"])
    assert code == 2 and "the data have one row (t = 0)" in message and "at least two times" in message


# ---------------------------------------------------------------------- design and identifiability
def test_design_reports_criterion_c_undefined_at_a_zero_parameter_and_prints_the_rest(tmp_path):
    text = model_file().read_text().replace("Aw = { init = 3.0", "Aw = { init = 0.0")
    (tmp_path / "model.toml").write_text(text)
    load_building_data().iloc[:150][["t", "Te", "Gv", "Qi"]].to_csv(tmp_path / "plan.csv", index=False)
    code, message = run_cli(["design", str(tmp_path / "model.toml"), str(tmp_path / "plan.csv")])
    assert code in (0, 1) and "Traceback" not in message, message
    assert "C not computed: criterion C (variances relative to θ², V = diag(1/θ)) is undefined: Aw is 0" in message
    row = message.split("criteria (smaller is better):")[1].splitlines()[2]
    assert "NaN" in row and "<NA>" in row and len(row.split()) == 9  # D, A and E with their ranks


def test_identifiability_without_a_plan_names_the_equation_its_generic_inputs_break(tmp_path):
    text = """
[model]
name = "radiator"
inputs = ["Tr", "Te"]
system = ["dTi = (k*(Tr - Ti)^1.3/C + (Te - Ti)/(R*C))*dt + s*dw1"]
[model.observations]
yTi = { equation = "Ti", variance = "e^2" }
[model.initial_state]
Ti = 20.0
[parameters]
k = { init = 0.05, lower = 0.001, upper = 1 }
C = { init = 1.0, lower = 0.1, upper = 10 }
R = { init = 5.0, lower = 0.1, upper = 100 }
s = { init = 0.1, lower = 0.001, upper = 1 }
e = { init = 0.1, lower = 0.001, upper = 1 }
"""
    (tmp_path / "radiator.toml").write_text(text)
    code, message = run_cli(["identifiability", str(tmp_path / "radiator.toml")])
    assert code == 2 and "no observation" not in message, message
    assert "the drift of 'dTi'" in message and "--plan" in message
    t = np.arange(100) * 0.1
    pd.DataFrame({"t": t, "Tr": 40 + 10 * np.sin(t), "Te": 5.0 + t / 10, "yTi": 20.0}).to_csv(
        tmp_path / "data.csv", index=False)
    (tmp_path / "radiator.toml").write_text(text + '[data]\nfile = "data.csv"\n')
    code, message = run_cli(["identifiability", str(tmp_path / "radiator.toml")])
    assert code == 1, message  # only combinations of k, C and R are seen
    assert "within the ranges of the model file's data" in message and "C*R" in message


def test_greyid_design_is_reachable_after_import_greyid_alone():
    done = subprocess.run([sys.executable, "-c", "import greyid; print(greyid.design.identifiability.__name__)"],
                          capture_output=True, text=True)
    assert done.returncode == 0 and done.stdout.strip() == "identifiability", done.stderr


# ---------------------------------------------------------------------- command line and cache
def test_a_negative_seed_is_refused_by_name():
    code, message = run_cli(["fit", str(model_file()), "--starts", "3", "--seed", "-1", "--quiet"])
    assert code == 2 and "--seed" in message and "Traceback" not in message
    with pytest.raises(ModelError, match="seed must be a non-negative integer"):
        greyid.Model.from_toml(model_file()).fit(load_building_data().iloc[:50], starts=2, seed=-1)


def test_help_shows_flags_as_flags():
    code, message = run_cli(["fit", "--help"])
    assert code == 0 and "<bool>" not in message
    assert "--report" in message and "--seed N" in message


def _cache_info(folder) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "greyid", "cache", "info"], capture_output=True, text=True,
                          env=dict(os.environ, GREYID_CACHE_DIR=str(folder)))


def test_cache_info_names_a_cache_folder_that_cannot_be_used(tmp_path):
    (tmp_path / "afile").write_text("x")
    os.symlink(tmp_path / "loop2", tmp_path / "loop1")
    os.symlink(tmp_path / "loop1", tmp_path / "loop2")
    for folder, words in ((tmp_path / "afile", "is a file, not a folder"), (tmp_path / "loop1", "leads nowhere")):
        done = _cache_info(folder)
        assert done.returncode == 2 and words in done.stderr and "Traceback" not in done.stderr, done.stderr
        assert done.stderr.count("cache folder") == 1  # said once, as the command's error
    done = _cache_info(tmp_path / "fine")
    assert done.returncode == 0 and "traced programs: 0 files" in done.stdout


def test_an_unusable_cache_folder_is_said_once(tmp_path):
    (tmp_path / "afile").write_text("x")
    script = ("import warnings; warnings.simplefilter('always')\n"
              "from greyid.datasets import building_model, load_building_data\n"
              "m = building_model(); print(m.loglik(m.initial_values(), load_building_data().iloc[:20]))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env=dict(os.environ, GREYID_CACHE_DIR=str(tmp_path / "afile")))
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("CacheWarning") == 1 and "programs are not kept" in done.stderr
    assert np.isfinite(float(done.stdout.split()[-1]))


def test_command_line_hints_name_the_options_and_keys_a_user_writes(tmp_path):
    folder = tmp_path / "houses"
    folder.mkdir()
    for k in range(2):
        load_building_data().iloc[:50].to_csv(folder / f"{k:03d}.csv", index=False)
    code, message = run_cli(["population", str(model_file()), str(folder), "--quiet"])
    assert code == 2 and "--random PARAMETER:lognormal" in message and "Traceback" not in message
    no_state = model_file().read_text().replace('[model.initial_state]\nTi = "Ti0"\nTw = "Tw0"\n', "")
    no_state = no_state.replace('file = "building.csv"', f'file = "{model_file().parent / "building.csv"}"')
    (tmp_path / "no_state.toml").write_text(no_state)
    code, message = run_cli(["fit", str(tmp_path / "no_state.toml"), "--quiet"])
    assert code == 2 and "[model.initial_state]" in message, message
