"""`socbench leaderboard` end to end on the real pieces: interrupt and resume, outputs, user errors.

The grid is small (2 models × 3 estimators × 1 scenario × 2 seeds); the two real fits are most of its time.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from socbench.cli import main

GRID = ["--models", "rint,shepherd", "--estimators", "coulomb,ekf,ukf", "--scenarios", "flight-10kg", "--seeds", "2"]
N_CELLS = 6
COLUMNS = ["model", "estimator", "scenario", "n_runs", "soc_rmse", "soc_max_abs", "v_mean", "v_rmse", "v_sd", "v_max",
           "nis_mean", "nees_mean", "frac_within_3sigma", "us_per_step", "failed_runs", "out_of_domain"]
REPO = Path(__file__).resolve().parents[1]


def command(out, *extra):
    return [sys.executable, "-m", "socbench.cli", "leaderboard", *GRID, "--out", str(out), *extra]


def env():
    e = dict(os.environ, MPLBACKEND="Agg")
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    return e


def snapshot(cells_dir: Path) -> dict:
    return {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in cells_dir.glob("*.json")}


def comparable(path: Path) -> pd.DataFrame:
    return pd.read_csv(path).drop(columns=["us_per_step"])


@pytest.fixture(scope="module")
def interrupted_then_resumed(tmp_path_factory):
    """Run the grid on the process backend, SIGINT it after its first finished cell, then rerun it to the end."""
    out = tmp_path_factory.mktemp("lb") / "out"
    cells = out / "store" / "cells"
    # SIGINT back to its default in the child: a runner started in the background (`nohup … &`, no job control)
    # ignores SIGINT, a child inherits that, and Python then never turns the signal into KeyboardInterrupt: the study
    # would run to its end (exit 0, every cell stored) and the test would judge an interrupt that never happened
    proc = subprocess.Popen(command(out, "--backend", "process", "--jobs", "2", "--no-figures"), env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 600
    while not (cells.is_dir() and any(cells.glob("*.json"))):
        if proc.poll() is not None:
            pytest.fail(f"the study ended before its first cell: {proc.communicate()}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("no cell finished within 10 minutes")
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    first = snapshot(cells)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    resumed = subprocess.run(command(out, "--backend", "serial", "--no-figures"), env=env(), capture_output=True,
                             text=True, timeout=1200)
    assert resumed.returncode == 0, resumed.stderr
    return out, first, resumed


@pytest.mark.slow
def test_an_interrupted_study_resumes_without_recomputing_finished_cells(interrupted_then_resumed, tmp_path):
    out, first, resumed = interrupted_then_resumed
    assert 1 <= len(first) < N_CELLS, "the interrupt must land part-way"
    cells = out / "store" / "cells"
    # every cell finished before the interrupt is byte-for-byte the same file, untouched
    after = snapshot(cells)
    assert len(after) == N_CELLS
    for name, state in first.items():
        assert after[name] == state
    # the audit trail: the first invocation was interrupted, the second computed exactly the missing cells
    logs = sorted((json.loads(p.read_text()) for p in (out / "store" / "runs").glob("*.json")),
                  key=lambda d: d["started"])
    assert [d["interrupted"] for d in logs] == [True, False]
    done_before = {n.removesuffix(".json") for n in first}
    assert set(logs[1]["reused"]) == done_before
    assert set(logs[1]["computed"]).isdisjoint(done_before)
    assert len(logs[1]["computed"]) == N_CELLS - len(first)
    assert f"{N_CELLS - len(first)} computed, {len(first)} reused from the store" in resumed.stdout
    assert not list((out / "store").rglob("*.tmp"))

    # the resumed table equals the table of an uninterrupted run of every cell; the fits (keyed by their data and
    # code, and the slow part) are handed over as a shared fit cache would be
    fresh_out = tmp_path / "fresh"
    shutil.copytree(out / "store" / "fits", fresh_out / "store" / "fits")
    fresh = subprocess.run(command(fresh_out, "--backend", "serial"), env=env(), capture_output=True, text=True,
                           timeout=1200)
    assert fresh.returncode == 0, fresh.stderr
    pd.testing.assert_frame_equal(comparable(out / "leaderboard.csv"), comparable(fresh_out / "leaderboard.csv"))

    # and the outputs of that run: the fixed columns, no NaN anywhere, the ranked Markdown and the figures
    table = pd.read_csv(fresh_out / "leaderboard.csv")
    assert list(table.columns) == COLUMNS and len(table) == N_CELLS
    assert "nan" not in (fresh_out / "leaderboard.csv").read_text().lower()
    assert set(table["n_runs"]) == {2}
    ok = table[table.failed_runs < table.n_runs]
    assert np.isfinite(ok[COLUMNS[4:]].to_numpy(dtype=float)).all()
    md = (fresh_out / "leaderboard.md").read_text()
    for scen in ("flight-10kg",):
        sub = ok[ok.scenario == scen].sort_values(["failed_runs", "soc_rmse"])
        best = sub.iloc[0]
        assert f"On {scen} the best combination is {best.model} + {best.estimator}" in md
        for prefix in ("heatmap", "soc_error", "voltage"):
            assert (fresh_out / f"{prefix}_{scen}.png").stat().st_size > 1000


@pytest.mark.parametrize("option,value,message", [
    ("--models", "rint,nope", "unknown model 'nope'"),
    ("--estimators", "kalman", "unknown estimator 'kalman'"),
    ("--scenarios", "mars", "unknown scenario 'mars'"),
    ("--seeds", "0", "--seeds must be at least 1"),
    ("--jobs", "0", "--jobs must be at least 1"),
    ("--scheduler", "tcp://127.0.0.1:1", "--scheduler needs --backend dask"),
])
def test_bad_options_are_one_line_errors_with_exit_2(option, value, message, tmp_path, capsys):
    code = main(["leaderboard", option, value, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out" / "leaderboard.csv").exists()
