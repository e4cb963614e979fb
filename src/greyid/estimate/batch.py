"""Many searches at once: the starts of one fit, the data sets of a fleet.

Each member is a [`Search`][greyid.estimate.trust_region.Search] with its own trust region, stage
and convergence; a member that has converged asks for nothing more.  In each
round the driver ([`drive()`][greyid.estimate.batch.drive]) gathers the members' pending requests,
evaluates those of one kind — value, scoring or exact derivatives — together in
one program vectorised over the members (``jax.vmap``), and hands each member
its answer.  The programs are those a single fit compiles, so a batch computes
exactly what separate fits would.  Values and scoring steps gain most from
vectorising; the exact Hessian does not, so members are evaluated one by one in
parallel threads (``benchmarks/fleet.py``).  The starts of a fit share the data; the
members of a fleet each bring their own series, padded to a common length.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

from .. import runtime  # noqa: F401  (64-bit JAX and greyid's cache folder before any JAX work)
import jax
import numpy as np

from ..runtime.jit import jit
from ..errors import ModelError
from ..filters.api import padded_inputs
from .objective import Programs, combine_hessian, combine_scoring, direction_blocks, worker_count
from .optimize import EXACT, SCORING, VALUE, Optimum, settle
from .trust_region import Search, SearchState

#: Largest number of members one program call evaluates: memory stays bounded, and
#: beyond it a vectorised step costs more per member, as the working set leaves the cache.
MAX_BATCH = 64


def batch_size(count: int) -> int:
    """Members per call for ``count`` requests: a power of two, so a handful of compiled sizes serve all."""
    return min(MAX_BATCH, 1 << max(count - 1, 0).bit_length())


def _stack(trees: Sequence):
    return jax.tree_util.tree_map(lambda *leaves: np.stack(leaves), *trees)


def _member(tree, i: int):
    return jax.tree_util.tree_map(lambda leaf: np.asarray(leaf)[i], tree)


def _scoring_matrix(scoring):
    """The scoring program with MMᵀ formed in it (all directions in one call): less to transfer."""
    def with_matrix(z, rows, *arguments):
        value, slopes, M, prior = scoring.__wrapped__(z, rows, *arguments)
        return value, slopes, M @ M.T, prior

    return with_matrix


def _with_prior(value, slopes, F, prior):
    """(f, g, F) with the prior's terms, as [`combine_scoring()`][greyid.estimate.objective.combine_scoring] forms
    them."""
    prior_value, prior_gradient, prior_hessian = prior
    return value + prior_value, slopes + prior_gradient, F + prior_hessian


class _Done:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


class BatchedPrograms:
    """``evaluate(groups)``: the requests of many members, each kind by one vectorised program.

    ``programs`` are a problem's compiled [`Programs`][greyid.estimate.objective.Programs];
    ``arguments`` the arguments they share (θ base, bounds, prior moments);
    ``data`` either the data sets all members share (the starts of a fit) or,
    with ``per_member=True``, a list with one stacked series (padded to a common
    length, see [`pad_series()`][greyid.estimate.batch.pad_series]) whose row ``data_index[member]`` a member
    uses (several starts of a fleet's data set share a row).  Calls are split over up to
    ``workers`` threads, each a power-of-two number of members, padded to a size already compiled
    where one holds them ([`size_for()`][greyid.estimate.batch.BatchedPrograms.size_for]).  Exact Hessians, and
    every kind when fewer than ``vectorise_from`` members ask for it, are evaluated
    member by member with the single fit's programs.
    """

    def __init__(self, structure_cache: dict, key, programs: Programs, n: int, arguments: tuple, data,
                 per_member: bool = False, workers: int | None = None, data_index=None, vectorise_from: int = 1):
        self.n, self.arguments, self.data, self.per_member = n, arguments, data, per_member
        self.data_index = data_index  # the row of the stacked data each member uses (default: its own)
        self.rows = jax.device_put(np.eye(n))
        cache_key = ("batched", key, per_member)
        if cache_key not in structure_cache:
            data_axis = 0 if per_member else None
            shared = (None,) * len(arguments)

            def vectorised(fun, with_rows):
                axes = (0, None, *shared, data_axis) if with_rows else (0, *shared, data_axis)
                return jit(jax.vmap(fun, in_axes=axes))

            structure_cache[cache_key] = {
                VALUE: vectorised(programs.value.__wrapped__, False),
                SCORING: None if programs.scoring is None else vectorised(_scoring_matrix(programs.scoring), True),
            }
        self.programs = structure_cache[cache_key]
        self.single, self.vectorise_from = programs, vectorise_from
        # The starts of a fit split directions into the blocks a single fit uses, and so
        # reuse its compiled programs; a fleet's members (with data of a shape of their
        # own) take all directions in one call, and the threads take different members.
        self.blocks = direction_blocks(n, 1 if per_member else None)
        # Sizes compiled for these data shapes (a new shape compiles anew).
        shapes = tuple(np.shape(a) for a in jax.tree_util.tree_leaves(data))
        self.compiled = self.programs.setdefault(("compiled", shapes), set())
        self.pool = ThreadPoolExecutor(max(1, min(worker_count() if workers is None else workers, 8)))
        self.workers = self.pool._max_workers
        self.pending = None  # the exact program compiling in the background

    def _member_data(self, member: int):
        if not self.per_member:
            return self.data
        row = member if self.data_index is None else self.data_index[member]
        return jax.tree_util.tree_map(lambda leaf: leaf[row], self.data)

    def _block(self, kind: str, member: int, z: np.ndarray, rows):
        """One member's value, or one block of its derivatives' directions, by the single fit's programs."""
        data = self._member_data(member)
        if kind == VALUE:
            return jax.device_get(self.single.value(z, *self.arguments, data))
        program = self.single.derivatives if kind == EXACT else self.single.scoring
        return jax.device_get(program(z, rows, *self.arguments, data))

    def size_for(self, kind: str, count: int) -> int:
        """Members per call for ``count`` requests of ``kind``: the smallest size this kind has compiled
        for these data that holds them, else the power of two of [`batch_size()`][greyid.estimate.batch.batch_size].

        A fleet's searches converge one by one, so the members that ask shrink from round to round; each
        new size would compile its own program (about a second on two cores) to save milliseconds per
        call, so the programs compiled for more members serve them, padded.
        """
        own = batch_size(count)
        sizes = [size for signature_kind, size in self.compiled if signature_kind == kind and size != "alone"]
        return min([size for size in sizes if size >= own], default=own)

    def _call(self, kind: str, members: list[int], Z: np.ndarray, size: int):
        pad = size - len(members)
        Z = np.concatenate([Z, np.repeat(Z[:1], pad, axis=0)])
        data = self.data
        if self.per_member:
            index = np.array(members + [members[0]] * pad)
            if self.data_index is not None:
                index = np.asarray(self.data_index)[index]
            data = jax.tree_util.tree_map(lambda leaf: leaf[index], self.data)
        program = self.programs[kind]
        if kind == VALUE:
            out = program(Z, *self.arguments, data)
        else:
            out = program(Z, self.rows, *self.arguments, data)
        out = jax.device_get(out)
        results = []
        for i in range(len(members)):
            part = _member(out, i)
            results.append((part,) if kind == VALUE else _with_prior(*part))
        return results

    def compile_exact_ahead(self, z) -> None:
        """Compile the exact program (by a first evaluation at z) in a worker thread, while the starts
        take their first scoring steps; the first exact request waits for it."""
        self.pending = self.pool.submit(lambda: [self._block(EXACT, 0, z, rows) for rows in self.blocks])

    def __call__(self, groups: list[tuple[str, list[int], np.ndarray]]) -> list[list]:
        """Outputs for each group ``(kind, members, Z)``, in order, as each member's program would give."""
        if self.pending is not None and any(kind == EXACT for kind, _, _ in groups):
            self.pending.result()
            self.pending = None
            self.compiled.add((EXACT, "alone"))
        tasks = []  # (group, members' positions in it, one block or a vectorised part, function, arguments)
        for g, (kind, members, Z) in enumerate(groups):
            if kind == EXACT or len(members) < self.vectorise_from:
                # Member by member, each block of directions a task of its own, so the
                # threads stay busy however few members ask.
                for i, (member, z) in enumerate(zip(members, Z)):
                    for rows in ([None] if kind == VALUE else self.blocks):
                        tasks.append((g, i, (kind, "alone"), self._block, (kind, member, z, rows)))
            else:
                # Enough calls to keep every worker busy, none larger than MAX_BATCH.
                count = max(-(-len(members) // MAX_BATCH), min(self.workers, len(members)))
                parts = np.array_split(np.arange(len(members)), count)
                size = self.size_for(kind, len(parts[0]))  # the largest part: one size for all of them
                for part in parts:
                    tasks.append((g, part, (kind, size), self._call,
                                  (kind, [members[i] for i in part], Z[part], size)))
        futures = []
        for _, _, signature, function, arguments in tasks:
            if signature in self.compiled:
                futures.append(self.pool.submit(function, *arguments))
            else:  # compiled once, here, rather than by several threads at once
                futures.append(_Done(function(*arguments)))
                self.compiled.add(signature)
        parts: dict = {}
        outputs: list[list] = [[None] * len(members) for _, members, _ in groups]
        for (g, where, signature, _, _), future in zip(tasks, futures):
            if signature[1] == "alone":
                parts.setdefault((g, where), []).append(future.result())
            else:
                for i, out in zip(where, future.result()):
                    outputs[g][i] = out
        for (g, i), blocks in parts.items():
            kind = groups[g][0]
            outputs[g][i] = ((blocks[0],) if kind == VALUE else
                             (combine_hessian if kind == EXACT else combine_scoring)(blocks, self.n))
        return outputs

    def close(self):
        self.pool.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


#: A start is pruned once it has taken PRUNE_AFTER steps, trails the best member by
#: more than PRUNE_GAP (criterion units), and has all but stopped: its last three
#: steps gained less than SETTLED_GAIN together.  It is settling on an optimum far
#: below the best, and only its polishing steps are saved.  Pruning on the pace of
#: progress alone loses optima: a Newton search can trail by 1000 units for 18 steps,
#: gaining about 9 a step, then find the best optimum (PRBS1's TiThTs with the window
#: area's bound at −5); gains projected from a geometric trend pruned every start but
#: one there, scoring steps' gains not being geometric early on.
PRUNE_AFTER = 8
PRUNE_GAP = 50.0
SETTLED_GAIN = 1.0


def prune_trailing(states: Sequence[SearchState], running: set[int]) -> dict[int, str]:
    """Starts to stop (see PRUNE_AFTER), with the reason."""
    best = min(s.f for s in states)
    out = {}
    for i in running:
        s = states[i]
        behind = s.f - best
        if s.iterations < PRUNE_AFTER or behind <= PRUNE_GAP or len(s.history) < 4:
            continue
        recent = s.history[-4] - s.history[-1]
        if recent < SETTLED_GAIN:
            out[i] = (f"pruned after {s.iterations} steps: {behind:.4g} below the best start and gaining "
                      f"{recent:.3g} in its last three steps")
    return out


def drive(searches: Sequence[Search], evaluate: Callable, prune: Callable | None = None,
          finished: Callable | None = None) -> list[Optimum | ModelError]:
    """Run all ``searches`` together; ``evaluate(groups)`` as
    [`BatchedPrograms`][greyid.estimate.batch.BatchedPrograms].

    A member whose search fails (a criterion not finite at its start) gets its
    [`ModelError`][greyid.errors.ModelError] in place of an optimum; the others go on.  ``prune(states,
    running) -> {member: reason}`` may stop members early (``states``: where each search stands, a
    [`SearchState`][greyid.estimate.trust_region.SearchState]); ``finished(member, result)`` is called
    as each member ends.
    """
    results: list = [None] * len(searches)
    states: list = [None] * len(searches)
    pending: dict[int, tuple[str, np.ndarray]] = {}

    def advance(i, answer):
        try:
            states[i] = searches[i].init() if answer is None else searches[i].step(states[i], answer)
        except ModelError as error:
            results[i] = error
        else:
            if states[i].optimum is None:
                pending[i] = states[i].request
                return
            results[i] = states[i].optimum
        pending.pop(i, None)
        if finished is not None:
            finished(i, results[i])

    for i in range(len(searches)):
        advance(i, None)
    while pending:
        groups = []
        for kind in (EXACT, SCORING, VALUE):
            members = [i for i, (k, _) in pending.items() if k == kind]
            if members:
                groups.append((kind, members, np.stack([pending[i][1] for i in members])))
        for (_, members, _), outputs in zip(groups, evaluate(groups)):
            for i, out in zip(members, outputs):
                advance(i, settle(out))
        if prune is not None and pending:
            for i, reason in prune(states, set(pending)).items():
                pending.pop(i)
                results[i] = searches[i].stopped(states[i], reason)
                if finished is not None:
                    finished(i, results[i])
    return results


def pad_series(series: Sequence, length: int, unique: int):
    """Stack filter inputs of several series, each padded to ``length`` rows and ``unique`` intervals
    ([`padded_inputs()`][greyid.filters.api.padded_inputs]: the padding changes nothing).
    """
    slots = max(len(s.delay_slots) for s in series)
    head = max(len(s.diffuse_rows) for s in series)
    padded = [padded_inputs(jax.device_get(s), length, unique, slots, head) for s in series]
    return _stack(padded)
