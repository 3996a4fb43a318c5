"""Shared fixtures. Real-data tests use ``data_dir``: skipped when SOCBENCH_DATA_DIR is unset, failed under CI."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# One BLAS thread per test process (inherited by the xdist workers, which start after this file is read): the fits
# factorise small matrices, where threads only add overhead, and on a shared 2-core machine several test processes
# each running a thread pool slow one another down by orders of magnitude.
# Likewise one thread for the compiled kernels' batches (socbench.kernels.engine.parallel_runs): the xdist workers
# already keep the cores busy. tests/test_kernels.py runs the threaded path itself, with the variable set there.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "SOCBENCH_THREADS"):
    os.environ.setdefault(_var, "1")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    d = os.environ.get("SOCBENCH_DATA_DIR")
    if not d:
        if os.environ.get("CI"):
            pytest.fail("SOCBENCH_DATA_DIR is not set under CI: real-data tests must run, not skip")
        pytest.skip("SOCBENCH_DATA_DIR not set")
    p = Path(d)
    if not p.is_dir():
        pytest.fail(f"SOCBENCH_DATA_DIR={d} is not a directory")
    return p


def pytest_collection_modifyitems(config, items):
    """The tests marked ``slow`` first (a stable sort: the order is otherwise the collection's). pytest-xdist hands
    tests to its workers in this order, and a minute-long test handed out last, while the other worker has run dry,
    is what the whole run then waits for."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
