"""The H∞ filter on fast records, with and without its prior cap (and the EKF beside it).

Each draw: the paper's DP, PNGV or GNL pack (its own truth), 30 min of random current steps sampled every 0.1, 0.2,
0.5 or 1 s, 5–30 mV voltage noise and 1 % C current noise; every filter starts 5–20 points off with SD 0.1 and the
sensor noise. Reported per filter: draws whose second-half SOC RMSE is above 2 %, and the median.

    python benchmarks/hinf_fast_records.py --draws 30 --seed 2
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from socbench.estimators import SensorNoise, make_estimator
from socbench.models import make_model, paper_params
from socbench.profile import Profile, ProfileMeta

FILTERS = (("ekf", {}), ("hinf", {"prior_cap": False}), ("hinf", {"prior_cap": True}))


def draw(rng):
    """``(model, profile, true SOC, sensor noise, filter start)`` of one draw (module docstring)."""
    name = str(rng.choice(["dp", "pngv", "gnl"]))
    m = make_model(name, paper_params(name))
    dt = float(rng.choice([0.1, 0.2, 0.5, 1.0]))
    n = int(1800 / dt)
    t = np.arange(n) * dt
    q = m.capacity_ah
    cur = np.repeat(rng.uniform(-0.3, 1.5, n // 50 + 1), 50)[:n] * q
    sim = m.simulate(Profile(t, cur, meta=ProfileMeta(capacity_ah=q)), soc0=rng.uniform(0.5, 0.95), segments=False)
    vsd = rng.uniform(0.005, 0.03)
    p = Profile(t, cur + rng.normal(0, 0.01 * q, n), sim.voltage_v + rng.normal(0, vsd, n), soc_ref=sim.soc,
                meta=ProfileMeta(capacity_ah=q))
    s0 = float(np.clip(sim.soc[0] + rng.choice([-1, 1]) * rng.uniform(0.05, 0.2), 0, 1))
    return m, p, sim.soc, SensorNoise(voltage_sd=vsd, current_sd=0.01 * q), s0


def second_half_rmse(est, z) -> float:
    h = z.size // 2
    return float(np.sqrt(np.mean((est.soc[0, h:] - z[h:]) ** 2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--seed", type=int, default=2)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    out = {k: [] for k in range(len(FILTERS))}
    t0 = time.perf_counter()
    for _ in range(args.draws):
        m, p, z, noise, s0 = draw(rng)
        for k, (name, opts) in enumerate(FILTERS):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est = make_estimator(name, m, noise, soc0_sd=0.1, **opts).run(p, soc0=s0, segments=False)
            out[k].append(second_half_rmse(est, z))
    print(f"Command: `python benchmarks/hinf_fast_records.py --draws {args.draws} --seed {args.seed}` "
          f"({time.perf_counter() - t0:.0f} s)\n")
    print("| filter | second-half SOC RMSE > 2 % | median |")
    print("|---|---|---|")
    for k, (name, opts) in enumerate(FILTERS):
        e = np.asarray(out[k])
        label = name + "".join(f", {a}={b}" for a, b in opts.items())
        print(f"| {label} | {int(np.sum(e > 0.02))}/{e.size} | {100 * np.median(e):.2f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
