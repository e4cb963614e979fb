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
    # initial_diffuse = ["Te"]         # optional: states started exactly diffuse (Koopman & Durbin)

    [model.observations]
    yTi = { equation = "Ti", variance = "exp(e11)" }

    [model.transforms]                 # optional: Lamperti transforms of states with state-dependent noise
    # Ti = "log"

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
``model.to_toml``); [`read_data()`][greyid.data.files.read_data] reads the data a model file points to.
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Mapping

import numpy as np

from ..data.files import read_data  # noqa: F401  (the data a model file names; read in data/)
from ..errors import ModelError
from ..outputs import write_atomic
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
        "observations": [_observation(model, o) for o in model._observations],
        "observation_covariance": _plain(model._observation_covariance),
        "algebraic": [a.text for a in model._algebraics],
        "transforms": dict(model._transforms),
        "latent_forces": {name: kernel.to_dict() for name, kernel in model._latent_forces.items()},
        "parameters": {n: parameter(p) for n, p in model.parameters.items()},
        "initial_state": None if model._initial_mean is None else {
            "mean": {k: _plain(v) for k, v in model._initial_mean.items()},
            "covariance": _plain(model._initial_covariance),
            "scale": model._initial_scale,
            **({"diffuse": list(model._diffuse)} if model._diffuse else {}),
        },
        "derived": model.derived,
        "units": model.units,
        "options": options,
        "population": dict(model.population),
    }


def _observation(model, entry) -> dict:
    """An observation's entry: its equation, variance and, where not normal, its distribution."""
    equation, _, variance = entry
    out = {"equation": equation.text, "variance": _plain(variance)}
    law = model._distributions.get(equation.lhs)
    if law is not None and not law.gaussian:
        out["distribution"] = law.to_dict()
        if variance is None:
            del out["variance"]
    return out


def model_from_dict(spec: Mapping, cls):
    """Rebuild a model of class ``cls`` from its [`model_to_dict()`][greyid.model.files.model_to_dict] form."""
    m = cls(spec.get("name", "model"), spec.get("description", ""))
    if spec.get("system"):
        m.add_system(*spec["system"])
    if spec.get("inputs"):
        m.add_inputs(*spec["inputs"])
    for a in spec.get("algebraic", []):
        m.add_algebraic(a)
    for state, transform in (spec.get("transforms") or {}).items():
        m.transform_state(state, transform)
    for name, kernel in (spec.get("latent_forces") or {}).items():
        m.add_latent_force(name, kernel)
    for o in spec["observations"]:
        m.add_observation(o["equation"], variance=o.get("variance"), distribution=o.get("distribution"))
    if spec.get("observation_covariance") is not None:
        m.set_observation_covariance(spec["observation_covariance"])
    for name, p in spec.get("parameters", {}).items():
        prior = p.get("prior")
        m.set_parameter(name, init=p.get("init"), lower=p.get("lower"), upper=p.get("upper"),
                        fixed=p.get("fixed", False), prior=None if prior is None else (prior["mean"], prior["sd"]))
    init = spec.get("initial_state")
    if init is not None:
        m.set_initial_state(mean=init["mean"], covariance=init["covariance"], scale=init.get("scale", 1.0),
                            diffuse=init.get("diffuse", ()))
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
    system = model.get("system") or []
    system = system if isinstance(system, list) else [system]
    observations = model["observations"]
    initial = model.get("initial_state")
    if initial is None and model.get("initial_diffuse"):  # every state diffuse: no means to give
        initial = {}
    options = {}
    for section in ("data", "filter", "estimation"):
        options.update(document.get(section, {}))
    return {
        "name": model.get("name", "model"),
        "description": model.get("description", ""),
        "system": list(system),
        "inputs": list(model.get("inputs", [])),
        "algebraic": list(model.get("algebraic", [])),
        "transforms": dict(model.get("transforms", {})),
        "latent_forces": dict(model.get("latent_forces", {})),
        "observations": [observation_entry(n, v) for n, v in observations.items()],
        "parameters": {n: parameter_entry(n, v) for n, v in document.get("parameters", {}).items()},
        "initial_state": None if initial is None else {
            "mean": dict(initial),
            "covariance": model.get("initial_covariance", "process"),
            "scale": model.get("initial_covariance_scale", 1.0),
            **({"diffuse": model["initial_diffuse"]} if "initial_diffuse" in model else {}),
        },
        "derived": dict(document.get("derived", {})),
        "units": dict(document.get("units", {})),
        "observation_covariance": model.get("observation_covariance"),
        "options": options,
        "population": dict(document.get("population", {})),
    }


def read_model(source, cls):
    """A model of class ``cls`` (a [`Model`][greyid.api.Model]) from a TOML model file (a path) or
    TOML text.

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
        model = model_from_dict(spec_from_toml(document), cls)
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
        if initial.get("diffuse"):
            lines.append(f"initial_diffuse = {_value(initial['diffuse'])}")
    if spec.get("observation_covariance") is not None:
        lines.append(f"observation_covariance = {_value(spec['observation_covariance'])}")
    lines += ["", "[model.observations]"]
    for o in spec["observations"]:
        name, rhs = (part.strip() for part in o["equation"].split("=", 1))
        entry = {"equation": rhs, **{k: o[k] for k in ("variance", "distribution") if k in o}}
        lines.append(f"{_key(name)} = {_value(entry)}")
    if spec.get("latent_forces"):
        lines += ["", "[model.latent_forces]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec["latent_forces"].items()]
    if spec.get("transforms"):
        lines += ["", "[model.transforms]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec["transforms"].items()]
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
        write_atomic(path, text)
    return text
