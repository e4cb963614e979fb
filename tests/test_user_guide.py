"""The numbers printed in docs/user-guide.md are the numbers the code gives today.

Each worked example's output block is parsed (log-likelihood line, parameter and
derived-quantity rows) and compared with a fresh fit, to the digits printed.
Estimates the fit marks unreliable (at a bound, in a flat direction) must be
marked so in the guide, not matched digit for digit.
"""

import os
import warnings
from pathlib import Path

import pytest

import greyid

ROOT = Path(__file__).resolve().parents[1]
GUIDE = (ROOT / "docs" / "user-guide.md").read_text(encoding="utf-8")
SHARED = Path(os.environ.get("GREYID_DATA_MIRROR", ROOT.parent / "shared" / "data"))


def output_block(after: str) -> list[str]:
    """The lines of the first plain ``` block that follows the line containing ``after``."""
    start = GUIDE.index(after)
    opening = GUIDE.index("```\n", GUIDE.index("\n```", start) + 4)
    closing = GUIDE.index("```", opening + 4)
    return GUIDE[opening + 4:closing].strip().splitlines()


def agrees(printed: str, value: float) -> bool:
    """``value`` rounds to ``printed`` (to its last printed digit, or 1e-6 relative)."""
    number = float(printed)
    mantissa, _, exponent = printed.lower().partition("e")
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    unit = 10.0 ** (-decimals) * 10.0 ** (int(exponent) if exponent else 0)
    return abs(number - value) <= 0.51 * unit + 1e-6 * abs(value)


def check(fit, lines):
    header = next(line for line in lines if line.startswith("log-likelihood:"))
    assert agrees(header.split()[1], fit.loglik), header
    assert f"observations: {fit.n_obs}" in header and f"parameters: {fit.n_params}" in header
    derived = fit.derived() if fit.model.derived else None
    checked = 0
    for line in lines:
        tokens = line.split()
        if tokens and tokens[0] in fit.params.index:
            row = fit.params.loc[tokens[0]]
            if not row["reliable"]:
                assert "unreliable" in line or "at bound" in line, line
                continue
            assert agrees(tokens[1], row["estimate"]) and agrees(tokens[2], row["std_error"]), line
            checked += 1
        elif derived is not None:
            name = next((n for n in derived.index if line.startswith(n + " ")), None)
            if name is not None:
                estimate, se = line[len(name):].split()[:2]
                assert agrees(estimate, derived.loc[name, "estimate"]), line
                assert agrees(se, derived.loc[name, "std_error"]), line
                checked += 1
    assert checked >= 3


def test_test_cell_example():
    from greyid.datasets.thesis import TEST_CELL_PARAMETERS, test_cell_inputs, test_cell_model

    model = test_cell_model()
    data = test_cell_inputs(seed=1)  # as examples/test_cell.py
    data["Ttr"] = model.simulate(TEST_CELL_PARAMETERS, data, method="exact", seed=1).outputs[0, :, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = model.fit(data)
    lines = output_block("python examples/test_cell.py out/test_cell")
    check(fit, lines)
    assert f"({fit.iterations} iterations)" in "\n".join(lines)


@pytest.mark.parametrize("example", ["armadillo", "annex58"])
def test_file_examples(example):
    from greyid.model.files import read_data

    model = greyid.Model.from_toml(ROOT / "examples" / f"{example}.toml")
    try:
        data = read_data(model)
    except greyid.DataError:
        if (SHARED / "README.md").exists():
            raise
        pytest.skip("the example's shared data are not available")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = model.fit(data)
    check(fit, output_block(f"greyid fit examples/{example}.toml"))


@pytest.mark.skipif(not (SHARED / "prbs1_test_house" / "inputPRBS1.csv").is_file(), reason="PRBS1 data not present")
def test_prbs1_example():
    """Section 3: TiTeTh on the PRBS1 house with four starts, to the digits the guide prints."""
    import pandas as pd

    from greyid import library

    data = pd.read_csv(SHARED / "prbs1_test_house" / "inputPRBS1.csv", sep=";")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = library.load_model("TiTeTh").fit(data, starts=4)
    check(fit, output_block("greyid fit TiTeTh dataset:prbs1 --starts 4"))
