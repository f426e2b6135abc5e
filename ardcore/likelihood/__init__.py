"""The likelihood of a model: the extended Kalman filter and RTS smoother over generated kernels, simulation (and
the reference measurement pipeline), and the posterior target the sampler draws from.

The modules are the interface: import from them (``from ardflow.ardcore.likelihood.ekf import ...``).
"""

__all__ = [
    "ekf", "posterior", "simulate",
]
