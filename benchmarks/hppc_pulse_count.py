"""Pulses counted alike on coarsely sampled HPPCs: the SOC axis of the OCV rest points with and without it.

    python benchmarks/hppc_pulse_count.py [--draws 400] [--seed 0]

Two generators that are not socbench's: ``tests/hppc_records.py`` (an exact continuous-time truth sampled at a random
phase every 0.1–10 s) and ``benchmarks/foreign_records.py`` (HPPCs of four layouts sampled every 0.1, 0.5, 1, 2, 5 or
10 s). Each draw is analysed (``socbench.identify.analyze_hppc`` with the cell's capacity) with the pulses counted
alike (``socbench.identify.hppc.pulse_count_correction``) and without (``PULSE_COUNT_MIN`` out of reach); per draw the
spread (max − min) over the OCV rest points of their SOC error against the truth: the bulge the count leaves along the
test (a constant error is the capacity's). Printed: median, 90th percentile and largest spread per sample-period band,
and the draws made better or worse by more than 0.01 point.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
import foreign_records as fr  # noqa: E402
import hppc_records as hr  # noqa: E402

import socbench.identify.hppc as hppc  # noqa: E402
from socbench.profile import Profile, ProfileMeta  # noqa: E402


def tests_generator(seed: int):
    """``(sample period s, spread function)`` of draw ``seed`` of tests/hppc_records.py."""
    rec = hr.random_hppc(seed)

    def spread():
        a = hppc.analyze_hppc(rec.profile, capacity_ah=rec.cell.capacity_ah)
        return float(np.ptp(hr.ocv_point_errors(rec, a)[0]))
    return rec.instrument.dt, spread


def foreign_generator(seed: int):
    """``(sample period s, spread function)`` of draw ``seed`` of benchmarks/foreign_records.py's HPPC."""
    r, cell, inst, dt, _, _, segs, z0 = fr.hppc_setup(seed)
    t, i, v, z = fr.measure(segs, cell, dt, z0, r, inst)
    profile = Profile(t, i, voltage_v=v, meta=ProfileMeta(name=f"foreign{seed}", source=f"foreign{seed}",
                                                          capacity_ah=cell["q"], n_series=1))

    def spread():
        a = hppc.analyze_hppc(profile, capacity_ah=cell["q"])
        ocv_rests = {float(x) for x in a.ocv_soc}
        ends = np.array([rest.stop - 1 for rest in a.rests if float(rest.soc_end) in ocv_rests])
        return float(np.ptp(a.soc[ends] - z[ends]))
    return dt, spread


def measure(generator, seeds) -> list:
    """``[(dt, spread without, spread with)]`` per draw."""
    rows = []
    default = hppc.PULSE_COUNT_MIN
    for seed in seeds:
        dt, spread = generator(seed)
        hppc.PULSE_COUNT_MIN = 10 ** 9  # the memo keys on the module's settings: analysed again
        before = spread()
        hppc.PULSE_COUNT_MIN = default
        rows.append((dt, before, spread()))
    return rows


def _stats(x) -> str:
    return f"{np.median(x):.2f} / {np.quantile(x, 0.9):.2f} / {x.max():.2f}"


def report(name: str, rows: list) -> list:
    out = [f"{name}: {len(rows)} draws", "", "| sample period | draws | spread without: median / q90 / max [points] | "
           "with: median / q90 / max | better / worse by > 0.01 point |", "|---|---|---|---|---|"]
    a = np.array(rows)
    for lo, hi in ((0.0, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, 10.01)):
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        if not m.any():
            continue
        b, w = 100 * a[m, 1], 100 * a[m, 2]
        out.append(f"| {lo:g}–{min(hi, 10):g} s | {int(m.sum())} | {_stats(b)} | {_stats(w)} | "
                   f"{int(np.sum(w < b - 0.01))} / {int(np.sum(w > b + 0.01))} |")
    return out + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    seeds = range(args.seed, args.seed + args.draws)
    lines = report("tests/hppc_records.py", measure(tests_generator, seeds))
    lines += report("benchmarks/foreign_records.py", measure(foreign_generator, seeds))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
