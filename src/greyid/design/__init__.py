"""Design of experiments before measuring (thesis chapter 6 and section 7.3).

* [`fisher_information()`][greyid.design.information.fisher_information] — the information matrix of a planned
experiment
  (a DataFrame of times and inputs, no outputs) at assumed parameter values;
* [`criterion()`][greyid.design.criteria.criterion] — the optimality criteria (6.32)–(6.35), every one minimised, also
in
  their MAP forms (6.53); [`average_criterion()`][greyid.design.criteria.average_criterion] over a prior (J₃) and
  [`minimax_criterion()`][greyid.design.criteria.minimax_criterion] over a box (6.39);
* [`cramer_rao_bound()`][greyid.design.criteria.cramer_rao_bound] — the least variance of unbiased estimates (6.30,
6.35);
* [`local_identifiability()`][greyid.design.information.local_identifiability] — the rank of that information at the
assumed values;
* [`compare_inputs()`][greyid.design.compare.compare_inputs] — candidate plans side by side, criteria and ranks (tables
7.4–7.5);
* [`frequency_information()`][greyid.design.frequency.frequency_information] — information per sample of a sinusoid
(6.47–6.49), and
  [`optimal_multisine()`][greyid.design.multisine.optimal_multisine] — the optimal input of a given power (6.3,
  7.49–7.50), local,
  averaged over a prior (6.36–6.38) or worst case over a box (6.39);
* [`sampling_table()`][greyid.design.sampling.sampling_table] — information per sample and per unit time against the
  sampling interval, and the joint input/sampling design (6.4, 6.72);
* `identifiability()` — structural identifiability before any data (6.1).
"""

from .compare import compare_inputs
from .criteria import CRITERIA, average_criterion, cramer_rao_bound, criterion, minimax_criterion, with_prior
from .frequency import frequency_information, frequency_information_grid, frequency_information_points
from .multisine import MultisineDesign, optimal_multisine
from .identifiability import Identifiability, identifiability
from .information import fisher_information, local_identifiability
from .sampling import aliased, sampling_table

__all__ = ["fisher_information", "local_identifiability", "cramer_rao_bound", "criterion", "CRITERIA",
           "average_criterion", "minimax_criterion", "with_prior", "compare_inputs", "frequency_information",
           "frequency_information_grid", "frequency_information_points", "optimal_multisine", "MultisineDesign",
           "sampling_table", "aliased",
           "identifiability", "Identifiability"]
