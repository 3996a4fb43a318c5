"""The ORNL Nissan Leaf cell, a record socbench was not built on: `socbench fit` on its HPPCs at 10, 25 and 40 °C, and
the 25 °C fit on the cell's 1C, 2C and 3C discharges (docs/nissan_leaf.md).

    python benchmarks/nissan_leaf.py [--json OUT.json] [--doc docs/nissan_leaf.md]
                                     [--before BEFORE.json --before-label TEXT]

Data: G. Wiggins, S. Allu, H. Wang, *Battery cell data from a 2013 Nissan Leaf*, Oak Ridge National Laboratory,
batterysim/nissan-leaf-data (`nissan_leaf_ornl/PROVENANCE.md`): a 33.1 Ah LMO/LNO–graphite pouch cell. Its HPPC files
are shaped unlike the Panasonic ones the project grew up on: each starts *empty* and charges to full at 10 A before the
test (30 s discharge pulse at 30 A, 40 s rest, 10 s charge pulse at 22.5 A, 10 % steps at 10 A, 1 h rests), samples
every 0.5–60 s, and has no temperature column (the file's ambient is used).

What is run, as a user would:

1. ``socbench fit --data HPPC --model M --mode MODE`` on each HPPC (subprocess), M in thevenin, dp, nrc, MODE paper and
   lookup: the fit's RMSE over the samples it fits, and the share of the record it left out;
2. the 25 °C fits, open loop on every discharge of the 1C/2C/3C files (each from the rest after its CC-CV charge, at
   the reference SOC there; RMSE where the reference SOC is at least 0.1, above the knee the HPPC's lowest rest point
   sits at): a record no fit saw;
3. ``socbench fit --data HPPC10 HPPC25 HPPC40 --model dp`` (the three-temperature tables) through the command line.

``--before`` reads the JSON of the same script run on an older commit and shows its numbers beside (the doc says which
commit).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MODELS = ("thevenin", "dp", "nrc")
MODES = ("paper", "lookup")
TEMPS = (10, 25, 40)
DISCHARGES = {"1C": "discharge_1C_bitrode.csv", "2C": "discharge_2C_bitrode.csv", "3C": "discharge_3C_bitrode.csv"}
#: discharges are scored where the reference SOC is at least this (the HPPC's lowest rest point is near 0.06)
SCORE_SOC_MIN = 0.1
#: a discharge segment: current above this [A] (the 1C/2C/3C steps are 30.6/61.2/91.8 A)
DISCHARGE_A = 5.0
CITE = ("G. Wiggins, S. Allu, H. Wang, *Battery cell data from a 2013 Nissan Leaf*, Oak Ridge National Laboratory, "
        "batterysim/nissan-leaf-data, MIT licence (`nissan_leaf_ornl/PROVENANCE.md`)")


def data_dir(folder: str = "nissan_leaf_ornl") -> Path:
    """``folder`` of the measured data (``SOCBENCH_DATA_DIR``); exits with one line when that is not set."""
    d = os.environ.get("SOCBENCH_DATA_DIR")
    if not d:
        sys.exit("SOCBENCH_DATA_DIR is not set (the measured data folder)")
    return Path(d) / folder


def cli(args, out: Path):
    """``socbench ARGS`` in a subprocess run from ``out``'s folder (a PYTHONPATH given — an older checkout, --before —
    then decides which socbench runs): ``(completed process, wall time [s], error line or None)``."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "socbench.cli", *map(str, args)], cwd=out.parent,
                          capture_output=True, text=True)
    error = None if done.returncode == 0 else (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
    return done, time.perf_counter() - t0, error


def cli_fit(files, model: str, mode: str, out: Path) -> dict:
    """``socbench fit`` in a subprocess: its PARAMS.json's ``fit`` block, the printed notes, the wall time."""
    done, wall, error = cli(["fit", "--data", *files, "--model", model, "--mode", mode, "--out", out], out)
    if error:
        return {"error": error, "wall_s": wall}
    saved = json.loads(out.read_text())
    return {"fit": saved["fit"], "notes": saved.get("notes", []), "wall_s": wall,
            "stdout": [ln for ln in done.stdout.splitlines() if "left out of the fit" in ln]}


#: the evaluation records of ``socbench diagnose --fit hppc_25degC.csv`` (section 4): the other ambients' HPPCs, which
#: start empty (a record that runs below the 25 °C HPPC's lowest rest point), and the discharge files
DIAGNOSE_EVALS = ("hppc_10degC.csv", "hppc_40degC.csv", *DISCHARGES.values())


def cli_diagnose(fit_file: Path, eval_file: Path, out: Path) -> dict:
    """``socbench diagnose --fit FIT --eval EVAL --model dp`` in a subprocess: what its ``diagnosis.json`` says."""
    _, wall, error = cli(["diagnose", "--fit", fit_file, "--eval", eval_file, "--model", "dp", "--out", out], out)
    if error:
        return {"error": error, "wall_s": wall}
    d = json.loads((out / "diagnosis.json").read_text())
    return {"added": d["effects_added"], "before_v": d["before"]["rmse_v"], "after_v": d["after"]["rmse_v"],
            "soc": {k: {"before": d["before"]["soc"][k]["soc_rmse"], "after": d["after"]["soc"][k]["soc_rmse"]}
                    for k in d["before"].get("soc", {})}, "wall_s": wall}


def discharges(profile):
    """Each discharge of a 1C/2C/3C file, from a few samples of the rest before it to its last sample."""
    on = profile.current_a > DISCHARGE_A
    edges = np.flatnonzero(np.diff(on.astype(int)))
    for a, b in zip(edges[::2], edges[1::2]):
        yield profile.slice(max(int(a) - 5, 0), int(b) + 1)


def thermocouple_max(d: Path) -> dict:
    """The warmest reading of the thermocouples during each of the 1C/2C/3C tests [°C] (their files have no clock in
    common with the tester's: only how warm the cell got is used)."""
    import pandas as pd

    out = {}
    for rate in DISCHARGES:
        t = pd.read_csv(d / f"temperature_{rate}_discharge_thermocouples.csv")
        out[rate] = float(t[[c for c in t.columns if c.startswith("tc")]].to_numpy().max())
    return out


def held_out(params_path: Path, segments: dict) -> dict:
    """Open-loop RMSE [V] of a fitted parameter set on each file's discharges (module docstring)."""
    from socbench.models import load_params, make_model

    name, params = load_params(params_path)
    m = make_model(name, params)
    out = {}
    for rate, segs in segments.items():
        sq, n = 0.0, 0
        for s in segs:
            e = s.voltage_v - m.simulate(s, soc0=float(s.soc_ref[0])).voltage_v
            ok = np.isfinite(e) & (s.soc_ref >= SCORE_SOC_MIN)
            sq += float(np.sum(e[ok] ** 2))
            n += int(ok.sum())
        out[rate] = float(np.sqrt(sq / n)) if n else None
    return out


def run(folder: Path) -> dict:
    from socbench.datasets import load

    d = data_dir()
    hppc = {t: d / f"hppc_{t}degC.csv" for t in TEMPS}
    segments = {rate: list(discharges(load(d / f))) for rate, f in DISCHARGES.items()}
    res = {"fits": {}, "held_out": {}, "segments": {r: len(s) for r, s in segments.items()},
           "thermocouple_max_c": thermocouple_max(d)}
    for model in MODELS:
        for mode in MODES:
            for t in TEMPS:
                key = f"{model}/{mode}/{t}"
                out = folder / f"{model}_{mode}_{t}.json"
                r = cli_fit([hppc[t]], model, mode, out)
                res["fits"][key] = {"rmse_v": r["fit"]["rmse_v"] if "fit" in r else None,
                                    "n_samples": (r["fit"].get("n_samples") if "fit" in r else None),
                                    "left_out": r.get("stdout", []), "error": r.get("error"),
                                    "wall_s": r["wall_s"]}
                if t == 25 and "fit" in r:
                    res["held_out"][f"{model}/{mode}"] = held_out(out, segments)
                print(key, res["fits"][key]["rmse_v"], res["held_out"].get(f"{model}/{mode}") if t == 25 else "",
                      flush=True)
    res["diagnose"] = {}
    for name in DIAGNOSE_EVALS:
        res["diagnose"][name] = cli_diagnose(hppc[25], d / name, folder / f"diagnose_{Path(name).stem}")
        print("diagnose", name, res["diagnose"][name], flush=True)
    r = cli_fit([hppc[t] for t in TEMPS], "dp", "paper", folder / "dp_3T.json")
    res["three_temperatures"] = ({"error": r["error"]} if "error" in r else
                                 {"by_temperature": {str(b["temperature_c"]): b["rmse_v"]
                                                     for b in r["fit"]["by_temperature"]},
                                  "wall_s": r["wall_s"]})
    return res


def mv(x) -> str:
    return "—" if x is None else f"{1000 * x:.1f}"


def write_doc(path: Path, res: dict, before: dict | None, before_label: str) -> None:
    def pair(now, old):
        return mv(now) if old is None else f"{mv(old)} → **{mv(now)}**"

    b = before or {}
    w = ["# The ORNL Nissan Leaf cell: HPPCs that start empty", "",
         f"*Generated by `python benchmarks/nissan_leaf.py` on {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC"
         + (f"; the numbers before the arrows are the same script on {before_label}" if before else "")
         + ". Every fit runs through `socbench fit` in a subprocess.*", "",
         f"**Data.** {CITE}. A 33.1 Ah pouch cell; each HPPC file starts empty and charges to full at 10 A before the "
         "test, then 30 A discharge and 22.5 A charge pulses, 10 % steps at 10 A and 1 h rests; no temperature column "
         "(the file's ambient is used); each ends at 3.0 V during its last 10 A step, with no rest at the bottom. The "
         "changes below were found on this data; the Panasonic HPPCs, on which the HPPC analysis grew up, start full "
         "and rest at their bottom, and are unchanged by them.",
         "",
         "**What changed.** Earlier (68676ef), a fit learnt to leave out the samples before the test reaches "
         "full (the charge from empty, whose SOC is counted back from full through a charge of unknown "
         "coulombic efficiency: near empty a point of SOC is tens of mV of OCV) and those further than 0.02 in"
         " SOC beyond the OCV's rest points (`socbench.identify.fit.OCV_FIT_MARGIN`), with a note saying how "
         "much. Since stop 49 the OCV is continued below the lowest rest point, down to the test's most "
         "discharged point, along its last step once the step's over-potential has settled (the voltage plus "
         "the current times the lowest pulse set's pulse resistance, "
         "`socbench.identify.hppc.HPPCAnalysis.ocv_bottom_extension`), instead of along the line through the "
         "two lowest rest points (3.43 V at empty where the cell reads 3.0 V under 10 A); the curve above the "
         "lowest rest point is held as the rest points give it, and the samples below it stay out of the fit. "
         "What a record running there reads changes (section 4); the fits above it change through the samples "
         "within 0.02 below the lowest rest point, which now see the continued curve (sections 1–3). Since "
         "stop 58 the filters widen their band across a step logged slowly while the current changes "
         "(`socbench.segments.hold_var`); the diagnosis of section 4 filters each record on bins of at least 1"
         " s and at most 4000 of them (`socbench.diagnose`), on which these files' 60 s steps are no longer "
         "gaps, and the arrows (the same script on stop 57's code) show that nothing on this page moved.", "",
         "## 1. Fit RMSE over the samples fitted [mV]", "",
         "| model | mode | 10 °C | 25 °C | 40 °C |", "|---|---|---|---|---|"]
    for model in MODELS:
        for mode in MODES:
            cells = [pair(res["fits"][f"{model}/{mode}/{t}"]["rmse_v"],
                          b.get("fits", {}).get(f"{model}/{mode}/{t}", {}).get("rmse_v")) for t in TEMPS]
            w.append(f"| {model} | {mode} | " + " | ".join(cells) + " |")
    left = res["fits"]["dp/paper/25"]["left_out"]
    if left:
        w += ["", "What `socbench fit` says it left out (dp, 25 °C): "
              + "; ".join(s.strip().removeprefix("note: ") for s in left) + "."]
    w += ["", "## 2. The 25 °C fit on discharges no fit saw: open-loop RMSE [mV]", "",
          f"Each discharge of the 1C/2C/3C files ({', '.join(f'{n} × {r}' for r, n in res['segments'].items())}), "
          "from the rest after its CC-CV charge at the reference SOC there, scored where the reference SOC is at least "
          f"{SCORE_SOC_MIN:g}. The cell heats: its thermocouples reach "
          + ", ".join(f"{c:.0f} °C ({r})" for r, c in res["thermocouple_max_c"].items())
          + " (their files share no clock with the tester's, so no temperature drives the model here): the 2C and 3C "
          "columns hold a temperature error no 25 °C fit can remove.", "",
          "| model | mode | " + " | ".join(DISCHARGES) + " |", "|---|---|" + "---|" * len(DISCHARGES)]
    for model in MODELS:
        for mode in MODES:
            now = res["held_out"].get(f"{model}/{mode}", {})
            old = b.get("held_out", {}).get(f"{model}/{mode}", {})
            w.append(f"| {model} | {mode} | " + " | ".join(pair(now.get(r), old.get(r)) for r in DISCHARGES) + " |")
    if before:
        w.append("")
        for rate in DISCHARGES:
            pairs = [(res["held_out"][k].get(rate), b["held_out"][k].get(rate)) for k in res["held_out"]
                     if k in b.get("held_out", {})]
            better = sum(1 for now, old in pairs if now is not None and old is not None and now < old)
            w.append(f"- {rate}: lower in {better} of {len(pairs)} fits (median {mv(np.median([o for _, o in pairs]))}"
                     f" → {mv(np.median([n for n, _ in pairs]))} mV).")
    tt = res.get("three_temperatures", {})
    w += ["", "## 3. The three HPPCs as one temperature-aware set", "",
          "`socbench fit --data hppc_10degC.csv hppc_25degC.csv hppc_40degC.csv --model dp` (paper mode): "]
    if "error" in tt:
        w[-1] += f"failed: {tt['error']}"
    else:
        old = b.get("three_temperatures", {}).get("by_temperature", {})
        w[-1] += ("fit RMSE per temperature " + ", ".join(f"{float(t):g} °C {pair(v, old.get(t))} mV"
                                                         for t, v in tt["by_temperature"].items())
                  + f" ({tt['wall_s']:.0f} s).")
    diag = res.get("diagnose", {})
    if diag:
        bd = b.get("diagnose", {})
        w += ["", "## 4. The closed loop from the 25 °C HPPC", "",
              "`socbench diagnose --fit hppc_25degC.csv --eval FILE --model dp` on each record below (the HPPCs at 10 "
              "and 40 °C start empty, where their first minutes run below the 25 °C HPPC's lowest rest point; no "
              "record has a temperature column, so no temperature effect can be named). Held-out voltage RMSE of the "
              "base model (*before*) and after the search, and the EKF's held-out SOC RMSE.", "",
              "| evaluation record | effects named | voltage before [mV] | voltage after [mV] | EKF SOC before [%] | "
              "EKF SOC after [%] |", "|---|---|---|---|---|---|"]

        def pct(x):
            return "—" if x is None else f"{100 * x:.2f}"

        def values(r):
            ekf = r.get("soc", {}).get("ekf", {})
            return {"added": ", ".join(r["added"]) or "none", "before_v": mv(r["before_v"]),
                    "after_v": mv(r["after_v"]), "soc_before": pct(ekf.get("before")),
                    "soc_after": pct(ekf.get("after"))}

        for name, r in diag.items():
            if "error" in r:
                w.append(f"| {name} | failed: {r['error']} | | | | |")
                continue
            now = values(r)
            old = values(bd[name]) if name in bd and "error" not in bd[name] else None
            cells = [now[k] if old is None else f"{old[k]} → **{now[k]}**" for k in now]
            w.append(f"| {name} | " + " | ".join(cells) + " |")
        both = [(r, bd[n]) for n, r in diag.items() if "error" not in r and "error" not in bd.get(n, {"error": 1})]
        if both:
            def lower(key, sub=None):
                get = (lambda x: x["soc"]["ekf"][sub]) if sub else (lambda x: x[key])
                return sum(get(r) < get(o) for r, o in both)

            w += ["", f"Against the code before: the base model's voltage error lower on {lower('before_v')} of "
                  f"{len(both)} records, after the search on {lower('after_v')}; the EKF's SOC error after the search "
                  f"lower on {lower(None, 'after')}."]
    w += ["", "## What this does not show", "",
          "- The temperature tables' interpolation on this cell: no record here has a known temperature between the "
          "HPPCs' (the C/15 cycling file does not say which cycle ran at which ambient).",
          "- The filters: the discharges are constant-current, where the SOC a filter reads is the OCV's under a "
          "constant over-potential; the Panasonic drive cycles (docs/real_data.md) are the filters' test.", ""]
    path.write_text("\n".join(w))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=str(REPO / "docs" / "nissan_leaf.json"))
    ap.add_argument("--doc", default=str(REPO / "docs" / "nissan_leaf.md"))
    ap.add_argument("--before", default=None, help="JSON of this script on an older commit, shown beside")
    ap.add_argument("--before-label", default="an older commit")
    ap.add_argument("--no-doc", action="store_true", help="write the JSON only")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="socbench-leaf-") as tmp:
        res = run(Path(tmp))
    Path(args.json).write_text(json.dumps(res, indent=1))
    if not args.no_doc:
        before = json.loads(Path(args.before).read_text()) if args.before else None
        write_doc(Path(args.doc), res, before, args.before_label)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
