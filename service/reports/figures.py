"""Figures of a study, rendered from its store as PNG bytes."""

from __future__ import annotations

import io

from ardflow.service.reports.plots import Labels, plot_data_and_psd, plot_evidence_history


def _data(store) -> bytes:
    ds = store.load_data()
    col = "y" if "y" in ds.columns else next(iter(ds.columns))
    buf = io.BytesIO()
    plot_data_and_psd(ds.t, ds.columns[col], buf, labels=Labels(f"data: {col}", "time", col), tau_seconds=None)
    return buf.getvalue()


def _evidence(store) -> bytes:
    hist = {k: v for k, v in store.histories().items() if v}
    if not hist:
        raise LookupError("no trial has finished yet")
    buf = io.BytesIO()
    plot_evidence_history(hist, buf)
    return buf.getvalue()


FIGURES = {"data.png": _data, "evidence.png": _evidence}


def render(name: str, store) -> bytes:
    """PNG bytes of figure ``name``; LookupError when the study has nothing to show yet."""
    return FIGURES[name](store)
