"""Reading data: the CSV file or named data set a model file points to, and data sets given as paths.

Everything greyid reads as data comes through here (the named data sets' own
readers are in [`named`][greyid.data.named]): a data file's problems are named with the
file, the column and the row.  The ``model`` these functions take is anything with
the model file's ``options`` (its ``[data]`` table) and ``source`` (the model file's
path, for data files named relative to it).
"""

from __future__ import annotations

import csv
import io
import re
import warnings
from pathlib import Path
from typing import Mapping

import pandas as pd

from ..errors import DataError
from .named import fetch
from .timestamps import parse_timestamps

#: How a saved fit names data that came from [`greyid.datasets.fetch()`][greyid.data.named.fetch] rather than a file.
DATASET_PREFIX = "dataset:"


def named_dataset(origin) -> str | None:
    """NAME of an origin written ``dataset:NAME`` (a saved fit's ``data_file``, a command line's DATA);
    None for a file's path."""
    text = str(origin)
    return text[len(DATASET_PREFIX):] if text.startswith(DATASET_PREFIX) else None


def _dataset_name(model, path) -> str | None:
    """The named data set the data come from: ``path`` written ``dataset:NAME``, else (no path) the model
    file's ``[data] dataset``; None for a file."""
    if path is not None:
        return named_dataset(path)
    options = model.options
    if "dataset" in options and "file" in options:
        raise DataError(f"the model file names both a data file ('{options['file']}') and a data set "
                        f"('{options['dataset']}') in [data]; keep one")
    return options.get("dataset")


def data_path(model, path=None) -> Path:
    """Where the data for ``model`` are: ``path``, else the model file's ``[data] file``
    (relative to the model file)."""
    if path is not None:
        return Path(path)
    options = model.options
    if "file" not in options:
        raise DataError("no data file given, and the model file names none ([data] file = \"...\" or "
                        "[data] dataset = \"armadillo\" for a data set greyid fetches by name)")
    path = Path(options["file"])
    if not path.is_absolute() and model.source is not None:
        path = Path(model.source).parent / path
    return path


def data_origin(model, path=None) -> str:
    """Where the data come from, as a saved fit keeps it: the data file's absolute path, or
    ``dataset:NAME`` for a data set of [`greyid.datasets.fetch()`][greyid.data.named.fetch]."""
    name = _dataset_name(model, path)
    return f"{DATASET_PREFIX}{name}" if name is not None else str(data_path(model, path).resolve())


def read_data(model, path=None, time: str | None = None):
    """Read the data for ``model``: the CSV file of [`data_path()`][greyid.data.files.data_path], or the named data set
    (``[data] dataset``, or ``path`` written ``dataset:NAME``) by [`greyid.datasets.fetch()`][greyid.data.named.fetch].

    The separator is ``[data] separator`` when given, else detected.  Column
    renaming by ``[data.columns]`` happens when the data are used.
    """
    name = _dataset_name(model, path)
    if name is not None:
        frame, where = fetch(name), f"data set '{name}'"
    else:
        path = data_path(model, path)
        if path.is_dir():
            raise DataError(f"data file '{path}' is a folder; give the CSV file inside it")
        if not path.is_file():
            raise DataError(f"data file '{path}' not found")
        frame = read_csv_file(path, model.options.get("separator"), model.options.get("decimal"))
        where = f"data file '{path}'"
    missing = [(n, column) for n, column in (model.options.get("columns") or {}).items()
               if column not in frame.columns]
    if missing:
        n, column = missing[0]
        raise DataError(f"[data.columns] maps '{n}' to the column '{column}', which {where} does not "
                        f"have; its columns are {list(frame.columns)}")
    return parse_timestamps(frame, time or model.options.get("time", "t"), model.options.get("time_format"),
                            model.options.get("time_zone"), str(path) if name is None else where)


def read_csv_file(path, separator=None, decimal=None, text_columns: int = 0):
    """A CSV file as a DataFrame, with a named error for every way it can fail to be one.

    The separator is detected where not given (``,`` ``;`` tab ...).  A file that
    is empty, not UTF-8 text, or has two columns of the same name is refused;
    ``;``-separated numbers with decimal commas are read as such (``decimal``,
    detected where not given).  The first ``text_columns`` columns are read as
    text as written (names such as ``001``).
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise DataError(f"data file '{path}' cannot be read ({err.strerror or err})") from None
    if not raw.strip():
        raise DataError(f"data file '{path}' is empty")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise DataError(f"data file '{path}' is not UTF-8 text (byte 0x{raw[err.start]:02x} at position "
                        f"{err.start}); save it as UTF-8") from None
    header = text.splitlines()[0]
    if separator is None:
        try:
            separator = csv.Sniffer().sniff(text[:65536], delimiters=",;\t| ").delimiter
        except csv.Error:
            separator = ","
    names = [n.strip().strip('"') for n in next(csv.reader([header], delimiter=separator))]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise DataError(f"data file '{path}' has two columns named '{duplicated[0]}'; rename one")
    if decimal is None:  # "1,5;2,25": decimal commas where the separator is not a comma
        body = text.splitlines()[1:50]
        decimal = "," if separator != "," and any(re.search(r"\d,\d", line) for line in body) else "."
    try:
        with warnings.catch_warnings():  # pandas' own warnings would be printed before greyid's message
            warnings.simplefilter("ignore")
            frame = pd.read_csv(io.StringIO(text), sep=separator, decimal=decimal,
                                dtype={k: str for k in range(text_columns)} or None)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, csv.Error) as err:
        raise DataError(f"data file '{path}' could not be read as CSV: {err}") from None
    return frame


def named_datasets(datasets) -> tuple[list, list]:
    """``(names, sources)`` from a mapping name → data or a sequence (names 0..n−1)."""
    if isinstance(datasets, pd.DataFrame):
        raise DataError("fit_many takes several data sets (a mapping name → DataFrame, or a list); "
                        "for one DataFrame use model.fit")
    if isinstance(datasets, Mapping):
        return list(datasets.keys()), list(datasets.values())
    if isinstance(datasets, (list, tuple)):
        return list(range(len(datasets))), list(datasets)
    raise DataError(f"datasets must be a mapping name → DataFrame or a list, not {type(datasets).__name__}")


def read_source(source) -> pd.DataFrame:
    """A data set given as a DataFrame or as a CSV file's path (read where it is fitted)."""
    if isinstance(source, pd.DataFrame):
        return source
    if isinstance(source, (str, Path)):
        path = Path(source)
        if path.is_dir():
            raise DataError(f"data file '{path}' is a folder")
        if not path.is_file():
            raise DataError(f"data file '{path}' not found")
        return read_csv_file(path)
    raise DataError(f"a data set must be a DataFrame or a CSV file's path, not {type(source).__name__}")


def read_covariates(path) -> pd.DataFrame:
    """A covariates CSV file: a row per data set, its first column the data sets' names (read as text)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"covariates file '{path}' not found")
    table = read_csv_file(path, text_columns=1)  # names such as "001" stay text, as the files' stems are
    table = table.set_index(table.columns[0])
    table.index = table.index.map(str)
    return table
