"""Shared fixtures. Real-data tests use ``data_dir``: skipped when SOCBENCH_DATA_DIR is unset, failed under CI."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


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
