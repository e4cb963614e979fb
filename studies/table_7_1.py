"""Thesis table 7.1 (and 7.2 with --horizon 4): the test-cell model of section 7.2.

    python studies/table_7_1.py [--series 50] [--horizon 1] [--seed 0] [--cov-type sandwich]

50 series of 1512 samples at 20 minutes are simulated from the model (7.43)
with the parameters of section 7.2, PRBS heating of order 6 with an 8 h clock
between 0 and 300 W and an outdoor temperature with a daily cycle; each series
is fitted by maximum likelihood with the 1-step (or k-step) criterion.  The
estimated variances are the fit's default (the Hessian for 1 step, the sandwich
for k steps) or those of ``--cov-type``.  The last column is the Cramér–Rao
bound of the design, from its exact Fisher information.
"""

import argparse
import time

from common import print_table

from greyid import design
from greyid.datasets.thesis import TEST_CELL_DERIVED, TEST_CELL_PARAMETERS, test_cell_inputs, test_cell_model
from greyid.fleet.study import run_study


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--series", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cov-type", choices=["hessian", "opg", "sandwich"], default=None)
    args = parser.parse_args()
    started = time.perf_counter()
    model, plan = test_cell_model(), test_cell_inputs(seed=args.seed)
    # The Cramér–Rao bound of this design, beside the table: the least variance any
    # unbiased estimator can reach (thesis: its σ²₁,m row lies 5–7 times below it).
    info = design.fisher_information(model, TEST_CELL_PARAMETERS, plan.drop(columns=list(model.output_names),
                                                                             errors="ignore"))
    bound = design.cramer_rao_bound(info, TEST_CELL_PARAMETERS, TEST_CELL_DERIVED)
    study = run_study(
        model, TEST_CELL_PARAMETERS, plan, args.series,
        report=["Hi", "Hm", "Ci", "Cm", "s1i", "s1m", "s2"], derived=TEST_CELL_DERIVED, seed=args.seed + 1,
        simulate={"method": "exact"}, fit={"horizon": args.horizon, "cov_type": args.cov_type}, progress=True,
    )
    covariance = args.cov_type or ("hessian" if args.horizon == 1 else "sandwich")
    print_table(f"Table 7.{1 if args.horizon == 1 else 2}: test-cell model, {args.horizon}-step criterion, "
                f"{covariance} covariance",
                study, started, bound)


if __name__ == "__main__":
    main()
