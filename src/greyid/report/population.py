"""The HTML report of a population fit: one file, figures embedded, no scripts.

Sections: the model and its population structure, the data sets, the
estimation (Laplace marginal likelihood, information criteria), the population
parameters with standard errors and 95 % intervals, Ω (standard deviations,
correlations, shrinkage), the covariate effects with each random effect η
against every covariate, the normal Q-Q plot of the η, the members' random
effects, and every member's residual tests (chapter 5) in one table.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from scipy import stats

from ..validation.validate import validate
from .figures import embedded_png
from .html import _correlation_table, _esc, _facts, _model_section, _number, _section, _table, page

_TESTS_CSS = "table.tests { font-size: 0.8em; } table.tests th { max-width: 7em; white-space: normal; }\n"

#: Section ids, in order.
POPULATION_SECTIONS = ("model", "data", "estimation", "parameters", "omega", "covariates", "random-effects",
                       "members")


def _population_structure(result) -> str:
    spec = result.spec
    rows = []
    for i, kind in zip(spec.random, spec.kinds):
        name = spec.names[i]
        effects = [spec.covariates[c] for j, c in spec.effects if j == i]
        shift = "".join(f" + β_{c}·({c} − mean {c})" for c in effects)
        if kind == "lognormal":
            rows.append(f"{name}_i = {name} · exp({shift[3:] + ' + ' if shift else ''}η_{name},i)")
        else:
            rows.append(f"{name}_i = {name}{shift} + η_{name},i")
    for i, c in spec.effects:  # covariate effects on parameters without a random effect
        if i not in spec.random:
            name = spec.names[i]
            log = spec.log_scale[spec.free.index(i)]
            rows.append(f"{name}_i = {name} · exp(β_{spec.covariates[c]}·({spec.covariates[c]} − mean))" if log
                        else f"{name}_i = {name} + β·({spec.covariates[c]} − mean)")
    shared = [spec.names[i] for i in spec.free if i not in spec.random and i not in [j for j, _ in spec.effects]]
    omega = "with correlations (Ω full)" if spec.full else "independent (Ω diagonal)"
    text = ("<h3>Population structure</h3><pre>" + _esc("\n".join(rows)) + "</pre>"
            f"<p>η_i ~ N(0, Ω), {omega}; shared by all members: {_esc(', '.join(shared) or 'none')}.</p>")
    return text


def _data_section(result) -> str:
    rows = pd.DataFrame({"observations": result._members.n_obs}, index=pd.Index(result.names, name="data set"))
    sources = [result.sources.get(n, "") for n in result.names]
    if any(sources):
        rows["file"] = sources
    parts = [_facts([("data sets", result.n_members), ("observations", result.n_obs),
                     ("left out", len(result.left_out))])]
    for name, why in result.left_out.items():
        parts.append(f'<div class="warning">data set {_esc(name)} left out: {_esc(why)}</div>')
    parts.append(_table(rows, index_name="data set"))
    return _section("data", "Data sets", "\n".join(parts))


def _estimation_section(result) -> str:
    call = result.call
    facts = [("likelihood", "Laplace approximation of the marginal likelihood (FOCE, exact Hessian in η)"),
             ("log-likelihood", f"{result.loglik:.6f}"), ("AIC", f"{result.aic:.4f}"),
             ("BIC", f"{result.bic:.4f} (n = {result.n_obs} observations)"),
             ("population parameters", result.n_params),
             ("filter", f"{call['method']}, {call['substeps']} sub-step(s) per sampling interval, hold {call['hold']}"),
             ("search", f"{result.iterations} iterations: {result.message}")]
    body = _facts(facts)
    if not result.converged:
        body += '<div class="warning">The outer search did not converge; the estimates are where it stopped.</div>'
    for direction in result.undetermined:
        body += f'<div class="warning">undetermined direction of the population parameters: {_esc(direction)}</div>'
    return _section("estimation", "Estimation", body)


def _parameters_section(result) -> str:
    table = result.params.copy()
    table = table[["kind", "estimate", "std_error", "ci_lower", "ci_upper"]]
    body = _table(table, 5, index_name="parameter")
    if result.spec.covariates:
        means = ", ".join(f"{c} = {m:.6g}" for c, m in zip(result.spec.covariates, result.spec.covariate_mean))
        body = f"<p>Typical values at the covariates' mean ({_esc(means)}).</p>" + body
    body += ("<p>Standard errors from the exact Hessian of the Laplace marginal likelihood; the 95 % intervals "
             "are taken where each quantity is unbounded (log ω, Fisher's z of a correlation, the bound "
             "transform of a typical value) and mapped back, so they need not be symmetric.</p>")
    return _section("parameters", "Population parameters", body)


def _omega_section(result) -> str:
    omega = result.omega
    sd = np.sqrt(np.diag(omega.to_numpy()))
    corr = pd.DataFrame(omega.to_numpy() / np.outer(sd, sd), index=omega.index, columns=omega.columns)
    rows = []
    for r, i in enumerate(result.spec.random):
        name = result.spec.names[i]
        row = result.params.loc[f"omega_{name}"]
        scale = "log scale (≈ coefficient of variation)" if result.spec.kinds[r] == "lognormal" else "parameter's unit"
        rows.append(dict(omega=row["estimate"], ci_lower=row["ci_lower"], ci_upper=row["ci_upper"],
                         shrinkage=float(result.shrinkage[name]), scale=scale))
    table = pd.DataFrame(rows, index=[result.spec.names[i] for i in result.spec.random])
    body = [_table(table, 4, index_name="random effect"),
            "<p>Shrinkage 1 − sd(η̂)/ω: near 0 each member's data determine its own η; near 1 the members' "
            "estimates are pulled to the typical value and plots of η̂ against covariates understate trends.</p>"]
    if result.spec.full:
        body.append("<h3>Correlation of the random effects</h3>"
                    + _correlation_table(corr, "The members' parameters vary together."))
    return _section("omega", "Between-member variation (Ω)", "\n".join(body))


def _eta_and_se(result) -> tuple[pd.DataFrame, pd.DataFrame]:
    """η̂ per member and random effect, and its conditional standard error (on η's scale)."""
    eta, se = pd.DataFrame(index=result.random_effects.index), pd.DataFrame(index=result.random_effects.index)
    for r, i in enumerate(result.spec.random):
        name = result.spec.names[i]
        eta[name] = result.random_effects[f"eta_{name}"]
        value, value_se = result.random_effects[name], result.random_effects[f"{name}_se"]
        se[name] = value_se / np.abs(value) if result.spec.kinds[r] == "lognormal" else value_se
    return eta, se


def _covariate_table(result) -> pd.DataFrame | None:
    """The members' covariates: the table given to the fit where kept, else the columns the effects use."""
    table = getattr(result, "covariates", None)
    if table is not None:
        table = table.loc[[n for n in result.names if n in table.index]]
        numeric = table.apply(pd.to_numeric, errors="coerce")
        return numeric.loc[:, numeric.notna().any()]
    if result.spec.covariates:
        return pd.DataFrame(result._members.raw, index=result.names, columns=list(result.spec.covariates))
    return None


def _label(ax, xlabel: str, ylabel: str | None, legend: str) -> None:
    """Axis labels, tick labels and legend of the report's small panels, at one size."""
    ax.set_xlabel(xlabel, fontsize=9)
    if ylabel:
        ax.set_ylabel(ylabel, fontsize=9)
    ax.tick_params(labelsize=8)
    ax.legend(fontsize=7, loc=legend)


def eta_covariate_figure(result) -> Figure | None:
    """Each random effect's η̂ (± its conditional SE) against each covariate; a line where the model
    has that covariate's effect on the parameter is drawn at η = 0 (the effect is in the typical value)."""
    table = _covariate_table(result)
    if table is None or table.empty:
        return None
    eta, se = _eta_and_se(result)
    names, columns = list(eta.columns), list(table.columns)
    fig = Figure(figsize=(min(3.2 * len(columns) + 0.8, 11), 2.6 * len(names) + 0.4), layout="constrained")
    axes = fig.subplots(len(names), len(columns), squeeze=False)
    effects = {(result.spec.names[i], result.spec.covariates[c]) for i, c in result.spec.effects}
    for r, name in enumerate(names):
        for c, column in enumerate(columns):
            ax = axes[r, c]
            x = table[column].reindex(eta.index).to_numpy(dtype=float)
            ax.errorbar(x, eta[name], yerr=se[name], fmt="o", ms=3, lw=0.6, color="k", ecolor="0.6")
            ax.axhline(0.0, color="C0" if (name, column) in effects else "0.7", lw=1.0,
                       label="effect in the model" if (name, column) in effects else None)
            finite = np.isfinite(x) & np.isfinite(eta[name].to_numpy())
            if (name, column) not in effects and finite.sum() > 2 and np.ptp(x[finite]) > 0:
                slope, intercept, rvalue, pvalue, _ = stats.linregress(x[finite], eta[name].to_numpy()[finite])
                grid = np.linspace(x[finite].min(), x[finite].max(), 2)
                ax.plot(grid, intercept + slope * grid, color="C1", lw=1.0, ls="--",
                        label=f"trend left in η̂ (p = {pvalue:.2g})")
            _label(ax, column, f"η̂ of {name}" if c == 0 else None, "best")
    fig.suptitle("random effects against covariates", fontsize=10)
    return fig


def eta_qq_figure(result) -> Figure:
    """Normal Q-Q plot of each random effect's η̂/ω (the population assumes η ~ N(0, ω²))."""
    eta, _ = _eta_and_se(result)
    names = list(eta.columns)
    fig = Figure(figsize=(min(3.2 * len(names) + 0.6, 11), 3.0), layout="constrained")
    axes = fig.subplots(1, len(names), squeeze=False)[0]
    for ax, name in zip(axes, names):
        omega = float(result.params.loc[f"omega_{name}", "estimate"])
        values = np.sort(eta[name].to_numpy(dtype=float) / omega)
        quantiles = stats.norm.ppf((np.arange(1, len(values) + 1) - 0.5) / len(values))
        ax.plot(quantiles, values, "o", ms=3, color="k")
        span = np.array([quantiles.min(), quantiles.max()]) if len(values) else np.array([-2.0, 2.0])
        ax.plot(span, span, color="C0", lw=1.0, label="η ~ N(0, ω²)")
        _label(ax, "normal quantile", f"η̂ / ω of {name}", "upper left")
    fig.suptitle("random effects: normal Q-Q plot (shrinkage pulls the points towards 0)", fontsize=10)
    return fig


def _covariates_section(result) -> str:
    spec = result.spec
    parts = []
    if spec.effects:
        names = [n for n in result.params.index if n.startswith("beta_")]
        table = result.params.loc[names, ["estimate", "std_error", "ci_lower", "ci_upper"]].copy()
        table.insert(0, "covariate", [spec.covariates[c] for _, c in spec.effects])
        table.insert(0, "parameter", [spec.names[i] for i, _ in spec.effects])
        table["scale"] = ["log (relative change per unit)" if spec.log_scale[spec.free.index(i)] else
                          "parameter's unit per unit" for i, _ in spec.effects]
        parts.append(_table(table, 5, index_name="effect"))
    else:
        parts.append("<p>The model has no covariate effects.</p>")
    figure = eta_covariate_figure(result)
    if figure is not None:
        parts.append(embedded_png(figure))
        parts.append("<p>η̂ are the members' conditional modes given the population estimates (error bars: their "
                     "conditional standard errors).  A trend left in η̂ against a covariate the model does not use "
                     "suggests an effect to add (then compare the fits with "
                     "<code>greyid.population.likelihood_ratio</code>).</p>")
    parts.append(embedded_png(eta_qq_figure(result)))
    return _section("covariates", "Covariate effects and random effects", "\n".join(parts))


def _random_effects_section(result) -> str:
    table = result.random_effects.copy()
    return _section("random-effects", "Members' parameters (conditional modes)",
                    "<p>Each random parameter at its member's conditional mode of η, with the conditional "
                    "standard error given the population estimates.</p>" + _table(table, 5, index_name="data set"))


def member_tests(result, level: float = 0.05) -> pd.DataFrame:
    """Every member's residual tests (chapter 5) at its individual parameters: a row per member, a column
    per test (and output, where several), the p-values; ``rejects`` counts the tests rejected at ``level``."""
    rows, problems = {}, {}
    for name in result.names:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                tests = validate(result.member(name), level=level).tests
        except (KeyError, ValueError, ArithmeticError) as error:
            problems[name] = str(error)
            continue
        outputs = tests["output"].nunique() > 1
        labels = [f"{o}: {t}" if outputs else t for t, o in zip(tests["test"], tests["output"])]
        rows[name] = pd.Series(tests["p_value"].to_numpy(dtype=float), index=labels)
    table = pd.DataFrame(rows).T
    table.index.name = "data set"
    table["rejects"] = (table < level).sum(axis=1).astype(int)
    table.attrs["problems"] = problems
    return table


def _p_cell(p, level) -> str:
    if not np.isfinite(p):
        return "<td>–</td>"
    cls = "reject" if p < level else "accept"
    text = "< 1e-16" if p < 1e-16 else _number(p, 3)
    return f'<td class="{cls}">{text}</td>'


def _members_section(result, level: float) -> str:
    table = member_tests(result, level)
    tests = [c for c in table.columns if c != "rejects"]
    # Headers break at the underscores (a table of ten tests then fits the page).
    head = ('<th class="name">data set</th>'
            + "".join(f"<th>{_esc(c.replace('_', ' ').replace('[', ' ['))}</th>" for c in tests)
            + "<th>rejects</th>")
    rows = []
    for name, row in table.iterrows():
        cells = "".join(_p_cell(row[c], level) for c in tests)
        rows.append(f'<tr><td class="name">{_esc(name)}</td>{cells}<td>{int(row["rejects"])}</td></tr>')
    counts = "".join(f"<td>{int((table[c] < level).sum())}</td>" for c in tests)
    rows.append(f'<tr><td class="name">members rejecting</td>{counts}<td>{int(table["rejects"].sum())}</td></tr>')
    expected = level * len(tests)
    body = [f"<p>p-values of each member's residual tests at its individual parameters (shaded red below "
            f"{level}).  With {len(tests)} tests per member about {expected:.1f} rejection(s) per member are "
            f"expected by chance alone, and about {level * len(table):.1f} member(s) per test; look for members and "
            "tests that reject together.</p>",
            f'<div style="overflow-x:auto"><table class="tests"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table></div>']
    for name, problem in table.attrs.get("problems", {}).items():
        body.append(f'<div class="warning">no tests for {_esc(name)}: {_esc(problem)}</div>')
    return _section("members", "Members' residual tests (chapter 5)", "\n".join(body))


def population_report(result, level: float = 0.05, title: str | None = None, members: bool = True) -> str:
    """The report of a [`PopulationResult`][greyid.population.result.PopulationResult] as one HTML document (a string).

    ``members=False`` leaves out the members' residual tests (they need every member's data)."""
    title = title or f"greyid population report: {result.model.name}"
    model = _model_section(SimpleNamespace(model=result.model))
    model = model.replace("</section>", _population_structure(result) + "\n</section>")
    sections = [model, _data_section(result), _estimation_section(result), _parameters_section(result),
                _omega_section(result), _covariates_section(result), _random_effects_section(result)]
    if members:
        sections.append(_members_section(result, level))
    ids = POPULATION_SECTIONS if members else POPULATION_SECTIONS[:-1]
    return page(title, ids, sections, _TESTS_CSS)
