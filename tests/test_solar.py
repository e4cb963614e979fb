"""Solar geometry inputs (pvlib) against spherical trigonometry, and the glazing transmittance function
against the textbook Fresnel formulas, in equations and in a fit."""

import numpy as np
import pandas as pd
import pytest

import greyid
from greyid.data.solar import solar_inputs
from greyid.model.physics import GLASS_INDEX, glazing_transmittance

pytest.importorskip("pvlib")


def test_incidence_on_a_wall_and_the_roof_follows_the_sun():
    times = pd.date_range("2026-03-20 00:00", periods=96, freq="15min", tz="UTC")
    wall = solar_inputs(times, 55.7, 12.5, tilt=90, azimuth=180, dni=np.full(96, 800.0), dhi=np.full(96, 100.0))
    roof = solar_inputs(times, 55.7, 12.5, tilt=0, azimuth=180)
    elevation = wall["solar_elevation"].to_numpy()
    # Horizontal surface: incidence = zenith.  South wall at solar noon: incidence = elevation, and at
    # the equinox the noon elevation is 90° − latitude.
    np.testing.assert_allclose(roof["incidence"], 90 - elevation, atol=1e-6)
    noon = int(np.argmax(elevation))
    assert elevation[noon] == pytest.approx(90 - 55.7, abs=0.6)
    assert wall["incidence"].iloc[noon] == pytest.approx(elevation[noon], abs=1.0)
    # Beam on the wall = DNI cos(incidence) while the sun is up and in front; nothing at night.
    up = elevation > 0
    np.testing.assert_allclose(wall["beam"][up], 800 * wall["cos_incidence"][up], rtol=1e-9)
    assert (wall["beam"][~up] == 0).all() and (wall["diffuse"] >= 0).all()
    np.testing.assert_allclose(wall["global"], wall["beam"] + wall["diffuse"])
    # Isotropic sky on a vertical wall: half the sky's diffuse plus the ground's reflection (albedo 0.25).
    ghi = 100 + 800 * np.clip(np.cos(np.radians(90 - elevation)), 0, None)
    np.testing.assert_allclose(wall["diffuse"], 100 * 0.5 + 0.25 * ghi * 0.5, rtol=1e-6)


def test_solar_inputs_name_bad_input():
    naive = pd.date_range("2026-06-01", periods=3, freq="h")
    with pytest.raises(greyid.DataError, match="no time zone"):
        solar_inputs(naive, 55.7, 12.5, 90, 180)
    times = naive.tz_localize("Europe/Copenhagen")
    with pytest.raises(greyid.DataError, match="row 1 holds"):
        solar_inputs(times, 55.7, 12.5, 90, 180, dni=[1.0, -5.0, 2.0], dhi=[0.0, 0.0, 0.0])
    with pytest.raises(greyid.DataError, match="dni with dhi"):
        solar_inputs(times, 55.7, 12.5, 90, 180, dni=[1.0, 2.0, 3.0])
    split = solar_inputs(times, 55.7, 12.5, 90, 180, ghi=[0.0, 300.0, 500.0])  # Erbs' split of GHI
    assert (split["beam"] >= 0).all() and split["global"].iloc[2] > 0


def test_glazing_transmittance_equals_the_fresnel_formulas():
    r = ((GLASS_INDEX - 1) / (GLASS_INDEX + 1)) ** 2
    for panes in (1, 2, 3):
        assert glazing_transmittance(0.0, panes) == pytest.approx((1 - r) / (1 + (2 * panes - 1) * r), rel=1e-12)
    theta = np.radians(np.array([10.0, 30.0, 60.0, 80.0]))
    refracted = np.arcsin(np.sin(theta) / GLASS_INDEX)
    perpendicular = np.sin(refracted - theta) ** 2 / np.sin(refracted + theta) ** 2
    parallel = np.tan(refracted - theta) ** 2 / np.tan(refracted + theta) ** 2
    for panes in (1.0, 2.0, 3.4):
        textbook = 0.5 * sum((1 - x) / (1 + (2 * panes - 1) * x) for x in (perpendicular, parallel))
        np.testing.assert_allclose(glazing_transmittance(theta, panes), textbook, rtol=1e-12)
    assert glazing_transmittance(np.radians(120.0), 2) == 0.0


def test_effective_number_of_panes_is_estimated_in_an_equation():
    """(7.52): beam gain A·F(θ_inc, N)·G through a window into a one-state room; N recovered from data."""
    m = greyid.Model("window")
    m.add_system("dT = ((Te - T)/(R*C) + A*glazing_transmittance(theta, N)*G/C)*dt + exp(p)*dw1")
    m.add_inputs("Te", "theta", "G")
    m.add_observation("y = T", variance="exp(e)")
    m.set_initial_state(mean={"T": "T0"}, covariance=[[0.1]])
    true = dict(R=2.0, C=5.0, A=4.0, N=2.0, p=-3.0, e=-5.0, T0=20.0)
    for name, value in true.items():
        m.set_parameter(name, init=value * 1.1 if name in "RAN" else value,
                        lower=0.5 if name == "N" else (0.0 if name in "RA" else None),
                        upper=8.0 if name == "N" else None)
    m.set_parameter("C", init=5.0, fixed=True)  # R, C, A alone are determined only as RC and A/C
    hours = np.arange(0, 24 * 12, 0.5)
    # Beam on the glazing through the day at incidences from 0° (noon) to 84° (6 h from noon).
    theta = np.radians(np.abs((hours % 24) - 12) * 14.0)
    sun = np.where(np.abs((hours % 24) - 12) <= 6, 1.0 + 0.5 * np.sin(hours / 17), 0.0)
    data = pd.DataFrame({"t": hours, "Te": 5 + 3 * np.sin(2 * np.pi * hours / 24 / 3), "theta": theta, "G": sun})
    data["y"] = m.simulate(true, data, method="euler", substeps=20, seed=4).outputs[0, :, 0]
    fit = m.fit(data)
    assert fit.converged
    estimate, se = fit.params.loc["N", ["estimate", "std_error"]]
    assert abs(estimate - 2.0) < 3 * se and se < 0.5, (estimate, se)
