"""What a user declares: the model (states, drift, noise, observation), its expressions, the built-in library,
the priors, and the numba kernels generated from its symbolic form.

The modules are the interface: import from them (``from ardflow.ardcore.model.codegen import ...``).
"""

__all__ = [
    "codegen", "declaration", "expr", "kinks", "library", "printing", "priors",
]
