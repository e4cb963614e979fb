"""A fleet fit on a Dask cluster: chunks of data sets fitted on the workers.

The client sends each chunk — the model as its dictionary form, the data sets
(DataFrames, or CSV paths read on the worker) and the settings — to a worker,
which builds the model once (:func:`_worker_model` keeps it for later chunks,
so a worker compiles once) and runs :func:`~.fit.fit_members` on the chunk.
Fits come back in their saved form and are rebuilt on the client around the
caller's model.  Scheduling, retries and data locality are Dask's.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pandas as pd

from ..progress import CountProgress
from .result import FleetResult


@functools.lru_cache(maxsize=8)
def _worker_model(spec_json: str):
    from ..model import Model

    return Model.from_dict(json.loads(spec_json))


def _fit_chunk(spec_json: str, names: list, sources: list, inits: list, given: dict):
    """On a worker: ``(rows, fits as dictionaries)`` of one chunk."""
    from .fit import fit_members

    model = _worker_model(spec_json)
    rows, fits = fit_members(model, names, sources, inits, False, given)
    return rows, [None if fit is None else fit.to_dict() for fit in fits]


def fit_on_cluster(client, model, names: list, sources: list, inits: list, chunk_size: int, progress,
                   given: dict) -> FleetResult:
    """:func:`~.fit.fit_many` with ``scheduler=client`` (a ``dask.distributed.Client``)."""
    try:
        from distributed import as_completed
    except ImportError:  # pragma: no cover - the extra is installed in CI
        raise ImportError('scheduler= needs Dask: pip install "greyid[dask]"') from None
    from ..estimate.results import fit_from_dict

    spec_json = json.dumps(model.to_dict())
    chunk_size = max(1, int(chunk_size))
    chunks = [list(range(i, min(i + chunk_size, len(names)))) for i in range(0, len(names), chunk_size)]
    futures = {client.submit(_fit_chunk, spec_json, [names[i] for i in chunk], [sources[i] for i in chunk],
                             [inits[i] for i in chunk], given, pure=False): chunk for chunk in chunks}
    rows, fits = [None] * len(names), [None] * len(names)
    with CountProgress(len(names), "fleet fit (dask)", progress) as shown:
        for future in as_completed(list(futures)):
            chunk = futures[future]
            try:
                chunk_rows, chunk_fits = future.result()
            except Exception as error:  # a worker lost or a failure outside any one data set
                chunk_rows = [dict(error=f"data set '{names[i]}': the worker failed ({error})") for i in chunk]
                chunk_fits = [None] * len(chunk)
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
