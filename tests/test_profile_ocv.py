"""Profile validation, OCV curve, parameter functions and metrics."""

from __future__ import annotations

import numpy as np
import pytest

from socbench import DataError, OCVCurve, Profile, ProfileMeta
from socbench.metrics import chi2_band, voltage_error_stats
from socbench.models.params import Constant, Lookup, Polynomial
from socbench.ocv import monotone_points
from socbench.profile import run_medians


def _meta():
    return ProfileMeta(name="t", source="run.csv")


def test_profile_rejects_nan_with_column_and_row():
    t = np.arange(5.0)
    v = np.array([4.0, 4.0, np.nan, 4.0, 4.0])
    with pytest.raises(DataError) as e:
        Profile(t, np.zeros(5), v, meta=_meta())
    assert e.value.column == "voltage_v" and e.value.row == 3 and e.value.file == "run.csv"
    assert "run.csv" in str(e.value) and "voltage_v" in str(e.value) and "row 3" in str(e.value)


@pytest.mark.parametrize("t, row, word", [([0, 1, 1, 2], 3, "duplicate"), ([0, 1, 3, 2], 4, "backwards")])
def test_profile_rejects_non_increasing_time(t, row, word):
    with pytest.raises(DataError) as e:
        Profile(np.array(t, float), np.zeros(4), meta=_meta())
    assert e.value.column == "time_s" and e.value.row == row and word in str(e.value)


def test_profile_rejects_empty_and_missing_columns():
    with pytest.raises(DataError, match="empty"):
        Profile(np.array([]), np.array([]), meta=_meta())
    with pytest.raises(DataError) as e:
        Profile(np.arange(3.0), None, meta=_meta())
    assert e.value.column == "current_a"
    p = Profile(np.arange(3.0), np.zeros(3), meta=_meta())
    with pytest.raises(DataError) as e:
        p.require("voltage_v")
    assert e.value.column == "voltage_v"


def test_profile_rejects_soc_in_percent_and_length_mismatch():
    # a reference in percent is refused where it is used (the profile itself loads: DESIGN.md, Reliability)
    p = Profile(np.arange(3.0), np.zeros(3), soc_ref=np.array([100.0, 99.0, 98.0]), meta=_meta())
    assert p.soc_ref is None
    for use in (lambda: p.require("soc_ref"), lambda: p.get("soc_ref"), lambda: p.slice(1).require("soc_ref")):
        with pytest.raises(DataError) as e:
            use()
        assert e.value.column == "soc_ref" and e.value.row == 1 and "percent" in str(e.value)
    with pytest.raises(DataError) as e:
        Profile(np.arange(3.0), np.zeros(4), meta=_meta())
    assert e.value.column == "current_a"


def test_profile_batch_views_and_amp_hours():
    t = np.arange(0.0, 3601.0, 1.0)
    i = np.stack([np.full(t.size, 2.0), np.full(t.size, 1.0)])
    p = Profile(t, i, meta=_meta())
    assert p.n_runs == 2 and p.batched and not p.run(1).batched
    np.testing.assert_allclose(p.amp_hours()[:, -1], [2.0, 1.0])
    gap = Profile(np.array([0, 1, 2, 3, 60, 61.0]), np.zeros(6), meta=_meta())
    assert gap.gaps() == [(5, 57.0)]


def test_run_medians_equal_numpy_per_run():
    """200 random draws of disjoint runs (lengths 1–40, odd and even, quantised values with ties): each median is
    np.median of its run's slice, exactly."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        values = np.round(rng.normal(size=rng.integers(50, 400)), int(rng.integers(0, 3)))
        cuts = np.sort(rng.choice(np.arange(1, values.size), size=int(rng.integers(1, 20)), replace=False))
        bounds = np.r_[0, cuts, values.size]
        runs = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if rng.random() < 0.6]
        want = [np.median(values[a:b]) for a, b in runs]
        np.testing.assert_array_equal(run_medians(values, runs), want)
    assert run_medians(np.arange(5.0), []).shape == (0,)
    np.testing.assert_array_equal(run_medians(np.array([3.0, 1.0, 2.0, 4.0]), [(3, 4), (0, 3), (0, 4)]), [4, 2, 2.5])


def test_ocv_pchip_is_monotone_with_exact_slope_and_inverse():
    z = np.linspace(0, 1, 11)
    v = 3.0 + 1.2 * z - 0.4 * np.exp(-20 * z)
    ocv = OCVCurve(z, v)
    zz = np.linspace(-0.1, 1.1, 1201)
    u, du = ocv.value_and_slope(zz)
    band = ocv.excursion(zz) <= 0.05  # linear extension within 0.05 of the rest points, held beyond (ocv.py)
    assert np.all(np.diff(u[band]) > 0) and np.all(np.diff(u) >= 0)
    h = 1e-6
    fd = (ocv(zz + h) - ocv(zz - h)) / (2 * h)
    knots = np.r_[z, z[0] - 0.05, z[-1] + 0.05]  # C¹ knots and the two kinks where the extension is held
    inside = np.min(np.abs(zz[:, None] - knots[None, :]), axis=1) > 1e-4  # compare off them
    np.testing.assert_allclose(du[inside], fd[inside], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(ocv(z), v, atol=1e-12)  # interpolates the rest points
    np.testing.assert_allclose(ocv.inverse(ocv(zz[band])), zz[band], atol=1e-9)
    assert ocv.excursion(1.1) == pytest.approx(0.1) and ocv.excursion(0.5) == 0.0


def test_ocv_rejects_decreasing_points_and_monotone_points_repairs_them():
    z, v = [0.0, 0.5, 0.6, 1.0], [3.0, 3.6, 3.55, 4.1]
    with pytest.raises(DataError, match="decrease"):
        OCVCurve(z, v)
    zz, vv = monotone_points(z, v)
    assert np.all(np.diff(vv) >= 0) and vv[1] == pytest.approx(3.575)
    OCVCurve(zz, vv)


def test_soc_functions_values_and_derivatives():
    p = Polynomial((2.0, -1.0, 0.5))  # 2 z² − z + 0.5
    v, d = p.value_and_deriv(np.array([0.3, 1.5, -0.2]))
    np.testing.assert_allclose(v, [2 * 0.09 - 0.3 + 0.5, 1.5, 0.5])
    np.testing.assert_allclose(d, [4 * 0.3 - 1, 0.0, 0.0])  # clipped → derivative 0
    lk = Lookup((0.0, 0.5, 1.0), (1.0, 2.0, 4.0))
    v, d = lk.value_and_deriv(np.array([0.25, 0.75, 1.2]))
    np.testing.assert_allclose(v, [1.5, 3.0, 4.0])
    np.testing.assert_allclose(d, [2.0, 4.0, 0.0])
    assert Constant(3.0).value_and_deriv(np.zeros(2))[1].tolist() == [0.0, 0.0]


def test_voltage_error_stats_definitions():
    meas = np.array([1.0, 2.0, 3.0, 4.0])
    model = np.array([1.1, 1.9, 3.0, 3.6])
    s = voltage_error_stats(meas, model)
    e = meas - model
    assert s["n"] == 4
    assert s["mean_v"] == pytest.approx(e.mean())
    assert s["rmse_v"] == pytest.approx(np.sqrt((e**2).mean()))
    assert s["sd_v"] == pytest.approx(np.sqrt(((e - e.mean()) ** 2).sum() / 3))
    assert s["max_v"] == pytest.approx(0.4)


def test_chi2_band_contains_its_mean():
    lo, hi = chi2_band(1, 100)
    assert lo < 1.0 < hi and hi - lo < 1.0


def test_voltage_level_check_refuses_a_cell_file_against_pack_parameters():
    from socbench.checks import check_voltage_level
    from socbench.models import paper_params

    pack = paper_params("thevenin")  # 6S pack, OCV ≈ 16–24.6 V
    cell = Profile(np.arange(3.0), np.ones(3), np.full(3, 3.7), meta=ProfileMeta(name="cell", source="cell.csv"))
    with pytest.raises(DataError) as e:
        check_voltage_level(cell, pack)
    assert e.value.column == "voltage_v" and e.value.file == "cell.csv"
    packdata = Profile(np.arange(3.0), np.ones(3), np.full(3, 22.5), meta=ProfileMeta(name="pack"))
    check_voltage_level(packdata, pack)  # a pack-level file passes
