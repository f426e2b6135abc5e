"""The one place results become JSON: infinity's spelling, NaN, numpy scalars, and atomic file writes.

A pruned ARD term has alpha = inf; JSON has no infinity, so it is written as the string ``"inf"`` and read
back by :func:`decode_alpha` / :func:`is_pruned`. No other module spells it.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np

_INF, _NEG_INF = "inf", "-inf"


def to_jsonable(x):
    """Plain JSON values: infinities as ``"inf"``/``"-inf"`` (pruned alphas), NaN as null, numpy as Python."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isinf(x):
            return _INF if x > 0 else _NEG_INF
        return None if math.isnan(x) else x
    if isinstance(x, np.integer):
        return int(x)
    return x


def encode_alpha(a: float):
    """An ARD precision as JSON: a number, or ``"inf"`` for a pruned term."""
    return _INF if a == math.inf else a


def decode_alpha(a) -> float:
    """An ARD precision from JSON (or already a float)."""
    return math.inf if a == _INF else float(a)


def is_pruned(a) -> bool:
    """True for alpha = inf, in either spelling."""
    return a == _INF or a == math.inf


def number(v) -> float:
    """A number from JSON that may hold ``"inf"``, ``"-inf"`` or ``"nan"`` strings (NaN if not a number)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader sees the old or the new file, never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
