"""Jung & Tullu's study on real data: fit every registered model on an HPPC test, predict a held-out drive cycle.

Data: Panasonic 18650PF, 25 °C (P. Kollmeyer, Mendeley Data, doi:10.17632/wykht8y7tg.1, 2018): the 5-pulse HPPC test
is the identification record, the US06 drive cycle (10 Hz, from full charge to 2.5 V) is held out. Every model gets
the same OCV curve (the HPPC rest points, monotone PCHIP: ECM_SPEC §3.3) and the same capacity (the charge the HPPC
discharges), and is fitted in the paper's mode (SOC polynomials for models 1–6, constants for the others).

Writes ``docs/paper_reproduction.md`` (every number in it comes from this run) and ``docs/figures/paper_*.png``.

    SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/paper_reproduction.py [--jobs 2] [--models a,b]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from socbench.datasets import load  # noqa: E402
from socbench.datasets.skew import align_voltage, voltage_lag  # noqa: E402
from socbench.identify import (  # noqa: E402
    analyze_hppc,
    compress_profile,
    fit_model,
    ocv_from_slow_test,
    select_fit,
    simulate_voltage,
    unrecorded_charge,
    validation_rmse,
)
from socbench.models import make_model, model_class, model_names  # noqa: E402
from socbench.models.params import params_to_dict  # noqa: E402

CITATION = "P. Kollmeyer, *Panasonic 18650PF Li-ion Battery Data*, Mendeley Data, doi:10.17632/wykht8y7tg.1 (2018)"
PAPER = ("S. Jung and A. Tullu, *Characteristics Evaluation of 14 Battery Equivalent Circuit Models*, IEEE Access "
         "(2023), Table 4, as re-aligned in ECM_SPEC §8")
#: Jung & Tullu Table 4 as re-aligned in ECM_SPEC §8 (volts): HPPC mean, RMS, SD, max; 0 kg RMS; 10 kg RMS
PAPER_TABLE4 = {
    "rint": (-0.0004, 0.058, 0.058, 0.6699, 0.0702, 0.1221),
    "thevenin": (0.0045, 0.0380, 0.0377, 0.7575, 0.0768, 0.0897),
    "pngv": (0.0264, 0.0773, 0.0726, 0.6532, 0.1411, 0.1085),
    "dp": (0.0231, 0.0751, 0.0715, 0.6718, 0.1371, 0.1007),
    "gnl": (0.019, 0.0612, 0.0582, 0.7088, 0.1203, 0.0961),
    "improved_rc": (0.0291, 0.077, 0.0713, 0.9777, 0.1106, 0.1288),
    "shepherd": (0.0007, 0.0371, 0.0371, 0.6372, 0.0753, 0.0875),
    "unnewehr": (0.0139, 0.0414, 0.039, 0.8018, 0.0754, 0.0902),
    "nernst": (0.0117, 0.0413, 0.0396, 0.8158, 0.0749, 0.0896),
    "fang": (0.0156, 0.0419, 0.0388, 0.8079, 0.0749, 0.0911),
    "liu": (0.0153, 0.0376, 0.0343, 0.6159, 0.0733, 0.0892),
    "tremblay1": (0.0156, 0.0418, 0.0388, 0.8135, 18.4553, 36.4302),
    "tremblay2": (0.004, 0.0397, 0.0395, 0.8134, 770508.7184, 1549746.3695),
    "plett": (0.0156, 0.0377, 0.0344, 0.6472, 0.0737, 0.0889),
}
#: evaluation grid of the HPPC record: every sample of the 10 s pulses is kept at 0.1 s, rests at least every 10 s
EVAL_GRID = {"first_step_s": 0.1, "growth": 2.0, "max_step_s": 10.0}


def panasonic_files(data_dir: Path) -> dict:
    folder = data_dir / "panasonic_18650pf" / "25degC"
    if not folder.is_dir():
        folder = data_dir / "25degC"
    pick = {}
    for key, pattern in (("hppc", "*HPPC*.mat"), ("us06", "*US06*.mat"), ("c20", "*C20*OCV*.mat"),
                         ("la92", "*LA92*.mat"), ("nn", "*NN*.mat")):
        files = sorted(folder.glob(pattern))
        if not files:
            raise SystemExit(f"no {pattern} in {folder}")
        pick[key] = files[0]
    return pick


def weighted_stats(e: np.ndarray, w: np.ndarray) -> dict:
    """Mean, RMS, SD and max of ``e`` with each sample weighted by the original samples it stands for."""
    w = w / w.sum()
    mean = float(np.sum(w * e))
    rms = float(np.sqrt(np.sum(w * e * e)))
    return {"mean_v": mean, "rmse_v": rms, "sd_v": float(np.sqrt(max(rms**2 - mean**2, 0.0))),
            "max_v": float(np.max(np.abs(e)))}


def plain_stats(e: np.ndarray) -> dict:
    return {"mean_v": float(e.mean()), "rmse_v": float(np.sqrt(np.mean(e * e))), "sd_v": float(e.std(ddof=1)),
            "max_v": float(np.max(np.abs(e)))}


# ------------------------------------------------------------------------------------------------ one model
_DATA: dict = {}


def _init(files: dict) -> None:
    hppc = load(files["hppc"], "panasonic-mat")
    us06 = load(files["us06"], "panasonic-mat")
    analysis = analyze_hppc(hppc)
    ocv = analysis.ocv(source=f"HPPC rest points, Panasonic 18650PF 25 °C ({files['hppc'].name})")
    grid = compress_profile(hppc, **EVAL_GRID)
    extra = unrecorded_charge(hppc)
    cum = np.concatenate([[0.0], np.cumsum(-extra / analysis.capacity_ah)])
    jumps = np.diff(cum[grid.index + 1], prepend=0.0)
    jumps[0] = 0.0
    weight = np.diff(np.append(grid.index, hppc.n)).astype(float)  # original samples each kept sample stands for
    _DATA.update(hppc=hppc, us06=us06, ocv=ocv, grid=grid, jumps=jumps, weight=weight, capacity=analysis.capacity_ah)
    # the validation-selected study: every record with its measured channel skew removed (socbench.datasets.skew)
    lags, aligned = {}, {}
    for key, prof in (("hppc", hppc), ("us06", us06), ("la92", load(files["la92"], "panasonic-mat")),
                      ("nn", load(files["nn"], "panasonic-mat"))):
        lags[key] = voltage_lag(prof)
        aligned[key] = align_voltage(prof, lags[key].lag)
    # the HPPC shows no skew at 1 Hz (align_voltage then returns the record itself): its OCV is the one above
    aligned_ocv = ocv if aligned["hppc"] is hppc else analyze_hppc(aligned["hppc"]).ocv()
    _DATA.update(lags=lags, aligned=aligned, aligned_ocv=aligned_ocv)


def run_model(name: str) -> dict:
    d = _DATA
    t0 = time.perf_counter()
    res = fit_model(name, d["hppc"], mode="paper", ocv=d["ocv"])
    fit_s = time.perf_counter() - t0
    model = make_model(name, res.params)
    g = d["grid"].profile
    y_hppc = simulate_voltage(model, g.time_s, g.current_a, g.temperature_c, model.x0(1.0), d["jumps"])
    e_hppc = g.voltage_v - y_hppc
    t1 = time.perf_counter()
    sim = model.simulate(d["us06"], soc0=1.0)
    sim_s = time.perf_counter() - t1
    e_us06 = d["us06"].voltage_v - sim.voltage_v
    ok = np.isfinite(e_hppc).all() and np.isfinite(e_us06).all()
    return {
        "name": name,
        "fit_s": fit_s,
        "us06_sim_s": sim_s,
        "n_params": len(res.values),
        "n_samples": res.n_samples,
        "fit_rmse_v": res.rmse_v,
        "warnings": res.warnings,
        "nsim": res.lsq.nsim if res.lsq is not None else None,
        "hppc": weighted_stats(e_hppc, d["weight"]) if ok else None,
        "us06": plain_stats(e_us06) if ok else None,
        "us06_low_soc_rmse_v": float(np.sqrt(np.mean(e_us06[sim.soc < 0.15] ** 2))),
        "selected": select_on_validation(name),
        "eval_n": int(y_hppc.size),
        "us06_v": sim.voltage_v.astype(np.float32),
        "hppc_v": y_hppc.astype(np.float32),
        "params": params_to_dict(name, res.params),
    }


def select_on_validation(name: str) -> dict:
    """Fit setting chosen on LA92 + NN (skew removed), then the held-out US06 scored with and without the skew."""
    d = _DATA
    a = d["aligned"]
    t0 = time.perf_counter()
    sel = select_fit(name, a["hppc"], [a["la92"], a["nn"]], ocv=d["aligned_ocv"])
    return {"chosen": sel.chosen, "seconds": time.perf_counter() - t0,
            "validation_rmse_v": {k: sel.mean_score(k) for k in sel.scores},
            "us06_rmse_v": validation_rmse(sel.fit, a["us06"]),
            "us06_raw_rmse_v": validation_rmse(sel.fit, d["us06"])}


# ------------------------------------------------------------------------------------------------ figures
def fig_ocv(path, ocv, analysis, slow):
    z = np.linspace(0, 1, 401)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.plot(z, slow.discharge(z), color="0.6", lw=1, ls="--", label="C/20 discharge branch")
    if slow.charge is not None:
        zc = z[z <= slow.charge.soc.max()]
        ax.plot(zc, slow.charge(zc), color="0.6", lw=1, ls=":", label="C/20 charge branch")
    ax.plot(z, ocv(z), color="C0", lw=1.6, label="OCV curve (monotone PCHIP)")
    ax.plot(analysis.ocv_soc, analysis.ocv_voltage, "o", color="C3", ms=5, label="HPPC rest points")
    ax.set_xlabel("SOC")
    ax.set_ylabel("voltage [V]")
    ax.set_title("OCV of the Panasonic 18650PF at 25 °C (cf. the paper's Fig. 3)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def fig_profiles(path, us06, results, names):
    t = us06.time_s / 60
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    axes[0].plot(t, us06.voltage_v, color="k", lw=0.6, label="measured")
    for k, n in enumerate(names):
        axes[0].plot(t, results[n]["us06_v"], lw=0.6, color=f"C{k}", label=n)
    axes[0].set_ylabel("terminal voltage [V]")
    axes[0].set_title("US06 at 25 °C, held out: measured vs models fitted on the HPPC (cf. the paper's Fig. 6)")
    axes[0].legend(fontsize=8, ncol=3)
    axes[0].grid(alpha=0.3)
    axes[1].plot(t, us06.current_a, color="0.3", lw=0.4)
    axes[1].set_ylabel("current [A]\n(+ discharge)")
    axes[1].set_xlabel("time [min]")
    axes[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def fig_deviation(path, us06, results, names):
    t = us06.time_s / 60
    fig, ax = plt.subplots(figsize=(9, 4.2))
    for k, n in enumerate(names):
        ax.plot(t, us06.voltage_v - results[n]["us06_v"], lw=0.5, color=f"C{k % 10}", label=n)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_ylim(-0.4, 0.4)
    ax.set_xlabel("time [min]")
    ax.set_ylabel("measured − model [V]")
    ax.set_title("Fluctuation deviation on the held-out US06 (cf. the paper's Fig. 7)")
    ax.legend(fontsize=7, ncol=4)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def fig_times(path, times: dict, title: str):
    names = list(times)
    fig, ax = plt.subplots(figsize=(8, 3.8))
    ax.bar(names, [times[n] for n in names], color="C0")
    ax.set_ylabel("fit time [s]")
    ax.set_title(title)
    ax.tick_params(axis="x", rotation=60, labelsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ report
def rank(values: dict) -> dict:
    order = sorted(values, key=lambda k: values[k])
    return {k: i + 1 for i, k in enumerate(order)}


def spearman(a: dict, b: dict) -> float:
    keys = [k for k in a if k in b]
    ra, rb = rank({k: a[k] for k in keys}), rank({k: b[k] for k in keys})
    x = np.array([ra[k] for k in keys], float)
    y = np.array([rb[k] for k in keys], float)
    return float(np.corrcoef(x, y)[0, 1])


def mv(x) -> str:
    return "—" if x is None else f"{1000 * x:.1f}"


def write_report(out: Path, results: dict, files: dict, analysis, slow, timing: dict | None, wall_s: float,
                 jobs: int, load_start: float) -> None:
    names = [n for n in model_names() if n in results]
    ok = [n for n in names if results[n]["us06"] is not None]
    lines = []
    w = lines.append
    w("# The paper's study on real data: 16 ECMs fitted on an HPPC test, scored on a held-out US06")
    w("")
    w("*Generated by `benchmarks/paper_reproduction.py`; every number below comes from that run. "
      f"Python {platform.python_version()}, {os.cpu_count()} CPU cores shared with other jobs "
      f"(1-minute load average {load_start:.1f} when this run started).*")
    w("")
    w(f"**Data.** {CITATION}. Cell: Panasonic 18650PF, 2.9 Ah nominal (NCA). Identification record: "
      f"`{files['hppc'].name}` (25 °C, five discharge pulses of 0.5–6 C at 15 SOC levels, 1200 s rests). "
      f"Held-out record: `{files['us06'].name}` (US06 at 10 Hz from full charge to 2.5 V). Both are read with "
      "`socbench.datasets.load(path, \"panasonic-mat\")`.")
    w("")
    w(f"**Protocol (the paper's, ECM_SPEC §1, §3).** One OCV curve for every model: the "
      f"{analysis.ocv_soc.size} HPPC rest points (end of the rest before each pulse set; SOC placed with the "
      "tester's amp-hour counter, because the discharges between pulse sets are not in the file), monotone PCHIP. "
      f"One capacity: the {analysis.capacity_ah:.4f} Ah the HPPC discharges from full to empty. Each model is fitted "
      "in *paper mode* — 6th-degree SOC polynomials for models 1–6, constants for the rest (and for `esc`, `nrc`, "
      "which are not in the paper) — by bounded least squares on the voltage (`socbench.identify.fit_model`). "
      "The US06 prediction starts at SOC 1 with all dynamic states at rest.")
    w("")
    w("**Columns.** Error = measured − model, in mV (ECM_SPEC §2). *HPPC fit*: the fitted record on an evaluation "
      f"grid that keeps every 0.1 s pulse sample and rest samples at least every 10 s ({analysis_grid_n(results)} "
      "samples), each weighted by the number of original samples it stands for, so the statistics estimate those "
      "of all 102 647 samples. *US06 prediction*: all samples of the held-out record.")
    w("")
    w("## Table 4 on the Panasonic cell")
    w("")
    w("| # | model | HPPC mean | HPPC RMS | HPPC SD | HPPC max | US06 mean | US06 RMS | US06 SD | US06 max | "
      "US06 RMS, SOC < 0.15 | params | fit [s] |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n in names:
        r = results[n]
        num = getattr(model_class(n), "paper_number", None)
        h, u = r["hppc"] or {}, r["us06"] or {}
        w(f"| {num or '—'} | {n} | {mv(h.get('mean_v'))} | {mv(h.get('rmse_v'))} | {mv(h.get('sd_v'))} | "
          f"{mv(h.get('max_v'))} | {mv(u.get('mean_v'))} | **{mv(u.get('rmse_v'))}** | {mv(u.get('sd_v'))} | "
          f"{mv(u.get('max_v'))} | {mv(r['us06_low_soc_rmse_v'])} | {r['n_params']} | {r['fit_s']:.1f} |")
    w("")
    best = min(ok, key=lambda n: results[n]["us06"]["rmse_v"])
    best_h = min(ok, key=lambda n: results[n]["hppc"]["rmse_v"])
    w(f"Best on the held-out US06: **{best}**, RMS {mv(results[best]['us06']['rmse_v'])} mV "
      f"(mean {mv(results[best]['us06']['mean_v'])} mV, max {mv(results[best]['us06']['max_v'])} mV). "
      f"Best HPPC fit: **{best_h}**, RMS {mv(results[best_h]['hppc']['rmse_v'])} mV.")
    w("")
    write_selected(w, results, names)
    w("## The paper's Table 4 (for comparison)")
    w("")
    w(f"{PAPER}. A 6S 22 Ah LiPo pack (22.2 V nominal), so the volts are pack volts — about six times a cell's. "
      "Flights are two hexacopter current profiles replayed in the lab.")
    w("")
    w("| # | model | HPPC mean | HPPC RMS | HPPC SD | HPPC max | flight 0 kg RMS | flight 10 kg RMS |")
    w("|---|---|---|---|---|---|---|---|")
    for n, row in PAPER_TABLE4.items():
        num = getattr(model_class(n), "paper_number", None) if n in model_names() else None
        w(f"| {num or '—'} | {n} | {row[0]:.4f} | {row[1]:.4f} | {row[2]:.4f} | {row[3]:.4f} | {row[4]:.4g} | "
          f"{row[5]:.4g} |")
    w("")
    # ---- rankings
    paper_names = [n for n in PAPER_TABLE4 if n in ok]
    ours_h = {n: results[n]["hppc"]["rmse_v"] for n in paper_names}
    ours_u = {n: results[n]["us06"]["rmse_v"] for n in paper_names}
    pap_h = {n: PAPER_TABLE4[n][1] for n in paper_names}
    pap_f = {n: PAPER_TABLE4[n][4] for n in paper_names}
    rh, ru, ph, pf = rank(ours_h), rank(ours_u), rank(pap_h), rank(pap_f)
    w("## Rankings (the paper's 14 models, by RMS; 1 = best)")
    w("")
    w("| model | ours HPPC | paper HPPC | ours US06 | paper flight 0 kg |")
    w("|---|---|---|---|---|")
    for n in paper_names:
        w(f"| {n} | {rh[n]} | {ph[n]} | {ru[n]} | {pf[n]} |")
    w("")
    w(f"Spearman rank correlation: HPPC ours vs paper {spearman(ours_h, pap_h):+.2f}; held-out ours (US06) vs paper "
      f"(0 kg flight) {spearman(ours_u, pap_f):+.2f}.")
    w("")
    rc = [n for n in ("rint", "thevenin", "pngv", "dp", "gnl", "improved_rc") if n in ok]
    static = [n for n in ("shepherd", "unnewehr", "nernst", "fang", "liu", "tremblay1", "tremblay2", "plett")
              if n in ok]
    best_rc = min(rc, key=lambda n: results[n]["us06"]["rmse_v"]) if rc else None
    st_rms = [results[n]["us06"]["rmse_v"] for n in static]
    rint_rms = results["rint"]["us06"]["rmse_v"] if "rint" in ok else None
    w("### Where we agree and where we do not, and why")
    w("")
    if st_rms:
        spread = max(st_rms) - min(st_rms)
        if spread < 0.005:
            head = "Models 7–14 form one cluster, as in the paper."
            tail = ("The order inside such a cluster is decided by a few mV that depend on the data, not on the model "
                    "structure, so the two rankings disagreeing inside it says nothing about the models.")
        else:
            best_st = min(static, key=lambda n: results[n]["us06"]["rmse_v"])
            head = "Models 7–14 do not form one tight cluster here, unlike in the paper."
            tail = (f"Fitted on this cell their static SOC terms are not mV-level corrections any more: with "
                    f"constants fitted freely they absorb part of the polarisation that builds up at low SOC, which "
                    f"helps most where the term has the right shape ({best_st} is best of them) and not at all for "
                    f"Shepherd's `K/z`, which only acts near empty.")
        w(f"* **{head}** In OCV-curve mode they are `U_oc(z) − R0·I` plus a static SOC term (ECM_SPEC §3.4). Here "
          f"their US06 RMS spans {mv(min(st_rms))}–{mv(max(st_rms))} mV (a spread of {mv(spread)} mV)"
          + (f", Rint {mv(rint_rms)} mV" if rint_rms is not None else "")
          + "; in the paper their 0 kg RMS spans 73.3–75.4 mV (Tremblay1/2 aside) and Rint is at 70.2 mV. " + tail)
    if best_rc is not None and st_rms:
        rc_best = results[best_rc]["us06"]["rmse_v"]
        rc_dyn = [n for n in rc if n != "rint"]
        dyn_rms = [results[n]["us06"]["rmse_v"] for n in rc_dyn]
        if dyn_rms and max(dyn_rms) < min(st_rms):
            verdict = (f"**every** RC model with a polarisation branch beats every static model here "
                       f"({mv(min(dyn_rms))}–{mv(max(dyn_rms))} mV vs {mv(min(st_rms))}–{mv(max(st_rms))} mV)")
        elif dyn_rms and min(dyn_rms) < min(st_rms):
            verdict = (f"the best RC model, {best_rc} ({mv(rc_best)} mV), beats every static model "
                       f"({mv(min(st_rms))} mV and up), though not every RC model does")
        else:
            verdict = (f"the RC models do not beat the static ones here either (best RC {best_rc}: {mv(rc_best)} mV, "
                       f"best static {mv(min(st_rms))} mV)")
        w(f"* **RC models against static models: this is where the rankings part.** The paper ranks its RC models "
          f"with SOC polynomials (PNGV, DP, GNL, improved RC) *worst* on the flights (0.10–0.14 V RMS against "
          f"0.073–0.077 V); on this cell {verdict}. A US06 discharge lasts 80 min and builds up a slow (diffusion) "
          "polarisation that only a model with an RC branch can carry; a static term cannot. The paper's RC fits "
          "were also hurt by defects ECM_SPEC documents: the `C0` integrator that double-counts the OCV decline "
          "(43–74 V of drift over a full discharge, §5.3; disabled here), the improved-RC equations with a "
          "KCL-breaking term and negative capacitances (§5.6; corrected here, positivity enforced by the fit), and "
          "polynomial coefficients that barely moved from the initial guess (PNGV `C0`).")
    w("* **Identical rows are expected.** With the `C0` integrator disabled (ECM_SPEC §5.3) PNGV is a Thevenin and "
      "GNL a DP, and Liu is the same Tremblay-2009 structure as Tremblay2 (§0 item 16): fitted on the same data "
      "they reach the same optimum, which the paper's differing rows for these pairs could not show.")
    w("* **Tremblay1/2 diverge in the paper, not here.** The paper evaluates `Q − I_L·t` with the instantaneous "
      "current times time, which crosses zero on a flight and gives its 18 V to 1.5 MV errors; socbench uses the "
      "integrated charge `it = Q(1 − z)` (ECM_SPEC §0 items 5–6), and both models behave like their neighbours.")
    w("* **HPPC column.** The HPPC maxima are many times the RMS: they sit in the last pulse sets (SOC < 0.1, see "
      "the HPPC deviation figure), where the cell's resistance rises steeply and the 4 C and 6 C pulses run into "
      "the 2.5 V limit. The rank correlation with the paper's HPPC column is weak or negative: the static models "
      "that rank best on the paper's pack rank in the lower half here, and the SOC-polynomial RC models, which the "
      "paper ranks last, rank first.")
    w("* **What is not comparable.** Different battery (one 2.9 Ah NCA cell vs a 22 Ah 6S LiPo pack), a drive cycle "
      "instead of a flight, 25 °C with the cell warming by several kelvin during US06, a different fitting tool "
      "(scipy `least_squares`, trust-region reflective, vs MATLAB Parameter Estimator). Absolute numbers are not "
      "comparable; the rankings are the comparison.")
    w("")
    # ---- identifiability
    w("## Fit diagnostics")
    w("")
    w("Standard errors from `(JᵀJ)⁻¹·s²` at the optimum (optimistic: the residuals are autocorrelated). Warnings "
      "list parameters with a standard error above 100 % of their value, parameters at a bound of the search range "
      "and parameter pairs with |correlation| > 0.99.")
    w("")
    w("| model | simulations | fitted samples | fit RMS [mV] | warnings (first two) |")
    w("|---|---|---|---|---|")
    for n in names:
        r = results[n]
        ws = "; ".join(r["warnings"][:2]) + (f" (+{len(r['warnings']) - 2} more)" if len(r["warnings"]) > 2 else "")
        w(f"| {n} | {r['nsim']} | {r['n_samples']} | {mv(r['fit_rmse_v'])} | {ws or 'none'} |")
    w("")
    # ---- timing
    w("## Fit times")
    w("")
    fit_total = sum(results[n]["fit_s"] for n in names)
    w(f"In this run ({jobs} worker process{'es' if jobs > 1 else ''}) fitting all {len(names)} models took "
      f"{fit_total:.0f} s of fit time (sum over models) and the whole study {wall_s:.0f} s of wall time, including "
      "the 48 061-step US06 simulations. "
      + ("That is within the one-minute target for fitting every model."
         if fit_total <= 60 else
         f"That is **{fit_total / 60:.0f}× the one-minute target** for fitting every model: the machine's two cores "
         f"were shared with other jobs (load average {load_start:.1f}, i.e. about {2 / max(load_start, 1):.0%} of a "
         "core per process), and the slowest fits are the 35-parameter polynomial ones and Fang, whose two offsets "
         "are nearly unidentifiable (many iterations)."))
    if timing and timing.get("models"):
        tm = timing["models"]
        w("")
        w(f"`benchmarks/fit_all_models.py` (one process, the median of {timing['repeats']} repeat(s) per model, "
          f"paper mode, load average {timing.get('load_start', float('nan')):.1f} at its start): **all "
          f"{len(tm)} models in {timing['total_median_s']:.1f} s** "
          f"(slowest: {max(tm, key=lambda k: tm[k]['median_s'])}, {max(v['median_s'] for v in tm.values()):.1f} s).")
    w("")
    w("![fit times](figures/paper_fit_times.png)")
    w("")
    w("How the fits are made fast: (a) the HPPC record is compressed before fitting — samples of constant current "
      "merged into longer zero-order-hold steps (exact for constant parameters, SOC steps ≤ 0.5 % otherwise), kept "
      "at 0, 1, 5, 21, 85, 341 s after every current change and then every 1200 s at most — from 102 647 to "
      f"{results[names[0]]['n_samples']} samples; (b) the finite-difference Jacobian of all P parameters is one "
      "batched simulation of P + 1 parameter variants (the SOC functions broadcast a parameter-batch axis), and "
      "every residual evaluation runs that batch, so an accepted step's Jacobian is already computed; (c) each "
      "simulation evaluates the whole record at once: the SOC path is a running sum of the current and every "
      "other state an affine recurrence given it, solved by a prefix scan (`socbench.models.recurrence`), instead "
      "of one Python-level step per sample (before/after in docs/performance.md).")
    w("")
    w("## Figures")
    w("")
    w("![OCV](figures/paper_ocv.png)")
    w("")
    w("*OCV curve with the HPPC rest points; the C/20 test's branches (its own SOC axis: "
      f"{slow.capacity_ah:.3f} Ah discharged) for reference — the rest points sit between them.*")
    w("")
    w("![US06 voltage](figures/paper_us06_voltage.png)")
    w("")
    w("![US06 deviation](figures/paper_us06_deviation.png)")
    w("")
    w("![HPPC deviation](figures/paper_hppc_deviation.png)")
    w("")
    w("## Reproduce")
    w("")
    w("```")
    w("SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/fit_all_models.py --json /tmp/fit_times.json")
    w("SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/paper_reproduction.py --timing /tmp/fit_times.json "
      f"--jobs {jobs}")
    w("```")
    out.write_text("\n".join(lines) + "\n")


def write_selected(w, results: dict, names: list) -> None:
    """The section on fits chosen by validation, with the records' channel skew removed."""
    sel = {n: results[n].get("selected") for n in names if results[n].get("selected")}
    if not sel:
        return
    lags = _DATA.get("lags", {})
    cands = list(next(iter(sel.values()))["validation_rmse_v"])
    w("## The same study with the fit setting chosen on validation cycles")
    w("")
    w("Two things the paper's protocol leaves open, settled here without looking at the US06:")
    w("")
    w("* **Channel skew.** `socbench.datasets.skew.voltage_lag` measures, at every current step, the edge resistance "
      "seen 0, 1, 2, 3 samples late. "
      + "; ".join(f"{k.upper()}: {v.describe()}" for k, v in lags.items())
      + ". The 10 Hz drive cycles pair each voltage with the current one sample (0.1 s) earlier; the 1 Hz HPPC "
      "does not show it. Every record below has its measured skew removed (`align_voltage`).")
    w("* **Fit setting.** Which samples of the HPPC the fit listens to (`socbench.identify.select.FIT_CANDIDATES`: "
      + ", ".join(f"`{c}`" for c in cands)
      + ") is chosen per model by the lowest mean open-loop RMSE on two *other* 25 °C drive cycles of the same "
      "cell, LA92 and NN (`select_fit`). The US06 is scored only after that choice.")
    w("")
    w("| model | " + " | ".join(f"validation RMS, {c}" for c in cands)
      + " | chosen | US06 RMS (skew removed) | US06 RMS (raw record) |")
    w("|---|" + "---|" * (len(cands) + 3))
    for n, r in sel.items():
        w(f"| {n} | " + " | ".join(mv(r["validation_rmse_v"][c]) for c in cands)
          + f" | {r['chosen']} | **{mv(r['us06_rmse_v'])}** | {mv(r['us06_raw_rmse_v'])} |")
    w("")
    best = min(sel, key=lambda n: sel[n]["validation_rmse_v"][sel[n]["chosen"]])
    best_us = min(sel, key=lambda n: sel[n]["us06_rmse_v"])
    verdict = ("within" if sel[best]["us06_rmse_v"] <= 0.025 else "above")
    w(f"Best on validation: **{best}** (`{sel[best]['chosen']}`, validation RMS "
      f"{mv(sel[best]['validation_rmse_v'][sel[best]['chosen']])} mV); its held-out US06 RMS is "
      f"**{mv(sel[best]['us06_rmse_v'])} mV**, {verdict} the 25 mV target "
      f"({mv(sel[best]['us06_raw_rmse_v'])} mV on the raw record with its skew). "
      + "How much such a number owes to where each fit starts: docs/fit_start_sensitivity.md (the dp `dense` fit "
      "from 15 starts). "
      + ("The best on the US06 itself is the same model." if best_us == best else
         f"The best on the US06 itself would be {best_us} ({mv(sel[best_us]['us06_rmse_v'])} mV), but choosing by "
         "the test record is not allowed here.")
      + f" Selection for all {len(sel)} models took {sum(r['seconds'] for r in sel.values()):.0f} s "
      f"({len(cands)} fits and {2 * len(cands)} validation simulations per model). "
      "`tests/test_identify.py::test_best_model_predicts_the_held_out_us06` repeats this selection and checks the "
      "25 mV bound.")
    w("")


def analysis_grid_n(results) -> str:
    n = next(iter(results.values()))["eval_n"]
    return f"{n:,}".replace(",", " ")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data-dir", default=os.environ.get("SOCBENCH_DATA_DIR"))
    ap.add_argument("--models", default=None, help="comma-separated subset (default: every registered model)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timing", default=None, help="JSON written by benchmarks/fit_all_models.py")
    ap.add_argument("--out", default=str(ROOT / "docs" / "paper_reproduction.md"))
    ap.add_argument("--json", default=None, help="also write the numbers here")
    ap.add_argument("--wall-s", type=float, default=float("nan"), help="with --report-only on a first-format file")
    ap.add_argument("--load-start", type=float, default=float("nan"), help="with --report-only on a first-format file")
    ap.add_argument("--report-only", default=None,
                    help="re-render the Markdown from a --json file of an earlier run (no fitting, figures kept)")
    args = ap.parse_args(argv)
    if not args.data_dir:
        raise SystemExit("set SOCBENCH_DATA_DIR or pass --data-dir")
    files = panasonic_files(Path(args.data_dir))
    if args.report_only:
        saved = json.loads(Path(args.report_only).read_text())
        if "results" in saved:
            results, meta = saved["results"], saved["run"]
        else:  # the first format: results only; the run facts come from its log (--wall-s, --load-start, --jobs)
            results = saved
            meta = {"wall_s": args.wall_s, "jobs": args.jobs, "load_start": args.load_start}
        if any("eval_n" not in r for r in results.values()):
            n_eval = compress_profile(load(files["hppc"], "panasonic-mat"), **EVAL_GRID).index.size
            for r in results.values():
                r.setdefault("eval_n", n_eval)
        timing = json.loads(Path(args.timing).read_text()) if args.timing and Path(args.timing).exists() else None
        if timing:
            fig_times(ROOT / "docs" / "figures" / "paper_fit_times.png",
                      {k: v["median_s"] for k, v in timing["models"].items()},
                      f"Fit time per model on the 25 °C HPPC (median of {timing['repeats']}; "
                      f"total {timing['total_median_s']:.1f} s)")
        hppc = load(files["hppc"], "panasonic-mat")
        slow = ocv_from_slow_test(load(files["c20"], "panasonic-mat"))
        write_report(Path(args.out), results, files, analyze_hppc(hppc), slow, timing, meta["wall_s"], meta["jobs"],
                     meta["load_start"])
        print(f"wrote {args.out} from {args.report_only}")
        return 0
    names = args.models.split(",") if args.models else model_names()
    load_start = os.getloadavg()[0]
    t0 = time.perf_counter()
    _init(files)
    results = {}
    if args.jobs > 1:
        with ProcessPoolExecutor(max_workers=args.jobs, initializer=_init, initargs=(files,)) as pool:
            for r in pool.map(run_model, names):
                results[r["name"]] = r
                print(f"{r['name']:12s} fit {r['fit_s']:6.1f} s  US06 RMS {mv(r['us06'] and r['us06']['rmse_v'])} mV",
                      flush=True)
    else:
        for n in names:
            r = run_model(n)
            results[n] = r
            print(f"{n:12s} fit {r['fit_s']:6.1f} s  US06 RMS {mv(r['us06'] and r['us06']['rmse_v'])} mV", flush=True)
    wall = time.perf_counter() - t0
    figs = ROOT / "docs" / "figures"
    figs.mkdir(parents=True, exist_ok=True)
    hppc, us06 = _DATA["hppc"], _DATA["us06"]
    analysis = analyze_hppc(hppc)
    slow = ocv_from_slow_test(load(files["c20"], "panasonic-mat"))
    fig_ocv(figs / "paper_ocv.png", _DATA["ocv"], analysis, slow)
    ok = [n for n in results if results[n]["us06"] is not None]
    top = sorted(ok, key=lambda n: results[n]["us06"]["rmse_v"])
    show = list(dict.fromkeys(top[:3] + [n for n in ("rint", "thevenin", "shepherd") if n in ok]))
    fig_profiles(figs / "paper_us06_voltage.png", us06, results, show)
    fig_deviation(figs / "paper_us06_deviation.png", us06, results, [n for n in model_names() if n in ok])
    # HPPC deviation on the evaluation grid
    g = _DATA["grid"].profile
    fig, ax = plt.subplots(figsize=(9, 4.2))
    for k, n in enumerate(show):
        ax.plot(g.time_s / 3600, g.voltage_v - results[n]["hppc_v"], lw=0.5, color=f"C{k}", label=n)
    ax.set_ylim(-0.5, 0.5)
    ax.set_xlabel("time [h]")
    ax.set_ylabel("measured − model [V]")
    ax.set_title("Deviation on the fitted HPPC record (the gaps between pulse sets are not in the file)")
    ax.legend(fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(figs / "paper_hppc_deviation.png", dpi=120)
    plt.close(fig)
    timing = None
    if args.timing and Path(args.timing).exists():
        timing = json.loads(Path(args.timing).read_text())
        fig_times(figs / "paper_fit_times.png", {k: v["median_s"] for k, v in timing["models"].items()},
                  f"Fit time per model on the 25 °C HPPC (median of {timing['repeats']}; "
                  f"total {timing['total_median_s']:.1f} s)")
    else:
        fig_times(figs / "paper_fit_times.png", {n: results[n]["fit_s"] for n in results},
                  f"Fit time per model on the 25 °C HPPC ({args.jobs} workers)")
    write_report(Path(args.out), results, files, analysis, slow, timing, wall, args.jobs, load_start)
    if args.json:
        slim = {n: {k: v for k, v in r.items() if k not in ("us06_v", "hppc_v")} for n, r in results.items()}
        run = {"wall_s": wall, "jobs": args.jobs, "load_start": load_start}
        Path(args.json).write_text(json.dumps({"results": slim, "run": run}, indent=1, default=float))
    print(f"wrote {args.out} ({wall:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
