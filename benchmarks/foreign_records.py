"""Records socbench did not make: `socbench fit` and `socbench diagnose` on HPPC and field records from a generator of
their own (docs/foreign_records.md).

    python benchmarks/foreign_records.py [--cases 30] [--seed 0] [--jobs 2] [--out DIR] [--doc docs/foreign_records.md]

The generator here is numpy only, no socbench code, and deliberately unlike the project's own
(`socbench.diagnose.randomized`, `tests/hppc_records.py`):

* **cell** — a two-RC cell ``v = U(z) − R0·I − v1 − v2`` solved exactly on a piecewise-constant current (each branch
  relaxes as ``e^{−t/τ}`` within a segment), ``R0·Q`` 0.02–0.12 Ω·Ah, ``R1`` 0.2–1 × R0 with ``τ1`` 3–40 s, ``R2``
  0.1–0.8 × R0 with ``τ2`` 200–2000 s, capacity 1–60 Ah (log-uniform), one of three analytic OCV shapes (NMC-like,
  LFP-like with a plateau and two knees, and a third with a ripple), no hysteresis, no temperature;
* **HPPC** — a rest of 5 min–2 h, then per SOC step (5, 10 or 20 %) a discharge pulse of 5–60 s at 0.5–3C, an optional
  charge pulse at 0.75 × that, 10–120 s between them, the step at 0.5C or 1C and a rest of 5 min–2 h; laid out (one
  of :data:`PROTOCOLS`, a quarter each) from full down, after a charge from 3 % to full, followed by a charge back to
  full, or in the charge direction (from 4 % up, each level reached by a charge step, the last to full);
* **field record** — from 95 % SOC, segments of 5–120 s at −0.5C (charge), 0.2, 0.5, 1 or 2C (×0.5–1.5), with a rest
  of 5–30 min after 5 % of them, down to 15 % SOC, with its reference SOC;
* **instrument** (the same on both records) — samples every 0.1–10 s (HPPC) and 1–5 s (field) at a random phase,
  time stamps from 0 or from a Unix epoch, voltage noise 0.5–5 mV and an ADC step of 0, 1 or 5 mV, current noise
  0–1 % of 1C, an ADC step of 0, 0.1 or 1 % of 1C and an offset of ±0.5 % of 1C;
* **what the HPPC file says of its SOC axis** (one of :data:`METADATA`, a third each, from a stream of its own): a
  JSON sidecar declaring the capacity; no capacity but a reference SOC column, the cycler's count of the charge (its
  own sensor's offset ±0.05 % of 1C) from a start read to ±1 point with a nominal capacity within ±3 %; or neither. The
  HPPC stops 5, 10 or 20 % above empty (its last level is one step up), so without either the count from full takes
  80–95 % of the capacity.

Each case runs `socbench fit` on the HPPC and `socbench diagnose --fit HPPC --eval FIELD` with the base model
alternating between Thevenin (the truth has a branch more: an extra RC is missing) and DP (the structure is right),
in subprocesses, as a user would. What the field record holds that the model lacks is therefore known: the current
sensor's offset (always), and on a Thevenin base the second branch. The report counts exit codes, tracebacks and
stderr lines that are not socbench's one-line warnings, wall times, how often the offset (where it is at least 0.1 %
of 1C) and the missing branch are named, how far the offset named lies from the sensor's, where the missing branch
stood when it was not (``branch_verdict``: read from the diagnosis report with the search's own rules), and every
other effect named (none is in the data).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: an offset at least this share of 1C is expected to be named
OFFSET_NAMED_FRAC = 0.001


def ocv_shape(kind: str):
    if kind == "nmc":
        return lambda z: 3.0 + 1.2 * z - 0.25 * np.exp(-12 * z) + 0.08 * np.tanh(8 * (z - 0.6)) + 0.05 * z**6
    if kind == "lfp":
        return lambda z: 3.30 + 0.03 * z - 0.45 * np.exp(-25 * z) + 0.12 * np.exp(-25 * (1 - z))
    return lambda z: 3.3 + 0.9 * z - 0.4 * np.exp(-15 * z) + 0.04 * np.sin(6 * z)


#: how the HPPC record is laid out around the test (drawn from a stream of its own, so that the cell, instrument and
#: pulse draws of a case do not depend on it): starting full; a charge from near empty to full before the test (the
#: ORNL Leaf files); a charge back to full after the test's final rest (a cycler's script); the test in the charge
#: direction, its levels reached by charge steps from near empty up to full
PROTOCOLS = ("from full", "charge first", "charge back after", "charge direction")
#: what the HPPC file says of its SOC axis (drawn from a stream of its own): its sidecar declares the capacity; its
#: reference SOC column, the cycler's count, without a capacity; neither
METADATA = ("sidecar capacity", "reference SOC", "neither")


def hppc_segments(r, q: float, protocol: str = "from full") -> tuple[list, float]:
    """``([(duration s, current A), ...], SOC at the record's start)``, discharge positive."""
    segs = [(r.uniform(300, 7200), 0.0)]
    pulse_s, pulse_c = float(r.choice([5, 10, 18, 30, 60])), float(r.choice([0.5, 1.0, 2.0, 3.0]))
    charge, step = r.random() < 0.6, float(r.choice([0.05, 0.1, 0.2]))
    rest, between = r.uniform(300, 7200), r.uniform(10, 120)
    up = protocol == "charge direction"
    z = level = 0.04 if up else 1.0
    while (level < 0.98 - step) if up else (z > step + 0.02):
        segs += [(pulse_s, pulse_c * q), (between, 0.0)]
        z -= pulse_s * pulse_c / 3600
        if charge:
            segs += [(pulse_s, -0.75 * pulse_c * q), (between, 0.0)]
            z += pulse_s * 0.75 * pulse_c / 3600
        c = float(r.choice([0.5, 1.0]))
        if up:  # a charge step to the next level; the last one to full
            level = level + step if level + 2 * step < 0.98 else 1.0
            segs += [((level - z) * 3600 / c, -c * q), (rest, 0.0)]
            z = level
        else:
            segs += [(step * 3600 / c, c * q), (rest, 0.0)]
            z -= step
    z0 = 0.04 if up else 1.0
    if protocol == "charge first":
        z0 = 0.03
        segs = [(600.0, 0.0), ((1.0 - z0) * 3600 / 0.3, -0.3 * q)] + segs
    elif protocol == "charge back after":
        segs += [((1.0 - z) * 3600 / 0.5, -0.5 * q), (3600.0, 0.0)]
    return segs, z0


def field_segments(r, q: float, z_start: float = 0.95, z_end: float = 0.15) -> list:
    """``[(duration s, current A), ...]`` of a field record from ``z_start`` down to ``z_end``: a parked rest, then
    segments of 5–120 s at −0.5C (charge), 0.2, 0.5, 1 or 2C (×0.5–1.5), a rest of 5–30 min after 5 % of them."""
    segs, z = [(r.uniform(60, 1800), 0.0)], z_start
    while z > z_end:
        d, c = r.uniform(5, 120), float(r.choice([-0.5, 0.2, 0.5, 1.0, 2.0])) * q * r.uniform(0.5, 1.5)
        segs.append((d, c))
        z -= d * c / 3600 / q
        if r.random() < 0.05:
            segs.append((r.uniform(300, 1800), 0.0))
    return segs


#: the longest piece a segment is cut into: the cell's parameters (its temperature) are held over each piece
PIECE_S = 30.0
#: the fit test's temperature [°C]
T_LAB_C = 25.0
R_GAS = 8.314462618
KELVIN = 273.15


def arrhenius(ea: float, t_c: float) -> float:
    """A resistance's factor at ``t_c`` °C against 25 °C for activation energy ``ea`` J/mol."""
    return float(np.exp(ea / R_GAS * (1.0 / (t_c + KELVIN) - 1.0 / (T_LAB_C + KELVIN))))


def simulate(segs, cell: dict, dt: float, z0: float, r, inst: dict, cold: dict | None = None,
             stop: dict | None = None, h0: float = 0.0):
    """Sample times, measured current and voltage, true SOC and the cell's temperature (°C) of the cell ``cell``
    under the segments ``segs`` (``[(s, A)]``, discharge positive), sampled every ``dt`` s at a random phase.

    Each segment is cut into pieces of at most :data:`PIECE_S`; over a piece the current and the cell's parameters are
    constant and the state is solved exactly: ``z`` by the charge, each branch as ``v·e^{−t/τ} + R·I·(1 − e^{−t/τ})``,
    the stop operator's state ``h`` linearly in the charge, clipped to ±1. ``cold``: ambient, activation energies,
    entropic coefficient and self-heating, the parameters taken at each piece's start temperature;
    ``stop``: ``{"M": V, "width": share of the capacity}`` (both: ``benchmarks/foreign_effects.py``). Without either,
    the cell of this benchmark: cutting a segment into pieces changes nothing, its parameters are constant."""
    ocv = ocv_shape(cell["ocv"])
    q, r0, branches = cell["q"], cell["r0"], cell["branches"]
    pieces = [(min(PIECE_S, d - s), c) for d, c in segs for s in np.arange(0.0, d, PIECE_S)]
    edges = np.cumsum([0.0] + [d for d, _ in pieces])
    t = np.arange(r.uniform(0, dt), edges[-1], dt)
    k = np.searchsorted(edges, t, side="right") - 1
    n = len(pieces)
    z_s, h_s, temp_s = np.empty(n), np.empty(n), np.empty(n)
    v_s, r_s, r0_s, du_s = np.empty((n, len(branches))), np.empty((n, len(branches))), np.empty(n), np.empty(n)
    z, h, v = z0, h0, np.zeros(len(branches))
    temp = cold["ambient_c"] if cold else T_LAB_C
    for m, (d, c) in enumerate(pieces):
        kr0 = arrhenius(cold["ea_r0"], temp) if cold else 1.0
        kb = arrhenius(cold["ea_branch"], temp) if cold else 1.0
        z_s[m], h_s[m], temp_s[m], v_s[m] = z, h, temp, v
        r0_s[m], r_s[m] = r0 * kr0, [rk * kb for rk, _ in branches]
        du_s[m] = cold["dudt"] * (temp - T_LAB_C) if cold else 0.0
        z -= c * d / 3600 / q
        v = np.array([vk * np.exp(-d / tau) + rk * kb * c * (1 - np.exp(-d / tau))
                      for vk, (rk, tau) in zip(v, branches)])
        if stop:
            h = float(np.clip(h - 2.0 * c * d / (3600 * q * stop["width"]), -1.0, 1.0))
        if cold:
            decay = np.exp(-d / cold["tau_th_s"])
            temp = cold["ambient_c"] + (temp - cold["ambient_c"]) * decay \
                + cold["rise_1c_k"] * (c / q) ** 2 * (1 - decay)
    cur = np.array([pieces[m][1] for m in k])
    tau_in = t - edges[k]
    zs = z_s[k] - cur * tau_in / 3600 / q
    pol = sum(v_s[k, j] * np.exp(-tau_in / tau) + r_s[k, j] * cur * (1 - np.exp(-tau_in / tau))
              for j, (_, tau) in enumerate(branches))
    hs = np.clip(h_s[k] - 2.0 * cur * tau_in / (3600 * q * stop["width"]), -1.0, 1.0) if stop else 0.0
    volt = ocv(np.clip(zs, 0, 1)) + du_s[k] + (stop["M"] * hs if stop else 0.0) - r0_s[k] * cur - pol
    return t + inst["t0"], *read(cur, volt, r, inst), zs, temp_s[k]


def measure(segs, cell: dict, dt: float, z0: float, r, inst: dict):
    """Sample times (random phase, period ``dt``), measured current and voltage, true SOC (:func:`simulate`, no
    effect)."""
    return simulate(segs, cell, dt, z0, r, inst)[:4]


def read(cur, volt, r, inst: dict):
    """``(current, voltage)`` as the instrument ``inst`` reads the true ones: the current sensor's offset and noise,
    the voltage noise, each ADC's step."""
    i_meas = cur + inst["i_offset"] + r.normal(0, inst["i_sd"], cur.size)
    v_meas = volt + r.normal(0, inst["v_sd"], volt.size)
    if inst["i_step"] > 0:
        i_meas = np.round(i_meas / inst["i_step"]) * inst["i_step"]
    if inst["v_step"] > 0:
        v_meas = np.round(v_meas / inst["v_step"]) * inst["v_step"]
    return i_meas, v_meas


def write(path: Path, t, i, v, soc=None, capacity_ah: float | None = 1.0, temperature=None):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "current_a", "voltage_v"] + (["temperature_c"] if temperature is not None else [])
                   + (["soc_ref"] if soc is not None else []))
        for k in range(t.size):
            w.writerow([f"{t[k]:.3f}", f"{i[k]:.6g}", f"{v[k]:.6g}"]
                       + ([f"{temperature[k]:.2f}"] if temperature is not None else [])
                       + ([f"{soc[k]:.6f}"] if soc is not None else []))
    side = {"n_series": 1, "name": path.stem, **({"capacity_ah": capacity_ah} if capacity_ah else {})}
    path.with_suffix(".json").write_text(json.dumps(side))


def cycler_reference(t, z_true, q: float, r) -> np.ndarray:
    """The reference SOC a cycler writes: its count of the charge (its own current sensor, an offset of ±0.05 % of
    1C) from a start read to ±1 point, with a nominal capacity within ±3 % of the cell's."""
    counted = (z_true[0] - z_true) * q + r.uniform(-5e-4, 5e-4) * q * (t - t[0]) / 3600.0
    return z_true[0] + r.uniform(-0.01, 0.01) - counted / (q * r.uniform(0.97, 1.03))


def cell_and_instrument(r) -> tuple[dict, dict, float, float]:
    """``(cell, instrument, HPPC sample period s, field sample period s)`` drawn from ``r`` (module docstring)."""
    q = float(np.exp(r.uniform(np.log(1.0), np.log(60.0))))
    r0 = r.uniform(0.02, 0.12) / q
    cell = {"q": q, "ocv": str(r.choice(["nmc", "lfp", "ripple"])), "r0": r0,
            "branches": [(r0 * r.uniform(0.2, 1.0), r.uniform(3, 40)),
                         (r0 * r.uniform(0.1, 0.8), r.uniform(200, 2000))]}
    inst = {"v_step": float(r.choice([0.0, 0.001, 0.005])), "i_step": float(r.choice([0.0, 0.001, 0.01])) * q,
            "v_sd": r.uniform(0.0005, 0.005), "i_sd": r.uniform(0.0, 0.01) * q,
            "i_offset": r.uniform(-0.005, 0.005) * q, "t0": float(r.choice([0.0, 1.7e9]))}
    dt_hppc, dt_field = float(r.choice([0.1, 0.5, 1.0, 2.0, 5.0, 10.0])), float(r.choice([1.0, 2.0, 5.0]))
    return cell, inst, dt_hppc, dt_field


def hppc_setup(seed: int) -> tuple:
    """``(r, cell, instrument, HPPC sample period s, field sample period s, protocol, segments, start SOC)`` of case
    ``seed``: the draws every benchmark on this generator shares, ``r`` left where the HPPC's measurement draws
    next."""
    r = np.random.default_rng(seed)
    cell, inst, dt_hppc, dt_field = cell_and_instrument(r)
    protocol = PROTOCOLS[int(np.random.default_rng([seed, 1]).integers(len(PROTOCOLS)))]
    segs, z0 = hppc_segments(r, cell["q"], protocol)
    return r, cell, inst, dt_hppc, dt_field, protocol, segs, z0


def draw(seed: int, folder: Path) -> dict:
    r, cell, inst, dt_hppc, dt_field, protocol, segs, z0 = hppc_setup(seed)
    q = cell["q"]
    hppc = measure(segs, cell, dt_hppc, z0, r, inst)
    rf = np.random.default_rng([seed, 2])  # the field record's own stream: it does not depend on the HPPC's layout
    field = measure(field_segments(rf, q), cell, dt_field, 0.95, rf, inst)
    rm = np.random.default_rng([seed, 3])  # what the HPPC file says of its axis: a stream of its own too
    metadata = METADATA[int(rm.integers(len(METADATA)))]
    reference = cycler_reference(hppc[0], hppc[3], q, rm) if metadata == "reference SOC" else None
    write(folder / f"case{seed}_hppc.csv", *hppc[:3], soc=reference,
          capacity_ah=q if metadata == "sidecar capacity" else None)
    write(folder / f"case{seed}_field.csv", *field, capacity_ah=q)
    return {"seed": seed, "capacity_ah": q, "ocv": cell["ocv"], "protocol": protocol, "metadata": metadata,
            "hppc_soc_range": [float(np.min(hppc[3])), float(np.max(hppc[3]))], "dt_hppc_s": dt_hppc,
            "dt_field_s": dt_field,
            "offset_c": inst["i_offset"] / q, "i_step_c": inst["i_step"] / q, "i_sd_c": inst["i_sd"] / q,
            "v_sd_mv": 1000 * inst["v_sd"], "v_step_mv": 1000 * inst["v_step"], "epoch": inst["t0"] > 0,
            "tau_s": [b[1] for b in cell["branches"]]}


def _cli(args: list, cwd: Path) -> tuple[int, str, float]:
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "socbench.cli", *args], cwd=cwd, capture_output=True, text=True)
    return done.returncode, done.stderr, time.perf_counter() - t0


def _leaks(stderr: str) -> list:
    """stderr lines that are not socbench's own one-line messages (a traceback, a library warning)."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("socbench ")]


def run_case(seed: int, folder: str, refine_ocv: str = "always") -> dict:
    from socbench.identify.hppc import NO_KNEE  # the warning's marker (the generator above stays numpy-only)

    folder = Path(folder)
    out = draw(seed, folder)
    model = "thevenin" if seed % 2 == 0 else "dp"
    hppc, field = folder / f"case{seed}_hppc.csv", folder / f"case{seed}_field.csv"
    rc_fit, err_fit, s_fit = _cli(["fit", "--data", str(hppc), "--model", model,
                                   "--out", str(folder / f"case{seed}.json")], folder)
    rc_diag, err_diag, s_diag = _cli(["diagnose", "--fit", str(hppc), "--eval", str(field), "--model", model,
                                      "--out", str(folder / f"case{seed}_diag"), "--no-figures",
                                      "--refine-ocv", refine_ocv], folder)
    added, branch, left, soc_before, soc_after, capacity_fit, offset_named = None, None, None, None, None, None, None
    reference = None
    if rc_fit == 0:
        capacity_fit = json.loads((folder / f"case{seed}.json").read_text())["capacity_ah"]
    if rc_diag == 0:
        diagnosis = json.loads((folder / f"case{seed}_diag" / "diagnosis.json").read_text())
        added, left = diagnosis["effects_added"], diagnosis.get("left")
        offset_named = next((st["params"]["b0"] for st in diagnosis["steps"] if st["effect"] == "current_bias"),
                            None)
        soc_before = diagnosis["before"].get("soc", {}).get("ekf", {}).get("soc_rmse")
        soc_after = diagnosis["after"].get("soc", {}).get("ekf", {}).get("soc_rmse")
        reference = diagnosis.get("soc", {}).get("reference_count")
        if model == "thevenin":
            branch = branch_verdict(diagnosis)
    offset_alone = None
    if ekf_grew(soc_before, soc_after):
        offset_alone = soc_with_sensor_offset(hppc, field, model, out["offset_c"] * out["capacity_ah"], refine_ocv)
    out.update({"model": model, "fit_exit": rc_fit, "diagnose_exit": rc_diag, "fit_s": s_fit, "diagnose_s": s_diag,
                "traceback": "Traceback" in err_fit + err_diag, "leaks": _leaks(err_fit) + _leaks(err_diag),
                "added": added, "offset_named_a": offset_named, "branch": branch, "left": left,
                "soc_rmse_before_ekf": soc_before, "soc_rmse_after_ekf": soc_after, "capacity_fit_ah": capacity_fit,
                "knee_warned": NO_KNEE in err_fit + err_diag, "soc_offset_alone": offset_alone,
                "reference_count": reference})
    return out


def soc_with_sensor_offset(hppc: Path, field: Path, model: str, offset_a: float, refine_ocv: str) -> dict:
    """Where the search made the SOC worse: the held-out EKF SOC RMSE of the diagnosis' base model as it is
    (``base``, which must equal the diagnosis' *before*) and with the current sensor's true offset fixed in
    (``offset``: a current-offset state at the drawn value, initial SD 1 nA, scored as the diagnosis scores its base,
    :func:`socbench.diagnose.core.model_soc_errors`). Where the offset alone makes it worse too, what the search added
    is right and the SOC had leant on the offset: it hid another error of the base (a capacity read off a reference
    SOC, the OCV of a flat cell)."""
    from socbench.commands.diagnose import REFINE_OCV_OPTION
    from socbench.datasets import load
    from socbench.diagnose import diagnose
    from socbench.diagnose.core import model_soc_errors
    from socbench.models.effects import augment, make_effect

    fit, evals = [load(hppc)], [load(field)]
    d = diagnose(model, fit, evals, soc=False, refine_ocv=REFINE_OCV_OPTION[refine_ocv])
    fixed = augment(d.base_model, [make_effect("current_bias", b0=offset_a, initial_sd=(1e-9,))])
    return {"base": model_soc_errors(d.base_model, evals)["ekf"]["soc_rmse"],
            "offset": model_soc_errors(fixed, evals)["ekf"]["soc_rmse"]}


def axis_gap(reference: dict | None) -> float:
    """``|Q_final/Q_ref − 1|`` of a diagnosis' ``soc.reference_count`` (:func:`socbench.diagnose.report.axis_gap`);
    0 without one, or where the reference is no count."""
    from socbench.diagnose.report import axis_gap as gap_of

    gap = gap_of(reference) if reference else None
    return 0.0 if gap is None else abs(gap)


#: why the missing branch of a Thevenin case was not named, read from the diagnosis (``branch_verdict``)
#: the words of the search's refusal of an extra branch beside the base's own (``Search._scored``): the twin rule
REFUSED = ("lies within",)
VERDICTS = ("named", "kept as the base's own branch", "held at the noise floor", "cut below the search's min_gain",
            "no held-out gain",
            "refused beside a base branch", "signature too weak to fit", "another candidate won")


def _refused(candidate: dict) -> bool:
    """Whether a round's extra-branch entry of ``diagnosis.json`` is the twin rule's score out (:data:`REFUSED`)."""
    return candidate["score"] is None and any(w in candidate["evidence"] for w in REFUSED)


def branch_verdict(diagnosis: dict) -> dict:
    """Where the extra RC branch stood in the diagnosis of a Thevenin case (the truth has a second branch): the last
    round in which it was fitted (else the last it was listed in) and why it was not named there, the first of
    :data:`VERDICTS` that applies, read from the report alone (scores, held-out RMSEs, evidence, the final measured
    noise) with the search's published rules: a round ends at the noise floor (held-out RMSE ≤ ``NOISE_FLOOR`` × the
    noise, ``NOISE_FLOOR_REFIT`` × once the base refit was added), an addition must cut the held-out RMSE by
    ``min_gain``, at the floor by ``FLOOR_GAIN``, the round's chosen candidate is added."""
    import inspect

    from socbench.diagnose import diagnose
    from socbench.diagnose.search import FLOOR_GAIN, noise_floor

    if "extra_rc" in diagnosis["effects_added"]:
        return {"verdict": "named"}
    if any(s["effect"] == "extra_rc" and s["kind"] == "base" for s in diagnosis["steps"]):
        return {"verdict": "kept as the base's own branch"}  # in the model, in place of a spare base branch
    min_gain = inspect.signature(diagnose).parameters["min_gain"].default  # what `socbench diagnose` runs with
    noise = float(diagnosis["fit"].get("voltage_noise_sd_binned_final") or 0.0)
    steps = [s["effect"] for s in diagnosis["steps"]]
    listed = [(k, c) for k, round_ in enumerate(diagnosis["rounds"]) for c in round_ if c["effect"] == "extra_rc"]
    # a branch the twin rule scored out (its score None, as every score out) was fitted all the same
    fitted = [(k, c) for k, c in listed if c["score"] is not None or _refused(c)]
    if not listed:
        return {"verdict": "signature too weak to fit"}
    k, c = (fitted or listed)[-1]
    now, after = c["rmse_v_before"], c["rmse_v_after"]
    floor = noise_floor(noise, "base_refit" in steps[:k])
    if _refused(c):
        verdict = "refused beside a base branch"
    elif c["score"] is None:
        verdict = "signature too weak to fit"
    elif c["score"] <= 0:
        verdict = "no held-out gain"
    elif after > (1.0 - min_gain) * now:
        verdict = "cut below the search's min_gain"
    elif now <= floor and (FLOOR_GAIN is None or after > (1.0 - FLOOR_GAIN) * now):
        verdict = "held at the noise floor"
    else:
        verdict = "another candidate won"
    return {"verdict": verdict, "round": k, "score": c["score"], "rmse_before_mv": 1e3 * now,
            "rmse_after_mv": 1e3 * after, "noise_mv": 1e3 * noise}


def summary(cases: list) -> dict:
    from socbench.diagnose.leftover import suggests_ocv  # what `diagnosis.md` suggests (the generator stays numpy-only)
    from socbench.diagnose.report import COUNT_GAP

    ran = [c for c in cases if c["added"] is not None]
    with_soc = [c for c in ran if c.get("soc_rmse_before_ekf") is not None and c.get("soc_rmse_after_ekf") is not None]
    alone = {c["seed"]: c.get("soc_offset_alone") or {} for c in with_soc}
    worse = [c for c in with_soc if ekf_grew(c["soc_rmse_before_ekf"], c["soc_rmse_after_ekf"])]
    offset = [c for c in ran if abs(c["offset_c"]) >= OFFSET_NAMED_FRAC]
    thev = [c for c in ran if c["model"] == "thevenin"]
    spurious = [(c["seed"], e, c.get("protocol", "")) for c in ran for e in c["added"]
                if e not in ("current_bias",) + (("extra_rc",) if c["model"] == "thevenin" else ())]
    return {"cases": len(cases), "fit_ok": sum(c["fit_exit"] == 0 for c in cases),
            "diagnose_ok": sum(c["diagnose_exit"] == 0 for c in cases),
            "tracebacks": sum(c["traceback"] for c in cases), "leaks": sum(len(c["leaks"]) for c in cases),
            "fit_s_max": max(c["fit_s"] for c in cases), "diagnose_s_max": max(c["diagnose_s"] for c in cases),
            "offset_cases": len(offset), "offset_named": sum("current_bias" in c["added"] for c in offset),
            "quantised_offset_cases": sum(c["i_step_c"] >= 0.01 for c in offset),
            "quantised_offset_named": sum(c["i_step_c"] >= 0.01 and "current_bias" in c["added"] for c in offset),
            "offset_error_c": _median_worst([abs(c["offset_named_a"] / c["capacity_ah"] - c["offset_c"])
                                             for c in offset if c.get("offset_named_a") is not None]),
            "thevenin_cases": len(thev), "extra_rc_named": sum("extra_rc" in c["added"] for c in thev),
            "left_points_at_ocv": [c["seed"] for c in ran if suggests_ocv(c.get("left"))],
            "branch_verdicts": {v: n for v in VERDICTS
                                if (n := sum((c.get("branch") or {}).get("verdict") == v for c in thev))},
            "spurious": spurious,
            # issue #13's bound on what the search's effects may cost the SOC estimate, on records it did not make
            "soc_cases": len(with_soc),
            "soc_worse": [(c["seed"], c["added"]) for c in worse],
            # of those, the ones whose base model is as much worse with the sensor's true offset fixed in alone
            "soc_worse_offset_alone": [k for k, a in alone.items() if ekf_grew(a.get("base"), a.get("offset"))],
            # of those, the ones where the diagnosis reports the field reference counting another capacity than the
            # final model's (socbench.socaxis.read_reference_count): the SOC axis' own error, which no filter removes
            "soc_worse_axis_gap": [c["seed"] for c in worse if axis_gap(c.get("reference_count")) > COUNT_GAP],
            "by_metadata": {m: _axis_summary([c for c in cases if c.get("metadata") == m]) for m in METADATA},
            "by_protocol": {p: {"cases": sum(c.get("protocol") == p for c in cases),
                                "fit_ok": sum(c.get("protocol") == p and c["fit_exit"] == 0 for c in cases),
                                "diagnose_ok": sum(c.get("protocol") == p and c["diagnose_exit"] == 0 for c in cases)}
                            for p in PROTOCOLS}}


def ekf_grew(before: float | None, after: float | None) -> bool:
    """Whether the EKF's held-out SOC RMSE grew from ``before`` to ``after`` by more than the diagnosis' bound
    (:func:`socbench.diagnose.core.soc_grew`); False where either is missing."""
    from socbench.diagnose.core import soc_grew

    return before is not None and after is not None and bool(soc_grew({"ekf": before}, {"ekf": after}))


def _cases_with_effects(pairs) -> str:
    """``case 5 (current_bias + extra_rc), …`` of ``[(seed, effects added)]`` (``none`` for no pair)."""
    return ", ".join(f"case {k} ({' + '.join(a) or 'nothing added'})" for k, a in pairs) or "none"


def _median_worst(values) -> tuple:
    """``(median, largest)`` of the values that are not None (None, None without any)."""
    values = [v for v in values if v is not None]
    return (float(np.median(values)), float(max(values))) if values else (None, None)


def _axis_summary(cases: list) -> dict:
    """Per kind of HPPC metadata: how far the fitted capacity lies from the cell's (median and worst |ratio − 1|), the
    diagnosis' held-out EKF SOC RMSE before and after its search (median and worst), and how many fits or diagnoses
    warned that the HPPC shows no end-of-discharge knee."""
    out = {"cases": len(cases), "knee_warned": sum(bool(c.get("knee_warned")) for c in cases)}
    for key, values in (("capacity_error", [abs(c["capacity_fit_ah"] / c["capacity_ah"] - 1.0) for c in cases
                                            if c.get("capacity_fit_ah")]),
                        ("soc_before", [c.get("soc_rmse_before_ekf") for c in cases]),
                        ("soc_after", [c.get("soc_rmse_after_ekf") for c in cases])):
        out[f"{key}_median"], out[f"{key}_max"] = _median_worst(values)
    return out


def write_doc(path: Path, s: dict, cases: list, command: str, wall: float):
    from socbench.diagnose.core import SOC_WORSE
    from socbench.diagnose.leftover import OCV_HINT_GAP
    from socbench.diagnose.report import COUNT_GAP

    w = ["# Records socbench did not make: fit and diagnose", "",
         f"*Generated by `{command}` on {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC ({wall:.0f} s wall); every "
         "number below comes from that run.*", "",
         "The records come from a generator of this benchmark's own (numpy only, no socbench code; its module "
         "docstring says what it draws): a two-RC cell, HPPCs of random layouts and field records with charge, "
         "sampled at 0.1–10 s, quantised, with noise and a current-sensor offset. The HPPC is laid out one of four "
         "ways around the test: from full down; after a charge from near empty to full (as the ORNL Leaf files); "
         "followed by a charge back to full (a cycler's script); or in the charge direction, each level reached by a "
         "charge step (its rest points then lie after charging). The field record is drawn from a stream of its own, "
         "the same whatever the HPPC's layout. `socbench fit` and `socbench "
         "diagnose` run on them as a user would (subprocesses). What the field record holds that the model lacks is "
         "known: the current sensor's offset, and on a Thevenin base the second branch.", "",
         "| measured | value |", "|---|---|",
         f"| `socbench fit` exit 0 | {s['fit_ok']}/{s['cases']} |",
         f"| `socbench diagnose` exit 0 | {s['diagnose_ok']}/{s['cases']} |",
         f"| tracebacks / stderr lines that are not socbench's one-line messages | {s['tracebacks']} / {s['leaks']} |",
         f"| slowest fit / diagnosis (wall, with start-up) | {s['fit_s_max']:.1f} s / {s['diagnose_s_max']:.1f} s |",
         f"| current offset ≥ {100 * OFFSET_NAMED_FRAC:.1f} % of 1C named | {s['offset_named']}/{s['offset_cases']} |",
         f"| … of those read with a 1 %-of-1C ADC step | {s['quantised_offset_named']}/{s['quantised_offset_cases']} |",
         "| … the offset named against the sensor's, median / worst error (% of 1C) | "
         + (" / ".join(f"{100 * x:.3f}" for x in s["offset_error_c"]) if s["offset_error_c"][0] is not None
            else "–") + " |",
         f"| missing second branch named (Thevenin base) | {s['extra_rc_named']}/{s['thevenin_cases']} |",
         "| … where it stood when not named (the last round it was fitted in; `branch` column below) | " + "; ".join(
             f"{v}: {n}" for v, n in s["branch_verdicts"].items() if v != "named") + " |",
         f"| what is left mostly follows the SOC, and the OCV's widest gap is wider than {100 * OCV_HINT_GAP:g} % "
         f"(the report suggests measuring the OCV) | {len(s['left_points_at_ocv'])}/{s['diagnose_ok']} (cases "
         f"{', '.join(str(k) for k in s['left_points_at_ocv']) or 'none'}) |",
         f"| effects named that are not in the data | {len(s['spurious'])} "
         f"({', '.join(f'case {k} ({p}, {e})' for k, e, p in s['spurious']) or 'none'}) |",
         f"| held-out EKF SOC RMSE worse by more than {100 * SOC_WORSE:.1f} points after the search (the issue's "
         f"bound: in at most 10 % of the cases) | {len(s['soc_worse'])}/{s['soc_cases']} "
         f"({_cases_with_effects(s['soc_worse'])}) |",
         "| … of those, where the base model with the current sensor's true offset fixed in (nothing else added) is "
         f"worse by as much: the offset had hidden another error of the base | "
         f"{len(s['soc_worse_offset_alone'])}/{len(s['soc_worse'])} (cases "
         f"{', '.join(str(k) for k in s['soc_worse_offset_alone']) or 'none'}) |",
         "| … of those, where the diagnosis reports the field record's reference SOC counting a capacity more than "
         f"{100 * COUNT_GAP:g} % off the final model's (`soc.reference_count`) | "
         f"{len(s['soc_worse_axis_gap'])}/{len(s['soc_worse'])} (cases "
         f"{', '.join(str(k) for k in s['soc_worse_axis_gap']) or 'none'}) |",
         "| fit / diagnose exit 0 per HPPC protocol | " + "; ".join(
             f"{p}: {v['fit_ok']}/{v['cases']} / {v['diagnose_ok']}/{v['cases']}" for p, v in s["by_protocol"].items())
         + " |", "",
         "The SOC axis, by what the HPPC file says of it (the HPPC stops 5–20 % above empty; `socbench fit`'s "
         "capacity against the cell's; the diagnosis' held-out EKF SOC RMSE on the field record, before and after its "
         "search; warnings that the HPPC shows no end-of-discharge knee, from either command):", "",
         "| HPPC file | cases | fit capacity error, median / worst | SOC RMSE before, median / worst | after, "
         "median / worst | no-knee warnings |", "|---|---|---|---|---|---|"]
    for m, v in s["by_metadata"].items():
        w.append(f"| {m} | {v['cases']} | {_pct_cell(v['capacity_error_median'])} / "
                 f"{_pct_cell(v['capacity_error_max'])} % | {_pct_cell(v['soc_before_median'])} / "
                 f"{_pct_cell(v['soc_before_max'])} % | {_pct_cell(v['soc_after_median'])} / "
                 f"{_pct_cell(v['soc_after_max'])} % | {v['knee_warned']} |")
    w += ["",
         "Where the missing branch was not named, the `branch` column says where it stood in the last round the "
         "search fitted it, read from `diagnosis.json` with the search's own rules (`socbench.diagnose.search`): "
         "*held at the noise floor* — it cut the held-out RMSE by at least `min_gain`, but the model was already "
         "within the noise floor's multiple of the measured voltage noise, where the search stops; *cut below the "
         "search's min_gain* — it helped by less than `min_gain`; *no held-out gain* — fitted, it did not lower the "
         "held-out error (the residual is something else: an OCV read from few rest points between which the curve "
         "bends, a branch the base fit already took); *signature too weak to fit* — its residual signature was too "
         "small for the search to fit it; *refused beside a base branch* — its time constant lay next to one of the "
         "base model's; *kept as the base's own branch* — it is in the final model, not named: the base fit had left "
         "two of its branches at one time constant or one slower than 10⁴ s (a ramp), and the extra one is where the "
         "spare branch belongs; "
         "*another candidate won* — it passed every rule, and the round added another effect. The last "
         "column is what the diagnosis left (`diagnosis.md`'s \"What is left\", "
         "`socbench.diagnose.leftover`): the held-out structure above the voltage noise, the share of its variance "
         "that follows the SOC and the current, and, with an OCV read from rest points, how many and the widest SOC "
         "gap between them.", "",
         "Per case:", "",
         "| case | base | OCV | HPPC protocol | HPPC file | HPPC SOC range % | capacity Ah (fit) | HPPC / field dt s | "
         "offset % of 1C | current step % of 1C | current noise % of 1C | voltage noise mV | fit s | diagnose s | "
         "named | held-out SOC RMSE before → after, EKF % | branch (Thevenin) | left: structure mV (follows SOC / "
         "current %; OCV points, widest gap %) |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        lo, hi = c["hppc_soc_range"]
        fitted = f" ({c['capacity_fit_ah']:.1f})" if c.get("capacity_fit_ah") else ""
        w.append(f"| {c['seed']} | {c['model']} | {c['ocv']} | {c['protocol']} | {c['metadata']} | "
                 f"{100 * lo:.0f}–{100 * hi:.0f} | {c['capacity_ah']:.1f}{fitted} | {c['dt_hppc_s']:g} / "
                 f"{c['dt_field_s']:g} | {100 * c['offset_c']:+.2f} | {100 * c['i_step_c']:.1f} | "
                 f"{100 * c['i_sd_c']:.2f} | {c['v_sd_mv']:.1f} | {c['fit_s']:.1f} | {c['diagnose_s']:.1f} | "
                 f"{', '.join(c['added']) if c['added'] is not None else 'failed'} | "
                 f"{_pct_cell(c.get('soc_rmse_before_ekf'))} → {_pct_cell(c.get('soc_rmse_after_ekf'))} | "
                 f"{_branch_cell(c.get('branch'))} | "
                 f"{_left_cell(c.get('left'))} |")
    path.write_text("\n".join(w) + "\n")


def _branch_cell(b) -> str:
    """The per-case table's branch column: the verdict, with the held-out RMSE before → after of the last round that
    fitted the branch and the measured noise."""
    if not b:
        return ""
    if "rmse_before_mv" not in b:
        return b["verdict"]
    return (f"{b['verdict']} (round {b['round'] + 1}: {b['rmse_before_mv']:.1f} → {b['rmse_after_mv']:.1f} mV, "
            f"noise {b['noise_mv']:.1f} mV)")


def _pct_cell(x) -> str:
    return "" if x is None else f"{100 * x:.2f}"


def _left_cell(left) -> str:
    """The per-case table's last column: what the diagnosis left (``diagnosis.json`` ``left``)."""
    if not left:
        return ""
    gap = (f"; {left['ocv_points']} points, {100 * left['ocv_widest_gap']:.0f}" if "ocv_widest_gap" in left else "")
    return (f"{1000 * left['structure_v']:.1f} ({100 * left['soc_share']:.0f} / {100 * left['current_share']:.0f}"
            f"{gap})")


def case_arguments(ap, cases: int, doc: str) -> None:
    """The arguments of every benchmark of this family: how many cases, from which seed, on how many processes, where
    the records go and where the report is written."""
    ap.add_argument("--cases", type=int, default=cases)
    ap.add_argument("--seed", type=int, default=0, help="first case's seed (cases use seed, seed+1, ...)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default=None, help="folder for the records and outputs (default: a temporary one)")
    ap.add_argument("--doc", default=str(REPO / "docs" / doc))


def doc_argument(doc: str, default: str) -> str:
    """``" --doc PATH"`` for a command line that reproduces a report written elsewhere than ``docs/default`` (the
    path relative to the repository where it lies inside it), else nothing."""
    path = Path(doc).resolve()
    if path == (REPO / "docs" / default).resolve():
        return ""
    return f" --doc {path.relative_to(REPO) if path.is_relative_to(REPO) else path}"


def run_cases(run, args, *extra) -> list:
    """``run(seed, folder, *extra)`` for each of ``args.cases`` seeds from ``args.seed`` on ``args.jobs`` processes,
    the records in ``args.out`` (default: a new temporary folder)."""
    folder = Path(args.out or tempfile.mkdtemp(prefix="socbench-foreign-"))
    folder.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.seed, args.seed + args.cases))
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        return list(pool.map(run, seeds, [str(folder)] * len(seeds), *[[x] * len(seeds) for x in extra]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    case_arguments(ap, 30, "foreign_records.md")
    ap.add_argument("--refine-ocv", default="always", choices=("coarse", "always", "never"),
                    help="passed to socbench diagnose (default: its own default, always)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    cases = run_cases(run_case, args, args.refine_ocv)
    s = summary(cases)
    command = (f"python benchmarks/foreign_records.py --cases {args.cases} --seed {args.seed} --jobs {args.jobs}"
               + (f" --refine-ocv {args.refine_ocv}" if args.refine_ocv != "always" else "")
               + doc_argument(args.doc, "foreign_records.md"))
    write_doc(Path(args.doc), s, cases, command, time.perf_counter() - t0)
    Path(args.doc).with_suffix(".json").write_text(json.dumps({"summary": s, "cases": cases}, indent=1))
    lists = ("spurious", "soc_worse", "soc_worse_offset_alone", "soc_worse_axis_gap")  # in the doc, case by case
    print(json.dumps({k: v for k, v in s.items() if k not in lists}), flush=True)
    return 0 if s["fit_ok"] == s["diagnose_ok"] == s["cases"] and not s["tracebacks"] else 1


if __name__ == "__main__":
    sys.exit(main())
