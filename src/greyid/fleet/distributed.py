"""A fleet fit on a Dask cluster: chunks of data sets fitted on the workers.

The client sends each chunk — the model as its dictionary form, the data sets
(DataFrames, or CSV paths read on the worker) and the settings — to a worker,
which builds the model once ([`_worker_model()`][greyid.fleet.distributed._worker_model] keeps it for later chunks,
so a worker compiles once) and runs [`fit_members()`][greyid.fleet.members.fit_members] on the chunk.
Fits come back in their saved form and are rebuilt on the client around the
caller's model.  Scheduling, retries and data locality are Dask's.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pandas as pd

from ..api import Model, fit_from_dict
from ..progress import CountProgress
from .members import fit_members
from .result import FleetResult


@functools.lru_cache(maxsize=8)
def _worker_model(spec_json: str):
    return Model.from_dict(json.loads(spec_json))


def _fit_chunk(spec_json: str, names: list, sources: list, inits: list, given: dict):
    """On a worker: ``(rows, fits as dictionaries)`` of one chunk."""
    model = _worker_model(spec_json)
    rows, fits = fit_members(model, names, sources, inits, False, given)
    return rows, [None if fit is None else fit.to_dict() for fit in fits]


#: Seconds the cluster may have no worker at all before the chunks still to come are given up.
NO_WORKER_TIMEOUT = 60.0
#: Seconds between looks at the cluster while chunks are pending.
POLL = 0.5


def _workers(client) -> int:
    try:
        return len(client.scheduler_info().get("workers", {}))
    except Exception:  # noqa: BLE001  a scheduler gone: no worker either
        return 0


def fit_on_cluster(client, model, names: list, sources: list, inits: list, chunk_size: int, progress,
                   given: dict, worker_timeout: float | None = None) -> FleetResult:
    """[`fit_many()`][greyid.fleet.fit.fit_many] with ``scheduler=client`` (a ``dask.distributed.Client``).

    A chunk whose worker dies is retried by Dask (``distributed.scheduler.allowed-failures``
    times, then it fails with ``KilledWorker``); where the cluster has had no worker at all for
    ``worker_timeout`` seconds (default [`NO_WORKER_TIMEOUT`][greyid.fleet.distributed.NO_WORKER_TIMEOUT]), the chunks
    still pending are
    cancelled.  Either way their members come back as failed rows that say why, and the call returns.
    """
    try:
        from distributed import wait
    except ImportError:  # pragma: no cover - the extra is installed in CI
        raise ImportError('scheduler= needs Dask: pip install "greyid[dask]"') from None
    import time

    worker_timeout = NO_WORKER_TIMEOUT if worker_timeout is None else float(worker_timeout)
    spec_json = json.dumps(model.to_dict())
    chunk_size = max(1, int(chunk_size))
    chunks = [list(range(i, min(i + chunk_size, len(names)))) for i in range(0, len(names), chunk_size)]
    futures = {client.submit(_fit_chunk, spec_json, [names[i] for i in chunk], [sources[i] for i in chunk],
                             [inits[i] for i in chunk], given, pure=False): chunk for chunk in chunks}
    rows, fits = [None] * len(names), [None] * len(names)

    def finished(future):
        """``(rows, fits)`` of a finished chunk, or failed rows that say why."""
        chunk = futures[future]
        try:
            return future.result()
        except Exception as error:  # a worker lost or a failure outside any one data set
            kind = type(error).__name__
            return ([dict(error=f"data set '{names[i]}': the worker failed ({kind}: {error})") for i in chunk],
                    [None] * len(chunk))

    def done_chunks():
        """Each chunk as it finishes; the pending ones failed once no worker has been seen for long."""
        pending, alone_since = set(futures), None
        while pending:
            try:
                done, pending = wait(pending, timeout=POLL, return_when="FIRST_COMPLETED")
            except TimeoutError:  # Dask's wait raises when nothing finished in time
                done = set()
            for future in done:
                yield future, finished(future)
            if not pending:
                return
            if _workers(client) > 0:
                alone_since = None
                continue
            alone_since = time.monotonic() if alone_since is None else alone_since
            if time.monotonic() - alone_since >= worker_timeout:
                for future in pending:
                    future.cancel()
                    chunk = futures[future]
                    yield future, ([dict(error=f"data set '{names[i]}': not fitted, the cluster had no worker "
                                               f"for {worker_timeout:g} s") for i in chunk], [None] * len(chunk))
                return

    with CountProgress(len(names), "fleet fit (dask)", progress) as shown:
        for future, (chunk_rows, chunk_fits) in done_chunks():
            chunk = futures[future]
            for i, row, spec in zip(chunk, chunk_rows, chunk_fits):
                rows[i] = row
                if spec is not None:
                    fit = fit_from_dict(spec, f"the fit of data set '{names[i]}'", model=model)
                    source = sources[i]
                    if isinstance(source, pd.DataFrame):
                        fit = fit.with_data(source)
                    elif isinstance(source, (str, Path)):
                        fit.data_file = str(source)
                    fits[i] = fit
            shown.advance(len(chunk))
    return FleetResult(model, names, rows, fits)
