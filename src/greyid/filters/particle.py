"""The bootstrap particle filter: the likelihood of any model and any observation distribution, estimated.

The filter carries P particles x^i with normalised log-weights (a
[`ParticleState`][greyid.filters.particle.ParticleState]).  Row k

* predicts each particle over the interval: for a time-invariant linear model by
  sampling its exact transition (Φ x + Γ b, Λ of (4.36)–(4.39)), otherwise by
  ``substeps`` Euler–Maruyama steps of dx = f dt + G dω;
* weighs each particle by the observations' density p(y_k | x^i)
  ([`distributions`][greyid.model.distributions]), the step's log-likelihood being
  log Σ_i w^i p(y_k | x^i) (the bootstrap filter's unbiased estimate of p(y_k | y_1..k−1),
  Gordon, Salmond & Smith 1993);
* resamples (systematic) where the effective sample size 1/Σ w_i² falls below
  ``resample`` · P.

Random numbers are fixed by ``seed`` (common random numbers): the estimate is a
deterministic function of θ, which an optimiser can work on.  Resampling picks
particles by index, which has no derivative; it is taken with a stop-gradient
(Ścibior & Wood 2021): after resampling each weight is w^a / ⊥(w^a), whose value is
uniform and whose derivative keeps the weights' own.  The value is the ordinary
bootstrap estimate; the gradient is the particle estimate of the score by
Fisher's identity, consistent as P grows, without the (discontinuous) effect of
which particles the resampling picks.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp

from ..model.distributions import moments, observations_log_density, probability_integral_transform
from ..model.structure import Structure
from . import small
from .delays import piece_drift, step_pieces
from .discretize import discretize, discretize_each
from .gaussian import initial_state
from .proposals import BOOTSTRAP, guided_draw, linearise
from .protocol import FilterInputs, FilterOptions, FilterSteps, Row, series_rows
from .updates import DensityTerms, observed_root, whiten

#: Random numbers for the initial particles, the rows' predictions and their resampling are drawn
#: from keys folded from the seed's with these tags.
_START, _PREDICT, _RESAMPLE, _PIT = 0, 1, 2, 4
#: The most standard normal numbers drawn before the scan (64 MB); a longer series draws each row's in its step.
PREDRAWN = 2**23


class ParticleState(NamedTuple):
    """The particles (P, n), their normalised log-weights (P,) and the number of rows done; with a guided
    proposal, the particles before the row's prediction, which the update moves again with an eye on y_k."""

    particles: jnp.ndarray
    log_weights: jnp.ndarray
    step: jnp.ndarray
    previous: jnp.ndarray | None = None

    def moments(self):
        """The weighted mean and covariance of the particles."""
        w = jnp.exp(self.log_weights)
        mean = w @ self.particles
        centred = self.particles - mean
        return mean, (centred * w[:, None]).T @ centred


class ParticleUpdate(NamedTuple):
    """One row's update: the state carried on, the step's log-likelihood, and the outputs' predictive
    mean and covariance (for the innovations a result shows)."""

    state: ParticleState
    terms: DensityTerms
    innovation: jnp.ndarray
    innovation_covariance: jnp.ndarray
    guarded: float = 0.0
    #: Each output's probability integral transform under the predicted particles (randomized for counts):
    #: uniform on (0, 1) where the model is right; 0.5 where unobserved.
    pit: jnp.ndarray | None = None


def systematic_indices(uniform, log_weights):
    """Systematic resampling: P indices drawn with one uniform number in [0, 1) (Kitagawa 1996)."""
    n = log_weights.shape[0]
    cumulative = jnp.cumsum(jnp.exp(jax.lax.stop_gradient(log_weights)))
    # Particle i is picked once for each point (u + j)/P below its cumulative weight C_i and at or above C_{i−1}.
    below = jnp.clip(jnp.ceil(n * cumulative / cumulative[-1] - uniform), 0, n).astype(jnp.int32)
    offspring = jnp.diff(below, prepend=0)
    return jnp.repeat(jnp.arange(n), offspring, total_repeat_length=n)


def resample(uniform, state: ParticleState, threshold: float) -> ParticleState:
    """Resample where the effective sample size is below ``threshold`` · P (see the module doc)."""
    lw = state.log_weights
    n = lw.shape[0]
    ess = 1.0 / jnp.sum(jnp.exp(2 * lw))

    def resampled(state):
        index = systematic_indices(uniform, state.log_weights)
        picked = state.log_weights[index]
        # Value log(1/P), derivative that of the picked weights (the stop-gradient of the module doc).
        return state._replace(particles=state.particles[index],
                              log_weights=picked - jax.lax.stop_gradient(picked) - jnp.log(n))

    return jax.lax.cond(ess < threshold * n, resampled, lambda state: state, state)


class SampledDynamics(NamedTuple):
    """Members (particles, an ensemble) moved by the model's dynamics with fixed random numbers: the
    members at t₀, ``advance(x, row, step)`` over row ``step``'s interval, ``guided(x, row, step, draw)``
    the same moves drawn by a proposal (see [`sampled_dynamics()`][greyid.filters.particle.sampled_dynamics]),
    and one uniform number per row."""

    initial: jnp.ndarray
    advance: Callable
    guided: Callable
    uniforms: jnp.ndarray


def sampled_dynamics(structure: Structure, options: FilterOptions, theta, data: FilterInputs, base,
                     members: int, delays=None) -> SampledDynamics:
    """x(t₀) ~ N(x0, P0) and the transitions of the module doc, for ``members`` members, random numbers
    from the key ``base``.

    ``guided(x, row, step, draw) -> (x_k, log_corrections)`` moves each member by the same steps, each
    step's standard normals w drawn by ``draw(end, scale, rest, e) -> (w, log_correction)`` from the
    row's fixed normals e instead of taking w = e: the step is x → m + scale · w, and the member would
    reach ``end`` + scale · w + rest · v (v ~ N(0, I), the later sub-steps' noise) at t_k
    ([`proposals`][greyid.filters.proposals]).  With ``delays`` (the series' delayed inputs; ``data`` then holds
    them and the rows their pieces) each interval or sub-step is cut where they switch.
    """
    n, substeps = structure.n_states, options.substeps
    f, G = structure.drift, structure.diffusion
    exact = structure.linear_dynamics is not None
    x0, P0 = initial_state(structure, theta, data)
    root = small.cholesky(0.5 * (P0 + P0.T))
    initial = x0 + jax.random.normal(jax.random.fold_in(base, _START), (members, n)) @ root.T
    if exact:  # one discretization per distinct interval, as the exact Kalman filter
        A, B, c = structure.linear_dynamics(theta)
        g = G(np.zeros(n), data.u_cur[0], data.t[0], theta)
        cache = discretize_each(A, g @ g.T, data.unique_dt)
        roots = jax.vmap(lambda L: small.cholesky(0.5 * (L + L.T)))(cache.noise_covariance)

    # Every row's random numbers drawn at once where they fit in PREDRAWN numbers (one call of the
    # generator costs a third less than one per row, benchmarks/particle.py); else row by row.
    rows = data.t.shape[0]
    per_row = (members, n) if exact else (substeps, members, len(structure.noise_names))
    predrawn = rows * int(np.prod(per_row)) <= PREDRAWN
    predict_key = jax.random.fold_in(base, _PREDICT)
    normals = jax.random.normal(predict_key, (rows, *per_row)) if predrawn else None
    uniforms = jax.random.uniform(jax.random.fold_in(base, _RESAMPLE), (rows,))

    def normals_at(step):
        if predrawn:
            return normals[step]
        return jax.random.normal(jax.random.fold_in(predict_key, step), per_row)

    def euler_maruyama(x, row: Row, noise, draw=None):
        step = row.dt / substeps
        du = (row.u_cur - row.u_prev) * data.foh
        if delays is not None:  # each sub-step cut where the delayed inputs switch inside it
            fraction = jnp.arange(substeps) / substeps
            cuts = step_pieces(delays, data, row.t_prev + row.dt * fraction, jnp.full(substeps, step),
                               row.u_prev + du * fraction[:, None],
                               row.u_prev + du * (fraction[:, None] + 1 / substeps), structure.n_inputs)

        def one(j, carry):
            x, correction = carry
            t = row.t_prev + j * step
            u = row.u_prev + du * (j / substeps)
            if delays is None:
                drift = jax.vmap(lambda xi: f(xi, u, t, theta))(x)
            else:
                cut = jax.tree_util.tree_map(lambda a: a[j], cuts)
                drift = jax.vmap(lambda xi: piece_drift(lambda x, u, t: f(x, u, t, theta), xi, cut, data.foh))(x)
            diffusion = jax.vmap(lambda xi: G(xi, u, t, theta))(x)
            if draw is None:
                return x + drift * step + jnp.einsum("pij,pj->pi", diffusion, noise[j]) * jnp.sqrt(step), correction
            # The drift held to t_k, the noise of this step and of the steps left (Golightly & Wilkinson's
            # modified diffusion bridge in the proposal's linearisation).
            remaining = row.dt - j * step
            rest = jnp.sqrt(jnp.maximum(remaining - step, 0.0))
            w, log_correction = jax.vmap(lambda xi, fi, gi, e: draw(xi + fi * remaining, gi * jnp.sqrt(step),
                                                                    gi * rest, e))(x, drift, diffusion, noise[j])
            moved = x + drift * step + jnp.einsum("pij,pj->pi", diffusion, w) * jnp.sqrt(step)
            return moved, correction + log_correction

        return jax.lax.fori_loop(0, substeps, one, (x, jnp.zeros(x.shape[0])))

    def exact_mean(x, row: Row):
        if row.pieces is not None:  # piece by piece where delayed inputs switch inside the interval
            def piece(x, p):
                disc = discretize(A, g @ g.T, p.length)
                b_start, b_end = B @ p.u_start + c, B @ p.u_end + c
                return (x @ disc.transition.T + disc.input_gain @ b_start
                        + data.foh * (disc.ramp_gain @ (b_end - b_start))), None

            return jax.lax.scan(piece, x, row.pieces)[0]
        disc = jax.tree_util.tree_map(lambda a: a[row.dt_index], cache)
        b_prev, b_cur = B @ row.u_prev + c, B @ row.u_cur + c
        return x @ disc.transition.T + disc.input_gain @ b_prev + data.foh * (disc.ramp_gain @ (b_cur - b_prev))

    def advance(x, row: Row, step):
        if not exact:
            return euler_maruyama(x, row, normals_at(step))[0]
        return exact_mean(x, row) + normals_at(step) @ roots[row.dt_index].T

    def guided(x, row: Row, step, draw):
        if not exact:
            return euler_maruyama(x, row, normals_at(step), draw)
        mean, scale = exact_mean(x, row), roots[row.dt_index]
        w, log_correction = jax.vmap(lambda m, e: draw(m, scale, None, e))(mean, normals_at(step))
        return mean + w @ scale.T, log_correction

    return SampledDynamics(initial, advance, guided, uniforms)


def prepare(structure: Structure, options: FilterOptions):
    """``steps(theta, data, key=None) -> FilterSteps`` of the particle filter (``method="particle"``), bootstrap or
    with a Gaussian-filter proposal (``proposal``, see [`proposals`][greyid.filters.proposals]); ``key``
    replaces the seed's random numbers (independent replicates)."""
    n_particles, threshold = options.particles, options.resample
    n = structure.n_states
    families = structure.output_families
    seed, proposal = options.seed, options.proposal
    guided = proposal != BOOTSTRAP
    full = structure.observation_covariance
    zeros = np.zeros(n)  # the noise's covariance does not depend on the state

    def steps(theta, data: FilterInputs, key=None) -> FilterSteps:
        base = jax.random.PRNGKey(seed) if key is None else key
        series = series_rows(structure, theta, data)
        dynamics = sampled_dynamics(structure, options, theta, series.data, base, n_particles, series.delays)
        initial = ParticleState(dynamics.initial, jnp.full(n_particles, -jnp.log(n_particles)),
                                jnp.zeros((), jnp.int32))
        if guided:
            initial = initial._replace(previous=dynamics.initial)
        uniforms = dynamics.uniforms
        pit_uniforms = jax.random.uniform(jax.random.fold_in(base, _PIT), (data.t.shape[0], len(families)))

        def law(x, row: Row):
            return jax.vmap(lambda xi: structure.observation_law(xi, row.u_cur, row.t, theta))(x)

        def whitened(row: Row, mask):
            """The row's observations and their law where the observed outputs' noise is independent with unit
            variances (correlated noise whitened by the Cholesky factor L of its covariance; their density is
            the whitened one's over det L), and log det L; as they are where the noise is independent."""
            if full is None:
                return row.y, (lambda x: structure.observation_law(x, row.u_cur, row.t, theta)), 0.0
            L = observed_root(full(zeros, row.u_cur, row.t, theta), mask)

            def law_of(x):
                m, S, a = structure.observation_law(x, row.u_cur, row.t, theta)
                return whiten(L, mask, m), jnp.ones_like(S), a

            return whiten(L, mask, row.y), law_of, jnp.sum(jnp.log(jnp.diag(L)))

        def log_densities(y, mask, m, S, a):
            return jax.vmap(lambda mi, si, ai: observations_log_density(families, y, mask, mi, si, ai))(m, S, a)

        def predict(state: ParticleState, row: Row):
            moved = state._replace(particles=dynamics.advance(state.particles, row, state.step))
            return (moved._replace(previous=state.particles) if guided else moved), jnp.eye(n)

        def guided_weights(state: ParticleState, row: Row, mask, y, law_of):
            """The particles moved again over the row's interval by the proposal, and their log-weights'
            corrections."""

            def conditional(x):
                m, S, a = law_of(x)
                both = [moments(fam, m[j], S[j], a[j]) for j, fam in enumerate(families)]
                return jnp.stack([b[0] for b in both]), jnp.stack([b[1] for b in both])

            def draw(end, scale, rest, normals):
                return guided_draw(linearise(proposal, conditional, end, scale, rest), y, mask, normals)

            return dynamics.guided(state.previous, row, state.step, draw)

        def update(state: ParticleState, row: Row, mask=None):
            mask = row.mask if mask is None else mask
            m, S, a = law(state.particles, row)
            y_white, law_of, log_root = whitened(row, mask)
            white = jax.vmap(law_of)
            if guided:
                particles, correction = guided_weights(state, row, mask, y_white, law_of)
                joint = state.log_weights + correction + log_densities(y_white, mask, *white(particles)) - log_root
                weighed = state._replace(particles=particles)
            else:
                joint = state.log_weights + log_densities(y_white, mask, *white(state.particles)) - log_root
                weighed = state
            increment = logsumexp(joint)
            weighed = weighed._replace(log_weights=joint - increment)
            carried = resample(uniforms[state.step], weighed, threshold)._replace(step=state.step + 1)
            # The outputs' predictive mean and covariance, and the transforms, under the predicted particles
            # (the dynamics' own moves, whatever the proposal).
            w = jnp.exp(state.log_weights)
            mean_y, var_y = jax.vmap(lambda mi, si, ai: jnp.stack(
                [jnp.stack(moments(fam, mi[j], si[j], ai[j])) for j, fam in enumerate(families)]))(m, S, a).transpose(
                2, 0, 1)
            y_pred = w @ mean_y
            spread = mean_y - y_pred
            R = (spread * w[:, None]).T @ spread + jnp.diag(w @ var_y)
            if full is not None:  # the noise's covariances beside its variances
                noise = full(zeros, row.u_cur, row.t, theta)
                R = R + noise - jnp.diag(jnp.diag(noise))
            innovation = jnp.where(mask > 0, row.y - y_pred, 0.0)
            terms = DensityTerms(increment, jnp.sum(mask))
            # Each output's own transform (its marginal law, S_jj where the noise is correlated), as the Gaussian
            # filters' standardized innovations are.
            transformed = jnp.stack([
                w @ probability_integral_transform(fam, row.y[j], m[:, j], S[:, j], a[:, j],
                                                   pit_uniforms[state.step, j])
                for j, fam in enumerate(families)])
            pit = jnp.where(mask > 0, transformed, 0.5)
            return ParticleUpdate(carried, terms, innovation, R, pit=pit), y_pred

        return FilterSteps(initial, series.rows, predict, update)

    return steps
