"""Fleets: one model fitted to many data sets in one call (batched, on Dask, on a GPU).

[`fit_many()`][greyid.fleet.fit.fit_many] returns a [`FleetResult`][greyid.fleet.result.FleetResult] (a table with one
row per data
set, each data set's `FitResult`); [`relate()`][greyid.fleet.population.relate]
regresses the estimates on covariates of the data sets (thesis section 8.4).
"""

from .fit import fit_many
from .population import relate
from .result import FleetResult

__all__ = ["fit_many", "FleetResult", "relate"]
