"""The extended Kalman filter and its iterated form (section 4.2.1).

Time update: the sub-sampled local linearization of appendix A.4 (A.46–A.50),
exact for linear models.  Measurement update: h linearized about the predicted
mean (4.27–4.29), or, iterated (``iekf``), about the latest estimate (4.43).
"""

from __future__ import annotations

from ..model.structure import Structure
from .gaussian import interval_steps, linearized_update
from .predictors import extended_predict
from .protocol import EKF, IEKF, FilterOptions


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data) -> FilterSteps`` of the EKF (``method="ekf"``) or the iterated EKF (``"iekf"``)."""
    assert options.method in (EKF, IEKF), options.method
    iterations = options.iterations if options.method == IEKF else 1

    def predict_interval(x, cov, interval, theta):
        return extended_predict(x, cov, interval, theta, structure.drift, structure.diffusion, options.substeps,
                                options.form)

    def update(state, row, mask, theta):
        return linearized_update(structure, theta, options.form, state, row, mask, iterations=iterations)

    return interval_steps(structure, options, predict_interval, update)
