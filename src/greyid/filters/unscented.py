"""The unscented Kalman filter (section 4.2.3).

Time update: the moment equations (4.19)–(4.20) with the expectations of f and
G Gᵀ over sigma points, integrated with the EKF's exponential sub-steps.
Measurement update: the output's moments over sigma points.
"""

from __future__ import annotations

from ..model.structure import Structure
from .gaussian import interval_steps, observation_noise
from .predictors import sigma_weights, unscented_predict, unscented_update
from .protocol import UKF, FilterOptions


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data) -> FilterSteps`` of the UKF with the options' α, β and κ."""
    assert options.method == UKF, options.method
    form = options.form
    weights = sigma_weights(structure.n_states, options.alpha, options.beta, options.kappa)

    def predict_interval(x, cov, interval, theta):
        return unscented_predict(x, cov, interval, theta, structure.drift, structure.diffusion, options.substeps,
                                 form, weights)

    def update(state, row, mask, theta):
        noise = observation_noise(structure, theta, state.mean, row.u_cur, row.t)
        return unscented_update(*state, row.y, mask, row.u_cur, row.t, theta, structure.observation, noise, form,
                                weights)

    return interval_steps(structure, options, predict_interval, update)
