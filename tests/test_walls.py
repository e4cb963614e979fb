"""Heat diffusion through a wall (thesis 7.1): the lumped networks of the infinite product expansion against
the thesis' (7.20) and (7.23), the exact response against a fine finite-difference ladder, the wall model's
transfer function against its ladder."""

import jax
import numpy as np
import pytest

import greyid
from greyid.library.walls import ladder_polynomials, lumped_wall, wall_frequency_response, wall_model


def test_first_and_second_order_networks_are_the_thesis():
    r, c = lumped_wall(1)
    np.testing.assert_allclose(r, [0.25, 0.75], atol=5e-5)
    np.testing.assert_allclose(c, [0.5404], atol=5e-5)
    r, c = lumped_wall(2)
    np.testing.assert_allclose(r, [0.1406, 0.3125, 0.5469], atol=5e-5)
    np.testing.assert_allclose(c, [0.2882, 0.3705], atol=5e-5)


@pytest.mark.parametrize("order", [3, 6])
def test_higher_orders_keep_the_gain_and_the_first_zeros(order):
    r, c = lumped_wall(order)
    k = np.arange(1, order + 1)
    b, _ = ladder_polynomials(r, c, -(k * np.pi) ** 2)
    _, d = ladder_polynomials(r, c, -((k - 0.5) * np.pi) ** 2)
    assert r.sum() == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(np.abs(b), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(d), 0.0, atol=1e-9)
    assert lumped_wall(2)[1].sum() < c.sum() < 1.0  # Σc → C as the order grows


def test_exact_response_is_the_limit_of_a_fine_ladder_and_lumped_ones_approach_it():
    R, C = 2.5, 4.0e5 / 3.6e6  # K m²/W and a capacity in units that make RC about 0.28
    omega = np.geomspace(1e-2, 1e3, 60)
    table = wall_frequency_response(R, C, omega, orders=(1, 2, 4))
    # Finite volumes on 400 slices: a node at each slice's centre holding C/400, R/400 between neighbours
    # and R/800 from the outer nodes to the surfaces.
    slices = 400
    r_fine = np.concatenate([[R / (2 * slices)], np.full(slices - 1, R / slices), [R / (2 * slices)]])
    c_fine = np.full(slices, C / slices)
    b, d = ladder_polynomials(r_fine, c_fine, 1j * omega)
    np.testing.assert_allclose(table["exact_BD_gain"], np.abs(b / d), rtol=2e-3)
    np.testing.assert_allclose(table["exact_D_gain"], np.abs(1 / d), rtol=2e-3, atol=1e-12)
    assert table["exact_BD_gain"].iloc[0] == pytest.approx(R, rel=1e-3)  # the static heat balance (7.14)
    # Each order is adequate (response within 0.01 of the exact one, in complex terms) over a wider band.
    exact = table["exact_BD_gain"] * np.exp(1j * np.radians(table["exact_BD_phase"]))
    edges = []
    for n in (1, 2, 4):
        lumped = table[f"order{n}_BD_gain"] * np.exp(1j * np.radians(table[f"order{n}_BD_phase"]))
        edges.append(np.argmax(np.abs(lumped - exact) > 0.01 * R))
    assert 0 < edges[0] < edges[1] < edges[2]
    with pytest.raises(greyid.ModelError, match="positive"):
        wall_frequency_response(-1.0, C, omega)


def test_wall_model_has_the_ladder_transfer_function():
    m = wall_model(3)
    assert m.state_names == ("T1", "T2", "T3") and m.output_names == ("q1",)
    r, c = lumped_wall(3)
    params = dict(m.initial_values())
    params.update({f"r{i}": 2.0 * v for i, v in enumerate(r, start=1)})
    params.update({f"c{i}": 5.0 * v for i, v in enumerate(c, start=1)})
    s = m.structure
    theta = np.asarray(m.parameter_vector(params))
    x0, u0 = np.zeros(3), np.zeros(2)
    A = np.asarray(jax.jacfwd(s.drift, argnums=0)(x0, u0, 0.0, theta))
    B = np.asarray(jax.jacfwd(s.drift, argnums=1)(x0, u0, 0.0, theta))
    Cm = np.asarray(jax.jacfwd(s.observation, argnums=0)(x0, u0, 0.0, theta))
    D = np.asarray(jax.jacfwd(s.observation, argnums=1)(x0, u0, 0.0, theta))
    for w in (0.01, 0.3, 4.0):
        G = Cm @ np.linalg.solve(1j * w * np.eye(3) - A, B) + D  # q1 from (v1, v2)
        b, d = ladder_polynomials(2.0 * r, 5.0 * c, 1j * w)
        # With v2 = 0: v1 = B q2, q1 = D q2, so q1/v1 = D/B; with v1 = 0: q1/v2 = −1/B.
        assert G[0, 0] == pytest.approx(d / b, rel=1e-10)
        assert G[0, 1] == pytest.approx(-1 / b, rel=1e-10)
    assert m.derived["U"] == "1/(r1 + r2 + r3 + r4)"


def test_walls_load_from_the_library_and_round_trip_their_model_file():
    from greyid import library

    m = library.load_model("wall4")
    assert m.state_names == ("T1", "T2", "T3", "T4") and "wall2" in library.names()
    again = greyid.Model.from_toml(m.to_toml())
    assert again.state_names == m.state_names and again.derived == m.derived
