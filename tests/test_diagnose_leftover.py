"""What the search leaves (socbench.diagnose.leftover): the held-out residual's structure above the noise and what it
follows, on residuals of known make-up, and in a diagnosis whose search may not name the effect hidden in the data."""

from __future__ import annotations

import numpy as np
import pytest

from socbench.diagnose import diagnose
from socbench.diagnose.leftover import current_share, leftover, ocv_gap, sentence, soc_share
from socbench.diagnose.synthetic import hidden_case

N = 3000


def _record(rng):
    """A discharge's SOC (0.95 → 0.2) and a current of random steps independent of it."""
    z = np.linspace(0.95, 0.2, N)
    i = np.repeat(rng.uniform(0.0, 40.0, N // 30), 30)
    return z, i


@pytest.mark.parametrize("seed", range(6))
def test_shares_point_at_what_the_residual_follows(seed):
    """A residual made of an SOC-shaped error is read as following the SOC, one proportional to the current as
    following the current, white noise as neither; the structure above the noise is the planted part's RMS."""
    rng = np.random.default_rng(seed)
    z, i = _record(rng)
    noise = rng.uniform(0.5e-3, 3e-3)
    white = noise * rng.standard_normal(N)
    # an OCV read too coarsely (amplitude 4–10 σ, a period of 30–60 % of SOC: six bins or more, the resolution the
    # share claims), a resistance the model has wrong (RMS 3–6 σ)
    bump = noise * rng.uniform(4.0, 10.0) * np.sin(2 * np.pi * z / rng.uniform(0.3, 0.6))
    resistive = -noise * rng.uniform(3.0, 6.0) * (i - i.mean()) / np.std(i)

    ocv_like = leftover(bump + white, z, i, [N], noise)
    assert ocv_like["soc_share"] > 0.8 > ocv_like["current_share"] + 0.6
    assert ocv_like["structure_v"] == pytest.approx(np.sqrt(np.mean((bump - bump.mean()) ** 2)), rel=0.15, abs=5e-4)

    res_like = leftover(resistive + white, z, i, [N], noise)
    assert res_like["current_share"] > 0.7 and res_like["soc_share"] < 0.2

    plain = leftover(white, z, i, [N], noise)
    assert plain["soc_share"] < 0.05 and plain["current_share"] < 0.05
    assert plain["structure_v"] < 0.3 * noise


def test_each_record_keeps_its_own_constant():
    """Two records at different offsets (an OCV or sensor offset between records is no structure): the SOC share of
    white noise stays small although the records cover different SOC ranges."""
    rng = np.random.default_rng(3)
    z = np.r_[np.linspace(0.9, 0.6, N), np.linspace(0.5, 0.2, N)]
    e = np.r_[np.full(N, 0.02), np.full(N, -0.02)] + 1e-3 * rng.standard_normal(2 * N)
    assert soc_share(e - e.mean(), z) > 0.9  # the offsets alone, not removed, would read as SOC structure
    assert leftover(e, z, np.ones(2 * N), [N, N], 1e-3)["soc_share"] < 0.05


def test_ocv_gap_counts_only_the_visited_soc_range():
    points = [0.0, 0.25, 0.5, 0.75, 1.0]
    assert ocv_gap(points, np.linspace(0.3, 0.6, 50)) == pytest.approx(0.2)  # [0.25, 0.5] seen from 0.3
    assert ocv_gap(points, np.linspace(0.0, 1.0, 50)) == pytest.approx(0.25)
    assert ocv_gap(None, np.linspace(0.0, 1.0, 50)) is None
    assert current_share(np.ones(5) - 1.0, np.arange(5.0)) == 0.0


def test_the_report_suggests_measuring_the_ocv_only_where_the_soc_and_a_wide_gap_say_so():
    rng = np.random.default_rng(8)
    z, i = _record(rng)
    bump = 0.01 * np.sin(2 * np.pi * z / 0.5) + 1e-3 * rng.standard_normal(N)
    wide, fine = [0.0, 0.25, 0.5, 0.75, 1.0], list(np.linspace(0.0, 1.0, 21))
    assert "slow OCV test" in sentence(leftover(bump, z, i, [N], 1e-3, wide))
    assert "slow OCV test" not in sentence(leftover(bump, z, i, [N], 1e-3, fine))  # 5 % steps: not the OCV's gaps
    assert "slow OCV test" not in sentence(leftover(-2e-4 * (i - i.mean()), z, i, [N], 1e-3, wide))  # the current


@pytest.mark.parametrize("hidden, allowed, follows", [
    ("capacity", ["butler_volmer", "extra_rc"], "soc_share"),  # an SOC drift the search may not name
    ("butler_volmer", ["capacity", "self_discharge"], "current_share"),  # a current nonlinearity it may not name
])
def test_a_diagnosis_that_cannot_name_the_effect_says_where_it_lies(hidden, allowed, follows):
    fit, ev = hidden_case(hidden, "thevenin", "steps", "large", v_sd=1e-3, seed=5)
    d = diagnose("thevenin", [fit], [ev], candidates=allowed, soc=False, base_refit=False)
    assert hidden not in d.effects_added
    left = d.left
    assert left["structure_v"] > 2 * left["noise_v"]
    other = "current_share" if follows == "soc_share" else "soc_share"
    assert left[follows] > 0.5 and left[follows] > left[other]

