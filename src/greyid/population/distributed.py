"""A population fit on a Dask cluster: the members' inner optimisations by chunks on the workers.

Each chunk of members — their stacked data and covariates, with the model as its
dictionary form, the population's layout and the filter's settings — is sent to
the cluster once (``client.scatter``); every outer evaluation then submits, per
chunk, the population parameters φ and the chunk's warm-start modes, and the
worker returns the chunk's conditional modes, Laplace values and (as asked)
gradients and Hessians.  The worker builds the model and compiles the programs
once (kept for later chunks and evaluations); the outer search stays on the
client.  Dask retries a chunk whose worker died; a chunk that fails anyway (its
scattered data were lost with the worker) is scattered again from the client's
copy and run again, up to [`RESENDS`][greyid.population.distributed.RESENDS] times; where the cluster has had no
worker at all for ``worker_timeout`` seconds the fit stops with an error that
says so instead of waiting.
"""

from __future__ import annotations

import asyncio
import json
import time
from concurrent.futures import CancelledError

import numpy as np

from ..errors import ModelError
from ..api import Model
from . import laplace
from .members import population_programs

#: Seconds between looks at the cluster while chunks are pending.
POLL = 0.5
#: Times a failed chunk is sent again (with its data) before the fit stops.
RESENDS = 2


#: On a worker: the programs of each (model, population layout, filter settings) seen, compiled once.
_PROGRAMS: dict = {}


def _worker_programs(spec_json: str, spec, options):
    key = (spec_json, spec.key(), options)
    if key not in _PROGRAMS:
        model = Model.from_dict(json.loads(spec_json))
        _PROGRAMS[key] = population_programs(model.structure, spec, options)
    return _PROGRAMS[key]


def _evaluate_chunk(payload, phi, u0, kind: str, path=None):
    """On a worker: [`evaluate()`][greyid.population.distributed.evaluate] of one chunk of members."""
    spec_json, spec, options, x, data = payload
    programs = laplace.MemberPrograms(_worker_programs(spec_json, spec, options), x, spec.base(), data, 1)
    try:
        return evaluate(programs, phi, u0, kind, path)
    finally:
        programs.close()


def evaluate(programs, phi, u0, kind: str, path=None):
    """The modes at φ and what ``kind`` ("value", "gradient", "exact") asks of them, for one set of members:
    ``(modes, values, gradients, hessians, path)``, None where not asked; ``path`` is the modes' tangents T and
    multipliers λ that the outer Hessian needs (laplace's module doc), given with every gradient.
    ``kind="hessian"`` takes ``u0`` as the modes at φ and ``path`` as their T and λ, both found before by a
    gradient at φ, and gives the outer Hessian alone (without ``path`` the gradient's program runs again for it);
    ``kind="differences"`` the same with P's second derivatives by differences of its slopes, ``path`` being T, λ
    and the steps
    ([`hessian_by_differences()`][greyid.population.laplace.MemberPrograms.hessian_by_differences]), and gives
    the steps for a later call as its ``path``."""
    if kind == "differences":
        hessians, steps = programs.hessian_by_differences(phi, u0, *path)
        return None, None, None, hessians, (steps,)
    if kind == "hessian":
        tangents, multipliers = path if path is not None else programs.gradient(phi, u0)[2:]
        return None, None, None, np.asarray(programs.hessian(phi, u0, tangents, multipliers)), None
    modes = laplace.conditional_modes(programs, phi, u0)
    values, gradients, hessians, path = laplace.laplace_values(modes), None, None, None
    if kind != "value" and modes.finite.all():
        values, gradients, tangents, multipliers = map(np.asarray, programs.gradient(phi, modes.u))
        path = (tangents, multipliers)
        if kind == "exact":
            hessians = np.asarray(programs.hessian(phi, modes.u, tangents, multipliers))
    return modes, values, gradients, hessians, path


class ClusterEvaluator:
    """[`evaluate()`][greyid.population.distributed.evaluate] over chunks of members on a Dask cluster."""

    def __init__(self, client, model, spec, options, members, chunk_size: int | None, worker_timeout: float):
        try:
            from distributed import wait  # noqa: F401
        except ImportError:  # pragma: no cover - the extra is installed in CI
            raise ImportError('scheduler= needs Dask: pip install "greyid[dask]"') from None
        import jax

        self.client, self.worker_timeout = client, float(worker_timeout)
        n = len(members.names)
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        size = max(1, int(chunk_size) if chunk_size else -(-n // workers))
        spec_json = json.dumps(model.to_dict())
        host = jax.device_get(members.data)
        self.chunks, self.payloads = [], []
        for start in range(0, n, size):
            index = np.arange(start, min(start + size, n))
            part = jax.tree_util.tree_map(lambda leaf, index=index: np.asarray(leaf)[index], host)
            self.payloads.append((spec_json, spec, options, members.x[index], part))
            self.chunks.append((index, client.scatter(self.payloads[-1], direct=False)))

    def _wait(self, futures):
        from distributed import wait

        alone_since = None
        pending = set(futures)
        while pending:
            try:
                _, pending = wait(pending, timeout=POLL, return_when="ALL_COMPLETED")
            except TimeoutError:
                pass
            except (CancelledError, asyncio.CancelledError):  # a chunk lost with its data: done, resent
                pending = {future for future in pending if not future.done()}
            if not pending:
                break
            try:
                alive = len(self.client.scheduler_info().get("workers", {}))
            except Exception:  # noqa: BLE001  a scheduler gone: no worker either
                alive = 0
            if alive:
                alone_since = None
                continue
            alone_since = time.monotonic() if alone_since is None else alone_since
            if time.monotonic() - alone_since >= self.worker_timeout:
                for future in pending:
                    future.cancel()
                raise ModelError(f"the population fit stopped: the cluster had no worker for "
                                 f"{self.worker_timeout:g} s")

    def __call__(self, phi, u0, kind: str, path=None):
        phi = np.asarray(phi, dtype=float)

        def submit(k):
            index, payload = self.chunks[k]
            part = None if path is None else tuple(np.asarray(leaf)[index] for leaf in path)
            return self.client.submit(_evaluate_chunk, payload, phi, u0[index], kind, part, pure=False)

        futures = [submit(k) for k in range(len(self.chunks))]
        for attempt in range(RESENDS + 1):
            self._wait(futures)
            failed = [k for k, future in enumerate(futures) if future.status != "finished"]
            if not failed:
                break
            if attempt == RESENDS:
                future = futures[failed[0]]
                why = (f"{type(future.exception()).__name__}: {future.exception()}" if future.status == "error"
                       else future.status)
                raise ModelError(f"the population fit stopped: a chunk of members failed on the cluster "
                                 f"{RESENDS + 1} times ({why})")
            # A chunk whose worker was lost took its scattered data with it (Dask cannot recompute
            # scattered data): the chunk is sent again from the client's copy and run again.
            for k in failed:
                self.chunks[k] = (self.chunks[k][0], self.client.scatter(self.payloads[k], direct=False))
                futures[k] = submit(k)
        parts = [future.result() for future in futures]
        modes = None if parts[0][0] is None else laplace.Modes(*(np.concatenate([p[0][k] for p in parts])
                                                                 for k in range(5)))
        values = None if parts[0][1] is None else np.concatenate([p[1] for p in parts])
        gradients = None if any(p[2] is None for p in parts) else np.concatenate([p[2] for p in parts])
        hessians = None if any(p[3] is None for p in parts) else np.concatenate([p[3] for p in parts])
        path = None if any(p[4] is None for p in parts) else tuple(np.concatenate([p[4][k] for p in parts])
                                                                   for k in range(len(parts[0][4])))
        return modes, values, gradients, hessians, path

    def close(self):
        pass
