"""The evidence: Chib-Jeliazkov and Laplace estimators, reweighting between ARD trials, and the evidence at one
psi.

The modules are the interface: import from them (``from ardflow.ardcore.evidence.estimators import ...``).
"""

__all__ = [
    "estimators", "evaluate", "reweight",
]
