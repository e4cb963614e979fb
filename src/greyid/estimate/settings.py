"""How a fit was made: its data, filter and estimation settings, kept with it and saved in its file."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from typing import Any


#: Settings that fit files of older greyid versions hold and a fit no longer keeps: a population
#: member's fit carried its population's random effects (``omega``; the population fit keeps them).
RETIRED = ("omega",)


@dataclass(frozen=True)
class FitSettings(Mapping):
    """The settings of a fit, typed; read as a mapping too (``fit.settings["method"]``).

    Parameters
    ----------
    time : str
        The data's time column.
    hold : str
        How inputs are held between samples: ``"zoh"`` or ``"foh"``.
    method : str
        The filter (``"kalman"``, ``"ekf"``, ...).
    form : str
        The covariance update's form (``"sqrt"`` or ``"plain"``).
    substeps : int
        The filter's sub-steps per sampling interval.
    iterations : int
        The iterated filter's iterations.
    steady_state : bool
        Whether the fit's programs switched to the filter's steady state.
    time_unit : str, optional
        The unit of the time column where it is a date.
    criterion : str
        ``"ml"`` or ``"map"``.
    robust : tuple, optional
        A robust norm and its constant, e.g. ``("huber", 2.0)``.
    horizon : int
        The prediction horizon of the criterion (1: the one-step likelihood).
    starts : int
        The number of starts.
    optimizer : str
        The optimiser asked for.
    prior : dict, optional
        The Gaussian prior of a MAP fit.
    cov_type : str
        How the estimates' covariance was computed: ``"hessian"``, ``"opg"`` or ``"sandwich"``.
    substep_note : str, optional
        What the choice of sub-steps says about the filter's accuracy between samples.
    substeps_accurate : bool, optional
        Whether the filter is accurate between samples with these sub-steps (None: not checked).
    start_labels : tuple of str
        Where each start came from.
    seed : int
        The seed of the starts and of the particle filter's random numbers.
    particles : int, optional
        The particle filter's particles (None for the Gaussian filters).
    resample : float, optional
        The particle filter's resampling threshold (a fraction of the particles).
    inflation : float, optional
        The ensemble Kalman filter's inflation (None for the other filters).
    proposal : str, optional
        The particle filter's proposal, ``"bootstrap"``, ``"ekf"`` or ``"ukf"`` (None for the other filters).
    scheme : str, optional
        The Laplace method's transitions, ``"auto"``, ``"euler"`` or ``"ctsmtmb"`` (None for the other methods).
    hessian : str
        How the Hessian at the optimum (and so the covariance ``"hessian"``) was computed: ``"exact"``
        (derivatives of the exact gradient), or ``"differences"`` (central differences of the exact gradient:
        ``optimizer="lbfgs"``, and ``"auto"`` for the Laplace method).

    Examples
    --------
    >>> s = FitSettings(time="t", hold="zoh", method="kalman", form="sqrt", substeps=1, iterations=5)
    >>> s["method"], s.get("robust"), s.filter_kwargs()["hold"]
    ('kalman', None, 'zoh')
    """

    time: str
    hold: str
    method: str
    form: str
    substeps: int
    iterations: int
    steady_state: bool = False
    time_unit: str | None = None
    criterion: str = "ml"
    robust: tuple | None = None
    horizon: int = 1
    starts: int = 1
    optimizer: str = "auto"
    prior: Any = None
    cov_type: str = "hessian"
    substep_note: str | None = None
    substeps_accurate: bool | None = None
    start_labels: tuple = field(default_factory=tuple)
    seed: int = 0
    particles: int | None = None
    resample: float | None = None
    inflation: float | None = None
    proposal: str | None = None
    scheme: str | None = None
    hessian: str = "exact"

    # A mapping of the fields, so that code and users that read a fit's settings by key go on working.
    def __getitem__(self, key: str):
        if key not in self._names():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return _FIELD_NAMES

    def updated(self, **changes) -> FitSettings:
        """A copy with ``changes``."""
        return replace(self, **changes)

    def filter_kwargs(self) -> dict:
        """The keyword arguments that rerun the fit's filter (time column, hold, method ...)."""
        return filter_settings(self)

    @classmethod
    def from_dict(cls, settings: Mapping, where: str = "the fit") -> FitSettings:
        """The settings of a saved fit (settings added since it was written take their defaults; a
        robust norm and the start labels back to tuples).

        Raises
        ------
        ModelError
            A setting greyid does not know, or one without a default that is missing; the message
            names ``where`` the settings came from.
        """
        from ..errors import ModelError

        unknown = sorted(set(settings) - set(cls._names()) - set(RETIRED))
        missing = [f.name for f in fields(cls) if f.name not in settings and f.default is MISSING
                   and f.default_factory is MISSING]
        if unknown or missing:
            problem = f"an unknown setting '{unknown[0]}'" if unknown else f"no setting '{missing[0]}'"
            raise ModelError(f"{where} has {problem} (settings are {list(cls._names())})")
        known = {k: v for k, v in settings.items() if k not in RETIRED}
        if known.get("robust"):
            known["robust"] = tuple(known["robust"])
        if "start_labels" in known:
            known["start_labels"] = tuple(known["start_labels"] or ())
        if "hessian" not in known and known.get("optimizer") == "lbfgs":  # written before the setting was kept
            known["hessian"] = "differences"
        return cls(**known)


def filter_settings(settings: Mapping) -> dict:
    """The keyword arguments that rerun a fit's filter (time column, hold, method ...), from a fit's or a
    population fit's settings."""
    out = {k: settings[k] for k in ("time", "hold", "method", "form", "substeps", "iterations")}
    if settings.get("steady_state"):
        out["steady_state"] = True
    if settings.get("time_unit"):
        out["time_unit"] = settings["time_unit"]
    if settings.get("particles") is not None:  # the particle and ensemble filters' own random numbers
        out.update(particles=settings["particles"], seed=settings.get("seed", 0))
        out.update({k: settings[k] for k in ("resample", "inflation", "proposal") if settings.get(k) is not None})
    if settings.get("scheme") is not None:
        out["scheme"] = settings["scheme"]
    return out


_FIELD_NAMES = tuple(f.name for f in fields(FitSettings))
