"""A study runner killed with SIGKILL (it cannot stop its workers) takes its process-pool workers with it: each asks
Linux for SIGTERM when its parent dies (``socbench.study.backends._die_with_parent``). Found by killing a
leaderboard with ``kill -9``: its worker waited on the task queue, orphaned, until killed by hand."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

RUNNER = textwrap.dedent("""
    import os, sys, time
    from socbench.study.backends import ProcessBackend

    def pid(_):
        return os.getpid()

    backend = ProcessBackend(jobs=2)
    pids = {backend.result(h) for h in [backend.submit(pid, k) for k in range(8)]}
    print(" ".join(map(str, sorted(pids))), flush=True)
    time.sleep(120)
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead for this purpose (its parent, init here, reaps it)
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(") ", 1)[1][0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_workers_die_with_a_runner_killed_with_sigkill():
    runner = subprocess.Popen([sys.executable, "-c", RUNNER], stdout=subprocess.PIPE, text=True)
    workers = []
    try:
        workers = [int(p) for p in runner.stdout.readline().split()]
        assert workers and all(_alive(p) for p in workers)
        runner.send_signal(signal.SIGKILL)
        runner.wait(timeout=10)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.1)
        assert not any(_alive(p) for p in workers), [p for p in workers if _alive(p)]
    finally:
        if runner.poll() is None:
            runner.kill()
        for p in (p for p in workers if _alive(p)):  # a failed run leaves no orphan behind
            os.kill(p, signal.SIGKILL)
