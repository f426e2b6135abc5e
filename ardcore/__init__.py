"""ardflow's numerics, as the method reads: ``model`` (what a user declares, and its generated kernels),
``likelihood`` (the EKF), ``sampling`` (parallel adaptive MCMC), ``evidence``, ``selection`` (ARD evidence
maximisation and the comparison of models), ``effects`` and ``screening`` (what the closed loop may add, and
how it is screened), ``loop`` (the closed loop); beside them the data sets (``data``), the progress events
(``events``), the one JSON spelling and atomic writer (``jsonio``) and the domain errors (``errors``).

No module here imports dask, zarr or fastapi.
"""

__all__ = [
    "data", "effects", "errors", "events", "evidence", "jsonio", "likelihood", "loop", "model", "sampling",
    "screening", "selection",
]
