"""``socbench COMMAND`` sets up (and imports) only that command's module: start-up is part of every command's time."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from socbench.cli import COMMANDS

ROOT = Path(__file__).resolve().parents[1]


def _loaded_commands(args: list[str]) -> set[str]:
    code = (f"import sys\nfrom socbench.cli import main\nmain({args!r})\n"
            "print(sorted(m for m in sys.modules if m.startswith('socbench.commands.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    return set(eval(out.stdout.strip().splitlines()[-1]))  # noqa: S307 - our own printed list


def test_a_command_imports_its_own_module_only():
    assert _loaded_commands(["models"]) == {"socbench.commands.models"}


def test_help_without_a_command_still_lists_every_command(capsys):
    from socbench.cli import main

    assert main([]) == 2
    out = capsys.readouterr().out
    assert all(name in out for name in COMMANDS)
