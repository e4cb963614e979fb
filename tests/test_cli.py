"""The README's main job: ``greyid demo`` fits the bundled model to the bundled data."""

import pytest

from greyid.cli import main


def test_demo_fits_bundled_model(capsys):
    assert main(["demo"]) == 0
    out = capsys.readouterr().out
    assert "greyid fit of model 'TiTw'" in out
    assert "converged: True" in out
    assert "UA [kW/K]" in out
    fitted = float(out.split("log-likelihood: ")[1].split()[0])
    truth = float(out.split("true parameters: ")[1].split()[0])
    assert fitted >= truth  # the maximum-likelihood fit beats the simulation's parameters


def test_cli_rejects_unknown_command():
    with pytest.raises(SystemExit):
        main(["frobnicate"])
