"""Exceptions raised by greyid for bad models and bad data."""


class ModelError(ValueError):
    """A model specification that cannot be used (names the equation or parameter)."""


class DataError(ValueError):
    """Data that cannot be used with a model (names the column or the row)."""


class UndeterminedWarning(UserWarning):
    """An information matrix that does not determine some direction of the parameters (names it)."""


class FilterWarning(UserWarning):
    """A filter step whose approximation needed a guard (e.g. a negative variance replaced)."""
