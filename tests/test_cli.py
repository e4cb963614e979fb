"""The command line: the README's main job, every command, exit codes and error messages."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.cli import main
from greyid.datasets import load_building_data
from greyid.datasets.building import model_file


def test_demo_fits_bundled_model_and_writes_report(demo_run):
    code, out, folder = demo_run
    assert code == 0
    assert "greyid fit of model 'TiTw'" in out
    assert "converged: True" in out
    assert "UA [kW/K]" in out
    fitted = float(out.split("log-likelihood: ")[1].split()[0])
    truth = float(out.split("true parameters: ")[1].split()[0])
    assert fitted >= truth  # the maximum-likelihood fit beats the simulation's parameters
    assert (folder / "report.html").stat().st_size > 100_000
    saved = greyid.load_fit(folder / "fit.json")
    assert saved.loglik == pytest.approx(fitted, abs=1e-4)


def test_unknown_command_and_missing_files_exit_2(tmp_path, capsys):
    assert main(["frobnicate"]) == 2
    assert main(["fit", str(tmp_path / "nothing.toml")]) == 2
    assert "model file" in capsys.readouterr().err
    assert main(["fit", "NoSuchModel"]) == 2
    assert "neither a model file" in capsys.readouterr().err
    assert main(["validate", str(tmp_path / "fit.json")]) == 2


def test_bad_model_file_message_names_the_problem(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[model]\nsystem = ['dx = -a*x*dt + dw1']\n[model.observations]\n"
                   "y = { equation = 'x', variance = 1 }\n[parameters]\na = { init = 1, lowr = 0 }\n")
    assert main(["fit", str(bad), "data.csv"]) == 2
    assert "unknown key 'lowr' in [parameters] a" in capsys.readouterr().err


def test_bad_data_column_is_named(tmp_path, capsys):
    data = load_building_data().drop(columns="Gv")
    data.to_csv(tmp_path / "d.csv", index=False)
    assert main(["fit", str(model_file()), str(tmp_path / "d.csv"), "--quiet"]) == 2
    assert "'Gv'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """``greyid fit`` of the bundled model file on a short piece of the bundled data."""
    folder = tmp_path_factory.mktemp("fit")
    data = load_building_data().iloc[:400]
    data.to_csv(folder / "data.csv", index=False)
    code = main(["fit", str(model_file()), str(folder / "data.csv"), "--out", str(folder / "out"), "--quiet"])
    return code, folder


def test_fit_writes_fit_summary_and_parameters(fitted):
    code, folder = fitted
    assert code == 0
    out = folder / "out"
    saved = greyid.load_fit(out / "fit.json")
    data = pd.read_csv(folder / "data.csv")
    assert saved.model.loglik(saved.values, data) == pytest.approx(saved.loglik, rel=1e-9)
    assert json.loads((out / "fit.json").read_text())["data_file"] == str((folder / "data.csv").resolve())
    params = pd.read_csv(out / "parameters.csv", index_col=0)
    assert np.allclose(params["estimate"], saved.params["estimate"])
    assert "greyid fit of model 'TiTw'" in (out / "summary.txt").read_text()


def test_validate_uses_the_fits_data_and_exit_code_follows_the_verdict(fitted, capsys, monkeypatch):
    """... and says on standard error what it waits for when it takes more than QUIET_START seconds."""
    from greyid import progress

    code, folder = fitted
    monkeypatch.setattr(progress, "QUIET_START", 0.0)
    result = main(["validate", str(folder / "out" / "fit.json")])
    printed = capsys.readouterr()
    text = printed.out
    assert printed.err.count("computing the residuals and their tests") == 1 and "cache folder" in printed.err
    monkeypatch.setattr(progress, "QUIET_START", 600.0)
    assert "validation of 'TiTw' at level 0.05" in text
    rejects = int(text.split("level 0.05: ")[1].split()[0])
    assert result == (1 if rejects else 0)
    # At level 0.999 nearly every test rejects, so the verdict is negative.
    assert main(["validate", str(folder / "out" / "fit.json"), "--level", "0.999"]) == 1
    assert "computing the residuals" not in capsys.readouterr().err


def test_simulate_from_a_fit_writes_paths(fitted, tmp_path):
    _, folder = fitted
    target = tmp_path / "sim.csv"
    assert main(["simulate", str(folder / "out" / "fit.json"), "--paths", "3", "--seed", "2",
                 "--out", str(target)]) == 0
    sim = pd.read_csv(target)
    assert sorted(sim["path"].unique()) == [0, 1, 2] and len(sim) == 3 * 400
    # the deterministic simulation equals the API's
    assert main(["simulate", str(folder / "out" / "fit.json"), "--deterministic", "--out", str(target)]) == 0
    saved = greyid.load_fit(folder / "out" / "fit.json")
    api = saved.model.simulate(saved.values, pd.read_csv(folder / "data.csv"), noise=False)
    assert np.allclose(pd.read_csv(target)["yTi"], api.outputs[0, :, 0])


def test_models_lists_and_prints_a_library_model(capsys):
    assert main(["models"]) == 0
    listing = capsys.readouterr().out
    for name in ("Ti", "TiTe", "TiTeThTs", "test_cell", "fuel_film", "lotka_volterra"):
        assert name in listing
    assert main(["models", "TiTe"]) == 0
    text = capsys.readouterr().out
    assert greyid.Model.from_toml(text).to_dict() == greyid.library.load_model("TiTe").to_dict()


def test_help_and_version_do_not_load_jax():
    """`greyid --help` and `--version` answer without importing JAX or SymPy (seconds saved);
    the first model use switches JAX to 64 bits."""
    import subprocess
    import sys

    code = ("import sys, contextlib, io\n"
            "from greyid.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n"
            "    main(['--help']); main(['--version'])\n"
            "assert 'jax' not in sys.modules and 'sympy' not in sys.modules, sorted(sys.modules)\n"
            "import greyid\n"
            "greyid.Model('m')\n"
            "import jax\n"
            "assert jax.config.jax_enable_x64\n"
            "print('ok')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


def test_help_names_every_likelihood_method(capsys):
    """`greyid fit --help` names every method a fit takes, `greyid population --help` those a population takes
    (all but the particle filter, which it refuses)."""
    from greyid.filters.protocol import METHODS, PARTICLE

    main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for method in METHODS:
        assert f" {method}," in text or f" {method} " in text, method
    main(["population", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for method in METHODS:
        assert (f" {method}," in text or f" {method} " in text) == (method != PARTICLE), method


def test_identifiability_command(capsys):
    assert main(["identifiability", "test_cell"]) == 0
    printed = capsys.readouterr().out
    assert "Hi   global" in printed and "not judged: Ti0, Tm0" in printed


def test_design_command_ranks_a_candidate_and_names_bad_input(tmp_path, capsys):
    from greyid.datasets.thesis import test_cell_inputs

    plan = test_cell_inputs(n=300)
    plan.to_csv(tmp_path / "prbs.csv", index=False)
    plan.assign(Qh=150.0).to_csv(tmp_path / "constant.csv", index=False)
    assert main(["design", "test_cell", str(tmp_path / "prbs.csv"), "--compare", str(tmp_path / "constant.csv"),
                 "--criterion", "D", "--criterion", "A"]) == 0
    printed = capsys.readouterr().out
    assert "Fisher information of plan 'prbs' (exact)" in printed and "Cramér–Rao bound" in printed
    assert "D rank" in printed and "A rank" in printed
    lines = printed.splitlines()
    assert lines[lines.index("criteria (smaller is better):") + 1].split()[:3] == ["plan", "D", "D"]
    assert lines[lines.index("Cramér–Rao bound (least standard deviation of an unbiased estimate; inf: not "
                             "determined):") + 1].split() == ["parameter", "value", "sd", "bound"]
    # Measured data as the plan: the outputs are left out, with a notice, and the answer is the inputs'.
    from greyid import library

    outputs = library.load_model("test_cell").output_names
    plan.assign(**{name: 20.0 for name in outputs}).to_csv(tmp_path / "measured.csv", index=False)
    assert main(["design", "test_cell", str(tmp_path / "measured.csv"), "--criterion", "D"]) == 0
    captured = capsys.readouterr()
    assert f"the measured output column(s) {', '.join(outputs)} left out" in captured.err
    assert main(["design", "test_cell", str(tmp_path / "prbs.csv"), "--criterion", "D"]) == 0
    same = capsys.readouterr().out.replace("prbs", "measured")
    assert same.split() == captured.out.split()
    assert main(["design", "test_cell", str(tmp_path / "missing.csv")]) == 2
    assert "plan file" in capsys.readouterr().err
    assert main(["design", "test_cell", str(tmp_path / "prbs.csv"), "--criterion", "Q"]) == 2
    assert "--criterion 'Q'" in capsys.readouterr().err
