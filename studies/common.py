"""Printing of Monte Carlo study tables in the thesis' layout."""

from __future__ import annotations

import time


def print_table(title: str, study, started: float, bound=None) -> None:
    """The study's table; ``bound`` (a mapping name → variance) adds the Cramér–Rao bound column."""
    table = study.table()
    crit = study.critical_values(0.1)
    n = len(study.estimates)
    print(f"\n{title}")
    print(f"n_e = {n} series, {int(study.converged.sum())} converged, "
          f"mean lag-1 residual autocorrelation {study.residual_acf1.mean():.3f}, "
          f"{time.perf_counter() - started:.1f} s")
    crb = f" {'CRB':>11s}" if bound is not None else ""
    print(f"{'parameter':10s} {'x_sim':>11s} {'mean':>11s} {'s_x^2':>11s} {'s_bar^2':>11s} {'F-stat':>8s} "
          f"{'|t|-stat':>8s}{crb}")
    for name, row in table.iterrows():
        extra = f" {bound[name]:11.4g}" if bound is not None and name in bound else ""
        print(f"{name:10s} {row.x_sim:11.5g} {row['mean']:11.5g} {row.s2_empirical:11.4g} "
              f"{row.s2_estimated:11.4g} {row.F:8.4f} {row.t:8.3f}{extra}")
    print(f"acceptance at level 0.1: F in [{crit['F'][0]:.2f}, {crit['F'][1]:.2f}], |t| < {crit['t']:.2f}")
    if bound is not None:
        print("CRB: Cramér–Rao bound of the design (exact information, greyid.design), the least variance "
              "of an unbiased estimate")
