"""A synthetic stand-in for the pendulum record that ardflow does not ship (its source states no licence).

Same physics and layout as the real record: a MATLAB file with ``t`` (s, 1 kHz, 0.061-120 s) and
``theta2`` (rad, encoder step pi*1e-5); held at 1.23 rad, released at 1.5 s, then
theta'' = -w0^2 sin(theta) - c theta' with a small-amplitude period of 0.993 s and viscous damping that
takes the swing to about 0.2 rad by 120 s (the real record: 1.23 -> 0.21 rad over 117 cycles, the period
shortening from 1.092 s to 0.993 s as the amplitude decays). Tests and the bench use it when
``$ARDFLOW_DATA`` does not hold the real record.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ardflow.ardcore.data import PENDULUM_RELPATH, external_path

W0 = 2 * np.pi / 0.993
DAMPING = 0.0305
RELEASE_S, THETA0 = 1.5, 1.23
ENCODER_STEP = np.pi * 1e-5


def pendulum_standin(seed: int = 0) -> dict[str, np.ndarray]:
    """``{"t", "theta2"}`` of the synthetic record (column vectors, as the MATLAB file holds them)."""
    from scipy.integrate import solve_ivp

    t = np.round(np.arange(61, 120_001) * 1e-3, 6)
    free = t >= RELEASE_S
    sol = solve_ivp(lambda _, x: [x[1], -W0**2 * np.sin(x[0]) - DAMPING * x[1]], (RELEASE_S, t[-1]),
                    [THETA0, 0.0], t_eval=t[free], rtol=1e-10, atol=1e-12, method="DOP853")
    theta = np.full(t.size, THETA0)
    theta[free] = sol.y[0]
    # a little sensor noise, then the encoder's quantisation
    theta += np.random.default_rng(seed).normal(0.0, 2e-4, t.size)
    theta = np.round(theta / ENCODER_STEP) * ENCODER_STEP
    return {"t": t[:, None], "theta2": theta[:, None]}


def pendulum_folder(tmp: Path) -> Path:
    """A folder for ``$ARDFLOW_DATA`` that holds ``pendulum/adip_pend_data.mat``: the real record's when
    ``$ARDFLOW_DATA`` already holds it, else ``tmp`` with the stand-in written into it."""
    real = external_path(PENDULUM_RELPATH)
    if real is not None:
        return real.parents[1]
    from scipy.io import savemat

    p = Path(tmp) / PENDULUM_RELPATH
    p.parent.mkdir(parents=True, exist_ok=True)
    savemat(p, pendulum_standin())
    return Path(tmp)
