"""Random admissible (state, current, dt, temperature) points for the generic model tests.

State ranges are keyed by state name, so a new model's states are covered by adding its names here once.
"""

from __future__ import annotations

import numpy as np

#: state name -> (low, high) of the uniform draw; the paper pack is 6S, 22 Ah (overpotentials of 0.1–0.5 V)
STATE_RANGES = {
    "z": (0.05, 0.95),
    "U0": (-0.5, 0.5),
    "Ue": (-0.3, 0.3),
    "Uc": (-0.3, 0.3),
    "Istar": (-30.0, 60.0),
    "h": (-1.0, 1.0),
    "s": (-1.0, 1.0),
    "cap": (0.7, 1.3),  # effects.Capacity: Q_model / Q_true
    "b": (-0.1, 0.1),  # effects.CurrentBias [A]: small enough that |I − b| stays above the sign/η kinks
    "dR0": (-2e-3, 2e-3),  # effects.ResistanceOffset [Ω]
    "eps_slow": (-3.0, 3.0),  # effects.ModelError: unit-variance Gauss–Markov states
    "eps_fast": (-3.0, 3.0),
    "eps_r": (-3.0, 3.0),
    "eps_mid": (-3.0, 3.0),
}


def state_range(name: str) -> tuple[float, float]:
    if name in STATE_RANGES:
        return STATE_RANGES[name]
    if name.startswith("U"):  # RC branch voltages U1, U2, ...
        return (-0.3, 0.3)
    if name.startswith("iR"):  # ESC resistor currents
        return (-30.0, 60.0)
    raise KeyError(f"add a sampling range for state '{name}' in tests/model_points.py")


def random_points(model, n: int, rng: np.random.Generator):
    """``(x, i, dt, temp)`` with x ``(n, nx)``; currents keep |I| > C/50 (η(I) and sign kinks excluded)."""
    cols = []
    for name in model.state_names:
        lo, hi = state_range(name)
        if name == "s":
            cols.append(rng.choice([-1.0, 0.0, 1.0], size=n))
        else:
            cols.append(rng.uniform(lo, hi, size=n))
    x = np.stack(cols, axis=-1)
    q = model.capacity_ah
    mag = rng.uniform(q / 50, 3 * q, size=n)
    sign = rng.choice([-1.0, 1.0], size=n, p=[0.3, 0.7])
    i = mag * sign
    dt = rng.choice([0.1, 1.0, 10.0], size=n)
    temp = rng.uniform(-10.0, 40.0, size=n)
    return x, i, dt, temp
