"""Filters across a logger pause: the SOC band after a pause in the middle of a load, with and without the variance
of the current the zero-order hold misses (socbench.segments.hold_var).

Each draw: a cell (one of four models with its reference parameters, its capacity scaled 0.5–3×: the same
resistances carry 0.5–3× the current), a load of held
levels (1–30 s, a mean that takes 40–80 % of the charge over 0.5–2 h, spread 30–90 % about it), sampled every
0.1–5 s; the truth simulated over the whole load, then a window of 1–20 minutes dropped from the record (the load went
on while the logger was off); voltage noise 1–5 mV, current noise 0–1 % C. Every filter starts at the true SOC with a
small band (P0 = 1e-6), so what it gets wrong after the pause is the pause's. Scored over the 10 minutes after the
pause: the fraction of samples whose SOC error lies within 3σ, and the SOC RMSE. "Before" is the same filter with
``hold=False`` (the hold's variance zeroed: what every filter did before it existed). This generator is not the one
tests/test_hold_var.py uses.

Pauses cut into measured currents (``--measured N``, needs SOCBENCH_DATA_DIR): the drive cycles of the Panasonic
18650PF at every temperature, the CALCE A123 DST/US06/FUDS records and the DJI Matrice 100 flight telemetry, each
with a window of 1–20 minutes dropped where the record has no gap of its own within 5 minutes. What the hold claims
is checked directly: the record's own mean current over the dropped window (charge over time) against the held sample,
in units of the hold's SD. A calibrated SD puts 68 / 95 / 99.7 % of the pauses within 1 / 2 / 3 SD; a band of zero
(no variance read) counts as outside. Two rules side by side: the windows and cut the filters use now, and the first
rule (30 s windows, each cut at its largest change whatever its size).

    python benchmarks/logger_pause.py --draws 60 --seed 2026 --measured 400 --md docs/logger_pauses.md
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from socbench import segments  # noqa: E402
from socbench.estimators import SensorNoise, make_estimator  # noqa: E402
from socbench.models import make_model, paper_params  # noqa: E402
from socbench.profile import Profile, ProfileMeta  # noqa: E402

MODELS = ("thevenin", "dp", "nrc", "esc")
ESTIMATORS = ("ekf", "ukf", "pf")
WINDOW_S = 600.0


def draw(rng):
    """One paused record: ``(model, profile as logged, first sample after the pause, sensor noise)``."""
    name = MODELS[int(rng.integers(len(MODELS)))]
    params = paper_params(name)
    model = make_model(name, dataclasses.replace(params, capacity_ah=params.capacity_ah * float(rng.uniform(0.5, 3))))
    q = model.capacity_ah
    dt = float(rng.choice([0.1, 0.5, 1.0, 2.0, 5.0]))
    n = int(round(rng.uniform(1800.0, 7200.0) / dt))
    mean = rng.uniform(0.4, 0.8) * 3600.0 * q / (n * dt)
    spread = rng.uniform(0.3, 0.9)
    cur = []
    while len(cur) < n:
        cur += [mean * (1.0 + rng.normal(0.0, spread))] * int(max(1, round(rng.uniform(1.0, 30.0) / dt)))
    cur = np.asarray(cur[:n])
    t = np.arange(n) * dt
    truth = model.simulate(Profile(t, cur, meta=ProfileMeta(capacity_ah=q)), soc0=float(rng.uniform(0.85, 1.0)),
                           segments=False)
    gap_n = int(round(rng.uniform(60.0, 1200.0) / dt))
    a = int(rng.uniform(0.2, 0.6) * (n - gap_n))
    keep = np.r_[0:a, a + gap_n:n]
    noise = SensorNoise(voltage_sd=float(rng.uniform(0.001, 0.005)), current_sd=float(rng.uniform(0.0, 0.01)) * q)
    prof = Profile(t[keep], cur[keep] + rng.normal(0.0, noise.current_sd, keep.size),
                   voltage_v=truth.voltage_v[keep] + rng.normal(0.0, noise.voltage_sd, keep.size),
                   soc_ref=np.clip(truth.soc[keep], 0.0, 1.0), meta=ProfileMeta(name="paused", capacity_ah=q))
    return model, prof, a, noise


#: the rules compared on measured currents: label → hold_var options
RULES = {"now (filters' default)": {},
         "first rule (30 s windows, always cut at the largest change)": {"window_s": 30.0, "dominant": 0.0}}
#: the measured records whose current is cut (glob patterns under SOCBENCH_DATA_DIR)
MEASURED = ("panasonic_18650pf/*/*US06*.mat", "panasonic_18650pf/*/*HWFT*.mat", "panasonic_18650pf/*/*LA92*.mat",
            "panasonic_18650pf/*/*_NN_*.mat", "panasonic_18650pf/*/*Cycle_*.mat",
            "calce_a123_lfp/A1-00x_*_from_full.csv", "uav_dji_m100/battery_telemetry_all_flights.csv")
CLEAR_S = 300.0


def measured_pauses(n: int, rng):
    """``{rule: z (n,)}``: |mean current over a dropped window − held sample| / hold SD for ``n`` pauses cut into the
    measured currents (inf where the hold reads no variance), and the number of records drawn from."""
    import glob
    import os

    from socbench.datasets import load

    root = os.environ.get("SOCBENCH_DATA_DIR")
    if not root:
        raise SystemExit("--measured needs SOCBENCH_DATA_DIR (the measured records)")
    records = []
    for pattern in MEASURED:
        for f in sorted(glob.glob(str(Path(root) / pattern))):
            p = load(f)
            records.append((np.asarray(p.time_s, float), np.asarray(p.current_a, float)))
    z = {rule: [] for rule in RULES}
    while len(z[next(iter(RULES))]) < n:
        t, cur = records[int(rng.integers(len(records)))]
        step = float(np.median(np.diff(t)))
        span = float(rng.uniform(60.0, 1200.0))
        s = int(np.searchsorted(t, t[0] + CLEAR_S + rng.uniform(0.0, max(t[-1] - t[0] - 2 * CLEAR_S - span, 0.0))))
        e = int(np.searchsorted(t, t[s] + span))
        lo, hi = np.searchsorted(t, t[s] - CLEAR_S), np.searchsorted(t, t[e] + CLEAR_S)
        if s < 1 or hi >= t.size or np.any(np.diff(t[lo:hi]) > segments.GAP_FACTOR * step):
            continue  # too near an end, or a gap of the record's own nearby: draw again
        mean = float(np.sum(cur[s - 1:e] * np.diff(t[s - 1:e + 1])) / (t[e] - t[s - 1]))
        keep = np.r_[0:s, e:t.size]
        prof = Profile(t[keep], cur[keep], meta=ProfileMeta(capacity_ah=1.0))
        for rule, opts in RULES.items():
            var = float(segments.hold_var(prof, **opts)[s - 1])
            z[rule].append(abs(mean - cur[s - 1]) / np.sqrt(var) if var > 0 else np.inf)
    return {rule: np.asarray(v) for rule, v in z.items()}, len(records)


def score(est, prof, a):
    k = (prof.time_s >= prof.time_s[a]) & (prof.time_s < prof.time_s[a] + WINDOW_S)
    err = est.soc[0, k] - prof.soc_ref[k]
    return float(np.mean(np.abs(err) <= 3.0 * est.soc_std[0, k])), float(np.sqrt(np.mean(err**2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=60)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--measured", type=int, default=0, help="also cut this many pauses into measured currents")
    ap.add_argument("--md", default=None, help="write the table to this markdown file")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = {(e, hold): [] for e in ESTIMATORS for hold in (True, False)}
    t0 = time.perf_counter()
    for _ in range(args.draws):
        model, prof, a, noise = draw(rng)
        z0 = float(prof.soc_ref[0])
        for e in ESTIMATORS:
            opts = {"n_particles": 500} if e == "pf" else {}
            for hold in (True, False):
                est = make_estimator(e, model, noise, hold=hold, **opts).run(prof, soc0=z0, P0=1e-6, seed=0,
                                                                             segments=False)
                rows[(e, hold)].append(score(est, prof, a))
    measured = measured_pauses(args.measured, np.random.default_rng(args.seed)) if args.measured else None
    wall = time.perf_counter() - t0
    lines = [
        "# Filters across a logger pause",
        "",
        f"*Generated by `python benchmarks/logger_pause.py --draws {args.draws} --seed {args.seed}"
        f"{f' --measured {args.measured}' if args.measured else ''}"
        f"{' --md ' + args.md if args.md else ''}` in {wall:.0f} s (Python {platform.python_version()}); every number "
        "below comes from that run.*",
        "",
        __doc__.split("\n\n")[1].replace("\n", " "),
        "",
        f"| estimator | hold's variance | draws with ≥ 90 % of the {WINDOW_S / 60:.0f} min after the pause within 3σ | "
        "mean fraction within 3σ | median SOC RMSE after the pause [%] | worst [%] |",
        "|---|---|---|---|---|---|",
    ]
    for e in ESTIMATORS if args.draws else ():
        for hold in (True, False):
            cov = np.array([c for c, _ in rows[(e, hold)]])
            rmse = np.array([r for _, r in rows[(e, hold)]])
            lines.append(f"| {e} | {'yes' if hold else 'no (before)'} | {int(np.sum(cov >= 0.9))}/{cov.size} = "
                         f"{100 * np.mean(cov >= 0.9):.0f} % | {cov.mean():.3f} | {100 * np.median(rmse):.3f} | "
                         f"{100 * rmse.max():.2f} |")
    if measured is not None:
        z, n_records = measured
        lines += ["", "## Pauses cut into measured currents", "", __doc__.split("\n\n")[2].replace("\n", " "), "",
                  f"{args.measured} pauses drawn from {n_records} records.", "",
                  "| rule | within 1 SD | within 2 SD | within 3 SD | no variance read |", "|---|---|---|---|---|",
                  "| a calibrated SD | 68 % | 95 % | 99.7 % | 0 % |"]
        for rule, v in z.items():
            lines.append(f"| {rule} | " + " | ".join(f"{100 * np.mean(v <= k):.1f} %" for k in (1, 2, 3))
                         + f" | {100 * np.mean(~np.isfinite(v)):.1f} % |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.md:
        Path(args.md).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
