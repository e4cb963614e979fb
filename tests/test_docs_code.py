"""The documentation's code runs as written.

Every ```python block of every page (README.md and docs/) runs, in order, in one namespace per page,
from a fresh folder that holds the repository's ``examples`` and ``src`` (the pages' relative paths);
a ```toml block right after a line that ends in "`NAME.toml`:" is written to that file first.  A block
that is an overview of the API, whose names stand for the reader's own model and data, says so in a
comment right above it, ``<!-- not run: REASON -->``, and is shown, not run; the tutorials have none
(but the Dask cluster's, which starts worker processes).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import matplotlib
import pytest
from conftest import release_memory

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").rglob("*.md")])
TUTORIALS = {"README.md", "getting-started.md", "user-guide.md", "design.md", "fleets.md", "population.md",
             "latent-forces.md"}
#: Pages whose code fits models of real data sets or populations: tens of seconds each.
SLOW = {"user-guide.md", "design.md", "population.md", "latent-forces.md"}
BLOCK = re.compile(r"```(python|toml)\n(.*?)```", re.S)
NOT_RUN = re.compile(r"<!-- not run: (.+?) -->\s*$")
FILE = re.compile(r"`([\w.-]+\.toml)`:\s*$")


def blocks(page: Path) -> list[dict]:
    """Each code block: its language, text, line, and the comment or file name just above it."""
    text = page.read_text(encoding="utf-8")
    out = []
    for match in BLOCK.finditer(text):
        before = text[:match.start()].rstrip("\n").splitlines()
        above = before[-1] if before else ""
        not_run, file = NOT_RUN.search(above), FILE.search(above)
        out.append(dict(language=match.group(1), code=match.group(2), line=text[:match.start()].count("\n") + 1,
                        not_run=not_run.group(1) if not_run else None, file=file.group(1) if file else None))
    return out


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


def test_every_block_that_is_not_run_says_why_and_tutorials_run_theirs():
    for page in PAGES:
        for block in blocks(page):
            if block["language"] == "python" and block["not_run"] is not None:
                assert len(block["not_run"]) > 10, f"{_name(page)}:{block['line']}: say why it is not run"
                if page.name in TUTORIALS:
                    assert "worker processes" in block["not_run"], (
                        f"{_name(page)}:{block['line']}: a tutorial's code must run as written")


PYTHON_PAGES = [page for page in PAGES
                if any(b["language"] == "python" and b["not_run"] is None for b in blocks(page))]


@pytest.mark.parametrize("page", [pytest.param(p, marks=pytest.mark.slow) if p.name in SLOW else p
                                  for p in PYTHON_PAGES], ids=_name)
def test_a_pages_code_runs_as_written(page, tmp_path, monkeypatch):
    mirror = os.environ.get("GREYID_DATA_MIRROR")
    code = "\n".join(b["code"] for b in blocks(page) if b["language"] == "python" and b["not_run"] is None)
    if "datasets.fetch" in code and not (mirror and Path(mirror).is_dir()):
        if os.environ.get("CI"):
            pytest.fail("the data sets the page fetches are not available: CI must run beside ../shared/data")
        pytest.skip("the data sets the page fetches are not available (GREYID_DATA_MIRROR)")
    matplotlib.use("Agg")
    for name in ("examples", "src"):
        (tmp_path / name).symlink_to(ROOT / name)
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    try:
        for block in blocks(page):
            if block["language"] == "toml" and block["file"]:
                (tmp_path / block["file"]).write_text(block["code"], encoding="utf-8")
            if block["language"] != "python" or block["not_run"] is not None:
                continue
            try:
                exec(compile(block["code"], f"{_name(page)}:{block['line']}", "exec"), namespace)
            except Exception as error:  # the page and line of the block that failed, with the error
                raise AssertionError(f"{_name(page)}, the block at line {block['line']}: "
                                     f"{type(error).__name__}: {error}") from error
    finally:
        import matplotlib.pyplot as plt

        plt.close("all")
        # A page's models end with it: their programs go too, rather than add to the next page's (the
        # pages run one after another in one process, beside the other test worker's tests).
        namespace.clear()
        release_memory(models_too=True)


#: The public API whose every argument the reference documents, in NumPy style (Parameters, Returns).
DOCUMENTED = ["greyid.api.Model", "greyid.api.FitResult", "greyid.api.load_fit",
              "greyid.estimate.likelihood.Likelihood", "greyid.fleet.fit.fit_many", "greyid.fleet.result.FleetResult",
              "greyid.fleet.population.relate", "greyid.population.fit.fit_population",
              "greyid.population.result.PopulationResult", "greyid.population.result.likelihood_ratio",
              "greyid.population.result.load_population", "greyid.data.named.fetch", "greyid.data.annex58.ten_minutes",
              "greyid.design.information.fisher_information", "greyid.design.information.local_identifiability",
              "greyid.design.criteria.cramer_rao_bound", "greyid.design.criteria.criterion",
              "greyid.design.criteria.average_criterion", "greyid.design.criteria.minimax_criterion",
              "greyid.design.criteria.with_prior", "greyid.design.compare.compare_inputs",
              "greyid.design.frequency.frequency_information", "greyid.design.frequency.frequency_information_grid",
              "greyid.design.frequency.frequency_information_points", "greyid.design.multisine.optimal_multisine",
              "greyid.design.sampling.sampling_table", "greyid.design.sampling.aliased",
              "greyid.design.identifiability.identifiability",
              "greyid.uncertainty.profile.profile", "greyid.uncertainty.profile.profile_interval",
              "greyid.uncertainty.profile.profile_intervals", "greyid.uncertainty.profile.plot_profile",
              "greyid.uncertainty.sampling.sample", "greyid.uncertainty.intervals.predict",
              "greyid.uncertainty.intervals.simulate", "greyid.uncertainty.intervals.parameter_draws",
              "greyid.uncertainty.intervals.plot_intervals", "greyid.simulate.signals.prbs",
              "greyid.simulate.signals.steps", "greyid.simulate.signals.multisine",
              "greyid.simulate.simulate.simulate", "greyid.library.available", "greyid.library.load_model",
              "greyid.library.names", "greyid.library.rc_network", "greyid.library.walls.wall_model",
              "greyid.library.walls.lumped_wall", "greyid.library.walls.wall_frequency_response",
              "greyid.library.walls.ladder_polynomials",
              "greyid.validation.independence.acf", "greyid.validation.independence.pacf",
              "greyid.validation.independence.ljung_box", "greyid.validation.independence.turning_point_test",
              "greyid.validation.independence.difference_sign_test", "greyid.validation.independence.rank_test",
              "greyid.validation.independence.ks_normality", "greyid.validation.spectral.periodogram",
              "greyid.validation.spectral.cumulative_periodogram",
              "greyid.validation.spectral.cumulative_periodogram_test",
              "greyid.validation.spectral.cross_correlation", "greyid.validation.spectral.input_correlation_test",
              "greyid.validation.spectral.coherency", "greyid.validation.spectral.coherency_test",
              "greyid.validation.bispectral.bispectrum", "greyid.validation.bispectral.gaussianity_test",
              "greyid.validation.bispectral.linearity_test", "greyid.validation.structure.lr_test",
              "greyid.validation.structure.wald_test", "greyid.validation.structure.lm_test",
              "greyid.validation.structure.cross_validation_test", "greyid.validation.structure.approximation_test",
              "greyid.validation.structure.simulated_datasets", "greyid.validation.structure.compare_fits",
              "greyid.validation.structure.fpe", "greyid.validation.selection.select_forward",
              "greyid.validation.bayes.posterior_odds", "greyid.validation.bayes.log_marginal_likelihood",
              "greyid.validation.simulation.simulation_check", "greyid.validation.simulation.parameter_bootstrap",
              "greyid.validation.validate.validate", "greyid.validation.plots.residual_dashboard",
              "greyid.validation.plots.coherency_figure"]


#: Classes greyid makes (a fit's result, a likelihood), never built by a user: their constructor's arguments
#: are greyid's own, and their docstrings list what they hold (Attributes) instead.
MADE_BY_GREYID = {"FitResult", "Likelihood", "PopulationResult", "FleetResult"}


def _documented_callables():
    import importlib
    import inspect

    for path in DOCUMENTED:
        module, name = path.rsplit(".", 1)
        obj = getattr(importlib.import_module(module), name)
        if inspect.isclass(obj):
            if obj.__name__ in MADE_BY_GREYID:
                assert "Attributes\n----------" in (inspect.getdoc(obj) or ""), f"{path}: no Attributes section"
            else:
                yield path, obj, obj.__init__
            seen = set()
            for cls in inspect.getmro(obj):  # greyid's own base classes too (ModelSpec, Estimates)
                if not cls.__module__.startswith("greyid"):
                    continue
                for member, value in vars(cls).items():
                    if member in seen or member.startswith("_"):
                        continue
                    seen.add(member)
                    if inspect.isfunction(inspect.unwrap(getattr(value, "__func__", value))):
                        yield f"{path}.{member}", getattr(obj, member), getattr(obj, member)
        else:
            yield path, obj, obj


def test_every_argument_of_the_public_api_is_documented():
    """Each public function and method: a Parameters section naming every argument (a class's in its own
    docstring, where the reference merges ``__init__``), and a Returns section where it returns something."""
    import inspect

    missing = []
    for path, documented, function in _documented_callables():
        if path.endswith(".to_dict") and "FitResult" not in path:
            continue
        doc = inspect.getdoc(documented) or ""
        signature = inspect.signature(function)
        names = [p.name for p in signature.parameters.values() if p.name not in ("self", "cls")]
        if function.__name__ == "__init__" and not names:
            continue
        for name in names:
            kind = signature.parameters[name].kind
            written = {inspect.Parameter.VAR_POSITIONAL: f"*{name}", inspect.Parameter.VAR_KEYWORD: f"**{name}"}
            label = written.get(kind, name)
            if not re.search(rf"^(\S+, )*{re.escape(label)}(, \S+)*( :|$)", doc, re.M):
                missing.append(f"{path}: {label}")
        returns = signature.return_annotation
        if (names or "Returns" in doc) and "Parameters\n----------" not in doc and names:
            missing.append(f"{path}: no Parameters section")
        if returns not in (None, "None", inspect.Signature.empty) and function.__name__ != "__init__" \
                and "Returns\n-------" not in doc and not isinstance(inspect.getattr_static(
                    documented if inspect.isclass(documented) else type(None), function.__name__, None), property):
            missing.append(f"{path}: no Returns section")
    assert not missing, "\n".join(missing)


def test_the_docstrings_examples_run():
    import doctest
    import importlib

    for module in ("greyid.api", "greyid.model.model", "greyid.estimate.likelihood", "greyid.fleet.fit",
                   "greyid.fleet.study", "greyid.data.named", "greyid.design.information",
                   "greyid.design.identifiability", "greyid.simulate.signals", "greyid.runtime.jit"):
        result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
        assert result.failed == 0, module
