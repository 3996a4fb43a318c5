"""The current sensor's offset read on the field records' rests (socbench.diagnose.search.rest_current), and what
it takes for the diagnosis to call it measured (|level| above four standard errors and 0.05 % of 1C).

A generator of this file's own draws field records: 1C–2C discharge stretches between quiet spells of 5–15 min,
sampled every 1–5 s, with white current noise of 0.1–1 % of 1C. Either every quiet spell is a rest and the sensor
reads an offset of 0.1–0.5 % of 1C, or the sensor reads none and two of the five quiet spells carry a steady small
load of 0.1–0.3 % of 1C (a vehicle creeping, its auxiliary load on): quiet and steady like a rest, so that it passes
the rest test under a noisy sensor. A sensor offset reads the same in every rest; the creeping spells scatter beyond
their noise (Cochran's Q).
"""

from __future__ import annotations

import numpy as np

from socbench.diagnose import search
from socbench.profile import Profile

DRAWS = 10
Q = 10.0


def record(seed: int, offset: bool):
    """``(profile, true offset [A])``: one draw of the module docstring."""
    rng = np.random.default_rng([seed, 1 if offset else 2])
    dt = float(rng.uniform(1.0, 5.0))
    b = float(rng.uniform(0.001, 0.005)) * Q * rng.choice([-1.0, 1.0]) if offset else 0.0
    creeping = set() if offset else set(rng.choice(5, 2, replace=False).tolist())
    pieces = []
    for k in range(5):
        pieces.append(np.full(int(rng.uniform(600.0, 1800.0) / dt), rng.uniform(1.0, 2.0) * Q))
        level = float(rng.uniform(0.001, 0.003)) * Q if k in creeping else 0.0
        pieces.append(np.full(int(rng.uniform(300.0, 900.0) / dt), level))
    cur = np.concatenate(pieces)
    noise = float(rng.uniform(0.001, 0.01)) * Q
    i_meas = cur + b + rng.normal(0.0, noise, cur.size)
    return Profile(np.arange(cur.size) * dt, i_meas), b


def measured(profile) -> bool:
    level, se, seconds = search.rest_current(profile, Q, min_s=search.FIELD_REST_MIN_S)
    return seconds >= search.REST_EVIDENCE_S and abs(level) > max(4.0 * se, Q * search.REST_OFFSET_C)


def test_a_sensor_offset_that_every_rest_reads_is_measured(monkeypatch):
    # rests that agree within their noise (Cochran's Q below its 99th percentile) leave the standard error as the
    # pooled level's alone (measured: in 10 of 10 draws)
    hits, same = 0, 0
    for seed in range(DRAWS):
        prof, b = record(seed, offset=True)
        level, se, _ = search.rest_current(prof, Q, min_s=search.FIELD_REST_MIN_S)
        hits += measured(prof) and abs(level - b) <= 4.0 * se
        with monkeypatch.context() as m:
            m.setattr(search, "REST_SPREAD", False)
            same += search.rest_current(prof, Q, min_s=search.FIELD_REST_MIN_S)[1] == se
    assert hits >= DRAWS - 1 and same >= DRAWS - 1


def test_quiet_spells_that_scatter_are_not_read_as_an_offset(monkeypatch):
    # with the scatter of the rests' levels in the standard error, creeping spells are not an offset; without it
    # (the pooled median's error alone) they are, in most draws: the rule is what keeps them out (measured: 1 and 7
    # of 10; the offsets of the other test are measured in 10 of 10 either way)
    scattered = [record(seed, offset=False)[0] for seed in range(DRAWS)]
    assert sum(measured(p) for p in scattered) <= 1
    monkeypatch.setattr(search, "REST_SPREAD", False)
    assert sum(measured(p) for p in scattered) >= DRAWS // 2
