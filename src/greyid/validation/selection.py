"""Forward model selection by likelihood-ratio tests (Bacher & Madsen, 2011).

Start from the simplest model; at each step fit the candidate extensions, keep
the one with the highest likelihood, and accept it only if the likelihood-ratio
test (5.3) against the current model rejects at ``level``.  Stop at the first
step that does not improve significantly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import pandas as pd

from ..errors import ModelError
from ..runtime.jit import release_compiled
from .structure import lr_test


@dataclass
class ForwardSelection:
    """The steps taken (a table), every fit by model name, and the chosen fit."""

    table: pd.DataFrame
    fits: dict = field(repr=False)
    chosen: object = field(repr=False)

    def __repr__(self) -> str:
        return f"<ForwardSelection: chose '{self.chosen.model.name}' after {len(self.table)} fits>"


def _why_below(fit) -> str:
    """Why an extension may have ended below the model it extends, from its starts."""
    nested = [s for s in fit.starts if s["start"] == "nested fit"]
    if not nested:
        return ""
    start = nested[0]
    return (f" (from the nested fit's start it reached {start['criterion']:.6g}: {start['message']}; "
            "the model's nested-start rule may not reproduce the smaller model closely enough)")


def select_forward(candidates, data, level: float = 0.05, **fit_options) -> ForwardSelection:
    """Forward model selection: fit candidates in order and stop when the LR test no longer prefers the extension.

    Each extension is fitted from the chosen model's fit (``init_from``, where the
    extension reduces to it) as well as from the usual starts; an extension that
    still ends below the model it extends is reported with the reason.  The compiled
    programs of a model that is no longer the one chosen so far are released as the
    selection goes on ([`release_compiled()`][greyid.runtime.jit.release_compiled]), so
    that a selection over many candidates holds the programs of one step, not of all;
    a released model's fit keeps its results, and a later call that needs its programs
    loads them again from the cache folder.

    Parameters
    ----------
    candidates : list
        Items that are models, lists of alternative models (the extensions tried at
        that step), or functions that take the model chosen so far and return that
        list; each step's models must nest the model chosen before.
    data : pandas.DataFrame
        The data.
    level : float
        The LR test's significance level.
    **fit_options
        Settings of every ``fit`` call.

    Returns
    -------
    ForwardSelection
        ``table`` (every model tried: log L, parameters, the LR test against the
        model it extends, whether it was chosen), ``fits`` by model name and
        ``chosen``, the chosen model's fit.
    """
    steps = [c if isinstance(c, (list, tuple)) or callable(c) else [c] for c in candidates]
    if len(steps) < 2 or callable(steps[0]) or not steps[0]:
        raise ModelError("give a starting model and at least one step of extensions")
    fits, rows = {}, []

    def fit_all(models, smaller=None):
        out = []
        for m in models:
            if m.name in fits:
                raise ModelError(f"two candidate models are named '{m.name}'; give each its own name")
            # An extension starts from the chosen model's fit too, so it cannot end below it
            # merely by starting far from where it nests the smaller model.
            fits[m.name] = m.fit(data, init_from=smaller, **fit_options)
            out.append(fits[m.name])
        return max(out, key=lambda f: f.loglik), out

    current, first = fit_all(steps[0])
    _release_all_but(current, first)
    nan = float("nan")
    for f in first:
        rows.append(dict(step=0, model=f.model.name, loglik=f.loglik, n_params=f.n_params, compared_with=None,
                         statistic=nan, df=nan, p_value=nan, chosen=f is current, note=""))
    for number, models in enumerate(steps[1:], start=1):
        if callable(models):
            models = list(models(current.model))
            if not models:
                break
        best, tried = fit_all(models, current)
        accepted = False
        for f in tried:
            try:  # an extension stuck below the current likelihood is reported, not fatal
                t, note = lr_test(current, f), ""
            except ModelError as err:
                t, note = None, str(err) + _why_below(f)
            chosen = bool(f is best and t is not None and t.p_value < level)
            accepted = accepted or chosen
            rows.append(dict(step=number, model=f.model.name, loglik=f.loglik, n_params=f.n_params,
                             compared_with=current.model.name, statistic=nan if t is None else t.statistic,
                             df=nan if t is None else t.df, p_value=nan if t is None else t.p_value,
                             chosen=chosen, note=note))
        if not accepted:
            _release_all_but(current, tried)
            break
        _release_all_but(best, [*tried, current])
        current = best
    return ForwardSelection(pd.DataFrame(rows), fits, current)


def _release_all_but(kept, fits) -> None:
    """Release the compiled programs of the models of ``fits`` but ``kept``'s (the model chosen so far)."""
    for fit in fits:
        if fit is not kept and fit.model.structure is not kept.model.structure:
            release_compiled(fit.model)
