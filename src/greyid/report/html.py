"""A self-contained HTML report of a fit: one file, figures embedded, no scripts.

Sections: model (equations rendered from SymPy as MathML), data, estimation
(criterion, log-likelihood, information criteria, warnings), the check of the
filter's approximation against the particle filter (nonlinear or non-Gaussian
models), parameters with
standard errors and 95 % Wald and profile-likelihood intervals, correlation matrix, derived
quantities, the residual tests of
chapter 5 with their verdicts, the residual dashboard and coherency of each
output, measured versus simulated outputs, and k-step predictions.
"""

from __future__ import annotations

import datetime as _dt
import html
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import ModelError
from ..estimate.results import p_value_text
from ..data.files import named_dataset
from ..model.units import figure_units, pretty
from ..validation.validate import validate
from .equations import inline_formula, model_equations
from .figures import data_figure, embedded_png, latent_force_figure

#: A particle reference whose runs spread by more than this (log-likelihood units) is flagged as uncertain.
RELIABLE_SPREAD = 3.0
#: Section ids, in order; a complete report has every one of them.
SECTIONS = ("model", "data", "estimation", "approximation", "parameters", "correlation", "derived", "identifiability",
            "validation", "residuals", "simulation", "prediction")

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; max-width: 1100px;
       margin: 2em auto; padding: 0 1em; color: #1d1d1f; line-height: 1.45; }
h1 { font-size: 1.7em; margin-bottom: 0.1em; } h2 { border-bottom: 2px solid #ddd; padding-bottom: 0.2em;
     margin-top: 2em; } h3 { margin-bottom: 0.3em; }
.subtitle { color: #666; margin-top: 0; }
nav a { margin-right: 0.9em; color: #2a62b5; text-decoration: none; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: right; }
td { white-space: nowrap; }  /* a number or an interval is never broken across lines */
td.strong { font-weight: bold; outline: 2px solid #1d1d1f; outline-offset: -2px; }
th { background: #f3f4f6; } td.name, th.name { text-align: left; font-family: ui-monospace, monospace; }
.reject { background: #fde2e1; } .accept { background: #e3f5e6; }
.warning { background: #fff4d6; border-left: 4px solid #e0a800; padding: 0.4em 0.8em; margin: 0.4em 0; }
.ok { background: #e3f5e6; border-left: 4px solid #2e9b47; padding: 0.4em 0.8em; margin: 0.4em 0; }
pre { background: #f6f8fa; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
img.figure { max-width: 100%; display: block; margin: 0.6em 0; }
math { font-size: 1.1em; margin: 0.3em 0; }
dl.facts { display: grid; grid-template-columns: max-content auto; gap: 0.2em 1.2em; }
dl.facts dt { color: #555; } dl.facts dd { margin: 0; font-family: ui-monospace, monospace; }
"""


def _esc(value) -> str:
    return html.escape(str(value))


def _number(value, digits: int = 4) -> str:
    if value is None or (isinstance(value, (float, np.floating)) and not np.isfinite(value)):
        return "–"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(value)
    return f"{value:.{digits}g}"


def _table(frame: pd.DataFrame, digits: int = 4, row_class=None, index_name: str = "") -> str:
    head = f'<th class="name">{_esc(index_name)}</th>' + "".join(f"<th>{_esc(c)}</th>" for c in frame.columns)
    rows = []
    for name, row in frame.iterrows():
        cls = f' class="{row_class(row)}"' if row_class else ""
        cells = "".join(f"<td>{_esc(_number(v, digits)) if not isinstance(v, str) else _esc(v)}</td>"
                        for v in row.to_numpy())
        rows.append(f'<tr{cls}><td class="name">{_esc(name)}</td>{cells}</tr>')
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"


#: |correlation| of two estimates above which the report flags the pair.
STRONG_CORRELATION = 0.95


ESTIMATES_ADVICE = ("The data determine a combination of these parameters better than each alone; see the "
                    "identifiability section.")


def _correlation_table(corr: pd.DataFrame, advice: str = ESTIMATES_ADVICE) -> str:
    """The correlation matrix, shaded by sign and size; pairs above
    [`STRONG_CORRELATION`][greyid.report.html.STRONG_CORRELATION] outlined
    and listed below the table."""
    head = '<th class="name"></th>' + "".join(f'<th class="name">{_esc(c)}</th>' for c in corr.columns)
    rows, strong = [], []
    for i, (name, row) in enumerate(corr.iterrows()):
        cells = []
        for j, (col, v) in enumerate(row.items()):
            shade = 0 if name == col or not np.isfinite(v) else min(abs(v), 1.0)
            color = f"rgba(214, 69, 65, {0.85 * shade:.2f})" if v > 0 else f"rgba(42, 98, 181, {0.85 * shade:.2f})"
            flagged = name != col and np.isfinite(v) and abs(v) > STRONG_CORRELATION
            if flagged and j < i:
                strong.append(f"{col} and {name} ({_number(v, 3)})")
            cls = ' class="strong"' if flagged else ""
            cells.append(f'<td{cls} style="background:{color}">{_number(v, 2)}</td>')
        rows.append(f'<tr><td class="name">{_esc(name)}</td>{"".join(cells)}</tr>')
    table = f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"
    if strong:
        table += (f'<div class="warning">Correlation above {STRONG_CORRELATION} in absolute value (outlined): '
                  f"{_esc('; '.join(strong))}. {_esc(advice)}</div>")
    return table


def _facts(items) -> str:
    return '<dl class="facts">' + "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in items) + "</dl>"


def _section(sid: str, title: str, body: str) -> str:
    return f'<section id="{sid}"><h2>{_esc(title)}</h2>\n{body}\n</section>'


def _model_section(fit) -> str:
    model = fit.model
    parts = []
    if model.description:
        parts.append(f"<p>{_esc(model.description)}</p>")
    if model._functions is not None:
        parts.append("<p>This model is defined by Python functions; it has no equations to show.</p>")
    else:
        equations = model_equations(model)
        parts += [math for math, _ in equations]
        parts.append("<h3>As written</h3><pre>" + _esc("\n".join(text for _, text in equations)) + "</pre>")
    s = model.structure
    parts.append(_facts([("class", f"{s.kind} ({'exact Kalman filter' if s.is_linear else 'nonlinear'})"),
                         ("states", ", ".join(s.state_names)), ("inputs", ", ".join(s.input_names) or "none"),
                         ("outputs", ", ".join(s.output_names))]
                        + ([("transformed states", ", ".join(f"{t.state}: {t.kind} (worked in that coordinate, "
                                                              "reported in the state's own)" for t in
                                                              s.state_transforms))] if s.state_transforms else [])))
    return _section("model", f"Model '{model.name}'", "\n".join(parts))


def _instant(value) -> str:
    """A time as a reader wants it: 167.8 h, not 167.83333333333334 (timestamps as they are)."""
    return f"{value:.6g}" if isinstance(value, (int, float, np.integer, np.floating)) else str(value)


def _data_section(fit, frames) -> str:
    time_name = fit.settings["time"]
    s = fit.model.structure
    parts = []
    for i, frame in enumerate(frames):
        t = frame[time_name]
        observed = {name: int(frame[name].notna().sum()) for name in s.output_names}
        title = f"<h3>Data set {i + 1}</h3>" if len(frames) > 1 else ""
        units = figure_units(fit.model, time_name, fit.settings)
        unit = f" {pretty(units[time_name])}" if time_name in units else ""
        span = f"{time_name} from {_instant(t.iloc[0])} to {_instant(t.iloc[-1])}{unit}"
        parts.append(title + _facts([("rows", len(frame)), ("time", span),
                                     ("observed values", ", ".join(f"{k}: {v}" for k, v in observed.items())),
                                     ("hold", fit.settings["hold"])]))
        parts.append(embedded_png(data_figure(frame, time_name, s.output_names, s.input_names, units)))
    if fit.data_file and named_dataset(fit.data_file) is not None:
        name = named_dataset(fit.data_file)
        parts.insert(0, f"<p>The data set <code>{_esc(name)}</code> (<code>greyid.datasets.fetch</code>).</p>")
    elif fit.data_file:
        parts.insert(0, f"<p>Read from <code>{_esc(fit.data_file)}</code>.</p>")
    return _section("data", "Data", "\n".join(parts))


def _latent_force_section(fit) -> str:
    """Each data set's latent forces, smoothed at the estimates (empty where the model has none)."""
    s = fit.model.structure
    if not s.latent_forces:
        return ""
    names = [f.name for f in s.latent_forces]
    smoothed = fit.smooth()
    time_name = fit.settings["time"]
    units = figure_units(fit.model, time_name, fit.settings)
    parts = [f"<p>{', '.join(names)}: unmeasured inputs modelled as Gaussian processes, their paths smoothed "
             "given all the data.</p>"]
    for result in smoothed if isinstance(smoothed, list) else [smoothed]:
        parts.append(embedded_png(latent_force_figure(result.times.to_numpy(), result.latent_forces, names,
                                                      time_name, units)))
    return _section("forces", "Latent forces", "\n".join(parts))


def _estimation_section(fit) -> str:
    s = fit.settings
    criterion = s["criterion"].upper()
    if s.get("robust"):
        convention = ", CTSM-R convention" if len(s["robust"]) > 2 else ""
        criterion += f", robust {s['robust'][0]} (c = {s['robust'][1]:g}{convention})"
    if s.get("horizon", 1) > 1:
        criterion += f", {s['horizon']}-step"
    facts = [("criterion", criterion), ("filter", f"{s['method']} ({s['form']})"),
             ("log-likelihood", f"{fit.loglik:.6f}"), ("AIC", f"{fit.aic:.4f}"), ("BIC", f"{fit.bic:.4f}"),
             ("observations", fit.n_obs), ("free parameters", fit.n_params),
             ("optimiser", f"{fit.message} after {fit.iterations} iterations")]
    if s.get("robust") or s.get("horizon", 1) > 1 or s["criterion"] == "map":
        facts.insert(3, ("criterion value", f"{fit.criterion_value:.6f}"))
    body = [_facts(facts)]
    if fit.converged and not fit.warnings:
        body.append('<div class="ok">Converged; no warnings.</div>')
    if not fit.converged:
        body.append('<div class="warning">The optimiser did not converge.</div>')
    body += [f'<div class="warning">{_esc(w)}</div>' for w in fit.warnings]
    return _section("estimation", "Estimation", "\n".join(body))


def _approximation_section(fit) -> str:
    """The fit's log-likelihood at its estimates beside the particle filter's estimate of it (8 runs of 1000
    particles with the EKF proposal, whose estimate stays sharp where the observations are, see
    [`particle_loglik()`][greyid.estimate.approximations.particle_loglik]): is the approximation trustworthy?"""
    from ..estimate.approximations import particle_loglik

    structure, method = fit.model.structure, fit.settings["method"]
    if structure.is_linear and not structure.distributions:
        return _section("approximation", "Approximation", "<p>The model is linear with Gaussian observations: "
                        "the Kalman filter's likelihood is exact, there is no approximation to check.</p>")
    where = {k: v for k, v in fit._filter_settings().items() if k in ("time", "hold", "time_unit")}
    reference = particle_loglik(fit.model, fit.values, fit._data(None), seed=fit.settings["seed"], proposal="ekf",
                                **where)
    facts = [("particle filter", f"{reference.loglik:.4f} (standard error {reference.std_error:.3g}; 8 runs of "
                                 f"1000 particles, EKF proposal, the spread of one run {reference.spread:.3g})")]
    unreliable = [] if reference.spread <= RELIABLE_SPREAD else [
        f'<div class="warning">The particle runs spread by {reference.spread:.3g} (more than {RELIABLE_SPREAD}): '
        "their estimate is itself uncertain here; compare with more particles "
        "(greyid.estimate.approximations.particle_loglik).</div>"]
    if method == "particle":
        body = [_facts(facts), "<p>The fit's own likelihood is a particle estimate: the runs above show its "
                               "Monte Carlo error at the estimates.</p>", *unreliable]
        return _section("approximation", "Approximation", "\n".join(body))
    difference = fit.loglik - reference.loglik
    allowed = max(3 * reference.std_error, 0.1)
    facts = [(f"{method} (the fit's)", f"{fit.loglik:.4f}"), *facts, ("difference", f"{difference:+.4f}")]
    verdict = (f'<div class="ok">The {method} likelihood agrees with the particle filter\'s within its errors '
               f"(|difference| ≤ {allowed:.3g}).</div>" if abs(difference) <= allowed else
               f'<div class="warning">The {method} likelihood differs from the particle filter\'s by '
               f"{difference:+.3g}, more than its errors allow ({allowed:.3g}): the approximation is biased "
               "here; compare methods with fit.compare_methods() and consider method='laplace' or "
               "method='particle'.</div>")
    note = ("<p>The particle filter moves its particles by Euler–Maruyama sub-steps (8 per interval) where the "
            "dynamics are nonlinear: a difference also holds their discretization error.</p>")
    return _section("approximation", "Approximation", "\n".join([_facts(facts), verdict, *unreliable, note]))


def _profile_intervals(fit):
    """``(intervals or None, notes)``; run in a thread beside the rest of the report."""
    from ..uncertainty.profile import profile_intervals

    notes: list[str] = []
    try:
        return profile_intervals(fit, 0.95, notes=notes), notes
    except ModelError as error:  # e.g. a fit that cannot be re-optimised: said, not hidden
        return None, [f"profile intervals not available: {error}"]


def _interval(lower, upper) -> str:
    return "–" if not (np.isfinite(lower) or np.isfinite(upper)) else f"[{_number(lower, 5)}, {_number(upper, 5)}]"


def _p_value(p) -> str:
    return "–" if not np.isfinite(p) else p_value_text(p)


def _reaches_bound(intervals: pd.DataFrame, params: pd.DataFrame) -> set[str]:
    """The parameters whose profile interval ends at a bound of the parameter (the likelihood does not
    fall to the χ² threshold inside the bounds: the interval is cut there)."""
    out = set()
    for name, row in intervals.iterrows():
        if name not in params.index:
            continue
        lower, upper = params.loc[name, "lower_bound"], params.loc[name, "upper_bound"]
        for end, bound in ((row["lower"], lower), (row["upper"], upper)):
            if bound is not None and np.isfinite(float(bound)) and np.isfinite(end) and \
                    abs(end - float(bound)) <= 1e-9 * max(1.0, abs(float(bound))):
                out.add(name)
    return out


def _parameters_section(fit, profile=None) -> str:
    """The parameter table; ``profile`` is the result of
    [`_profile_intervals()`][greyid.report.html._profile_intervals] (or None).

    One column per interval ("[lower, upper]") so that the table fits a page.
    """
    params = fit.params
    table = params[["estimate", "std_error"]].copy()
    if "unit" in params:
        table["unit"] = [pretty(u) for u in params["unit"]]
    wald = fit.conf_int(0.95)
    table["95 % Wald interval"] = [_interval(lo, hi) for lo, hi in zip(wald["lower"], wald["upper"])]
    notes = []
    if profile is not None:
        likelihood_ratio, notes = profile
        if likelihood_ratio is not None:
            reaches = _reaches_bound(likelihood_ratio, params)
            table["95 % profile interval"] = [_interval(lo, hi) + (" reaches a bound" if name in reaches else "")
                                              for name, lo, hi in zip(likelihood_ratio.index, likelihood_ratio["lower"],
                                                                      likelihood_ratio["upper"])]
    tested = fit.tests_against_zero
    table["t"] = [t if tested.get(n, True) else np.nan for n, t in params["t_value"].items()]
    table["p"] = [_p_value(p) if tested.get(n, True) else "–" for n, p in params["p_value"].items()]
    table["bounds"] = [_interval(lo, hi) if not fixed else "–" for lo, hi, fixed in
                       zip(params["lower_bound"].astype(float), params["upper_bound"].astype(float), params["fixed"])]
    table["note"] = ["fixed" if r["fixed"] else ("at bound" if r["at_bound"] else
                                                 ("unreliable" if not r["reliable"] else ""))
                     for _, r in params.iterrows()]
    text = ("<p>Standard errors from the exact Hessian of the negative log-likelihood, mapped to the natural "
            "parameters; 95 % intervals by Wald (estimate ± t quantile × SE) and, where computed, by the "
            "profile likelihood (where 2(ℓ̂ − ℓ_p) reaches the χ²₁ quantile; it follows a skewed "
            "likelihood); t and p test the parameter against 0, and are left out (–) for log-parameters "
            "(exp(p) in the equations: p = 0 is a value of 1 in its unit) and parameters of the initial state "
            "only (0 °C is no null hypothesis); a log-parameter's unit is written log(unit).</p>")
    text += "".join(f"<p>{_esc(n)}</p>" for n in notes)
    return _section("parameters", "Parameters",
                    _table(table, 5, row_class=lambda r: "reject" if r["note"] in ("at bound", "unreliable") else "")
                    + text)


def _derived_section(fit) -> str:
    if not fit.model.derived:
        body = "<p>The model declares no derived quantities (<code>[derived]</code> in its model file).</p>"
    else:
        table = fit.derived().join(pd.Series(fit.model.derived, name="expression"))
        body = _table(table, 5) + "<p>Standard errors by the delta method (6.35).</p>"
    return _section("derived", "Derived quantities", body)


def _identifiability_section(fit) -> str:
    """Structural identifiability (section 6.1) of the model at the estimates, for LTI models."""
    from ..design import identifiability

    model = fit.model
    if model.structure.kind != "lti" or model.structure.delays:
        what = ("has delayed inputs (a delay's e^{-sτ} is not rational in s)" if model.structure.delays
                else f"is {model.structure.kind}")
        body = (f"<p>Structural identifiability is decided before any data for linear time-invariant models "
                f"without delays; this model {_esc(what)}: judge it on a planned experiment with "
                "<code>greyid.design.identifiability(model, plan=...)</code>.</p>")
        return _section("identifiability", "Structural identifiability", body)
    result = identifiability(model, fit.values)
    table = pd.DataFrame({"status": pd.Series(result.status)})
    meanings = "".join(f"<li><b>{_esc(status)}</b>: {_esc(IDENTIFIABILITY_MEANING[status])}</li>"
                       for status in IDENTIFIABILITY_MEANING if status in set(table["status"]))
    body = ["<p>Which parameters an experiment on this model can determine at all, judged from its equations "
            "before any data (thesis section 6.1): what any experiment reveals is the model's input–output "
            "behaviour, its transfer functions G(p) and H(p) and the innovations' covariance (6.15–6.18); a "
            "parameter is determined if only one value of it reproduces that behaviour.</p>",
            _table(table, row_class=lambda r: "reject" if r["status"] == "not identifiable" else "accept",
                   index_name="parameter"),
            f"<ul>{meanings}</ul>"]
    if result.combinations:
        formulas = ", ".join(inline_formula(c, model.parameter_names) for c in result.combinations)
        body.append(f"<p>Determined although their factors are not: {formulas}. Data fix these combinations; "
                    "fix all but one of each combination's parameters (or give priors) to estimate the rest.</p>")
    body += [f"<p>{_esc(note)}</p>" for note in result.notes]
    body.append("<p>Judged at generic points around the estimates; \"global\" where SymPy solves G's equations "
                "uniquely within the bounds.</p>")
    return _section("identifiability", "Structural identifiability", "\n".join(body))


#: What each identifiability status tells a reader (the report's table).
IDENTIFIABILITY_MEANING = {
    "global": "one value only reproduces the model's input–output behaviour",
    "local": "near the estimate one value only does; a few separate values elsewhere may do too (e.g. two "
             "resistances that could swap places), which no data tell apart",
    "not identifiable": "a continuum of values does: no experiment determines it alone",
}


def _validation_sections(fit, validation, steps: int, n_paths: int, seed: int) -> list[str]:
    tests = validation.tests.set_index("test")
    verdict = (f"{int(tests['reject'].sum())} of {len(tests)} tests reject at level {validation.level}.")
    body = [f"<p>{_esc(verdict)}</p>",
            _table(tests, 4, row_class=lambda r: "reject" if r["reject"] else "accept", index_name="test")]
    for test, output, reason in validation.skipped:
        body.append(f'<div class="warning">skipped {_esc(test)} for {_esc(output)}: {_esc(reason)}</div>')
    sections = [_section("validation", "Residual tests (chapter 5)", "\n".join(body))]

    residual_parts = []
    for label in validation.residuals:
        residual_parts.append(f"<h3>{_esc(label)}</h3>" + embedded_png(validation.plot(label)))
        if fit.model.input_names:
            try:
                residual_parts.append(embedded_png(validation.plot_coherency(label)))
            except (ModelError, ValueError, np.linalg.LinAlgError) as err:
                residual_parts.append(f'<div class="warning">no coherency plot: {_esc(err)}</div>')
    sections.append(_section("residuals", "Residual analysis", "\n".join(residual_parts)))
    sections.append(_section("simulation", "Measured and simulated outputs",
                             embedded_png(validation.plot_simulation(n_paths=n_paths, seed=seed))
                             + "<p>The deterministic simulation from the estimated initial state, driven by the "
                               "measured inputs alone, with a Monte Carlo band of the stochastic model.</p>"))
    predictions = [embedded_png(validation.plot_prediction(steps=k)) for k in sorted({1, steps})]
    sections.append(_section("prediction", "Predictions", "\n".join(predictions)))
    return sections


def html_report(fit, level: float = 0.05, steps: int = 4, n_paths: int = 100, seed: int = 0,
                title: str | None = None, profile: bool = True) -> str:
    """The report of ``fit`` as one HTML document (a string); see the module docstring."""
    if fit.attach_stored_data() is None:
        raise ModelError("this fit carries no data (it was loaded from a file); attach it with fit.with_data(data)")

    # The profile intervals are Newton steps on the fit's compiled Hessian program (refits where
    # those fail), code that leaves the interpreter free: they run in a thread while the figures are drawn.
    with ThreadPoolExecutor(max_workers=1) as pool:
        intervals = pool.submit(_profile_intervals, fit) if profile else None
        validation = validate(fit, level=level)
        title = title or f"greyid report: {fit.model.name}"
        later = [_section("correlation", "Correlation of the estimates", _correlation_table(fit.corr)),
                 _derived_section(fit), _identifiability_section(fit),
                 *_validation_sections(fit, validation, steps, n_paths, seed)]
        sections = [_model_section(fit), _data_section(fit, fit.data), _latent_force_section(fit),
                    _estimation_section(fit),
                    _approximation_section(fit),
                    _parameters_section(fit, None if intervals is None else intervals.result()), *later]
    ids = SECTIONS if not fit.model.structure.latent_forces else ("model", "data", "forces", *SECTIONS[2:])
    return page(title, ids, [part for part in sections if part])


def page(title: str, ids, sections: list[str], css: str = "") -> str:
    """One HTML document: the title, greyid's version and the time, links to the sections ``ids``."""
    from .. import __version__

    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    nav = "".join(f'<a href="#{sid}">{sid}</a>' for sid in ids)
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{_esc(title)}</title><style>{_CSS}{css}</style></head><body>"
            f"<h1>{_esc(title)}</h1><p class='subtitle'>greyid {__version__}, {stamp}</p>"
            f"<nav>{nav}</nav>\n" + "\n".join(sections) + "\n</body></html>\n")


def write_report(fit, path, **options) -> Path:
    """Write [`html_report()`][greyid.report.html.html_report] to ``path``; returns the path."""
    from ..outputs import write_atomic

    path = Path(path)
    write_atomic(path, html_report(fit, **options))
    return path
