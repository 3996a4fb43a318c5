"""Synthetic cases with one effect hidden in the data: the undeclared-effect unit tests use them (the randomised
benchmark has a generator of its own, :mod:`socbench.diagnose.randomized`).

A "truth" cell is a base model with constant parameters (so that a constant-mode fit of the same structure can match
it exactly) plus, optionally, one hidden effect. Two records are generated from it:

* the **fit** record: a short HPPC (1 C pulses, compressed rests) at the reference temperature, from a lab cycler;
* the **evaluation** record: a load profile suited to reveal the effect (pulses with rests, charge segments, a warming
  cell, …), from the field sensor.

Where the effect lives: in both records (hysteresis, extra RC, Butler–Volmer, coulombic efficiency); only in the
evaluation record for the ones that are about *change* between characterisation and use — capacity fade (the cell
aged), a current-sensor offset (the field sensor, not the lab cycler), self-discharge (a cell that developed a
leak, at a rate that would be a fault: %/h) and temperature (the fit record is at the reference temperature, where
the effect is zero by definition). Noise is white Gaussian on the measured voltage
(and current). The profiles' metadata are silent: name ``synthetic-fit`` / ``synthetic-eval``, no effect anywhere.
"""

from __future__ import annotations

import numpy as np

from .. import loads
from ..models import Constant, ModelParams, make_model, paper_ocv
from ..models.effects import augment, make_effect
from ..ocv import OCVCurve
from ..profile import Profile, ProfileMeta

#: one synthetic 2.5 Ah cell: OCV = the paper pack's curve / 6 (one LiPo cell), parameters per base structure
CAPACITY_AH = 2.5
CELL_PARAMS = {
    "rint": {"R0": 0.035},
    "thevenin": {"R0": 0.030, "R1": 0.015, "C1": 2000.0},
    "dp": {"R0": 0.025, "R1": 0.012, "C1": 1500.0, "R2": 0.010, "C2": 20000.0},
}

#: the hidden effects: (values, in the fit record too?) for a "small" and a "large" magnitude
HIDDEN = {
    "temperature": ({"Ea": 25e3, "dUdT": 0.0}, {"Ea": 40e3, "dUdT": 3e-4}, False),
    "hysteresis": ({"M": 0.025, "M0": 0.0, "gamma": 60.0, "h0": 1.0}, {"M": 0.05, "M0": 0.005, "gamma": 30.0,
                                                                       "h0": 1.0}, True),
    "capacity": ({"cap0": 1.15}, {"cap0": 1.3}, False),
    "current_bias": ({"b0": 0.06}, {"b0": -0.1}, False),
    "extra_rc": ({"R": 0.02, "log10_tau": 2.8}, {"R": 0.03, "log10_tau": 2.5}, True),
    "butler_volmer": ({"I0": 1.0, "dR": -0.02}, {"I0": 0.5, "dR": -0.03}, True),
    "coulombic_efficiency": ({"eta_c": 0.93}, {"eta_c": 0.9}, True),
    "self_discharge": ({"rate": 0.03}, {"rate": 0.05}, False),
}


def cell(base: str = "thevenin") -> tuple[str, ModelParams]:
    """The synthetic cell's base model name and parameters."""
    pack = paper_ocv()
    ocv = OCVCurve(pack.soc, pack.voltage / 6.0, "paper pack OCV / 6 (synthetic single cell)")
    return base, ModelParams(CAPACITY_AH, ocv, {k: Constant(v) for k, v in CELL_PARAMS[base].items()},
                             source="socbench.diagnose.synthetic")


def _segments(segs, dt=1.0):
    i = np.concatenate([np.full(int(round(s / dt)), float(a)) for a, s in segs])
    return np.arange(i.size) * dt, i


def eval_current(kind: str, q: float = CAPACITY_AH, seed: int = 0):
    """``(time, current)`` of an evaluation load. Kinds: ``pulses`` (mixed discharge pulses, brief charges, rests),
    ``cycling`` (1 C charge / discharge between ~85 % and ~35 % SOC), ``rests`` (discharge blocks with long rests),
    ``steps`` (current steps of many amplitudes, 0.1–3 C, both signs)."""
    rng = np.random.default_rng(seed)
    if kind == "pulses":
        segs = []
        for _ in range(9):
            segs += [(q * rng.uniform(0.5, 2.0), rng.uniform(60, 240)), (0.0, rng.uniform(30, 180)),
                     (-q * rng.uniform(0.2, 0.6), rng.uniform(20, 60)), (0.0, rng.uniform(20, 60))]
        return _segments(segs, 2.0)
    if kind == "cycling":
        segs = []
        for _ in range(2):
            segs += [(q, 1800.0), (0.0, 300.0), (-q, 1500.0), (0.0, 300.0)]
        segs += [(q, 1800.0), (0.0, 300.0)]
        return _segments(segs, 5.0)
    if kind == "rests":
        segs = []
        for _ in range(5):
            segs += [(q * rng.uniform(0.5, 1.0), rng.uniform(300, 500)), (0.0, rng.uniform(1500, 2400))]
        return _segments(segs, 5.0)
    if kind == "steps":
        segs = []
        for a in rng.permutation(np.r_[np.linspace(0.1, 3.0, 10), -np.linspace(0.1, 1.0, 4)]):
            segs += [(a * q, 40.0), (0.0, 60.0)]
        segs = segs * 2
        return _segments(segs, 2.0)
    raise ValueError(f"unknown load kind {kind!r}")


def _measure(model, t, i, temp, soc0, v_sd, i_sd, rng, name, i_offset=0.0) -> Profile:
    prof = Profile(t, i, temperature_c=temp)
    sim = model.simulate(prof, soc0=soc0)
    v = sim.voltage_v + rng.normal(0.0, v_sd, t.size) if v_sd > 0 else sim.voltage_v
    i_meas = i + i_offset + (rng.normal(0.0, i_sd, t.size) if i_sd > 0 else 0.0)
    meta = ProfileMeta(name=name, source=name, capacity_ah=CAPACITY_AH, n_series=1)
    return Profile(t, i_meas, voltage_v=v, temperature_c=temp, soc_ref=np.clip(sim.soc, 0.0, 1.0), meta=meta)


def hidden_case(effect: str | None, base: str = "thevenin", load: str = "pulses", magnitude: str = "small",
                v_sd: float = 1e-3, i_sd: float = 0.0, seed: int = 0, eval_soc0: float = 0.95,
                hppc_rest_s: float = 1800.0):
    """``(fit_profile, eval_profile)`` with ``effect`` (None: no effect) hidden in the data (module docstring)."""
    rng = np.random.default_rng(seed)
    name, params = cell(base)
    base_model = make_model(name, params)
    truth = base_model
    in_fit = True
    bias = 0.0
    if effect is not None:
        small, large, in_fit = HIDDEN[effect]
        values = dict(small if magnitude == "small" else large)
        if effect == "current_bias":  # the sensor reads I + b; the truth runs on the true current
            bias = values["b0"]
        else:
            truth = augment(base_model, [make_effect(effect, **values)])
    q = CAPACITY_AH
    hp = loads.hppc(q, dt=2.0, rest_s=hppc_rest_s, pulse_s=10.0, rest_pulse_s=40.0)
    t25 = np.full(hp.n, 25.0)
    fit = _measure(truth if in_fit else base_model, hp.time_s, hp.current_a, t25, 1.0, v_sd, i_sd, rng,
                   "synthetic-fit")
    t, i = eval_current(load, q, seed)
    if effect == "temperature":  # a cold cell warming up: −5 → 20 °C over the record
        temp = np.linspace(-5.0, 20.0, t.size)
    else:
        temp = np.full(t.size, 25.0)
    ev = _measure(truth, t, i, temp, eval_soc0, v_sd, i_sd, rng, "synthetic-eval", i_offset=bias)
    return fit, ev
