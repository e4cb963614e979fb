"""Experiment-design benchmarks (issue "Experiment design", section Speed).

    python benchmarks/design.py

On the test-cell model (7.43) with the parameters of section 7.2: the exact
information of the 1512-sample plan of section 7.2 (first call, i.e. with
compilation, and compiled), the Monte Carlo information with 100 paths, an
optimal multisine for the heating (τ = 1 h), and compare_inputs over the eight
candidate signals of table 7.3 (studies/table_7_4.py's plans).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from timing import timed  # noqa: E402


def main():
    from table_7_4 import candidates

    from greyid import design
    from greyid.datasets.thesis import TEST_CELL_PARAMETERS, test_cell_inputs, test_cell_model

    model = test_cell_model()
    plan = test_cell_inputs().drop(columns=list(model.output_names), errors="ignore")
    print("test-cell model (7.43), 1512 samples at 20 min:")
    timed("exact information", lambda: design.fisher_information(model, TEST_CELL_PARAMETERS, plan), repeat=5)
    timed("Monte Carlo information, 100 paths", lambda: design.fisher_information(
        model, TEST_CELL_PARAMETERS, plan, method="montecarlo", n_paths=100), repeat=1)
    timed("optimal multisine (Qh, tau = 1 h, 4 parameters)", lambda: design.optimal_multisine(
        model, TEST_CELL_PARAMETERS, "Qh", 1.0, free=["Hi", "Hm", "Ci", "Cm"], include_noise=False), repeat=1)
    free = ["Hi", "Hm", "Ci", "Cm"]
    box = {"Ci": (0.5 * TEST_CELL_PARAMETERS["Ci"], 2 * TEST_CELL_PARAMETERS["Ci"]),
           "Hm": (0.5 * TEST_CELL_PARAMETERS["Hm"], 2 * TEST_CELL_PARAMETERS["Hm"])}
    timed("Bayesian multisine, 20 prior draws", lambda: design.optimal_multisine(
        model, TEST_CELL_PARAMETERS, "Qh", 1.0, free=free, include_noise=False,
        prior={"mean": {k: TEST_CELL_PARAMETERS[k] for k in box},
               "sd": {k: 0.2 * TEST_CELL_PARAMETERS[k] for k in box}}), repeat=1)
    timed("minimax multisine, 3 x 3 grid on (Ci, Hm)", lambda: design.optimal_multisine(
        model, TEST_CELL_PARAMETERS, "Qh", 1.0, free=free, include_noise=False, minimax=box, levels=3), repeat=1)
    plans = candidates(504)
    timed("compare_inputs, 8 signals of table 7.3 (504 h)", lambda: design.compare_inputs(
        model, TEST_CELL_PARAMETERS, plans, free=["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"],
        interest=["Hi", "Hm", "Ci", "Cm"]), repeat=1)


if __name__ == "__main__":
    main()
