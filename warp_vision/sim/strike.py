"""The old name of :mod:`warp_vision.sim.intercept_trials`, kept only for ``sim/cli.py``, which still imports
the ``intercept`` command's work from here: remove this module once it imports from intercept_trials."""

from warp_vision.sim.intercept_trials import intercept, pick_shots

__all__ = ["intercept", "pick_shots"]
