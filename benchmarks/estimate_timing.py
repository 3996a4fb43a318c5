"""Where the time of `socbench estimate` goes on one measured record (docs/performance.md).

    SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/estimate_timing.py [--repeats 3] [--estimators ekf,ukf]

Fits dp on the Panasonic 18650PF 25 °C HPPC (``socbench fit``), then, for each estimator, in fresh processes: the whole
command's wall time (``python -m socbench.cli estimate …``, what a user waits for) and, inside one process, the import
of ``socbench.cli``, the first ``estimate`` call (it loads the compiled kernels from the cache: their one-off cost in
a process) and a second identical call (kernels loaded). Medians over ``--repeats`` fresh processes.
The data: Panasonic 18650PF (Kollmeyer 2018), /work/shared/data/panasonic_18650pf/PROVENANCE.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

INNER = """
import json, sys, time
t0 = time.perf_counter()
from socbench.cli import main
t1 = time.perf_counter()
args = json.loads(sys.argv[1])
main(args + ["--out", sys.argv[2] + "/a"])
t2 = time.perf_counter()
main(args + ["--out", sys.argv[2] + "/b"])
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1, "second_call_s": t3 - t2}))
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--estimators", default="ekf,ukf")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    folder = Path(os.environ.get("SOCBENCH_DATA_DIR", "")) / "panasonic_18650pf" / "25degC"
    us06, hppc = sorted(folder.glob("*US06*.mat")), sorted(folder.glob("*HPPC*.mat"))
    if not us06 or not hppc:
        print("needs SOCBENCH_DATA_DIR with panasonic_18650pf/25degC", file=sys.stderr)
        return 2
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = {"data": us06[0].name, "loadavg_before": list(os.getloadavg())}
    with tempfile.TemporaryDirectory(prefix="socbench-estimate-timing-") as tmp:
        params = Path(tmp) / "dp.json"
        subprocess.run([sys.executable, "-m", "socbench.cli", "fit", "--data", str(hppc[0]), "--model", "dp",
                        "--out", str(params)], check=True, capture_output=True, env=env)
        for name in args.estimators.split(","):
            cmd = ["estimate", "--data", str(us06[0]), "--params", str(params), "--estimator", name]
            whole, parts = [], []
            for rep in range(args.repeats):
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "socbench.cli", *cmd, "--out", f"{tmp}/{name}{rep}"],
                               check=True, capture_output=True, env=env)
                whole.append(time.perf_counter() - t0)
                p = subprocess.run([sys.executable, "-c", INNER, json.dumps(cmd), tmp], check=True,
                                   capture_output=True, text=True, env=env)
                parts.append(json.loads(p.stdout.strip().splitlines()[-1]))
            row = {"command_s": statistics.median(whole), "command_repeats_s": whole}
            for key in ("import_s", "first_call_s", "second_call_s"):
                row[key] = statistics.median(p[key] for p in parts)
            out[name] = row
            print(f"socbench estimate --estimator {name}: command {row['command_s']:.2f} s; in one process: import "
                  f"{row['import_s']:.2f} s, first call {row['first_call_s']:.2f} s (kernels loaded from the cache), "
                  f"second call {row['second_call_s']:.2f} s", flush=True)
    out["loadavg_after"] = list(os.getloadavg())
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
