"""The closed loop (`ardflow diagnose`): residuals and their tests, the free run, confirmation by ARD
re-selection, the halves and backward checks, law replacement, the simulation fit, the verdict and what the
loop returns.

The modules are the interface: import from them (``from ardflow.ardcore.loop.checks import ...``).
"""

__all__ = [
    "checks", "config", "confirm", "diagnose", "freerun", "initial", "replace", "residuals",
    "result", "simulation_fit", "verdict",
]
