"""Do the filters re-acquire the SOC from a start far off? The EKF family with and without ``gate_widen``, the UKF
beside them.

Each draw: a paper pack (Thevenin, DP or Rint, the paper's parameters), a random 1 s load for 30 min from a true SOC
of 40–95 %, 20 mV voltage noise; every filter starts at 0–20 % with an SD of 0.5 and the sensor noise alone. Reported
per filter: draws whose final SOC error is above 2 %, the median and the largest final error.

    python benchmarks/reacquire.py --draws 20 --seed 11
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from socbench.estimators import make_estimator
from socbench.models import make_model, paper_params
from socbench.profile import Profile, ProfileMeta

FILTERS = (("ekf", False), ("ekf", True), ("iekf", False), ("iekf", True), ("aekf", False), ("aekf", True),
           ("hinf", False), ("hinf", True), ("dual", False), ("dual", True), ("ukf", None))


def draw(rng, n: int = 1800):
    """``(model, profile, true SOC, filter start)`` of one draw (module docstring)."""
    name = rng.choice(["thevenin", "dp", "rint"])
    m = make_model(name, paper_params(name))
    t = np.arange(n) * 1.0
    q = m.capacity_ah
    cur = q * np.clip(0.3 + 0.5 * np.sin(t / rng.uniform(60, 400)) + 0.2 * rng.standard_normal(n), -0.5, 1.5)
    sim = m.simulate(Profile(t, cur, meta=ProfileMeta(capacity_ah=q)), soc0=rng.uniform(0.4, 0.95), segments=False)
    prof = Profile(t, cur, sim.voltage_v + rng.normal(0, 0.02, n), soc_ref=sim.soc,
                   meta=ProfileMeta(capacity_ah=q, name="drive"))
    return m, prof, sim.soc, rng.uniform(0.0, 0.2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    final = {f: [] for f in FILTERS}
    t0 = time.perf_counter()
    for _ in range(args.draws):
        m, prof, z, s0 = draw(rng)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for name, widen in FILTERS:
                opts = {} if widen is None else {"gate_widen": widen}
                est = make_estimator(name, m, soc0_sd=0.5, **opts).run(prof, soc0=s0, segments=False)
                final[(name, widen)].append(abs(float(est.soc[0, -1]) - z[-1]))
    print(f"Command: `python benchmarks/reacquire.py --draws {args.draws} --seed {args.seed}` "
          f"({time.perf_counter() - t0:.0f} s)\n")
    print("| filter | gate_widen | final error > 2 % | median final error | largest |")
    print("|---|---|---|---|---|")
    for (name, widen), errors in final.items():
        e = np.asarray(errors)
        print(f"| {name} | {'–' if widen is None else ('on' if widen else 'off')} | {int(np.sum(e > 0.02))}/{e.size} "
              f"| {100 * np.median(e):.2f} % | {100 * e.max():.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
