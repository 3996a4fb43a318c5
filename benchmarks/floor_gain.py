"""The null distribution behind the search's ``FLOOR_GAIN``: how much an effect cuts the held-out error at the noise
floor when the data hold no effect at all.

    python benchmarks/floor_gain.py --seeds 9101 9102 9103 9104 9105 --jobs 2 --json /tmp/floor_gain.json

Runs the null cases (no hidden effect) of the randomised generator (:mod:`socbench.diagnose.randomized`, 40 of every
200 indices) of seeds that neither the tests nor the benchmark's reported runs use, with the floor stopping the search
as it did before the rule (``FLOOR_GAIN = None`` in this script's processes only). Each case's statistic: in every
round whose held-out RMSE stood at or below the floor (``NOISE_FLOOR`` × the binned noise measured at the start,
``NOISE_FLOOR_REFIT`` × once the base refit was adopted), the largest relative cut of the held-out RMSE that any
effect fitted there made (the base refit excluded); −1 where no round stood at the floor or no effect scored above
zero there. Prints the quantiles and how many cases each share would let an effect through; ``FLOOR_GAIN`` is the
99th percentile, rounded up to 0.05.

Every finished case is appended to ``OUT.cases.jsonl`` at once; ``--resume`` keeps those already there.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core per worker
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from socbench.diagnose import search  # noqa: E402
from socbench.diagnose.randomized import case_kind, draw_case, run_case  # noqa: E402

QUANTILES = (0.5, 0.9, 0.95, 0.99, 1.0)


def one(job) -> dict:
    import warnings

    warnings.filterwarnings("ignore")
    search.FLOOR_GAIN = None  # the floor as it was: every round at the floor is recorded, none goes on
    seed, index = job
    r = run_case(draw_case(index, seed), soc=False)
    return {"seed": seed, "index": index, "added": r.get("added"), "error": r.get("error"),
            "largest_cut_at_floor": largest_cut_at_floor(r)}


def largest_cut_at_floor(r: dict) -> float:
    """The statistic of the module docstring from a case row of :func:`~socbench.diagnose.randomized.run_case`
    (``rounds``: per round ``[effect, score, held-out RMSE after (mV), worst block]``)."""
    if r.get("error") or not r.get("noise_sd_binned"):
        return -1.0
    noise, now, steps, best = r["noise_sd_binned"], r["rmse_before"], r["steps"], -1.0
    for k, round_ in enumerate(r["rounds"]):
        if now <= search.noise_floor(noise, search.BASE_REFIT in steps[:k]):
            cuts = [1.0 - c[2] / 1000.0 / now for c in round_ if c[0] != search.BASE_REFIT and c[1] > 0]
            best = max([best, *cuts])
        adopted = [c for c in round_ if k < len(steps) and c[0] == steps[k]]
        if adopted:
            now = adopted[0][2] / 1000.0
    return float(best)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--cases", type=int, default=200, help="indices per seed (a fifth of them are null cases)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", required=True)
    ap.add_argument("--resume", action="store_true")
    args = ap.parse_args(argv)
    rows_path = Path(args.json + ".cases.jsonl")
    done = []
    if args.resume and rows_path.exists():
        done = [json.loads(line) for line in rows_path.read_text().splitlines() if line.strip()]
    have = {(r["seed"], r["index"]) for r in done}
    jobs = [(s, i) for s in args.seeds for i in range(args.cases) if case_kind(i)[0] == "null" and (s, i) not in have]
    with ProcessPoolExecutor(args.jobs) as pool, rows_path.open("a" if args.resume else "w") as out:
        for r in pool.map(one, jobs):
            out.write(json.dumps(r) + "\n")
            out.flush()
            done.append(r)
            print(f"[{len(done)}] seed {r['seed']} case {r['index']}: {r['largest_cut_at_floor']:.3f}", file=sys.stderr)
    cuts = np.array([r["largest_cut_at_floor"] for r in done])
    summary = {"seeds": args.seeds, "null_cases": len(done), "errors": sum(bool(r["error"]) for r in done),
               "added_with_the_floor": sum(bool(r["added"]) for r in done),
               "quantiles": {str(q): float(np.quantile(cuts, q)) for q in QUANTILES},
               "let_through": {f"{g:.2f}": int(np.sum(cuts >= g)) for g in (0.10, 0.15, 0.20, 0.25, 0.30)},
               "floor_gain": float(np.ceil(np.quantile(cuts, 0.99) / 0.05) * 0.05)}
    Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
