"""The minimiser: trust-region subproblem, Newton steps, rejected steps, honest convergence."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

from greyid.estimate.lbfgs import conditional_scales, quasi_newton_start, scaled_difference_hessian
from greyid.estimate.trust_region import newton_trust_region, trust_region_step


def derivatives(f):
    return jax.jit(lambda z: (f(z), jax.grad(f)(z), jax.hessian(f)(z)))


def rosenbrock(z):
    return jnp.sum(100.0 * (z[1:] - z[:-1] ** 2) ** 2 + (1.0 - z[:-1]) ** 2)


def test_trust_region_step_solves_the_subproblem():
    """The step's model value is the constrained minimum (reference: SLSQP from many starts)."""
    rng = np.random.default_rng(3)
    for case in range(12):
        n = int(rng.integers(2, 6))
        B = rng.normal(size=(n, n))
        H = B + B.T + (case % 3 - 1) * 2.0 * np.eye(n)  # indefinite, mixed and positive cases
        g = rng.normal(size=n)
        radius = float(rng.uniform(0.1, 3.0))
        w, V = np.linalg.eigh(H)
        p = trust_region_step(w, V, g, radius)

        def model(q):
            return g @ q + 0.5 * q @ H @ q

        best = min(
            minimize(model, rng.normal(size=n) * radius / np.sqrt(n), method="SLSQP",
                     constraints=[{"type": "ineq", "fun": lambda q: radius**2 - q @ q}]).fun
            for _ in range(8))
        assert np.linalg.norm(p) <= radius * (1 + 1e-5)
        assert model(p) <= best + 1e-6 * max(1.0, abs(best))


def test_hard_case_leaves_a_saddle_point():
    """At a saddle the gradient vanishes: the step follows the negative curvature."""
    H = np.diag([-2.0, 1.0])
    w, V = np.linalg.eigh(H)
    p = trust_region_step(w, V, np.zeros(2), 0.5)
    assert abs(p[0]) == pytest.approx(0.5) and p[1] == pytest.approx(0.0)

    opt = newton_trust_region(derivatives(lambda z: z[1] ** 2 - z[0] ** 2 + z[0] ** 4), np.zeros(2))
    assert opt.converged and abs(opt.z[0]) == pytest.approx(np.sqrt(0.5), abs=1e-8)
    assert opt.value == pytest.approx(-0.25, abs=1e-12)


@pytest.mark.parametrize("n", [2, 3])  # (n ≥ 4 has a second local minimum)
def test_newton_finds_the_rosenbrock_minimum(n):
    opt = newton_trust_region(derivatives(rosenbrock), np.tile([-1.2, 1.0], n)[:n], maxiter=200)
    assert opt.converged, opt.message
    assert opt.value < 1e-11 and opt.z == pytest.approx(np.ones(n), abs=1e-5)
    assert opt.iterations < 40
    assert opt.hessian == pytest.approx(np.asarray(jax.hessian(rosenbrock)(jnp.asarray(opt.z))))


def test_badly_scaled_problem_takes_no_more_steps():
    """The scaled trust region makes the steps independent of the parameters' units."""
    def scaled(z):
        return rosenbrock(z * jnp.array([1e3, 1e-3]))

    plain = newton_trust_region(derivatives(rosenbrock), np.array([-1.2, 1.0]))
    stretched = newton_trust_region(derivatives(scaled), np.array([-1.2e-3, 1e3]))
    assert stretched.converged and stretched.z == pytest.approx([1e-3, 1e3], rel=1e-5)
    assert stretched.iterations <= plain.iterations + 2


def test_non_finite_evaluation_is_a_rejected_step():
    def f(z):  # z − log z, undefined (NaN) for z < 0, minimum at z = 1
        return jnp.sum(z - jnp.log(z))

    # From z = 6 the first Newton step lands at z = −24, where f is NaN.
    opt = newton_trust_region(derivatives(f), np.array([6.0]), maxiter=100)
    assert opt.converged and opt.z[0] == pytest.approx(1.0, abs=1e-8)
    assert opt.evaluations > opt.iterations + 1  # at least one step was rejected


def test_stopping_early_is_not_called_converged():
    opt = newton_trust_region(derivatives(rosenbrock), np.array([-1.2, 1.0]), maxiter=3)
    assert not opt.converged and "maximum number of iterations" in opt.message
    assert opt.iterations == 3


def test_coordinate_without_curvature_at_the_start_still_moves():
    """A coordinate in a Huber norm's linear part, curvature 2e-31 and slope 2 (an initial state
    seen only through an outlier): its trust-region scale is floored, so trial steps in it are
    not 1e15 long and the region does not collapse at the start (it did, after 19 evaluations)."""
    def f(z):
        a = jnp.abs(z[1])
        huber = jnp.where(a < 1.0, z[1] ** 2, 2.0 * a - 1.0)
        return (z[0] - 1.0) ** 2 + huber + 1e-31 * z[1] ** 2

    z0 = np.array([3.0, 3.0])
    assert float(jax.hessian(f)(jnp.asarray(z0))[1, 1]) == pytest.approx(2e-31)
    opt = newton_trust_region(derivatives(f), z0, maxiter=500)
    assert opt.converged, opt.message
    np.testing.assert_allclose(opt.z, [1.0, 0.0], atol=1e-8)


def test_quasi_newton_from_a_nearby_hessian_reaches_the_exact_minimum_on_gradients_alone():
    """Warm start near the optimum with the Hessian of another point (as a profile's refits have):
    BFGS steps ask only for values and gradients and reach Newton's minimum (1e-9)."""
    from greyid.estimate.optimize import EXACT, GRADIENT, run_alone
    from greyid.estimate.trust_region import Search

    def f(z):  # smooth, non-quadratic, minimum near (1, -0.5, 2)
        return (jnp.sum(jnp.exp(0.3 * (z - jnp.array([1.0, -0.5, 2.0]))) - 0.3 * z)
                + 0.5 * (z[0] - z[1]) ** 2 + 0.1 * (z[1] * z[2]) ** 2)

    exact = derivatives(f)
    reference = newton_trust_region(exact, np.zeros(3))
    asked = []

    def gradient(z):
        asked.append(GRADIENT)
        return f(z), jax.grad(f)(z)

    start = reference.z + np.array([0.3, -0.2, 0.25])
    search = Search(start, maxiter=50, hessian=np.asarray(exact(reference.z + 0.5)[2]))
    quasi = run_alone(search, {GRADIENT: gradient, EXACT: lambda z: pytest.fail("an exact Hessian was asked")})
    assert reference.converged and quasi.converged
    np.testing.assert_allclose(quasi.z, reference.z, atol=1e-5)  # decrement 1e-12: z to ~1e-5 here
    assert quasi.value == pytest.approx(reference.value, abs=1e-9)
    assert len(asked) <= 15


def test_value_expansions_save_scoring_steps_and_reach_the_same_minimum():
    """Scoring from far away (long-series fits): steps held back by the region grow by value alone
    and the search reaches the minimum of a plain scoring search with fewer scoring evaluations."""
    from greyid.estimate.optimize import EXACT, SCORING, VALUE, run_alone
    from greyid.estimate.trust_region import Search

    t = np.linspace(0.0, 20.0, 400)
    y = 3.0 * np.exp(-0.5 * t) + 0.01 * np.random.default_rng(5).normal(size=t.size)

    def residuals(z):  # z = (log a, log b)
        return y - jnp.exp(z[0]) * jnp.exp(-jnp.exp(z[1]) * t)

    def f(z):
        return 0.5 * jnp.sum(residuals(z) ** 2)

    exact = derivatives(f)

    def scoring(z):
        J = jax.jacfwd(residuals)(z)
        return f(z), jax.grad(f)(z), J.T @ J

    def run(expand):
        counts = {SCORING: 0, VALUE: 0, EXACT: 0}

        def counted(kind, fun):
            def evaluate(z):
                counts[kind] += 1
                return fun(z)
            return evaluate

        search = Search(np.array([np.log(0.05), np.log(0.01)]), maxiter=200, scoring=True, value=True,
                        handover=0.0, expand=expand)
        programs = {SCORING: counted(SCORING, scoring), EXACT: counted(EXACT, exact),
                    VALUE: counted(VALUE, lambda z: (f(z),))}
        return run_alone(search, programs), counts

    plain, plain_counts = run(False)
    grown, grown_counts = run(True)
    assert plain.converged and grown.converged
    np.testing.assert_allclose(grown.z, plain.z, atol=1e-7)
    np.testing.assert_allclose(np.exp(grown.z), [3.0, 0.5], rtol=0.02)
    assert grown_counts[SCORING] < plain_counts[SCORING]
    assert grown_counts[VALUE] > 0


def test_quasi_newton_start_descends_within_its_budget_and_stops_at_a_non_finite_value():
    """L-BFGS from the start: the best point seen (its value the function's there), near the
    minimum given evaluations, held to its budget, and ended by the first non-finite value."""
    value_and_grad = jax.jit(jax.value_and_grad(rosenbrock))
    z0 = np.array([-1.2, 1.0])
    full = quasi_newton_start(value_and_grad, z0, 200)
    assert full.value == pytest.approx(float(rosenbrock(full.z)), rel=1e-12)
    assert full.value < 1e-6 and full.z == pytest.approx(np.ones(2), abs=1e-2)
    assert full.iterations < full.evaluations < 100
    short = quasi_newton_start(value_and_grad, z0, 10)
    assert short.evaluations <= 11 and 0 < short.iterations < 10  # SciPy may finish the line search
    assert float(rosenbrock(z0)) > short.value > full.value

    walled = jax.jit(jax.value_and_grad(lambda z: jnp.where(z[0] < -1.0, rosenbrock(z), jnp.inf)))
    stopped = quasi_newton_start(walled, z0, 200)
    assert stopped.evaluations < 10 and stopped.z[0] < -1.0 and np.isfinite(stopped.value)
    assert stopped.value <= float(rosenbrock(z0))
    nowhere = quasi_newton_start(walled, np.array([0.0, 1.0]), 200)
    assert nowhere.evaluations == 1 and nowhere.value == np.inf and np.array_equal(nowhere.z, [0.0, 1.0])


def test_a_search_is_explicit_state_that_can_be_copied_and_continued():
    """init/step: the state says what it asks for next and where it stands; a copy taken halfway
    continues to the same optimum as the original (nothing lives outside the state), and a search
    stopped halfway reports where it stood."""
    import copy

    from greyid.estimate.optimize import EXACT, settle
    from greyid.estimate.trust_region import Search

    def f(z):
        return (1 - z[0]) ** 2 + 100 * (z[1] - z[0] ** 2) ** 2

    exact = derivatives(f)
    search = Search(np.array([-1.2, 1.0]), maxiter=200)
    state = search.init()
    assert state.request[0] == EXACT and np.array_equal(state.request[1], [-1.2, 1.0])
    for _ in range(10):
        state = search.step(state, settle(exact(state.request[1])))
    assert state.optimum is None and state.iterations > 0 and np.isfinite(state.f)
    stopped = search.stopped(state, "stopped by hand")
    assert not stopped.converged and stopped.message == "stopped by hand"
    np.testing.assert_array_equal(stopped.z, state.z)
    halfway = copy.deepcopy(state)

    def finish(state):
        while state.optimum is None:
            state = search.step(state, settle(exact(state.request[1])))
        return state.optimum

    first, second = finish(state), finish(halfway)
    assert first.converged and second.converged
    np.testing.assert_array_equal(first.z, second.z)
    assert first.iterations == second.iterations and first.evaluations == second.evaluations
    np.testing.assert_allclose(first.z, [1.0, 1.0], atol=1e-5)  # a decrement of 1e-12 leaves z to ~1e-6


def test_the_scaled_difference_hessian_recovers_a_badly_scaled_curvature():
    """Two passes of central differences: from a step guess 2e5 times too large along a stiff coordinate,
    the second pass's steps of conditional standard deviations give the exact Hessian of a quartic
    (its third derivative makes a too-large step's difference wrong)."""
    curvature = np.array([[4.0e6, 1.0e3], [1.0e3, 2.0]])

    def f(z):
        return 0.5 * z @ curvature @ z + 1e6 * z[0] ** 4 + z[1] ** 4

    def value_and_grad(z):
        return f(z), curvature @ z + np.array([4e6 * z[0] ** 3, 4 * z[1] ** 3])

    z = np.array([1e-3, 0.5])
    exact = curvature + np.diag([12e6 * z[0] ** 2, 12 * z[1] ** 2])
    guessed = np.array([100.0, 1.0])
    H = scaled_difference_hessian(value_and_grad, z, guessed)
    np.testing.assert_allclose(H, exact, rtol=1e-7)
    np.testing.assert_allclose(conditional_scales(np.diag(H), guessed), 1 / np.sqrt(np.diag(exact)), rtol=1e-7)
    # Where the curvature is not a positive finite number, the guess stays.
    np.testing.assert_array_equal(conditional_scales(np.array([-1.0, np.nan]), guessed), guessed)


def test_an_lbfgs_search_whose_difference_hessian_is_not_finite_ends_unconverged_and_says_why():
    """At an optimum on the edge of where the model is defined (here the gradient is NaN for z₀ > 0), a
    difference step of the Hessian lands outside: the search ends, not converged, with the best point and a
    message that says the Hessian by differences is not finite (not numpy's error from its eigenvalues)."""
    from greyid.estimate.lbfgs import lbfgs_search

    def value_and_grad(z):
        gradient = np.array([z[0], 2.0 * z[1]])
        if z[0] > 0:
            gradient[0] = np.nan
        return 0.5 * z[0] ** 2 + z[1] ** 2, gradient

    optimum = lbfgs_search(value_and_grad, np.array([-1.0, 1.0]), maxiter=100)
    assert not optimum.converged
    assert "Hessian by differences of the gradient is not finite" in optimum.message
    assert not np.all(np.isfinite(optimum.hessian))
    assert optimum.value < 1e-10 and np.all(np.isfinite(optimum.z))
