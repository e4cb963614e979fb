"""One validation layer for what users write: settings, model files and saved fits.

Each kind of document has its schema here — the sections and keys it may
hold, the type of every value (booleans as booleans, lists as lists) — and the
functions that check a document against it, raising a [`ModelError`][greyid.errors.ModelError] that
names the file, section, key or parameter.  The API and the command line call
the same checks: ``Model.set_options`` and model files (settings),
[`greyid.model.files.read_model()`][greyid.model.files.read_model] (model files),
[`greyid.api.load_fit()`][greyid.api.load_fit] and ``fit_from_dict`` (saved fits).
Data are checked against a model where they meet it, column by column and row
by row ([`greyid.data.prepare.prepare_series()`][greyid.data.prepare.prepare_series]).
"""

from __future__ import annotations

from typing import Mapping

from .errors import ModelError

# ---------------------------------------------------------------------- settings
#: Data settings: time column, hold order, time unit of datetime columns, and the
#: mapping from model names (inputs, outputs) to the data's column names.
DATA_KEYS = ("time", "hold", "time_unit", "columns", "time_format", "time_zone")
#: Filter settings (see [`greyid.filters.api.filter_options()`][greyid.filters.api.filter_options]).
FILTER_KEYS = ("method", "form", "substeps", "iterations", "alpha", "beta", "kappa", "steady_state", "particles",
               "resample", "scheme", "inflation", "proposal")
#: Estimation settings of [`Model.fit()`][greyid.api.Model.fit].
ESTIMATION_KEYS = ("criterion", "robust", "horizon", "starts", "seed", "maxiter", "prior_correlation", "cov_type",
                   "optimizer")
#: Where the data live, for the command line: a CSV file (relative to the model
#: file), its field separator and its decimal mark (both detected where not given).
FILE_KEYS = ("file", "dataset", "separator", "decimal")
ALL_KEYS = DATA_KEYS + FILE_KEYS + FILTER_KEYS + ESTIMATION_KEYS

HOLDS = ("zoh", "foh")
METHODS = ("kalman", "ekf", "iekf", "ekf2", "ukf", "truncated2", "gaussian2", "enkf", "particle", "laplace")
FORMS = ("sqrt", "plain")
#: The fit's searches (what each does: greyid.estimate.estimation, where they are run).
OPTIMIZERS = ("auto", "scoring", "newton", "quasi-newton", "lbfgs")


def check_options(options: Mapping) -> dict:
    """Validate settings by name and type; returns a plain dict."""
    out = {}
    for key, value in options.items():
        if key not in ALL_KEYS:
            raise ModelError(f"unknown setting '{key}'; settings are {list(ALL_KEYS)}")
        if value is None:
            continue
        text_keys = ("time", "file", "dataset", "separator", "decimal", "time_unit", "time_format", "time_zone")
        if key in text_keys and not isinstance(value, str):
            raise ModelError(f"setting '{key}' must be a string, got {value!r}")
        if key == "hold" and value not in HOLDS:
            raise ModelError(f"setting 'hold' must be 'zoh' or 'foh', got {value!r}")
        if key == "method" and value not in METHODS:
            raise ModelError(f"setting 'method' must be one of {list(METHODS)}, got {value!r}")
        if key == "inflation" and not (isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 1):
            raise ModelError(f"setting 'inflation' must be a number of at least 1, got {value!r}")
        if key == "scheme" and value not in ("auto", "euler", "ctsmtmb"):
            raise ModelError(f"setting 'scheme' must be 'auto', 'euler' or 'ctsmtmb', got {value!r}")
        if key == "proposal" and value not in ("bootstrap", "ekf", "ukf"):
            raise ModelError(f"setting 'proposal' must be 'bootstrap', 'ekf' or 'ukf', got {value!r}")
        if key == "form" and value not in FORMS:
            raise ModelError(f"setting 'form' must be 'sqrt' or 'plain', got {value!r}")
        if key == "criterion" and value not in ("ml", "map"):
            raise ModelError(f"setting 'criterion' must be 'ml' or 'map', got {value!r}")
        if key == "cov_type" and value not in ("hessian", "opg", "sandwich"):
            raise ModelError(f"setting 'cov_type' must be 'hessian', 'opg' or 'sandwich', got {value!r}")
        if key == "optimizer" and value not in OPTIMIZERS:
            raise ModelError(f"setting 'optimizer' must be {', '.join(map(repr, OPTIMIZERS[:-1]))} or "
                             f"{OPTIMIZERS[-1]!r}, got {value!r}")
        if key == "resample" and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                      and 0 < value <= 1):
            raise ModelError(f"setting 'resample' must be a fraction in (0, 1] of the particles, got {value!r}")
        if key in ("horizon", "starts", "substeps", "iterations", "maxiter", "particles") and not (
            isinstance(value, int) and not isinstance(value, bool) and value >= 1
        ):
            raise ModelError(f"setting '{key}' must be a positive integer, got {value!r}")
        if key == "steady_state" and not isinstance(value, bool):
            raise ModelError(f"setting 'steady_state' must be true or false, got {value!r}")
        if key == "seed" and not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise ModelError(f"setting 'seed' must be a non-negative integer, got {value!r}")
        if key == "robust":
            value = tuple(value) if isinstance(value, list) else value
        if key == "columns":
            if not isinstance(value, Mapping) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in value.items()
            ):
                raise ModelError("setting 'columns' must map model names to column names (strings)")
            value = dict(value)
        if key == "prior_correlation":
            value = prior_correlation(value)
        out[key] = value
    return out


def prior_correlation(value) -> dict[tuple[str, str], float]:
    """``{("a", "b"): ρ}``; keys may also be written ``"a,b"`` (as in a TOML file)."""
    if not isinstance(value, Mapping):
        raise ModelError("prior_correlation must map parameter pairs to correlations")
    out = {}
    for key, rho in value.items():
        pair = tuple(s.strip() for s in key.split(",")) if isinstance(key, str) else tuple(key)
        if len(pair) != 2 or not all(isinstance(p, str) and p for p in pair):
            raise ModelError(f"prior correlation key {key!r} must name two parameters, e.g. 'Ci,Cw'")
        if not isinstance(rho, (int, float)) or not -1 < rho < 1:
            raise ModelError(f"prior correlation of {pair} must be a number in (-1, 1), got {rho!r}")
        out[pair] = float(rho)
    return out


# ---------------------------------------------------------------------- model files
#: Sections of a model file and the keys each may hold (None: any names, checked by kind).
MODEL_SECTIONS = {
    "model": ("name", "description", "inputs", "system", "algebraic", "observations", "initial_state", "transforms",
              "latent_forces",
              "initial_covariance", "initial_covariance_scale", "initial_diffuse", "observation_covariance"),
    "parameters": None,
    "derived": None,
    "units": None,
    "data": DATA_KEYS + FILE_KEYS,
    "filter": FILTER_KEYS,
    "estimation": ESTIMATION_KEYS,
    "population": ("random", "effects", "omega", "covariates", "omega_init"),
}
PARAMETER_KEYS = ("init", "lower", "upper", "fixed", "prior")
OBSERVATION_KEYS = ("equation", "variance", "distribution")


def check_keys(table: Mapping, allowed, where: str) -> None:
    for key in table:
        if key not in allowed:
            raise ModelError(f"unknown key '{key}' in {where}; allowed keys are {list(allowed)}")


def observation_entry(name: str, value) -> dict:
    """A ``[model.observations]`` entry, checked: ``{equation, variance}``, or ``{equation, distribution}``
    for counts (``{equation, variance, distribution}`` for the Student-t and log-normal distributions)."""
    if not isinstance(value, Mapping) or "equation" not in value or not ({"variance", "distribution"} & set(value)):
        raise ModelError(f"observation '{name}' must be a table {{ equation = \"...\", variance = ... }} "
                         "(or {{ equation = \"...\", distribution = \"poisson\" }} for counts)")
    check_keys(value, OBSERVATION_KEYS, f"[model.observations] {name}")
    out = {"equation": f"{name} = {value['equation']}", "variance": value.get("variance")}
    if "distribution" in value:
        out["distribution"] = value["distribution"]
    return out


def parameter_entry(name: str, value) -> dict:
    """A ``[parameters]`` entry, checked: a number (the initial value) or ``{init, lower, upper, fixed, prior}``."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {"init": float(value)}  # shorthand: `Ci = 1.0` gives the initial value only
    if not isinstance(value, Mapping):
        raise ModelError(f"parameter '{name}' must be a number or a table {{ init = ..., lower = ..., upper = ... }}")
    check_keys(value, PARAMETER_KEYS, f"[parameters] {name}")
    out = {k: value.get(k) for k in ("init", "lower", "upper")}
    fixed = value.get("fixed", False)
    if not isinstance(fixed, bool):
        raise ModelError(f"[parameters] {name}: 'fixed' must be true or false, got {fixed!r}")
    out["fixed"] = fixed
    prior = value.get("prior")
    if prior is not None:
        if not isinstance(prior, Mapping) or set(prior) != {"mean", "sd"}:
            raise ModelError(f"prior of parameter '{name}' must be {{ mean = ..., sd = ... }}")
        out["prior"] = dict(prior)
    return out


def check_model_document(document: Mapping) -> None:
    """The sections and keys of a parsed model file, and the types of [model]'s lists."""
    check_keys(document, tuple(MODEL_SECTIONS), "the model file")
    if "model" not in document:
        raise ModelError("the model file has no [model] section")
    for section, keys in MODEL_SECTIONS.items():
        if keys is not None and section in document:
            check_keys(document[section], keys, f"[{section}]")
    model = document["model"]
    system = model.get("system")
    if isinstance(system, str):
        system = [system]
    if not system and not model.get("latent_forces"):
        raise ModelError("[model] needs system = [\"dx = ...*dt + ...*dw1\", ...] (or [model.latent_forces])")
    system = system or []
    for key in ("system", "inputs", "algebraic", "initial_diffuse"):
        value = system if key == "system" else model.get(key, [])
        if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise ModelError(f"[model] {key} must be a list of strings, e.g. {key} = [\"...\"], got {value!r}")
    forces = model.get("latent_forces", {})
    if not (isinstance(forces, Mapping) and all(isinstance(v, Mapping) for v in forces.values())):
        raise ModelError("[model.latent_forces] must be a table of name = { kernel = \"matern32\", scale = ..., "
                         f"lengthscale = ... }}, got {forces!r}")
    transforms = model.get("transforms", {})
    if not (isinstance(transforms, Mapping) and all(isinstance(v, str) for v in transforms.values())):
        raise ModelError(f"[model.transforms] must be a table of state = \"transform\" (e.g. x = \"log\"), got "
                         f"{transforms!r}")
    if not model.get("observations"):
        raise ModelError("the model file has no [model.observations]; "
                         "add e.g. y = { equation = \"x\", variance = \"s\" }")


# ---------------------------------------------------------------------- saved fits
FIT_FORMAT = "greyid-fit-1"
#: Entries every saved fit holds.
FIT_KEYS = ("model", "params", "cov", "loglik", "criterion_value", "n_obs", "converged", "message", "iterations",
            "settings")


def check_fit_document(spec, where: str) -> None:
    """A saved fit's dictionary: its format, its entries, a table with an estimate per parameter."""
    if not isinstance(spec, dict) or spec.get("format") != FIT_FORMAT:
        raise ModelError(f"{where} is not a greyid fit file (no \"format\": \"{FIT_FORMAT}\")")
    for key in FIT_KEYS:
        if key not in spec:
            raise ModelError(f"{where} lacks the entry '{key}'")
    for name, entry in spec["params"].items() if isinstance(spec["params"], dict) else [("params", None)]:
        if not isinstance(entry, dict) or "estimate" not in entry:
            raise ModelError(f"{where}: parameter entry '{name}' must be a table with an 'estimate'")
        for column in ("estimate", "std_error", "t_value", "p_value", "lower_bound", "upper_bound", "gradient"):
            if column in entry and entry[column] is not None and not _number(entry[column]):
                raise ModelError(f"{where}: '{column}' of parameter '{name}' must be a number, got {entry[column]!r}")
        for column in ("fixed", "at_bound", "reliable"):
            if column in entry and not isinstance(entry[column], bool):
                raise ModelError(f"{where}: '{column}' of parameter '{name}' must be true or false, "
                                 f"got {entry[column]!r}")
    for key in ("loglik", "criterion_value"):
        if not _number(spec[key]):
            raise ModelError(f"{where}: '{key}' must be a number, got {spec[key]!r}")
    for key in ("n_obs", "iterations"):
        value = spec[key]
        if not (isinstance(value, int) and not isinstance(value, bool) and value >= 0):
            raise ModelError(f"{where}: '{key}' must be a whole number ≥ 0, got {value!r}")
    if not isinstance(spec["converged"], bool):
        raise ModelError(f"{where}: 'converged' must be true or false, got {spec['converged']!r}")
    if not isinstance(spec["message"], str):
        raise ModelError(f"{where}: 'message' must be text, got {spec['message']!r}")
    if not isinstance(spec["settings"], dict):
        raise ModelError(f"{where}: 'settings' must be a table, got {spec['settings']!r}")
    cov = spec["cov"]
    if not (isinstance(cov, dict) and isinstance(cov.get("names"), list) and isinstance(cov.get("matrix"), list)):
        raise ModelError(f"{where}: 'cov' must be a table with 'names' and 'matrix'")
    names, matrix = cov["names"], cov["matrix"]
    if not all(isinstance(n, str) for n in names) or (isinstance(spec["params"], dict)
                                                         and any(n not in spec["params"] for n in names)):
        raise ModelError(f"{where}: 'cov' names {names!r}, which are not all parameters of the fit")
    flat = [v for row in matrix for v in (row if isinstance(row, list) else [row])]
    if len(flat) != len(names) ** 2 or not all(v is None or _number(v) for v in flat):
        raise ModelError(f"{where}: 'cov' matrix must hold {len(names)}×{len(names)} numbers for its "
                         f"{len(names)} names, got {len(flat)} values")
    data_file = spec.get("data_file")
    if data_file is not None and not isinstance(data_file, str):
        raise ModelError(f"{where}: 'data_file' must be a path (text), got {data_file!r}")


def _number(value) -> bool:
    """A JSON number (NaN and infinities included, as written by Python's json)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)
