"""Model selection: the ARD evidence maximiser (a state machine) and its settings, one candidate's run and the
comparison of candidates, a study as data, a model's result, and the validation of a study's models.

The modules are the interface: import from them (``from ardflow.ardcore.selection.config import ...``).
"""

__all__ = [
    "config", "fit", "maximiser", "spec", "study", "summary", "validation",
]
