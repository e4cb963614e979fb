"""Fleets: one model fitted to many data sets in one call (batched, on Dask, on a GPU).

[`fit_many()`][greyid.fleet.fit.fit_many] returns a [`FleetResult`][greyid.fleet.result.FleetResult] (a table with one
row per data
set, each data set's `FitResult`); [`relate()`][greyid.fleet.population.relate]
regresses the estimates on covariates of the data sets (thesis section 8.4);
[`run_study()`][greyid.fleet.study.run_study] fits a model to many series simulated from it (a Monte Carlo
validation of the estimator, thesis section 7.2).
"""

from .fit import fit_many
from .population import relate
from .result import FleetResult
from .study import StudyResult, run_study

__all__ = ["fit_many", "FleetResult", "relate", "run_study", "StudyResult"]
