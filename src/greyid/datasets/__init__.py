"""Bundled example: a two-state building model and data simulated from it."""

from .building import TRUE_PARAMETERS, building_model, load_building_data

__all__ = ["building_model", "load_building_data", "TRUE_PARAMETERS"]
