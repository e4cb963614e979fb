"""The filters' protocol: a family is a module with ``prepare``, run by the one driver.

A family written here, outside greyid, whose state is not a mean and a covariance
(a dictionary that also counts the rows it has seen and carries a derived scalar),
runs through the driver's summed and per-row scans and gives the exact Kalman
filter's log-likelihood; every built-in method is a registered family.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import random_linear_parameters
from greyid.estimate.criteria import step_criterion
from greyid.filters import driver, kalman, protocol
from greyid.filters.api import filter_options, prepare_datasets
from greyid.filters.updates import GaussianState, StepTerms
from test_kalman_dense import random_data


class CountedUpdate(NamedTuple):
    """What the driver needs of an update: the state carried on and the step's terms."""

    state: dict
    terms: StepTerms


def counted_prepare(structure, options):
    """The exact Kalman filter's steps, with the state a dict {"gaussian", "rows"}."""
    inner = kalman.prepare(structure, dataclasses.replace(options, method=protocol.KALMAN))

    def steps(theta, data):
        parts = inner(theta, data)

        def predict(state, row):
            predicted, transition = parts.predict(state["gaussian"], row)
            return {"gaussian": predicted, "rows": state["rows"]}, transition

        def update(state, row, mask=None):
            upd, y_pred = parts.update(state["gaussian"], row, mask)
            return CountedUpdate({"gaussian": upd.state, "rows": state["rows"] + 1}, upd.terms), y_pred

        initial = {"gaussian": parts.initial, "rows": jnp.zeros((), jnp.int32)}
        return protocol.FilterSteps(initial, parts.rows, predict, update)

    return steps


@pytest.fixture
def counted_family(monkeypatch):
    monkeypatch.setattr(protocol, "METHODS", (*protocol.METHODS, "counted"))
    monkeypatch.setitem(driver.FAMILIES, "counted", counted_prepare)


def test_every_method_is_a_registered_family_or_marginal():
    assert set(driver.FAMILIES) | set(driver.MARGINALS) == set(protocol.METHODS)
    assert not set(driver.FAMILIES) & set(driver.MARGINALS)


def test_a_family_with_its_own_state_runs_through_the_driver(linear_model, counted_family):
    rng = np.random.default_rng(7)
    params, _ = random_linear_parameters(rng)
    frame, *_ = random_data(rng, N=45)
    structure = linear_model.structure
    theta = linear_model.parameter_vector(params)
    (_, inputs), = prepare_datasets(structure, theta, frame, "t", "zoh", None)
    reference = filter_options(structure, "kalman")
    counted = dataclasses.replace(reference, method="counted")

    def summed(options):
        return float(driver.make_summed_filter(structure, options, step_criterion)(jnp.asarray(theta), inputs))

    assert summed(counted) == pytest.approx(summed(reference), rel=1e-12)
    # The per-row scan hands the driver's collect the family's own predicted state.
    seen = driver.scan_rows(driver.filter_steps(structure, counted)(jnp.asarray(theta), inputs),
                            inputs.t.shape[0], lambda predicted, transition, upd, y_pred: upd.state["rows"])
    np.testing.assert_array_equal(np.asarray(seen), np.arange(1, inputs.t.shape[0] + 1))
    assert isinstance(driver.filter_steps(structure, reference)(jnp.asarray(theta), inputs).initial, GaussianState)
