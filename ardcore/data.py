"""Data sets: named columns over a strictly increasing time axis.

CSV (header row of names; ``.csv.gz`` too), NPZ (one array per name) and MATLAB
``.mat`` files (1-D variables of equal length) load through :func:`read_dataset`. Every
problem is reported as a :class:`~ardcore.errors.DataError` whose message
names the file, the column and, where it helps, the row.
"""

from __future__ import annotations

import csv
import gzip
import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError

MIN_POINTS = 10
"""Fewest samples a data set may have."""

SILVERBOX_FS = 1e7 / 2**14
"""Silverbox sampling frequency, Hz."""


@dataclass
class Dataset:
    """Sampled measurements.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Strictly increasing sample times.
    columns : dict of str to ndarray
        Named data columns, each of shape (n,). NaN marks a missing
        observation (allowed in observed columns only).
    meta : dict
        Free-form provenance (source file, sidecar contents, ...). Several records carry
        ``meta["records"]``: one dict per record (``name``, ``source``, ``t0``: its own first time,
        ``initial_mean`` / ``initial_std``: its initial-state prior by state name).
    starts : tuple of int
        First row of each record (``(0,)`` for one record). Records are separate experiments: the
        filter starts each from its initial-state prior, and the time axis joins them with a gap of one
        sample interval (see :func:`join_records`).
    """

    t: np.ndarray
    columns: dict[str, np.ndarray]
    meta: dict = field(default_factory=dict)
    starts: tuple = (0,)

    def __post_init__(self):
        self.t = np.ascontiguousarray(self.t, dtype=float)
        self.columns = {k: np.ascontiguousarray(v, dtype=float) for k, v in self.columns.items()}
        self.starts = tuple(int(s) for s in self.starts)
        _validate(self.t, self.columns, self.meta.get("source", "data set"))
        if not self.starts or self.starts[0] != 0 or any(b <= a for a, b in zip(self.starts, self.starts[1:])) \
                or self.starts[-1] >= self.t.size:
            raise DataError(f"{self.meta.get('source', 'data set')}: record starts {list(self.starts)} must "
                            f"begin at 0 and increase within the {self.t.size} rows")

    def __len__(self) -> int:
        return self.t.size

    def with_columns(self, columns: dict) -> "Dataset":
        """The same rows, records and provenance with ``columns`` (every column: pass the old ones to keep them)."""
        return Dataset(self.t, columns, dict(self.meta), self.starts)

    @property
    def n_records(self) -> int:
        return len(self.starts)

    def record_slices(self) -> list[slice]:
        """The rows of each record."""
        ends = list(self.starts[1:]) + [self.t.size]
        return [slice(a, b) for a, b in zip(self.starts, ends)]

    def record_info(self) -> list[dict]:
        """What ``meta["records"]`` says of each record (empty dicts where nothing is declared)."""
        return self.meta.get("records") or [{}] * self.n_records

    def record_names(self) -> list[str]:
        """Each record's name (``record r`` where none is given)."""
        return [str(x.get("name") or f"record {r}") for r, x in enumerate(self.record_info())]

    def record(self, r: int) -> "Dataset":
        """Record ``r`` alone, on its own time axis."""
        s = self.record_slices()[r]
        info = self.record_info()[r]
        t = self.t[s] - self.t[s][0] + info.get("t0", self.t[s][0])
        meta = {k: v for k, v in self.meta.items() if k != "records"}
        meta.update({k: v for k, v in info.items() if k in ("source", "initial_mean", "initial_std")})
        if self.n_records > 1:
            meta["records"] = [dict(info)]
        return Dataset(t, {k: v[s].copy() for k, v in self.columns.items()}, meta)

    def slice(self, start: int | None = None, stop: int | None = None) -> "Dataset":
        """Rows ``start:stop`` as a new data set (the records that begin inside it keep their starts; rows
        before the first of them are a record of their own)."""
        s = slice(start, stop)
        a, b, _ = s.indices(self.t.size)
        inside = [r for r, x in enumerate(self.starts) if a < x < b]
        first = max([r for r, x in enumerate(self.starts) if x <= a], default=0)
        keep = [first] + inside
        meta = dict(self.meta, slice=[start, stop])
        if self.meta.get("records"):
            meta["records"] = [dict(self.meta["records"][r]) for r in keep]
        if a != self.starts[first]:  # cut inside a record: its declared initial state is not this row's
            for d in (meta, *meta.get("records", [])[:1]):
                d.pop("initial_mean", None)
                d.pop("initial_std", None)
        return Dataset(self.t[s].copy(), {k: v[s].copy() for k, v in self.columns.items()}, meta,
                       (0, *(self.starts[r] - a for r in inside)))

    def arrays(self, observed: list[str], inputs: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contiguous ``(t, Y, U)`` for a model's observed and input columns.

        Raises
        ------
        DataError
            If a column is missing, an input has NaN, or an observed column has
            no finite value at all.
        """
        src = self.meta.get("source", "data set")
        for c in list(observed) + list(inputs):
            if c not in self.columns:
                raise DataError(f"{src}: missing column {c!r} (columns: {sorted(self.columns)})")
        for c in inputs:
            bad = np.flatnonzero(~np.isfinite(self.columns[c]))
            if bad.size:
                raise DataError(f"{src}: input column {c!r} has NaN at row {bad[0] + 1}; inputs must be complete")
        for c in observed:
            if not np.isfinite(self.columns[c]).any():
                raise DataError(f"{src}: observed column {c!r} has no values")
        n = self.t.size
        Y = np.empty((n, len(observed)))
        for j, c in enumerate(observed):
            Y[:, j] = self.columns[c]
        U = np.zeros((n, max(len(inputs), 1)))
        for j, c in enumerate(inputs):
            U[:, j] = self.columns[c]
        return self.t, Y, U

    def to_csv(self, path: str | Path) -> None:
        """Write ``t`` then the columns, full precision."""
        names = ["t"] + list(self.columns)
        M = np.column_stack([self.t] + [self.columns[k] for k in self.columns])
        with open(path, "w", newline="") as fh:
            fh.write(",".join(names) + "\n")
            np.savetxt(fh, M, delimiter=",", fmt="%.17g")


def join_records(records: list[Dataset], names: list[str] | None = None) -> Dataset:
    """Several records (separate experiments) as one :class:`Dataset` with their ``starts``.

    Every record must have the same columns. Record ``r``'s times are shifted to begin one sample
    interval (its own first) after the previous record ends, so the joined axis increases; each record's
    own first time is kept as ``meta["records"][r]["t0"]``. One record is returned unchanged.
    """
    if len(records) == 1:
        return records[0]
    cols = list(records[0].columns)
    for r, ds in enumerate(records[1:], 1):
        if sorted(ds.columns) != sorted(cols):
            raise DataError(f"record {r} ({ds.meta.get('source', '?')}) has columns {sorted(ds.columns)}; "
                            f"record 0 has {sorted(cols)}: every record needs the same columns")
    ts, starts, info, end = [], [], [], None
    for r, ds in enumerate(records):
        t = ds.t - ds.t[0]
        if end is not None:
            t = t + end + (ds.t[1] - ds.t[0])
        else:
            t = t + ds.t[0]
        starts.append(sum(len(x) for x in records[:r]))
        ts.append(t)
        end = t[-1]
        entry = {"name": (names[r] if names else None) or f"record {r}", "source": ds.meta.get("source"),
                 "t0": float(ds.t[0]), "n": len(ds)}
        entry.update({k: dict(ds.meta[k]) for k in ("initial_mean", "initial_std") if ds.meta.get(k)})
        info.append(entry)
    joined = {c: np.concatenate([ds.columns[c] for ds in records]) for c in cols}
    source = " + ".join(str(e["source"]) for e in info)
    return Dataset(np.concatenate(ts), joined, {"source": source, "records": info}, tuple(starts))


def _validate(t: np.ndarray, columns: dict[str, np.ndarray], src: str) -> None:
    n = t.size
    if t.ndim != 1:
        raise DataError(f"{src}: time must be one-dimensional")
    if n == 0:
        raise DataError(f"{src}: no data rows")
    if n < MIN_POINTS:
        raise DataError(f"{src}: too few points ({n}); at least {MIN_POINTS} are needed")
    if not np.isfinite(t).all():
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise DataError(f"{src}: time is not finite at row {i + 1}")
    dt = np.diff(t)
    if (dt <= 0).any():
        i = int(np.flatnonzero(dt <= 0)[0])
        raise DataError(f"{src}: time is not strictly increasing at row {i + 2} "
                        f"(t={float(t[i + 1])!r} after t={float(t[i])!r})")
    for k, v in columns.items():
        if v.shape != (n,):
            raise DataError(f"{src}: column {k!r} has {v.size} values for {n} times")
        if np.isinf(v).any():
            i = int(np.flatnonzero(np.isinf(v))[0])
            raise DataError(f"{src}: column {k!r} has an infinite value at row {i + 1}")


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


SILVERBOX_SHA256 = "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1"
"""Checksum of the Silverbox record as published (``SNLS80mV.csv``, before compression)."""


def silverbox_path() -> Path:
    """The Silverbox record shipped with ardflow (``examples/data/SNLS80mV.csv.gz``; source, citation and
    licence note in ``examples/data/README.md``)."""
    # the examples sit beside the packages, in the repository and in an installed ardflow alike
    return Path(__file__).resolve().parents[1] / "examples" / "data" / "SNLS80mV.csv.gz"


def load_silverbox(path: str | Path | None = None, *, verify: bool = True) -> Dataset:
    """Silverbox benchmark (Wigren & Schoukens 2013): ``u`` = V1 input, ``y`` = V2 output (volts).

    Parameters
    ----------
    path : str or Path, optional
        A copy of ``SNLS80mV.csv`` (or ``.csv.gz``); default: the record shipped with ardflow.
    verify : bool
        Check the shipped record against :data:`SILVERBOX_SHA256` (a damaged copy is a DataError).
    """
    if path is None:
        path = silverbox_path()
        if verify:
            digest = hashlib.sha256(gzip.decompress(path.read_bytes())).hexdigest()
            if digest != SILVERBOX_SHA256:
                raise DataError(f"{path.name}: checksum {digest[:12]}... is not the published record's "
                                f"({SILVERBOX_SHA256[:12]}...); reinstall ardflow")
    ds = read_dataset(path, fs=SILVERBOX_FS, rename={"V1": "u", "V2": "y"})
    ds.meta["units"] = {"t": "s", "u": "V", "y": "V"}
    return ds


DATA_ENV = "ARDFLOW_DATA"
"""Environment variable naming a folder of records that ardflow does not ship (relative data paths in
a spec are looked up there when they are not found beside the spec)."""

PENDULUM_RELPATH = "pendulum/adip_pend_data.mat"
"""Where :func:`load_pendulum` looks for the pendulum record under ``$ARDFLOW_DATA``."""


def external_path(rel: str | Path) -> Path | None:
    """``$ARDFLOW_DATA/rel`` when the variable is set and the file exists there, else None."""
    root = os.environ.get(DATA_ENV)
    if root and (Path(root) / rel).exists():
        return Path(root) / rel
    return None


def load_pendulum(path: str | Path | None = None) -> Dataset:
    """Free-decay pendulum record: ``t`` (s) and ``y`` = theta2 (rad).

    The record's source states no licence, so ardflow does not ship it: give its ``path``, or set
    ``ARDFLOW_DATA`` to the folder that holds ``pendulum/adip_pend_data.mat``.
    """
    if path is None:
        path = external_path(PENDULUM_RELPATH)
        if path is None:
            raise DataError(f"the pendulum record is not shipped with ardflow (its source states no licence): "
                            f"set {DATA_ENV} to the folder that holds {PENDULUM_RELPATH}")
    ds = read_dataset(path, rename={"theta2": "y"}, columns=["y"])
    ds.meta["units"] = {"t": "s", "y": "rad"}
    return ds


SILVERBOX_SPLITS = {
    "estimation": (40650, 105712),
    "test_multisine": (105712, 127400),
    "test_arrow": (100, 40575),
}
"""Customary Silverbox segments (row ranges)."""
