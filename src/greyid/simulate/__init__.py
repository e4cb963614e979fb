"""Simulation of SDE models (section 2.5) and input signals for experiments."""

from .schemes import make_integrator, make_step
from .signals import multisine, prbs, steps
from .simulate import Simulation, simulate

__all__ = ["Simulation", "simulate", "make_integrator", "make_step", "prbs", "steps", "multisine"]
