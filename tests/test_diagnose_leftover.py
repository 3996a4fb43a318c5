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



def test_the_hidden_fade_is_the_fade_whose_voltage_equals_the_noise():
    """``hidden_fade`` from the OCV's slope is the fade that, simulated on the curve itself (not linearised), moves
    a record's voltage, its mean removed, by the noise, and a steep curve hides less than LFP's plateau; 1 where the
    curve is flat."""
    from socbench.diagnose.leftover import hidden_fade
    from socbench.ocv import OCVCurve
    from tests.hppc_records import OCV_SHAPES

    rng = np.random.default_rng(5)
    amps = np.clip(rng.normal(0.6, 0.5, 3600), -0.5, 2.5)  # 1 h of a drive at 0.6 C mean on a 1 Ah cell
    ah = np.r_[0.0, np.cumsum(amps[:-1]) / 3600.0]
    sigma = 2e-3
    out = {}
    for shape in ("nmc", "lfp"):
        ocv = OCVCurve(*OCV_SHAPES[shape], shape)
        z = 0.85 - ah  # from 85 % on the fit's axis, never near empty
        f = hidden_fade(ocv.value_and_slope(z)[1], ah, 1.0, [z.size], sigma)

        def footprint(fade, ocv=ocv, z=z):  # the fade simulated on the curve, each record's mean removed
            dv = ocv(z - ah * fade / (1.0 - fade)) - ocv(z)
            return float(np.sqrt(np.mean((dv - dv.mean()) ** 2)))

        # first order in the fade: within 20 % of the noise at f* (LFP's kinks bend it most), and f* parts what the
        # record shows from what it does not
        assert footprint(f) == pytest.approx(sigma, rel=0.2), shape
        assert footprint(0.5 * f) < sigma < footprint(2.0 * f), shape
        out[shape] = f
    assert out["nmc"] < 0.5 * out["lfp"], out  # a steep curve hides less than the plateau
    assert hidden_fade(np.zeros(10), np.linspace(0.0, 0.5, 10), 1.0, [10], sigma) == 1.0


def test_a_record_on_a_flat_curve_is_said_to_hide_a_fade(tmp_path):
    """A drive that keeps an LFP cell on its plateau cannot show a capacity fade above its noise, and the report
    says how large a fade it hides; the same drive of an NMC cell shows a fade of a fraction of a percent, and the
    report says nothing of it."""
    from socbench.diagnose.leftover import FADE_HINT
    from tests.hppc_records import Cell, Instrument, Layout, drive_record, hppc_record

    ins = Instrument(dt=1.0, i_noise_c=0.002, v_noise=2e-3, phase=0.0)
    hidden = {}
    for shape in ("lfp", "nmc"):
        cell = Cell(5.0, shape, 0.02, ((0.01, 30.0),))
        fit = hppc_record(cell, Layout(), ins, seed=1).profile
        ev = drive_record(cell, ins, seed=2, duration_s=3600.0, soc0=0.85).profile
        assert ev.soc_ref.min() > 0.3  # LFP's plateau: no knee in the record
        d = diagnose("thevenin", [fit], [ev], soc=False)
        hidden[shape] = d.left["hidden_fade"]
        assert ("a capacity fade of up to" in sentence(d.left)) == (shape == "lfp"), sentence(d.left)
    assert hidden["lfp"] >= FADE_HINT > 1.5 * hidden["nmc"], hidden
