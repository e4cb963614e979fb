"""Parameter declarations: initial values, bounds and fixed values."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import ModelError


@dataclass(frozen=True)
class Parameter:
    """One model parameter as the user declared it.

    ``init`` is the starting value for estimation, or the value itself when
    ``fixed`` is true.  Bounds are optional (``None`` means unbounded).
    """

    name: str
    init: float | None = None
    lower: float | None = None
    upper: float | None = None
    fixed: bool = False

    def __post_init__(self) -> None:
        for label, value in (("init", self.init), ("lower", self.lower), ("upper", self.upper)):
            if value is not None and (not isinstance(value, (int, float)) or math.isnan(value)):
                raise ModelError(f"parameter '{self.name}': {label} must be a number, got {value!r}")
        if self.lower is not None and self.upper is not None and self.lower >= self.upper:
            raise ModelError(
                f"parameter '{self.name}': lower bound {self.lower} must be below upper bound {self.upper}"
            )
        if self.init is not None and not math.isfinite(self.init):
            raise ModelError(f"parameter '{self.name}': init must be finite, got {self.init}")
        if self.init is not None and not self.fixed:
            if (self.lower is not None and self.init < self.lower) or (
                self.upper is not None and self.init > self.upper
            ):
                raise ModelError(
                    f"parameter '{self.name}': initial value {self.init} is outside its bounds "
                    f"[{self.lower}, {self.upper}]"
                )
        if self.fixed and self.init is None:
            raise ModelError(f"parameter '{self.name}' is fixed but has no value")
