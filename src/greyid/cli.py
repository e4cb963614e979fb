"""The ``greyid`` command line.

    greyid fit MODEL [DATA] [--out DIR] [--report]    estimate, print the summary, save the fit
    greyid simulate MODEL [DATA] --out FILE            sample paths driven by the data's inputs
    greyid validate FIT [DATA]                         the residual tests of chapter 5
    greyid report FIT [DATA] --out FILE.html           a self-contained HTML report
    greyid design MODEL PLAN [--candidate CSV ...]    information, criteria and bounds of a planned experiment
    greyid identifiability MODEL [--plan CSV]         which parameters any experiment can determine
    greyid models [NAME]                               the model library, or one model's file
    greyid demo [--out DIR]                            fit the bundled model to its bundled data
    greyid cache info | clear                          the cache of traced and compiled programs

MODEL is a model file (``.toml``), a saved fit (``.json``) or a library model's
name; DATA is a CSV file, by default the one the model file names.  Exit codes:
0 done, 1 done with a negative verdict (the fit did not converge, or a test
rejects), 2 bad input (model, data or arguments; the message says which).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape

from .errors import DataError, ModelError
from .schema import METHODS

OK, VERDICT, BAD_INPUT = 0, 1, 2

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="Grey-box identification of physical systems with stochastic differential equations.")
out = Console(highlight=False, soft_wrap=True, markup=False)
err = Console(stderr=True, highlight=False, soft_wrap=True, markup=False)


class InputProblem(Exception):
    """Bad input named by the message; the command exits with code 2."""


DEBUG = {"on": False}  # --debug: show tracebacks of bad input too
#: Whether this process is greyid's own (``greyid ...`` run from a shell, not ``main([...])`` called by a
#: user's script), and whether its layers are loaded (see _load_layers).
OWN_PROCESS = {"on": False, "loaded": False}


def _version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        out.print(f"greyid {version('greyid')}")
        raise typer.Exit(OK)


@app.callback()
def _options(debug: bool = typer.Option(False, "--debug", help="show the traceback of an error"),
             show_version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                               help="print the version and exit")) -> None:
    """Grey-box identification of physical systems with stochastic differential equations."""
    DEBUG["on"] = debug


# ---------------------------------------------------------------------- loading
def load_model_or_fit(source: str):
    """``(model, fit or None)`` from a model file, a saved fit or a library name."""
    from . import library
    from .api import load_fit
    from .api import Model

    path = Path(source)
    if path.suffix == ".json":
        if not path.is_file():
            raise InputProblem(f"fit file '{path}' not found")
        fit = load_fit(path)
        return fit.model, fit
    if path.suffix == ".toml" or path.exists():
        return Model.from_toml(path), None
    if source in library.names() or library._rc_states(source) is not None:
        return library.load_model(source), None
    raise InputProblem(f"'{source}' is neither a model file (.toml), a fit file (.json) nor a library model "
                       f"(see 'greyid models')")


def _writable_folder(folder: Path, what: str) -> None:
    """Refuse a folder greyid cannot create files in, by creating (and removing) one."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".greyid-check-"):
            pass
    except OSError as problem:
        raise InputProblem(f"{what}: cannot write in '{folder}' ({problem.strerror or problem})") from None


def check_output_file(path: Path) -> None:
    """Refuse an output file that cannot be written, before any work is done."""
    try:
        if path.is_dir():
            raise InputProblem(f"--out '{path}' is a folder; give a file name")
        if not path.parent.is_dir():
            raise InputProblem(f"--out '{path}': the folder '{path.parent}' does not exist")
    except OSError as problem:  # a symlink loop, a name too long ...
        raise InputProblem(f"--out '{path}' cannot be used ({problem.strerror or problem})") from None
    _writable_folder(path.parent, f"--out '{path}'")


def check_output_folder(path: Path) -> None:
    """Refuse an output folder that cannot be created or written, before any work is done."""
    what = f"--out '{path}'"
    try:
        if path.exists() and not path.is_dir():
            raise InputProblem(f"{what} is a file; give a folder for fit.json, summary.txt, parameters.csv")
        existing = path
        while not existing.exists():  # the nearest folder that exists: where the new ones are made
            if existing.is_symlink():
                raise InputProblem(f"{what}: '{existing}' is a symbolic link that leads nowhere "
                                   "(a loop or a missing target)")
            existing = existing.parent
        if not existing.is_dir():
            raise InputProblem(f"{what}: '{existing}' is a file, not a folder")
    except OSError as problem:  # a symlink loop, a name too long ...
        raise InputProblem(f"{what} cannot be used ({problem.strerror or problem})") from None
    _writable_folder(existing, what)


def load_data(model, data: Optional[Path], fit=None, time: Optional[str] = None):
    """``(frame, origin)``: DATA (a CSV file, or ``dataset:NAME``), else the fit's data, else the model file's
    ``[data] file`` or ``[data] dataset``; ``origin`` is what a saved fit keeps to find the data again.

    A time column of timestamps is parsed (``[data] time_format``, ``time_zone``)
    and the conversion is said on standard error.
    """
    import pandas as pd

    from .data.files import data_origin, named_dataset, read_data

    if data is None and fit is not None and fit.data_file:
        if named_dataset(fit.data_file) is None and not Path(fit.data_file).is_file():
            raise InputProblem(f"the fit's data file '{fit.data_file}' does not exist (moved or deleted?); "
                               "give the data after the fit file")
        data = fit.data_file
    frame = read_data(model, data, time)
    name = time or model.options.get("time", "t")
    if name in frame.columns and pd.api.types.is_datetime64_any_dtype(frame[name]):
        from .data.timestamps import READ_AS

        unit = model.options.get("time_unit") or "s"
        read_as = frame.attrs.get(READ_AS)
        how = f" (dates read {read_as})" if read_as in ("day-first", "month-first") else ""
        err.print(f"time column '{name}': timestamps from {frame[name].iloc[0]}{how} read as elapsed time in "
                  f"'{unit}' since the first row (set [data] time_unit to change it)")
    return frame, data_origin(model, data)


def _writing_report(enabled: bool = True):
    """A line on standard error if the report takes seconds: its residual tests, profile intervals,
    simulations and predictions compile programs on a first report of a model."""
    from .progress import KEPT, Waiting

    return Waiting("  writing the report: a first report of a model compiles the programs of its residual tests, "
                   f"intervals and figures; {KEPT}", enabled)


def _fit_warning():
    """FitWarning (greyid.errors), taken from estimate.results, whose import loads JAX (and with it sets up
    the cache): imported inside ``_run``'s handling of warnings, so that the cache's own warning is handled too."""
    from .estimate.results import FitWarning

    return FitWarning


def _load_layers() -> None:
    """In greyid's own process, before a command that computes: load JAX, SymPy, pandas and greyid's
    layers with the garbage collector paused and freeze what they made, and keep every compiled program
    in the cache folder however quick its compilation.

    Both would reach a user's own objects and programs, so they are done only here: frozen, the
    imports' quarter of a million objects are walked by no later collection, and the report's many
    small programs compile once for every later command (``benchmarks/runtime.py`` measures what
    each buys ``greyid demo``; docs/performance.md).
    """
    if not OWN_PROCESS["on"] or OWN_PROCESS["loaded"]:
        return
    import gc

    OWN_PROCESS["loaded"] = True
    enabled = gc.isenabled()
    gc.disable()
    try:
        from . import api  # noqa: F401  (every layer a command uses, and JAX, SymPy and pandas)
    finally:
        if enabled:
            gc.freeze()
            gc.enable()
    import jax

    from .runtime import config

    if config.cache_dir() is not None and jax.config.jax_compilation_cache_dir == config.cache_dir():
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def _run(command, quiet_cache: bool = False) -> None:
    """Run a command; turn bad input into a plain message and exit code 2 (``quiet_cache``: the cache
    commands, which say themselves what is wrong with the cache folder and load no model)."""
    import warnings

    from . import errors

    def plainly(message, category, *where, **more):
        # greyid's own warnings as the command's lines; others (a dependency's) as Python prints them.
        if category.__module__.startswith("greyid"):
            err.print(f"warning: {message}")
        else:
            shown(message, category, *where, **more)

    if not quiet_cache:
        _load_layers()
    try:
        with warnings.catch_warnings():
            shown = warnings.showwarning
            warnings.showwarning = plainly
            if quiet_cache:  # the command itself says what is wrong with the cache folder
                warnings.simplefilter("ignore", errors.CacheWarning)
            # A fit's warnings are printed once, at the end of its summary.
            warnings.simplefilter("ignore", _fit_warning())
            code = command()
    except (InputProblem, ModelError, DataError, ImportError) as problem:
        # ImportError: an optional dependency a command needs is missing (its message says what to install).
        if DEBUG["on"]:
            import traceback

            err.print(traceback.format_exc())
        err.print(f"[bold red]error:[/] {escape(str(problem))}", markup=True)
        raise typer.Exit(BAD_INPUT) from None
    raise typer.Exit(code)


# ---------------------------------------------------------------------- commands
@app.command()
def fit(model: str = typer.Argument(..., metavar="MODEL", help="model file (.toml) or library model name"),
        data: Optional[Path] = typer.Argument(None, metavar="DATA",
                                              help="CSV data or dataset:NAME (default: the fit's data, the "
                                                   "model file's [data] file or dataset)"),
        out_dir: Optional[Path] = typer.Option(None, "--out", metavar="DIR",
                                               help="folder for fit.json, summary.txt, parameters.csv"),
        method: Optional[str] = typer.Option(None, metavar="NAME",
                                             help=f"likelihood: {', '.join(METHODS)}"),
        hold: Optional[str] = typer.Option(None, metavar="zoh|foh", help="input hold between samples: zoh or foh"),
        time_column: Optional[str] = typer.Option(None, "--time", metavar="COLUMN", help="name of the time column"),
        starts: Optional[int] = typer.Option(None, min=1, metavar="N",
                                             help="number of starting points (random ones inside the "
                                                  "bounds)"),
        seed: Optional[int] = typer.Option(None, min=0, metavar="N", help="seed of the random starting points"),
        report: bool = typer.Option(False, "--report", help="also write report.html into --out"),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output")):
    """Estimate the parameters of MODEL from DATA and print the summary."""

    def command() -> int:
        if out_dir is not None:
            check_output_folder(out_dir)
        if report and out_dir is None:
            raise InputProblem("--report needs --out DIR to write the report into")
        m, saved = load_model_or_fit(model)
        frame, data_file = load_data(m, data, saved, time=time_column)
        if not quiet:
            err.print(f"fitting '{m.name}' to {len(frame)} rows of {data_file}")
        started = time.perf_counter()
        result = m.fit(frame, time=time_column, hold=hold, method=method, starts=starts, seed=seed,
                       progress=not quiet)
        result.data_file = data_file
        if not quiet:
            err.print(f"fitted in {time.perf_counter() - started:.2f} s")
        out.print(result.summary())
        if m.derived:
            out.print("\nderived quantities (delta-method standard errors):")
            out.print(result.derived().to_string())
        if out_dir is not None:
            import json

            from .outputs import write_generation

            # One generation: all of this run's files replace the previous run's, or none do.
            files = {"fit.json": json.dumps(result.to_dict(), indent=2), "summary.txt": result.summary() + "\n",
                     "parameters.csv": result.params.to_csv()}
            if report:
                with _writing_report(not quiet):
                    files["report.html"] = result.report()
            write_generation(out_dir, files)
            err.print(f"wrote {', '.join(files)} to {out_dir}")
        elif report:
            raise InputProblem("--report needs --out DIR to write the report into")
        return OK if result.converged else VERDICT

    _run(command)


def _pairs(values: list[str], option: str, what: str) -> dict:
    """``NAME:VALUE`` options as a mapping (several values of one name gathered in a list for effects)."""
    out: dict = {}
    for text in values:
        name, sep, value = text.partition(":")
        if not sep or not name or not value:
            raise InputProblem(f"{option} '{text}': write {what}")
        out.setdefault(name, []).append(value)
    return out


def _population_data(paths: list[Path]) -> dict:
    """Name → CSV path: each file given, and each CSV file of each folder given (named by the file's stem)."""
    files: dict = {}
    for path in paths:
        if path.is_dir():
            found = sorted(path.glob("*.csv"))
            if not found:
                raise InputProblem(f"data folder '{path}' holds no .csv file")
            members = found
        elif path.is_file():
            members = [path]
        else:
            raise InputProblem(f"data file or folder '{path}' not found")
        for file in members:
            if file.stem in files:
                raise InputProblem(f"two data files are named '{file.stem}' ({files[file.stem]} and {file}); "
                                   "the members' names must be unique")
            files[file.stem] = file
    return files


@app.command(name="population")
def population_command(
        model: str = typer.Argument(..., metavar="MODEL", help="model file (.toml) or library model name"),
        data: list[Path] = typer.Argument(..., metavar="DATA...",
                                          help="a folder of CSV files (a data set each) or several CSV files"),
        random: list[str] = typer.Option([], "--random", help="PARAMETER:normal or PARAMETER:lognormal (repeat; "
                                                              "default: the model file's [population] random)"),
        covariates: Optional[Path] = typer.Option(None, help="CSV with a row per data set (first column: the "
                                                              "data sets' names, i.e. the files' stems)"),
        effect: list[str] = typer.Option([], "--effect", help="PARAMETER:COVARIATE, a covariate effect (repeat)"),
        omega: Optional[str] = typer.Option(None, help="diagonal or full (correlated random effects; default: "
                                                       "the model file's, else diagonal)"),
        method: Optional[str] = typer.Option(None, metavar="NAME",
                                             help="each member's likelihood: "
                                                  + ", ".join(m for m in METHODS if m != "particle")),
        hessian: str = typer.Option("differences", metavar="differences|exact",
                                    help="the outer Hessian (the standard errors): with the members' second "
                                         "derivatives by central differences of their exact first derivatives, "
                                         "or exact"),
        hold: Optional[str] = typer.Option(None, metavar="zoh|foh", help="input hold between samples: zoh or foh"),
        time_column: Optional[str] = typer.Option(None, "--time", metavar="COLUMN", help="name of the time column"),
        out_dir: Optional[Path] = typer.Option(None, "--out", metavar="DIR",
                                               help="folder for population.json, summary.txt, "
                                                    "parameters.csv, random_effects.csv"),
        report: bool = typer.Option(False, "--report", help="also write report.html (the population report) "
                                                            "into --out"),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output")):
    """Fit a population (mixed-effects) model to many data sets and print its summary (docs/population.md)."""

    def command() -> int:
        if report and out_dir is None:
            raise InputProblem("--report needs --out DIR to write the report into")
        if out_dir is not None:
            check_output_folder(out_dir)
        files = _population_data(data)
        kinds = {name: values[-1] for name, values in _pairs(random, "--random", "PARAMETER:normal or "
                                                              "PARAMETER:lognormal").items()}
        effects = _pairs(effect, "--effect", "PARAMETER:COVARIATE")
        m, _ = load_model_or_fit(model)
        table = None
        if covariates is not None:
            from .data.files import read_covariates

            table = read_covariates(covariates)
        elif effects and not m.population.get("covariates"):
            raise InputProblem("--effect needs --covariates FILE.csv (or covariates = \"...\" in the model "
                               "file's [population])")
        if not quiet:
            err.print(f"fitting the population of '{m.name}' to {len(files)} data sets")
        started = time.perf_counter()
        import warnings

        from .population import PopulationWarning, fit_population

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PopulationWarning)  # the summary lists the members left out
            result = fit_population(m, files, kinds or None, covariates=table, effects=effects or None, omega=omega,
                                    time=time_column, hold=hold, method=method, hessian=hessian,
                                    progress=not quiet)
        if not quiet:
            err.print(f"fitted in {time.perf_counter() - started:.2f} s")
        out.print(result.summary())
        if out_dir is not None:
            import json

            from .outputs import write_generation
            from .population.saved import population_to_dict

            files_out = {"population.json": json.dumps(population_to_dict(result), indent=1),
                         "summary.txt": result.summary() + "\n", "parameters.csv": result.params.to_csv(),
                         "random_effects.csv": result.random_effects.to_csv()}
            if report:
                with _writing_report(not quiet):
                    files_out["report.html"] = result.report()
            write_generation(out_dir, files_out)
            err.print(f"wrote {', '.join(files_out)} to {out_dir}")
        return OK if result.converged else VERDICT

    _run(command)


@app.command()
def simulate(model: str = typer.Argument(..., metavar="MODEL",
                                         help="model file, fit file (.json) or library model name"),
             data: Optional[Path] = typer.Argument(None, metavar="DATA",
                                                   help="CSV with the time column and the inputs"),
             out_file: Optional[Path] = typer.Option(None, "--out", metavar="DIR",
                                                     help="CSV to write (default: print)"),
             paths: int = typer.Option(1, help="number of sample paths"),
             seed: int = typer.Option(0, help="random seed"),
             method: str = typer.Option("euler", help="euler, milstein, heun or exact (linear models)"),
             substeps: int = typer.Option(10, help="integration steps per sampling interval"),
             deterministic: bool = typer.Option(False, "--deterministic", help="the noise-free solution only")):
    """Simulate MODEL (at a fit's estimates, or the model file's initial values) on DATA's times and inputs."""

    def command() -> int:
        if deterministic and paths > 1:
            raise InputProblem(f"--deterministic has no noise: --paths {paths} would write {paths} copies of "
                               "one path; leave --paths out")
        if out_file is not None:
            check_output_file(out_file)
        m, saved = load_model_or_fit(model)
        frame, _ = load_data(m, data, saved)
        params = saved.values if saved is not None else m.initial_values()
        sim = m.simulate(params, frame, n_paths=paths, seed=seed, method=method, substeps=substeps,
                         noise=not deterministic)
        table = sim.to_frame() if paths > 1 else sim.frame(0)
        if out_file is None:
            out.print(table.to_csv(index=False), end="")
        else:
            from .outputs import write_atomic

            write_atomic(out_file, table.to_csv(index=False))
            err.print(f"wrote {paths} path(s), {len(frame)} rows each, to {out_file}")
        return OK

    _run(command)


def _fit_with_data(fit_file: Path, data: Optional[Path]):
    from .api import load_fit

    if not fit_file.exists():
        raise InputProblem(f"fit file '{fit_file}' not found")
    if fit_file.suffix != ".json" or not fit_file.is_file():
        raise InputProblem(f"'{fit_file}' is not a fit file; write one with 'greyid fit MODEL DATA --out DIR'")
    saved = load_fit(fit_file)
    frame, data_file = load_data(saved.model, data, saved)
    return saved.with_data(frame, data_file)


@app.command()
def validate(fit_file: Path = typer.Argument(..., metavar="FIT", help="fit file written by 'greyid fit --out'"),
             data: Optional[Path] = typer.Argument(None, metavar="DATA",
                                                   help="the data (default: the data the fit used)"),
             level: float = typer.Option(0.05, help="significance level of the tests")):
    """Run the residual tests of chapter 5 on a saved fit; exit code 1 if any test rejects."""

    def command() -> int:
        from .progress import KEPT, Waiting

        fitted = _fit_with_data(fit_file, data)
        with Waiting(f"  computing the residuals and their tests: a first run for a model compiles its programs; "
                     f"{KEPT}"):
            result = fitted.validate(level=level)
        out.print(result.summary())
        return VERDICT if len(result.rejected) else OK

    _run(command)


@app.command()
def report(fit_file: Path = typer.Argument(..., metavar="FIT", help="fit file written by 'greyid fit --out'"),
           data: Optional[Path] = typer.Argument(None, metavar="DATA",
                                                 help="the data (default: the data the fit used)"),
           out_file: Path = typer.Option(Path("report.html"), "--out", help="HTML file to write"),
           level: float = typer.Option(0.05, help="significance level of the tests"),
           steps: int = typer.Option(4, help="prediction horizon shown beside 1-step predictions")):
    """Write a self-contained HTML report of a saved fit."""

    def command() -> int:
        check_output_file(out_file)
        fitted = _fit_with_data(fit_file, data)
        with _writing_report():
            fitted.report(out_file, level=level, steps=steps)
        err.print(f"wrote {out_file}")
        return OK

    _run(command)


def _read_plan(m, path: Path):
    if path.is_dir():
        raise InputProblem(f"plan '{path}' is a folder; give a CSV file")
    if not path.is_file():
        raise InputProblem(f"plan file '{path}' not found")
    from .data.files import read_csv_file

    try:
        table = read_csv_file(path, m.options.get("separator"), m.options.get("decimal"))
    except DataError as problem:
        raise InputProblem(f"plan {problem}") from None
    measured = [name for name in m.output_names if name in table.columns]
    if measured:  # measured data used as a plan: its inputs are the plan
        err.print(f"plan '{path.stem}': the measured output column(s) {', '.join(measured)} left out "
                  "(a plan is the times and inputs)")
        table = table.drop(columns=measured)
    return table


@app.command(name="design")
def design_command(model: str = typer.Argument(..., metavar="MODEL",
                                               help="model file, fit file (.json) or library model name"),
                   plan: Path = typer.Argument(..., metavar="PLAN",
                                               help="CSV with the time column and the inputs (measured "
                                                    "outputs in it are left out, with a notice)"),
                   candidates: Optional[list[Path]] = typer.Option(None, "--compare", "--candidate",
                                                                  help="another plan to rank against PLAN "
                                                                       "(repeatable)"),
                   criterion: Optional[list[str]] = typer.Option(None, "--criterion",
                                                                 help="D, A, C or E (repeatable; default all)"),
                   method: Optional[str] = typer.Option(None, help="exact (linear models) or montecarlo"),
                   paths: int = typer.Option(100, help="simulated data sets for montecarlo"),
                   hold: Optional[str] = typer.Option(None, metavar="zoh|foh",
                                                      help="input hold between samples: zoh or foh")):
    """The Fisher information of a planned experiment, its criteria and Cramér–Rao bounds (chapter 6)."""

    def command() -> int:
        import warnings

        import numpy as np
        import pandas as pd

        from . import design
        from .errors import UndefinedCriterionWarning
        from .errors import UndeterminedWarning as design_warning

        m, saved = load_model_or_fit(model)
        params = saved.values if saved is not None else m.initial_values()
        options = dict(time=m.options.get("time", "t"), hold=hold or m.options.get("hold", "zoh"), method=method,
                       n_paths=paths)
        names = list(criterion or ["D", "A", "C", "E"])
        bad = [c for c in names if c not in ("D", "A", "C", "E")]
        if bad:
            raise InputProblem(f"--criterion '{bad[0]}' is not one of D, A, C, E")
        plans = {plan.stem: _read_plan(m, plan)}
        for path in candidates or []:
            if path.stem in plans:
                raise InputProblem(f"two plans are named '{path.stem}'; give the files different names")
            plans[path.stem] = _read_plan(m, path)
        with warnings.catch_warnings():  # printed below, as the command's own lines
            warnings.simplefilter("ignore", design_warning)
            warnings.simplefilter("ignore", UndefinedCriterionWarning)
            table = design.compare_inputs(m, params, plans, criteria={c: c for c in names}, **options)
            info = table.attrs["information"][plan.stem]
            bound = design.cramer_rao_bound(info)
        out.print(f"Fisher information of plan '{plan.stem}' ({info.attrs.get('method')}), natural parameters:")
        out.print(info.rename_axis("parameter").reset_index().to_string(index=False,
                                                                         float_format=lambda v: f"{v:.4g}"))
        out.print()
        out.print("Cramér–Rao bound (least standard deviation of an unbiased estimate; inf: not determined):")
        out.print(pd.DataFrame({"value": pd.Series(params)[bound.index], "sd bound": np.sqrt(bound)})
                  .rename_axis("parameter").reset_index().to_string(index=False, float_format=lambda v: f"{v:.4g}"))
        out.print()
        out.print("criteria (smaller is better):")
        out.print(table.rename_axis("plan").reset_index().to_string(index=False, float_format=lambda v: f"{v:.5g}"))
        for label, message in table.attrs["undefined"].items():
            out.print(f"{label} not computed: {message}")
        flat = design.local_identifiability(info)
        for name, direction in table.attrs["undetermined"].items():
            out.print(f"not determined by plan '{name}': the direction {direction} (scaled parameters)")
        return OK if flat.empty else VERDICT

    _run(command)


@app.command(name="identifiability")
def identifiability_command(model: str = typer.Argument(..., metavar="MODEL",
                                                        help="model file, fit file (.json) or library model name"),
                           plan: Optional[Path] = typer.Option(None, "--plan",
                                                               help="CSV plan (needed for nonlinear models)")):
    """Which parameters any experiment can determine (section 6.1); exit code 1 if some cannot."""

    def command() -> int:
        from . import design

        m, saved = load_model_or_fit(model)
        params = saved.values if saved is not None else None
        frame = None if plan is None else _read_plan(m, plan)
        result = design.identifiability(m, params, plan=frame)
        out.print(result.summary())
        return OK if all(result.identifiable.values()) else VERDICT

    _run(command)


@app.command()
def models(name: Optional[str] = typer.Argument(None, help="print this model's file")):
    """List the model library, or print one model as a model file to start from."""
    from . import library

    def command() -> int:
        if name is None:
            for key, description in library.available().items():
                out.print(f"[bold]{key:16s}[/] {escape(description)}", markup=True)
            return OK
        out.print(library.load_model(name).to_toml(), end="")
        return OK

    _run(command)


@app.command()
def demo(out_dir: Path = typer.Option(Path("greyid-demo"), "--out", help="folder for the fit and its report"),
         report: bool = typer.Option(True, "--report/--no-report", help="write report.html"),
         quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress output")):
    """Fit the bundled building model to its bundled (simulated) data, print the summary, write a report."""

    def command() -> int:
        from .datasets import TRUE_PARAMETERS, building_model

        check_output_folder(out_dir)
        model = building_model()
        data, data_file = load_data(model, None)
        out.print(model)
        out.print(f"model file: {model.source}")
        out.print(f"data: {len(data)} rows, t from {data['t'].iloc[0]:.6g} to {data['t'].iloc[-1]:.6g} h")
        started = time.perf_counter()
        result = model.fit(data, progress=not quiet)
        result.data_file = data_file
        out.print(f"fitted in {time.perf_counter() - started:.2f} s\n")
        out.print(result.summary())
        out.print("\nphysical characteristics (delta-method standard errors):")
        out.print(result.derived().to_string())
        truth = model.loglik(TRUE_PARAMETERS, data)
        out.print(f"\nlog-likelihood at the simulation's true parameters: {truth:.4f}")
        import json

        from .outputs import write_generation

        files = {"fit.json": json.dumps(result.to_dict(), indent=2)}
        if report:
            with _writing_report(not quiet):
                files["report.html"] = result.report()
        write_generation(out_dir, files)
        if report:
            out.print(f"report: {out_dir / 'report.html'}")
        return OK if result.converged else VERDICT

    _run(command)


cache_app = typer.Typer(no_args_is_help=True, help="greyid's cache of traced and compiled programs.")
app.add_typer(cache_app, name="cache")


def _size(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n} B"


@cache_app.command(name="info")
def cache_info():
    """Where greyid keeps traced programs and JAX's compiled code, and how much is there."""

    def command() -> int:
        from .runtime import store as programs

        usage = programs.usage()
        if usage["folder"] is None:
            out.print("greyid's cache is switched off (GREYID_CACHE_DIR=off)")
            return OK
        if usage["problem"]:
            raise InputProblem(f"greyid's cache folder '{usage['folder']}' (GREYID_CACHE_DIR) {usage['problem']}; "
                               "programs are not kept")
        exists = "" if Path(usage["folder"]).is_dir() else " (not made yet: made by the first fit)"
        out.print(f"folder: {usage['folder']} (GREYID_CACHE_DIR){exists}")
        files, size = usage["programs"]
        out.print(f"traced programs: {files} files, {_size(size)} (programs/)")
        files, size = usage["compiled"]
        out.print(f"compiled programs (JAX's persistent cache): {files} files, {_size(size)}")
        return OK

    _run(command, quiet_cache=True)


@cache_app.command(name="clear")
def cache_clear():
    """Remove the kept traced and compiled programs (they are made again when next needed)."""

    def command() -> int:
        from .runtime import store as programs

        usage = programs.usage()
        if usage["problem"]:
            raise InputProblem(f"greyid's cache folder '{usage['folder']}' (GREYID_CACHE_DIR) {usage['problem']}; "
                               "nothing to clear")
        removed = programs.clear()
        out.print(f"removed {removed} files from {programs.usage()['folder'] or 'nothing (cache off)'}")
        return OK

    _run(command, quiet_cache=True)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (for tests and ``python -m greyid``)."""
    if argv is None:  # run from a shell: the process is greyid's own (see _load_layers)
        OWN_PROCESS["on"] = True
    try:
        app(args=argv, prog_name="greyid")
    except SystemExit as done:
        return done.code if isinstance(done.code, int) else (OK if done.code is None else BAD_INPUT)
    return OK


if __name__ == "__main__":
    sys.exit(main())
