"""Propagation methods, registered by name (:mod:`rwwarp.wave.methods.registry`): ``asm`` (band-limited
angular spectrum), ``focal`` (reference wave handled analytically), ``pixel`` (pixels many Airy radii wide),
``direct`` (brute-force Rayleigh-Sommerfeld summation, a reference for small cases)."""
from .registry import (METHOD_MODULES, PLANNER_CHOICES, PlanContext, Planned, Propagation, check_method,  # noqa: F401
                       choices, gauss_nodes_xy, get, names, register, unregister)
