"""Filter and smoother results as pandas objects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class FilterResult:
    """Output of a continuous–discrete filter on one data set.

    Means are DataFrames indexed like the data; covariances are arrays of shape
    (N, n, n).  Innovations ε_k and their covariances R_k (4.32–4.33) are NaN
    where an output was not observed.
    """

    method: str
    times: pd.Series
    predicted: pd.DataFrame  # x_{k|k-1}
    predicted_cov: np.ndarray  # P_{k|k-1}
    filtered: pd.DataFrame  # x_{k|k}
    filtered_cov: np.ndarray  # P_{k|k}
    output_predictions: pd.DataFrame  # ŷ_{k|k-1}
    innovations: pd.DataFrame  # ε_k
    innovation_cov: np.ndarray  # R_{k|k-1}
    loglik_terms: pd.Series
    transitions: np.ndarray  # Φ over the interval ending at row k (for smoothing)
    #: Rows whose measurement update gave a covariance that was not positive semi-definite and was
    #: replaced by the guarded (Joseph) form (UKF and second-order filters; see ``filters.predictors``).
    guarded: pd.Series | None = None
    #: One-step-ahead quantile residuals Φ⁻¹(u_k), u_k the probability integral transform of y_k under the
    #: filter's predictive law (randomized for counts): standard normal where the model is right, whatever the
    #: observations' distribution (NaN where unobserved).  The particle filter's come from its predicted
    #: particles; a Gaussian filter's (and the ensemble Kalman filter's) are the standardized innovations,
    #: its predictive law being N(ŷ, R_k).
    quantile_residuals: pd.DataFrame | None = None
    #: Each latent force's filtered value H x_{k|k} and its standard deviation (columns ``<force>``,
    #: ``<force>_sd``), where the model has latent forces.
    latent_forces: pd.DataFrame | None = None

    @property
    def loglik(self) -> float:
        """Gaussian log-likelihood (3.18) with the full constant."""
        return float(self.loglik_terms.sum())

    @property
    def n_obs(self) -> int:
        """Number of observed output elements."""
        return int(self.innovations.notna().to_numpy().sum())

    @property
    def standardized_innovations(self) -> pd.DataFrame:
        """ε_k,i / √R_k,ii per output (NaN where unobserved)."""
        sd = np.sqrt(np.diagonal(self.innovation_cov, axis1=1, axis2=2))
        return self.innovations / sd

    @property
    def predicted_std(self) -> pd.DataFrame:
        sd = np.sqrt(np.diagonal(self.predicted_cov, axis1=1, axis2=2))
        return pd.DataFrame(sd, index=self.predicted.index, columns=self.predicted.columns)

    @property
    def filtered_std(self) -> pd.DataFrame:
        sd = np.sqrt(np.diagonal(self.filtered_cov, axis1=1, axis2=2))
        return pd.DataFrame(sd, index=self.filtered.index, columns=self.filtered.columns)


@dataclass(frozen=True)
class SmootherResult:
    """Smoothed states x_{k|N}, P_{k|N}: Rauch–Tung–Striebel after a filter, or the Laplace method's mode and its
    marginal covariances (``filter_result`` None)."""

    times: pd.Series
    smoothed: pd.DataFrame
    smoothed_cov: np.ndarray
    filter_result: FilterResult | None
    #: Each latent force's smoothed value H x_{k|N} and its standard deviation (columns ``<force>``,
    #: ``<force>_sd``), where the model has latent forces.
    latent_forces: pd.DataFrame | None = None

    @property
    def smoothed_std(self) -> pd.DataFrame:
        sd = np.sqrt(np.diagonal(self.smoothed_cov, axis1=1, axis2=2))
        return pd.DataFrame(sd, index=self.smoothed.index, columns=self.smoothed.columns)
