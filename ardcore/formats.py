"""Data files as :class:`~ardcore.data.Dataset`: CSV (header row of names; ``.csv.gz`` too), NPZ (one array
per name) and MATLAB ``.mat`` files (1-D variables of equal length). Every problem is a
:class:`~ardcore.errors.DataError` whose message names the file, the column and, where it helps, the row."""

from __future__ import annotations

import csv
import gzip
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from .data import Dataset
from .errors import DataError


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    if path.suffix.lower() == ".gz":
        try:
            text = gzip.decompress(path.read_bytes()).decode()
        except (OSError, EOFError, UnicodeDecodeError) as exc:  # truncated or not gzip
            raise DataError(f"{path}: cannot read gzip-compressed CSV ({exc})") from None
    else:
        text = path.read_text()
    if not text.strip():
        raise DataError(f"{path}: empty file")
    try:
        rows = list(csv.reader(io.StringIO(text)))
    except csv.Error as exc:  # e.g. a cell over the csv module's field size limit
        raise DataError(f"{path}: not a CSV table ({exc})") from None
    header = [h.strip().strip('"').strip() for h in rows[0]]
    body = [r for r in rows[1:] if any(c.strip() for c in r)]
    keep = [i for i, h in enumerate(header) if h]
    # a trailing comma yields an unnamed, empty column (Silverbox's header): drop it
    for i, h in enumerate(header):
        if not h and any(i < len(r) and r[i].strip() for r in body):
            raise DataError(f"{path}: column {i + 1} has values but no name in the header")
    names = [header[i] for i in keep]
    if len(set(names)) != len(names):
        raise DataError(f"{path}: duplicate column names in header {names}")
    if names and all(_is_number(h) for h in names):
        raise DataError(f"{path}: the first row must be a header of column names, got numbers")
    out = np.full((len(body), len(keep)), np.nan)
    width = max(keep) + 1 if keep else 0
    for r, row in enumerate(body):
        if len(row) < width:  # a missing value is an empty cell ("1,,3"), never a short row
            raise DataError(f"{path}: row {r + 2} has {len(row)} cells, the header names {len(names)} columns")
        for j, i in enumerate(keep):
            cell = row[i].strip() if i < len(row) else ""
            if cell == "" or cell.lower() in ("nan", "na"):
                continue
            try:
                out[r, j] = float(cell)
            except ValueError:
                raise DataError(f"{path}: row {r + 2}, column {names[j]!r}: {cell!r} is not a number") from None
    return {n: out[:, j] for j, n in enumerate(names)}


def _read_mat(path: Path) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    try:
        raw = loadmat(path)
    except Exception as exc:  # scipy raises several types for bad files
        raise DataError(f"{path}: cannot read MATLAB file ({exc})") from None
    cols = {}
    for k, v in raw.items():
        if k.startswith("__") or not isinstance(v, np.ndarray) or v.dtype.kind not in "fiu":
            continue
        if v.ndim == 2 and 1 in v.shape and v.size > 1:
            cols[k] = v.astype(float).ravel()
    return cols


def read_columns(path: str | Path) -> dict[str, np.ndarray]:
    """Read named numeric columns from CSV, NPZ or MAT (no validation yet)."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    suf = path.suffix.lower()
    if suf == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                cols = {k: np.asarray(z[k], dtype=float).ravel() for k in z.files}
        except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as exc:  # truncated or not a zip
            raise DataError(f"{path}: cannot read NPZ file ({exc or type(exc).__name__})") from None
    elif suf == ".mat":
        cols = _read_mat(path)
    else:
        cols = _read_csv(path)
    if not cols:
        raise DataError(f"{path}: no data columns")
    lengths = {k: v.size for k, v in cols.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(f"{path}: columns have different lengths {lengths}")
    return cols


def read_dataset(path: str | Path, *, time: str = "t", fs: float | None = None,
                 rename: dict[str, str] | None = None, columns: list[str] | None = None) -> Dataset:
    """Load and validate a data set.

    Parameters
    ----------
    path : str or Path
        ``.csv`` (header row), ``.npz`` or ``.mat``.
    time : str
        Name of the time column.
    fs : float, optional
        Sampling frequency; when given and there is no time column,
        ``t = arange(n) / fs``.
    rename : dict, optional
        ``old -> new`` column names (applied before ``columns``).
    columns : list of str, optional
        Keep only these columns; an unknown name is an error.

    Raises
    ------
    DataError
        Empty file, non-numeric cells, missing time column, time not strictly
        increasing, infinite values, too few points, unknown columns.
    """
    path = Path(path)
    cols = read_columns(path)
    for old, new in (rename or {}).items():
        if old not in cols:
            raise DataError(f"{path}: unknown column {old!r} (columns: {sorted(cols)})")
        cols[new] = cols.pop(old)
    if time in cols:
        t = cols.pop(time)
    elif fs is not None:
        if not (fs > 0 and np.isfinite(fs)):
            raise DataError(f"sampling frequency must be positive and finite, got {fs}")
        n = len(next(iter(cols.values())))
        t = np.arange(n) / fs
    else:
        raise DataError(f"{path}: no time column {time!r} (columns: {sorted(cols)}); "
                        "name it, or give the sampling frequency")
    if columns is not None:
        unknown = [c for c in columns if c not in cols]
        if unknown:
            raise DataError(f"{path}: unknown column {unknown[0]!r} (columns: {sorted(cols)})")
        cols = {c: cols[c] for c in columns}
    if not cols:
        raise DataError(f"{path}: no data columns besides time")
    meta = {"source": str(path)}
    side = path.with_suffix(".json")
    if side.exists():
        try:
            meta["sidecar"] = json.loads(side.read_text())
        except json.JSONDecodeError:
            pass
    return Dataset(t, cols, meta)
