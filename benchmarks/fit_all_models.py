"""Time fitting every registered model on the Panasonic 18650PF 25 °C HPPC (Kollmeyer 2018, doi:10.17632/wykht8y7tg.1).

One process, models one after the other, ``--repeats`` fits per model; reports the median seconds per model and their
sum (the time to fit every model once). Loading the file is not timed.

    SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/fit_all_models.py [--mode paper] [--repeats 3] \
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from socbench.datasets import load  # noqa: E402
from socbench.identify import fit_model, ocv_from_hppc  # noqa: E402
from socbench.models import model_names  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=os.environ.get("SOCBENCH_DATA_DIR"))
    ap.add_argument("--mode", default="paper", choices=("paper", "constant", "lookup"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--models", default=None, help="comma-separated subset (default: every registered model)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if not args.data_dir:
        raise SystemExit("set SOCBENCH_DATA_DIR or pass --data-dir")
    folder = Path(args.data_dir) / "panasonic_18650pf" / "25degC"
    path = sorted(folder.glob("*HPPC*.mat"))[0]
    hppc = load(path, "panasonic-mat")
    ocv = ocv_from_hppc(hppc)  # shared by every model, as in the paper; built once, not timed
    names = args.models.split(",") if args.models else model_names()
    load_start = os.getloadavg()[0]
    out = {}
    for name in names:
        secs, res = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = fit_model(name, hppc, mode=args.mode, ocv=ocv)
            secs.append(time.perf_counter() - t0)
        out[name] = {"median_s": float(np.median(secs)), "runs_s": secs, "rmse_v": res.rmse_v,
                     "n_params": len(res.values), "n_samples": res.n_samples,
                     "simulations": res.lsq.nsim if res.lsq is not None else None}
        print(f"{name:12s} {out[name]['median_s']:6.2f} s (median of {args.repeats})  "
              f"{out[name]['simulations']} simulations  fit RMS {1000 * res.rmse_v:.1f} mV", flush=True)
    total = float(sum(v["median_s"] for v in out.values()))
    print(f"all {len(out)} models: {total:.1f} s  (load average {load_start:.1f} at the start, {os.cpu_count()} cores)")
    if args.json:
        Path(args.json).write_text(json.dumps({"mode": args.mode, "repeats": args.repeats, "data": str(path),
                                               "models": out, "total_median_s": total, "load_start": load_start,
                                               "cpu_count": os.cpu_count()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
