"""Second-order filters (section 4.2.2): the EKF with bias corrections and the modified truncated and
Gaussian second-order filters.

* ``ekf2``: the EKF with the second-order terms of the mean's prediction (4.58) and
  of the predicted output (4.60);
* ``truncated2`` and ``gaussian2``: the same mean's prediction with the noise
  correction of the covariance, and a moment-based update whose output
  covariance holds the second-order terms (truncated, or with the Gaussian
  fourth moments).
"""

from __future__ import annotations

from ..model.structure import Structure
from .gaussian import interval_steps, linearized_update, observation_noise
from .predictors import extended_predict, second_order_update
from .protocol import EKF2, GAUSSIAN2, SECOND_ORDER, FilterOptions


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data) -> FilterSteps`` of ``ekf2``, ``truncated2`` or ``gaussian2``."""
    method, form = options.method, options.form
    assert method in (EKF2, *SECOND_ORDER), method

    def predict_interval(x, cov, interval, theta):
        return extended_predict(x, cov, interval, theta, structure.drift, structure.diffusion, options.substeps,
                                form, bias_correction=True, noise_correction=method in SECOND_ORDER)

    def update(state, row, mask, theta):
        if method == EKF2:
            return linearized_update(structure, theta, form, state, row, mask, bias=True)
        noise = observation_noise(structure, theta, state.mean, row.u_cur, row.t)
        return second_order_update(*state, row.y, mask, row.u_cur, row.t, theta, structure.observation, noise, form,
                                   gaussian=method == GAUSSIAN2)

    return interval_steps(structure, options, predict_interval, update)
