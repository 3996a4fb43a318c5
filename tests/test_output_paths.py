"""Output paths of every command: a bad ``--out``/``--json`` is a user error (one line, exit 2), before any work."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from socbench.cli import main

HPPC = "builtin:hppc"

#: command -> (arguments before the output option, output option, "dir" or "file")
COMMANDS = {
    "simulate --json": (["simulate", "--data", HPPC, "--params", "paper:thevenin"], "--json", "file"),
    "simulate --out": (["simulate", "--data", HPPC, "--params", "paper:thevenin"], "--out", "file"),
    "fit --out": (["fit", "--data", HPPC, "--model", "rint"], "--out", "file"),
    "estimate --out": (["estimate", "--data", HPPC, "--params", "paper:thevenin", "--estimator", "ekf"], "--out",
                       "dir"),
    "leaderboard --out": (["leaderboard", "--models", "rint", "--estimators", "coulomb", "--scenarios", "flight-10kg",
                           "--seeds", "1", "--backend", "serial", "--no-figures"], "--out", "dir"),
    "diagnose --out": (["diagnose", "--fit", HPPC, "--eval", HPPC, "--model", "rint"], "--out", "dir"),
    "bench --json": (["bench", "--tiny"], "--json", "file"),
}


def read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot write into: permission bits where they apply, else (root) a read-only mount."""
    if os.geteuid() != 0:
        d = tmp_path / "read-only"
        d.mkdir()
        d.chmod(0o555)
        return d
    for candidate in (Path("/sys"), Path("/proc/sys")):
        if candidate.is_dir():
            try:
                (candidate / ".socbench-probe").touch()
            except OSError:
                return candidate
    pytest.skip("no folder this (root) process cannot write into")


def cases(tmp_path: Path, kind: str) -> dict:
    a_file = tmp_path / "existing.txt"
    a_file.write_text("not a folder")
    a_dir = tmp_path / "existing-folder"
    a_dir.mkdir()
    ro = read_only_folder(tmp_path)
    out = {
        "under a file": (str(a_file / "sub" / ("x.json" if kind == "file" else "out")), "is a file, not a folder"),
        "read-only folder": (str(ro / ("x.json" if kind == "file" else "out")), "cannot write"),
    }
    if kind == "dir":
        out["an existing file"] = (str(a_file), "is an existing file; expected a folder")
        out["read-only existing folder"] = (str(ro), "cannot write into this folder")
    else:
        out["an existing folder"] = (str(a_dir), "is an existing folder; expected a file name")
    return out


@pytest.mark.parametrize("command", list(COMMANDS))
def test_bad_output_paths_are_one_line_user_errors(command, tmp_path, capsys):
    argv, option, kind = COMMANDS[command]
    for what, (path, message) in cases(tmp_path, kind).items():
        code = main([*argv, option, path])
        err = capsys.readouterr().err.strip()
        assert code == 2, f"{command} {what}: exit {code}: {err}"
        lines = err.splitlines()
        assert len(lines) == 1, f"{command} {what}: {err}"
        assert lines[0].startswith(f"socbench {argv[0]}: error: {option} {path}"), lines[0]
        assert message in lines[0], lines[0]
        assert "Traceback" not in err and "internal error" not in err


def test_a_good_output_path_is_created(tmp_path, capsys):
    """The check creates what is missing: a nested new folder, and the folder of a new file."""
    out = tmp_path / "new" / "deeper"
    assert main(["estimate", "--data", "builtin:1c", "--params", "paper:rint", "--estimator", "coulomb",
                 "--out", str(out)]) == 0
    assert (out / "metrics.json").is_file() and (out / "estimate.csv").is_file()
    js = tmp_path / "a" / "b" / "m.json"
    assert main(["simulate", "--data", "builtin:1c", "--params", "paper:rint", "--json", str(js)]) == 0
    assert js.is_file()
    capsys.readouterr()
