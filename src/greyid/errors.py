"""Exceptions and warnings raised by greyid for bad models and bad data."""

import os
import sys
import warnings


class ModelError(ValueError):
    """A model specification that cannot be used (names the equation or parameter)."""


class DataError(ValueError):
    """Data that cannot be used with a model (names the column or the row)."""


class FitWarning(UserWarning):
    """A fit finished with something to look at: an active bound, an ill-determined
    direction, no convergence.  The message is also in ``fit.warnings``."""


class PopulationWarning(UserWarning):
    """A member left out of a population fit, or a fit that did not converge."""


class UndeterminedWarning(UserWarning):
    """An information matrix that does not determine some direction of the parameters (names it)."""


class UndefinedCriterionWarning(UserWarning):
    """A design criterion that is not defined at the parameters given (e.g. C where a parameter is 0)."""


class CacheWarning(UserWarning):
    """greyid's cache folder cannot be used: programs are compiled again in every process."""


class FilterWarning(UserWarning):
    """A filter step whose approximation needed a guard (e.g. a negative variance replaced)."""


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn(message: str, category: type[Warning]) -> None:
    """Issue a warning attributed to the user's line: the first caller outside greyid's own modules.

    Parameters
    ----------
    message : str
        The warning's text.
    category : type of Warning
        Its class (``FitWarning``, ``UndeterminedWarning``, ...).
    """
    frame = sys._getframe(1)
    while frame is not None and (os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE)
                                 or frame.f_code.co_filename.startswith("<frozen importlib")):
        frame = frame.f_back
    if frame is None:  # called from greyid alone (a thread it started): its own line
        warnings.warn(message, category, stacklevel=2)
        return
    names = frame.f_globals
    warnings.warn_explicit(message, category, frame.f_code.co_filename, frame.f_lineno,
                           module=names.get("__name__"), registry=names.setdefault("__warningregistry__", {}))
