"""Wall time of the default leaderboard study (`socbench leaderboard` with no study options), from an empty store.

    python benchmarks/default_leaderboard.py [--backend process] [--jobs 2] [--out DIR] [--json OUT.json]

Runs the real command in a subprocess (what a user types), into a fresh output folder unless ``--out`` names one that
already holds a store (then it measures a resume). Prints the wall time and the study's own summary; ``--json`` also
writes ``{"seconds", "cpu_seconds", "backend", "jobs", "cells", "computed", "reused", "failed_runs", "cpu_count",
"loadavg"}`` (``cpu_seconds``: user + system time of the command and its worker processes, the figure least inflated
by other jobs on a shared machine; on idle cores the wall time is about ``cpu_seconds / cores`` plus serial parts).
Speed targets live here, never in timed tests (the machines are shared and noisy): the load average before and after
is reported so a slow figure on a busy machine can be read as such.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def breakdown(store: Path) -> dict:
    """Worker time spent on fits and on cells, from the records in the store (complete or not)."""

    def seconds(kind):
        out = []
        for p in (store / kind).glob("*.json"):
            try:
                out.append(float(json.loads(p.read_text()).get("seconds") or 0.0))
            except (json.JSONDecodeError, OSError):
                continue
        return out

    fits, cells = seconds("fits"), seconds("cells")
    return {"fits": len(fits), "fit_seconds": sum(fits), "fit_max_seconds": max(fits, default=0.0),
            "cells": len(cells), "cell_seconds": sum(cells)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default=None, help="leaderboard --backend (default: the command's default)")
    ap.add_argument("--jobs", type=int, default=None, help="leaderboard --jobs (default: the command's default)")
    ap.add_argument("--out", default=None, help="output folder (default: a new temporary folder)")
    ap.add_argument("--json", default=None, help="write the measurement here")
    ap.add_argument("extra", nargs=argparse.REMAINDER, help="more leaderboard options after --")
    args = ap.parse_args(argv)

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="socbench-default-leaderboard-"))
    cmd = [sys.executable, "-m", "socbench.cli", "leaderboard", "--out", str(out)]
    if args.backend:
        cmd += ["--backend", args.backend]
    if args.jobs:
        cmd += ["--jobs", str(args.jobs)]
    cmd += [a for a in args.extra if a != "--"]
    load_before = os.getloadavg()
    print("$", " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run(cmd)
    seconds = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # CPU seconds of the command and every worker process it waited for: the figure a busy machine inflates least
    cpu_s = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    load_after = os.getloadavg()
    work = breakdown(out / "store")
    print(f"work in the store: {work['fits']} fits, {work['fit_seconds']:.0f} s "
          f"(max {work['fit_max_seconds']:.0f} s); {work['cells']} cells, {work['cell_seconds']:.0f} s "
          f"(worker seconds, summed over workers)")
    if proc.returncode != 0:
        print(f"leaderboard exited {proc.returncode} after {seconds:.1f} s (rerun the same command to resume)",
              file=sys.stderr)
        return proc.returncode

    logs = sorted((out / "store" / "runs").glob("*.json"), key=lambda p: p.stat().st_mtime)
    last = json.loads(logs[-1].read_text()) if logs else {}
    import pandas as pd

    table = pd.read_csv(out / "leaderboard.csv")
    result = {
        "seconds": seconds,
        "cpu_seconds": cpu_s,
        "backend": last.get("backend"),
        "jobs": last.get("jobs"),
        "cells": int(len(table)),
        "computed": len(last.get("computed", [])),
        "reused": len(last.get("reused", [])),
        "failed_runs": int(table["failed_runs"].sum()),
        "runs": int(table["n_runs"].sum()),
        "cpu_count": os.cpu_count(),
        "loadavg": {"before": load_before, "after": load_after},
        "out": str(out),
        "work": work,
    }
    print(f"default leaderboard: {seconds:.1f} s wall, {cpu_s:.1f} CPU-s ({result['backend']} backend, "
          f"{result['jobs']} jobs, {result['cells']} cells, {result['computed']} computed, {result['reused']} reused; "
          f"load average {load_before[0]:.1f} before, {load_after[0]:.1f} after; {os.cpu_count()} cores)")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
