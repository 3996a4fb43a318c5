"""The SOC bound: a Kalman update that leaves [0, 1] is projected back with the whole state (estimators.safety)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from socbench.cli import main
from socbench.estimators.safety import project_soc


def _spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_projection_moves_the_correlated_states_and_only_the_runs_that_crossed():
    rng = np.random.default_rng(11)
    for _ in range(50):
        n = int(rng.integers(1, 7))
        P = np.stack([_spd(rng, n) for _ in range(4)])
        x = rng.normal(size=(4, n))
        x[:, 0] = [1.03, 0.5, -0.2, 1.0]
        P[1] = np.inf  # an in-range run with a broken covariance must be left alone
        before = x.copy()
        out = project_soc(x, P)
        assert out.tolist() == [True, False, True, False]
        assert x[0, 0] == 1.0 and x[2, 0] == 0.0
        for r, b in ((0, 1.0), (2, 0.0)):
            d = before[r, 0] - b
            np.testing.assert_allclose(x[r, 1:], before[r, 1:] - P[r, 1:, 0] * d / P[r, 0, 0], rtol=1e-12)
        np.testing.assert_array_equal(x[[1, 3]], before[[1, 3]])
        # the square-root form gives the same state from L with P = L Lᵀ
        L = np.linalg.cholesky(P[[0, 2, 3]])
        xf = before[[0, 2, 3]].copy()
        project_soc(xf, L, factor=True)
        np.testing.assert_allclose(xf, x[[0, 2, 3]], rtol=1e-10, atol=1e-12)


def test_soc_clipped_alone_where_the_covariance_cannot_project():
    x = np.array([[1.2, 0.3]])
    P = np.array([[[0.0, 0.0], [0.0, 1.0]]])
    assert project_soc(x, P).tolist() == [True]
    assert x.tolist() == [[1.0, 0.3]]


def test_filters_hold_a_full_charge_rest_under_the_noise_recipe(tmp_path):
    """The synthetic HPPC starts full and rests: the scheduled recipe model pushes the SOC against 1 sample after
    sample. With the SOC clipped alone, dp and gnl EKFs diverged in 162 of 200 runs (the robustness sweep,
    docs/reliability.md); projected, none may."""
    out = tmp_path / "lb"
    assert main(["leaderboard", "--models", "dp,gnl", "--estimators", "ekf,ukf", "--scenarios", "hppc",
                 "--seeds", "20", "--out", str(out)]) == 0
    table = pd.read_csv(out / "leaderboard.csv")
    assert len(table) == 4
    assert table["failed_runs"].sum() == 0, table[["model", "estimator", "failed_runs"]]
    assert (table["soc_rmse"] < 0.05).all(), table[["model", "estimator", "soc_rmse"]]
