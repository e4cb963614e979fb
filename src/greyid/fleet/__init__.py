"""Fleets: one model fitted to many data sets in one call (batched, on Dask, on a GPU).

:func:`fit_many` returns a :class:`FleetResult` (a table with one row per data
set, each data set's :class:`~greyid.estimate.FitResult`); :func:`relate`
regresses the estimates on covariates of the data sets (thesis section 8.4).
"""

from .fit import fit_many
from .population import relate
from .result import FleetResult

__all__ = ["fit_many", "FleetResult", "relate"]
