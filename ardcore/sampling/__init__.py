"""Parallel adaptive MCMC: chain state and one DRAM round, the unconstrained coordinates, INCA adaptation,
starting points, ArviZ's diagnostics and the stationary stage's stopping rule, settings, and the driver.

The modules are the interface: import from them (``from ardflow.ardcore.sampling.adaptation import ...``).
"""

__all__ = [
    "adaptation", "chains", "config", "diagnostics", "driver", "starts", "transform",
]
