"""What an effect is (a term added to a model, with shape parameters) and the library of effect families the loop
screens.

The modules are the interface: import from them (``from ardflow.ardcore.effects.base import ...``).
"""

__all__ = [
    "base", "families", "states",
]
