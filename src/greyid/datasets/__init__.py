"""Bundled example: a two-state building model and data simulated from it; real data sets by name
([`fetch()`][greyid.data.named.fetch])."""

from .building import TRUE_PARAMETERS, building_model, load_building_data
from ..data.named import SOURCES, fetch

__all__ = ["building_model", "load_building_data", "TRUE_PARAMETERS", "fetch", "SOURCES"]
