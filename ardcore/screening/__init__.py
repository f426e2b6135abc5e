"""The evidence screen of candidate effects: the EKF score and information of new terms, the adjustment for
coloured innovations, and forward selection of distinct candidates.

The modules are the interface: import from them (``from ardflow.ardcore.screening.robust import ...``).
"""

__all__ = [
    "robust", "score", "screen",
]
