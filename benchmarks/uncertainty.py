"""Uncertainty benchmarks (issue "Uncertainty beyond the Hessian", section Speed).

    python benchmarks/uncertainty.py

On the Armadillo fit (pySIP's TwTi_RoRi, first-order hold, 232 rows, 7 free
parameters; the data set armadillo): a profile of 21 points of
Cw (first call and compiled), the profile intervals of all seven parameters,
the profile of a derived quantity (UA = 1/(Ri + Ro)), NUTS with 4 chains of
1000 draws after 500 warm-up steps (first call, with compilation, and again),
and 12-step predictions with 200 parameter draws.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import timed  # noqa: E402



def main():
    import greyid
    from greyid.datasets.reference import armadillo_model

    warnings.simplefilter("ignore")
    model = armadillo_model()
    data = greyid.datasets.fetch("armadillo").iloc[:-1]
    fit = model.fit(data, time="Time", hold="foh")
    print(f"Armadillo fit: log L {fit.loglik:.4f}, {fit.n_params} free parameters")
    timed("profile of Cw, 21 points", lambda: fit.profile("Cw"), repeat=3)
    timed("profile intervals, 7 parameters", lambda: fit.conf_int(method="profile"), repeat=1)
    timed("profile of UA = 1/(Ri + Ro), 21 points", lambda: fit.profile("UA", expression="1/(Ri+Ro)"), repeat=1)
    posterior = timed("NUTS, 4 chains x (500 warm-up + 1000 draws)", lambda: fit.sample(), repeat=1)
    print(f"    divergences {posterior.divergences}, max R-hat {posterior.r_hat.max():.4f}, "
          f"min ESS {posterior.ess.min():.0f}")
    timed("12-step predictions with 200 parameter draws", lambda: fit.predict(
        steps=12, parameter_uncertainty=True), repeat=3)


if __name__ == "__main__":
    main()
