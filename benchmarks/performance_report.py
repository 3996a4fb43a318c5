"""The figures of docs/performance.md from a `socbench bench` JSON: the scaling plot and the Markdown tables.

    python -m socbench.cli bench --json docs/performance_bench.json --estimators ekf,ukf,pf
    python benchmarks/performance_report.py docs/performance_bench.json [--figure docs/figures/scaling_vs_filterpy.png]

Reads only the JSON (every number in the tables is a median the bench measured; ratios are of timings taken side by
side in one process), draws µs per run-step against runs for each filter with one line per engine (the bare filterpy
loop, socbench numpy, socbench compiled), and prints the tables docs/performance.md shows.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ENGINES = ("bare filterpy", "socbench numpy", "socbench compiled")
STYLE = {"bare filterpy": ("k", "o", "--"), "socbench numpy": ("tab:blue", "s", "-"),
         "socbench compiled": ("tab:red", "^", "-")}
FILTERS = ("ekf", "ukf", "pf")


def plot(res: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in FILTERS if f"{n}_scaling_rows" in res]
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.6), sharey=True)
    axes = [axes] if len(names) == 1 else axes
    for ax, name in zip(axes, names):
        rows = res[f"{name}_scaling_rows"]
        for engine in ENGINES:
            pts = sorted((r["runs"], r["us_per_run_step"]) for r in rows if r["engine"] == engine)
            color, marker, ls = STYLE[engine]
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], ls, color=color, marker=marker, label=engine)
        title = name.upper() + (f" ({rows[0]['particles']} particles)" if name == "pf" else "")
        ax.set_title(title)
        ax.set_xlabel("runs in the batch")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("µs per run-step (median wall)")
    axes[0].legend(fontsize=8)
    m = res["machine"]
    fig.suptitle(f"dp model, one run-step = one sample of one Monte Carlo run; {m['cpu_count']} cores, load "
                 f"{m['loadavg'][0]:.1f} → {m.get('loadavg_after', [float('nan')])[0]:.1f}", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)


def tables(res: dict, source: str) -> str:
    lines = []
    for name in (n for n in FILTERS if f"{n}_scaling_rows" in res):
        bare = res[f"{name}_bare_us_per_step"]
        comp = res[f"{name}_compiled_us_per_run_step"]
        nump = res[f"{name}_numpy_us_per_run_step"]
        lines.append(f"**{name.upper()}** — bare filterpy loop {bare:.1f} µs per step "
                     f"(`{source}`, key `{name}_bare_us_per_step`)\n")
        lines.append("| runs | compiled µs/run-step | × bare filterpy | numpy µs/run-step | × bare filterpy |")
        lines.append("|---:|---:|---:|---:|---:|")
        for R in comp:
            lines.append(f"| {R} | {comp[R]:.3g} | {bare / comp[R]:.0f}× | {nump[R]:.3g} | {bare / nump[R]:.2g}× |")
        lines.append("")
    first = res.get("first_call_s") or {}
    cold = res.get("cold_compile")
    if cold:
        lines.append(f"Cold compile of every kernel (empty cache, fresh process): {cold['wall_s']:.0f} s wall, "
                     f"{cold['cpu_s']:.0f} CPU-s (`cold_compile`); loading them from the cache in a new process: "
                     f"{first.get('total', float('nan')):.1f} s (`first_call_s.total`).")
    us06 = res.get("estimate_us06_s")
    if us06:
        lines.append(f"`socbench estimate` on {us06['data']} (whole command in a subprocess, kernels from the cache): "
                     f"EKF {us06['ekf']:.2f} s, UKF {us06['ukf']:.2f} s (`estimate_us06_s`).")
    if res.get("default_leaderboard_s") is not None:
        lines.append(f"Default leaderboard from an empty store: {res['default_leaderboard_s']:.1f} s wall "
                     f"(`default_leaderboard_s`; {res.get('default_leaderboard_summary', '')}).")
    if "fit_all_models_s" in res:
        lines.append(f"Fitting every model ({res['fit_effort']} effort, {res['fit_data']}): "
                     f"{res['fit_all_models_s']:.1f} s (`fit_all_models_s`).")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", help="a socbench bench JSON")
    ap.add_argument("--figure", default="docs/figures/scaling_vs_filterpy.png")
    args = ap.parse_args(argv)
    res = json.loads(Path(args.json).read_text())
    plot(res, Path(args.figure))
    print(tables(res, f"socbench bench --json {args.json}"))
    print(f"\nwrote {args.figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
