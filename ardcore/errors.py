"""Exceptions with messages meant for users (the CLI and API print them as they are)."""


class ArdflowError(Exception):
    """Base class: a problem with the user's input that has a clear message."""


class ModelError(ArdflowError, ValueError):
    """A model declaration is invalid."""


class DataError(ArdflowError, ValueError):
    """A data set cannot be used."""


class SpecError(ArdflowError, ValueError):
    """A study or simulation specification is invalid."""


class FitError(ArdflowError):
    """A model could not be fitted to its data (no finite likelihood anywhere the search reached)."""
