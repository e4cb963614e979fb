"""Model files: a model, its parameters and its settings as TOML, and as a dict.

A model file holds what the Python API holds, readable at a glance::

    [model]
    name = "TiTe"
    inputs = ["Ta", "Ps", "Ph"]
    system = [
      "dTi = (1/(Ci*Rie)*(Te-Ti) + Aw/Ci*Ps + Ph/Ci)*dt + exp(p11)*dw1",
      "dTe = (1/(Ce*Rie)*(Ti-Te) + 1/(Ce*Rea)*(Ta-Te))*dt + exp(p22)*dw2",
    ]
    initial_covariance = "process"     # or a matrix, or a vector of variances

    [model.observations]
    yTi = { equation = "Ti", variance = "exp(e11)" }

    [model.initial_state]
    Ti = "Ti0"
    Te = "Te0"

    [parameters]
    Ci = { init = 1.0, lower = 1e-3, upper = 20 }
    Aw = { init = 5.0, fixed = true }
    Rie = { init = 1.0, lower = 0.01, upper = 10, prior = { mean = 1.0, sd = 0.3 } }

    [derived]
    UA = "1/(Rie + Rea)"

    [data]
    file = "data.csv"       # optional, relative to this file; or dataset = "armadillo"
    time = "t"
    hold = "zoh"
    [data.columns]          # model name = column in the data, where they differ
    yTi = "T_indoor"

    [filter]
    method = "kalman"

    [estimation]
    criterion = "ml"
    starts = 1

[`read_model()`][greyid.model.files.read_model] and [`write_model()`][greyid.model.files.write_model] round-trip
(``Model.from_toml`` /
``model.to_toml``); [`read_data()`][greyid.model.files.read_data] reads the data a model file points to.
"""

from __future__ import annotations

import io
import json
import math
import re
import tomllib
from pathlib import Path
from typing import Mapping

import numpy as np

from ..data.timestamps import parse_timestamps
from ..errors import DataError, ModelError
from ..schema import MODEL_SECTIONS, check_model_document, observation_entry, parameter_entry


# ---------------------------------------------------------------------- dict form
def _plain(value):
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return float(value)
    return value


def model_to_dict(model) -> dict:
    """Everything needed to rebuild ``model`` (equations as text), JSON-ready."""
    if model._functions is not None:
        raise ModelError("a model defined by Python functions cannot be written out; rebuild it in code")

    def parameter(p) -> dict:
        out = {"init": p.init, "lower": p.lower, "upper": p.upper, "fixed": p.fixed}
        if p.prior is not None:
            out["prior"] = {"mean": p.prior[0], "sd": p.prior[1]}
        return out

    options = model.options
    if "prior_correlation" in options:  # tuple keys survive neither JSON nor TOML
        options["prior_correlation"] = {f"{a},{b}": r for (a, b), r in options["prior_correlation"].items()}
    if "robust" in options:
        options["robust"] = list(options["robust"])
    return {
        "name": model.name,
        "description": model.description,
        "system": [e.text for e in model._system],
        "inputs": list(model._inputs),
        "observations": [{"equation": o[0].text, "variance": _plain(o[2])} for o in model._observations],
        "observation_covariance": _plain(model._observation_covariance),
        "algebraic": [a.text for a in model._algebraics],
        "parameters": {n: parameter(p) for n, p in model.parameters.items()},
        "initial_state": None if model._initial_mean is None else {
            "mean": {k: _plain(v) for k, v in model._initial_mean.items()},
            "covariance": _plain(model._initial_covariance),
            "scale": model._initial_scale,
        },
        "derived": model.derived,
        "units": model.units,
        "options": options,
        "population": dict(model.population),
    }


def model_from_dict(spec: Mapping, cls=None):
    """Rebuild a model written by [`model_to_dict()`][greyid.model.files.model_to_dict]."""
    if cls is None:
        from .model import Model as cls
    m = cls(spec.get("name", "model"), spec.get("description", ""))
    m.add_system(*spec["system"])
    if spec.get("inputs"):
        m.add_inputs(*spec["inputs"])
    for a in spec.get("algebraic", []):
        m.add_algebraic(a)
    for o in spec["observations"]:
        m.add_observation(o["equation"], variance=o["variance"])
    if spec.get("observation_covariance") is not None:
        m.set_observation_covariance(spec["observation_covariance"])
    for name, p in spec.get("parameters", {}).items():
        prior = p.get("prior")
        m.set_parameter(name, init=p.get("init"), lower=p.get("lower"), upper=p.get("upper"),
                        fixed=p.get("fixed", False), prior=None if prior is None else (prior["mean"], prior["sd"]))
    init = spec.get("initial_state")
    if init is not None:
        m.set_initial_state(mean=init["mean"], covariance=init["covariance"], scale=init.get("scale", 1.0))
    for name, expr in spec.get("derived", {}).items():
        m.add_derived(name, expr)
    if spec.get("units"):
        m.set_units(spec["units"])
    m.set_options(**spec.get("options", {}))
    if spec.get("population"):
        m.set_population(**spec["population"])
    return m


# ---------------------------------------------------------------------- reading TOML
def spec_from_toml(document: Mapping) -> dict:
    """The [`model_to_dict()`][greyid.model.files.model_to_dict] form of a parsed TOML model file (checked by
    [`greyid.schema`][greyid.schema])."""
    check_model_document(document)
    model = document["model"]
    system = model["system"] if isinstance(model["system"], list) else [model["system"]]
    observations = model["observations"]
    initial = model.get("initial_state")
    options = {}
    for section in ("data", "filter", "estimation"):
        options.update(document.get(section, {}))
    return {
        "name": model.get("name", "model"),
        "description": model.get("description", ""),
        "system": list(system),
        "inputs": list(model.get("inputs", [])),
        "algebraic": list(model.get("algebraic", [])),
        "observations": [observation_entry(n, v) for n, v in observations.items()],
        "parameters": {n: parameter_entry(n, v) for n, v in document.get("parameters", {}).items()},
        "initial_state": None if initial is None else {
            "mean": dict(initial),
            "covariance": model.get("initial_covariance", "process"),
            "scale": model.get("initial_covariance_scale", 1.0),
        },
        "derived": dict(document.get("derived", {})),
        "units": dict(document.get("units", {})),
        "observation_covariance": model.get("observation_covariance"),
        "options": options,
        "population": dict(document.get("population", {})),
    }


def read_model(source):
    """A [`Model`][greyid.model.model.Model] from a TOML model file (a path) or TOML text.

    A relative ``[data] file`` is kept relative to the model file's folder.
    """
    path = None
    if isinstance(source, Path) or (isinstance(source, str) and "\n" not in source and "=" not in source):
        path = Path(source)
        if not path.is_file():
            raise ModelError(f"model file '{path}' not found")
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as err:
            raise ModelError(f"model file '{path}' is not UTF-8 text (byte 0x{err.object[err.start]:02x} at "
                             f"position {err.start}); save it as UTF-8") from None
    elif isinstance(source, str):
        text = source
    else:
        raise ModelError(f"a model file must be a path or TOML text, got {type(source).__name__}")
    where = f"model file '{path}'" if path else "model text"
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ModelError(f"{where} is not valid TOML: {err}") from None
    try:
        model = model_from_dict(spec_from_toml(document))
    except ModelError as err:
        raise ModelError(f"{where}: {err}") from None
    model.source = path
    return model


# ---------------------------------------------------------------------- writing TOML
def _key(name: str) -> str:
    return name if name.replace("_", "a").replace("-", "a").isalnum() else json.dumps(name)


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ModelError(f"{value} cannot be written to a model file")
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise ModelError(f"cannot write {value!r} to a model file")


def model_to_toml(model) -> str:
    """The model file text for ``model``."""
    spec = model_to_dict(model)
    lines = ["# greyid model file", "[model]", f"name = {_value(spec['name'])}"]
    if spec["description"]:
        lines.append(f"description = {_value(spec['description'])}")
    if spec["inputs"]:
        lines.append(f"inputs = {_value(spec['inputs'])}")
    lines += ["system = ["] + [f"  {_value(e)}," for e in spec["system"]] + ["]"]
    if spec["algebraic"]:
        lines += ["algebraic = ["] + [f"  {_value(e)}," for e in spec["algebraic"]] + ["]"]
    initial = spec["initial_state"]
    if initial is not None:
        lines.append(f"initial_covariance = {_value(initial['covariance'])}")
        if initial["scale"] != 1.0:
            lines.append(f"initial_covariance_scale = {_value(initial['scale'])}")
    if spec.get("observation_covariance") is not None:
        lines.append(f"observation_covariance = {_value(spec['observation_covariance'])}")
    lines += ["", "[model.observations]"]
    for o in spec["observations"]:
        name, rhs = (part.strip() for part in o["equation"].split("=", 1))
        lines.append(f"{_key(name)} = {_value({'equation': rhs, 'variance': o['variance']})}")
    if initial is not None:
        lines += ["", "[model.initial_state]"] + [f"{_key(k)} = {_value(v)}" for k, v in initial["mean"].items()]
    if spec["parameters"]:
        lines += ["", "[parameters]"]
        for name, p in spec["parameters"].items():
            entry = {k: p[k] for k in ("init", "lower", "upper") if p.get(k) is not None}
            if p["fixed"]:
                entry = {"init": p["init"], "fixed": True}
            if p.get("prior"):
                entry["prior"] = p["prior"]
            lines.append(f"{_key(name)} = {_value(entry)}")
    if spec["derived"]:
        lines += ["", "[derived]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec["derived"].items()]
    if spec.get("units"):
        lines += ["", "[units]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec["units"].items()]
    if spec.get("population"):
        lines += ["", "[population]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec["population"].items()]
    options = spec["options"]
    for section in ("data", "filter", "estimation"):
        keys = MODEL_SECTIONS[section]
        simple = {k: options[k] for k in keys if k in options and not isinstance(options[k], Mapping)}
        tables = {k: options[k] for k in keys if k in options and isinstance(options[k], Mapping)}
        if simple or tables:
            lines += ["", f"[{section}]"] + [f"{_key(k)} = {_value(v)}" for k, v in simple.items()]
        for name, table in tables.items():
            lines += [f"[{section}.{name}]"] + [f"{_key(k)} = {_value(v)}" for k, v in table.items()]
    return "\n".join(lines) + "\n"


def write_model(model, path=None) -> str:
    """Write ``model`` as a TOML model file to ``path`` (when given); returns the text."""
    text = model_to_toml(model)
    if path is not None:
        from ..outputs import write_atomic

        write_atomic(path, text)
    return text


# ---------------------------------------------------------------------- data
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
    """Read the data for ``model``: the CSV file of [`data_path()`][greyid.model.files.data_path], or the named data set
    (``[data] dataset``, or ``path`` written ``dataset:NAME``) by [`greyid.datasets.fetch()`][greyid.data.named.fetch].

    The separator is ``[data] separator`` when given, else detected.  Column
    renaming by ``[data.columns]`` happens when the data are used.
    """
    name = _dataset_name(model, path)
    if name is not None:
        from ..data.named import fetch

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
    import csv
    import warnings

    import pandas as pd

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
