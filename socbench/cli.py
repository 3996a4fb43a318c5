"""The ``socbench`` command (the contract is in DESIGN.md, "Command line contract").

Every command prints a short human summary, writes machine-readable results where ``--out``/``--json`` says, exits 0 on
success, 2 on a user error (one line, no traceback) and 1 on an internal error. Set ``SOCBENCH_DEBUG=1`` for tracebacks.

Each sub-command is a small module in ``socbench/commands/`` with ``add_arguments(parser)`` and ``run(args) -> int``;
this file only registers them.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from .errors import SocbenchWarning, UserError

#: sub-command -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "models": ("socbench.commands.models", "list the model registry"),
    "simulate": ("socbench.commands.simulate", "simulate a model on a profile and score the voltage"),
    "fit": ("socbench.commands.fit", "fit a model's parameters to a record (HPPC) and write PARAMS.json"),
    "estimate": ("socbench.commands.estimate", "estimate SOC with coulomb counting, EKF, UKF or PF and score it"),
    "scenarios": ("socbench.commands.scenarios", "list the scenario catalog"),
    "leaderboard": ("socbench.commands.leaderboard", "run the models × estimators × scenarios study and rank it"),
    "bench": ("socbench.commands.bench", "time the batched engines against a loop of filterpy runs (--quick: < 1 min)"),
    "diagnose": ("socbench.commands.diagnose", "find the effect a model lacks from its residual, add it, refit"),
}


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad option as a one-line user error (exit 2), as it already does, but quietly."""

    def error(self, message):  # noqa: D401 - argparse API
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command; with ``only``, the options of that command alone are set up (the others keep
    their name and help line): a command imports its own module, not all of them (a second or more of start-up)."""
    parser = _Parser(prog="socbench", description="Battery SOC estimation testbed")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if only is None or name == only:
            importlib.import_module(module).add_arguments(p)
    return parser


def _command_in(argv) -> str | None:
    """The sub-command ``argv`` names (its first word, when that is a command), else None."""
    args = sys.argv[1:] if argv is None else list(argv)
    return args[0] if args and args[0] in COMMANDS else None


def main(argv=None) -> int:
    parser = build_parser(_command_in(argv))
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    module = importlib.import_module(COMMANDS[args.command][0])
    try:
        with warnings.catch_warnings():
            _one_line_warnings(args.command)
            return int(module.run(args) or 0)
    except UserError as exc:
        print(f"socbench {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print(f"socbench {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # an internal error: one line unless debugging
        if os.environ.get("SOCBENCH_DEBUG"):
            raise
        print(f"socbench {args.command}: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1


def _one_line_warnings(command: str) -> None:
    """Inside a command: socbench's own warnings print as one line each (no file, line or source excerpt), the same
    message once; numpy's floating-point RuntimeWarnings are not for users (a result that matters is checked, not
    warned about) and are silenced."""
    seen = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message).strip().splitlines()[0] if str(message).strip() else category.__name__
        if text in seen:
            return
        seen.add(text)
        prefix = "warning" if issubclass(category, SocbenchWarning) else f"warning ({category.__name__})"
        print(f"socbench {command}: {prefix}: {text}", file=sys.stderr)

    warnings.showwarning = show
    warnings.simplefilter("always", SocbenchWarning)
    warnings.simplefilter("ignore", RuntimeWarning)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
