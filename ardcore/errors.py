"""Exceptions with messages meant for users (the CLI and API print them as they are)."""


class ArdflowError(Exception):
    """Base class: a problem with the user's input that has a clear message."""


class ModelError(ArdflowError, ValueError):
    """A model declaration is invalid."""


class DataError(ArdflowError, ValueError):
    """A data set cannot be used."""


class SpecError(ArdflowError, ValueError):
    """A study or simulation specification is invalid."""


class Damaged(ArdflowError):
    """A stored file cannot be read whole (cut short, garbled or removed): the message says which and what is
    still readable."""


class FitError(ArdflowError):
    """A model could not be fitted to its data (no finite likelihood anywhere the search reached)."""


def did_you_mean(name: str, choices) -> str:
    """``" (did you mean 'x'?)"`` for the closest of ``choices`` to a mistyped ``name``, or ``""``."""
    import difflib

    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class LoopFailed(ArdflowError):
    """The closed loop failed after its first fit: ``partial`` holds what it had (the rounds so far, the last
    model it held and the reason), which the caller writes before it reports the error."""

    def __init__(self, message: str, partial: dict):
        super().__init__(message)
        self.partial = partial
