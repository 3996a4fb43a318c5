"""The diagnosis' base fit on an HPPC read at coarse SOC steps: its rest-point OCV refined between the points
(``diagnose(…, refine_ocv="coarse")``; the default, True, tries it on every HPPC; socbench.identify.pseudo_ocv), on
records of the tests' own generator (tests/hppc_records.py)."""

from __future__ import annotations

from dataclasses import replace

from socbench.diagnose import diagnose
from tests.hppc_records import drive_record, hppc_record, random_setup


def test_a_coarse_hppc_ocv_is_refined_between_its_points_and_fits_better():
    """HPPCs in 20–25 % steps of cells with hand-drawn OCV curves (tests/hppc_records.py, not the project's
    generator), evaluated on a drive cycle: the diagnosis refines the rest-point OCV between its points
    (``refine_ocv="coarse"``), keeps it only where it validates better, and its base model then predicts the drive
    cycle better (held-out, before any effect) than the same diagnosis without the refinement in most draws and worse
    in none; an HPPC in 10 % steps is left as it is."""
    # only the base fit is compared: the search, the fit test and the filters are left out (they do not change
    # ``before``, the base model's held-out error)
    base_only = {"soc": False, "max_steps": 0, "fit_test": False}
    better = 0
    for seed in range(5):
        rng, cell, lay, ins = random_setup(100 + seed)
        lay = replace(lay, step=float(rng.uniform(0.2, 0.25)), gaps=False)
        fit, ev = hppc_record(cell, lay, ins, seed=seed).profile, drive_record(cell, ins, seed=seed).profile
        model = "thevenin" if len(cell.branches) == 1 else "dp"
        plain = diagnose(model, [fit], [ev], refine_ocv=False, **base_only)
        coarse = diagnose(model, [fit], [ev], refine_ocv="coarse", **base_only)
        assert coarse.before["rmse_v"] <= plain.before["rmse_v"] * (1 + 1e-9)
        better += coarse.before["rmse_v"] < 0.8 * plain.before["rmse_v"]
    assert better >= 3
    rng, cell, lay, ins = random_setup(100)
    fine = replace(lay, step=0.1, gaps=False)
    d = diagnose("thevenin", [hppc_record(cell, fine, ins, seed=0).profile], [drive_record(cell, ins, seed=0).profile],
                 refine_ocv="coarse", **base_only)
    assert "refined" not in d.fit["ocv"] and "ocv_refinement" not in d.fit


def test_refine_ocv_takes_only_true_false_or_coarse():
    """``refine_ocv="never"`` (the CLI's word) is a truthy string: taken as given it would refine. The API refuses
    any value other than True, False and "coarse" with one clear error, before any work."""
    import pytest

    from socbench.errors import ConfigError

    rng, cell, lay, ins = random_setup(100)
    fit, ev = hppc_record(cell, lay, ins, seed=0).profile, drive_record(cell, ins, seed=0).profile
    for bad in ("never", "always", 2):
        with pytest.raises(ConfigError, match="refine_ocv"):
            diagnose("thevenin", [fit], [ev], soc=False, refine_ocv=bad)
