"""``diagnose``: fit a model on the fit data, find what its residual on the evaluation data lacks, add it, refit.

1. **Fit** the base model on the fit data with :func:`socbench.identify.fit_model`. A fit record that moves most of
   its charge below C/10 is a slow OCV test: it gives the OCV curve (:func:`~socbench.identify.ocv_from_slow_test`:
   the mean of the charge and discharge branches when both are there, or with ``slow_ocv="discharge"`` the discharge
   branch, the paper's convention of rest points taken after discharge steps) and the capacity, and the model is
   fitted on the other record with that curve. Nothing is read from names or metadata but the declared capacity.
2. **Prepare** the evaluation data (:mod:`socbench.diagnose.data`): bins of ≥ ``dt`` s — coarser where a record
   would keep more than ``max_samples`` samples, which bounds the cost of every fit — and the train / held-out split.
3. **Search** (:mod:`socbench.diagnose.search`): signatures, bounded fits on the training part, held-out scores, the
   forward steps while the held-out RMSE falls by ≥ 10 %.
4. **SOC** (where the data carry a reference SOC): the EKF on the original and on the augmented model, scored on the
   held-out part with :func:`socbench.estimators.scoring.score`.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..identify import fit_model, ocv_from_slow_test
from ..models import make_model
from ..models.base import T_REF_C
from ..profile import Profile
from .data import Split, bin_average, make_split
from .search import Search, held_out, initial_soc

#: a fit record whose |I| never exceeds this C-rate is a slow OCV test
SLOW_TEST_C_RATE = 0.1


@dataclass
class Diagnosis:
    """Everything the report needs (``to_dict`` gives ``diagnosis.json``)."""

    model: str
    base_model: object
    final_model: object
    steps: list
    rounds: list
    before: dict
    after: dict
    split: Split
    fit: dict
    seconds: dict = field(default_factory=dict)
    soc: dict = field(default_factory=dict)
    domain: dict = field(default_factory=dict)  # {"before", "after"}: socbench.domain reports on the held-out data

    @property
    def effects_added(self) -> list:
        return [s.effect for s in self.steps]

    def to_dict(self) -> dict:
        first = self.rounds[0]["candidates"] if self.rounds else []
        return {
            "model": self.model,
            "effects_added": self.effects_added,
            "before": self.before,
            "after": self.after,
            "candidates": [c.to_dict() for c in first],
            "steps": [{"effect": s.effect, "rmse_v_before": s.rmse_before, "rmse_v_after": s.rmse_after,
                       "params": s.params, "score": s.score, "evidence": s.evidence} for s in self.steps],
            "split": self.split.describe(),
            "rounds": [[c.to_dict() for c in r["candidates"]] for r in self.rounds],
            "fit": self.fit,
            "soc": self.soc,
            "domain": self.domain,
            "seconds": self.seconds,
        }


def _capacity(profile: Profile) -> float | None:
    if profile.meta.capacity_ah:
        return float(profile.meta.capacity_ah)
    return None


def is_slow_test(profile: Profile) -> bool:
    """Data-only test: at least 80 % of the charge the record moves moves at |I| ≤ C/10 (a slow OCV test; a CV
    top-off at its start may be faster). C is the declared capacity, else the largest Ah excursion of the record."""
    ah = profile.amp_hours()
    q = _capacity(profile) or float(np.ptp(ah)) or 1.0
    moved = np.abs(profile.current_a[:-1]) * profile.dt
    slow = np.abs(profile.current_a[:-1]) <= SLOW_TEST_C_RATE * q
    return bool(moved.sum() > 0 and moved[slow].sum() >= 0.8 * moved.sum())


def fit_base(name: str, fit_profiles, mode: str = "constant", slow_ocv: str = "mean"):
    """``(model, info)``: the base model fitted on the fit data (see the module docstring)."""
    fit_profiles = list(fit_profiles)
    slow = [p for p in fit_profiles if is_slow_test(p)]
    dynamic = [p for p in fit_profiles if not is_slow_test(p)]
    if not dynamic:
        raise DataError("the fit data need one record with load (not only a slow OCV test)")
    if len(dynamic) > 1:
        raise DataError("give one dynamic fit record (and optionally one slow OCV test)")
    ocv = capacity = None
    info = {"records": [p.name for p in fit_profiles]}
    if slow:
        cur = np.abs(slow[0].current_a)
        moving = cur[cur > 1e-3 * float(cur.max())]
        # the branches are the runs at the test's typical (median) current, whatever a CV top-off did before
        s = ocv_from_slow_test(slow[0], capacity_ah=_capacity(slow[0]), i_min=0.5 * float(np.median(moving)))
        use_mean = slow_ocv == "mean" and s.mean is not None
        ocv = s.mean if use_mean else s.discharge
        capacity = s.capacity_ah
        info["ocv"] = f"slow test {slow[0].name}: " + ("mean of both branches" if use_mean else "discharge branch")
        # the hysteresis branch the curve lies on: the mean of both (0) or the discharge branch (−1)
        info["ocv_branch"] = 0.0 if use_mean else -1.0
    else:
        info["ocv"] = "HPPC rest points (after discharge steps)"
        info["ocv_branch"] = -1.0
    prof = dynamic[0]
    capacity = capacity or _capacity(prof)
    res = fit_model(name, prof, mode=mode, ocv=ocv, capacity_ah=capacity)
    info.update({"fitted_on": prof.name, "mode": mode, "rmse_v": res.rmse_v, "seconds": res.seconds,
                 "capacity_ah": res.params.capacity_ah, "values": res.values, "warnings": list(res.warnings)})
    t_fit = prof.temperature_c
    info["t_ref_c"] = float(np.mean(t_fit)) if t_fit is not None else T_REF_C
    return make_model(name, res.params), info


def soc_errors(model, split: Split, voltage_sd: float) -> dict | None:
    """Held-out SOC RMSE of the EKF on ``model`` (None without a reference SOC or without the estimators)."""
    if any(p.soc_ref is None for p, _ in split.held):
        return None
    try:
        from ..estimators import SensorNoise, make_estimator
        from ..estimators.scoring import score
    except ImportError:  # pragma: no cover - the estimators package is part of socbench
        return None
    noise = SensorNoise(voltage_sd=max(voltage_sd, 1e-3), current_sd=0.01 * model.capacity_ah)
    sq, n = 0.0, 0
    for prof, k in split.held:
        est = make_estimator("ekf", model, noise).run(prof, soc0=float(prof.soc_ref[0]))
        s = score(est, prof, skip_s=float(prof.time_s[k] - prof.time_s[0]))
        if s.get("soc_rmse") is None:
            return None
        sq += s["soc_rmse"] ** 2 * s["n"]
        n += s["n"]
    return {"soc_rmse": float(np.sqrt(sq / n))}


def _coarse(profile: Profile, dt: float, max_samples: int) -> Profile:
    """``profile`` on bins of ``dt`` s, coarser if that leaves more than ``max_samples`` samples (fit cost)."""
    p = bin_average(profile, dt)
    if p.n > max_samples:
        p = bin_average(profile, dt * p.n / max_samples)
    return p


def diagnose(model_name: str, fit_profiles, eval_profiles, *, mode: str = "constant", dt: float = 1.0,
             train_fraction: float = 0.5, candidates=None, min_gain: float = 0.10, max_steps: int = 3,
             max_nfev: int = 15, max_fits: int = 3, max_samples: int = 1500, slow_ocv: str = "mean",
             soc: bool = True) -> Diagnosis:
    """Run the whole diagnosis (module docstring). Profiles are :class:`~socbench.profile.Profile` objects."""
    t0 = _time.perf_counter()
    base, fit_info = fit_base(model_name, fit_profiles, mode, slow_ocv)
    t_fit = _time.perf_counter()
    evals = [_coarse(p, dt, max_samples) for p in eval_profiles]
    for p in evals:
        p.require("voltage_v")
    split = make_split(evals, train_fraction)
    search = Search(base, split, fit_info["t_ref_c"], candidates, min_gain=min_gain, max_nfev=max_nfev,
                    max_steps=max_steps, max_fits=max_fits, h_ref=fit_info["ocv_branch"])
    final, steps, rounds, _ = search.run()
    fit_info["voltage_noise_sd"] = search.noise_sd
    before = held_out(base, split)[0]  # the search scores on every held-out sample: these are its numbers
    after = steps[-1].rmse_after if steps else before
    t_search = _time.perf_counter()
    soc_info = {}
    before_d, after_d = {"rmse_v": before}, {"rmse_v": after}
    if soc:
        train_rmse = {}
        for key, m in (("before", base), ("after", final)):
            sim = m.simulate(split.train, soc0=initial_soc(m, split.train))
            train_rmse[key] = float(np.sqrt(np.mean((split.train.voltage_v - sim.voltage_v) ** 2)))
        sb = soc_errors(base, split, train_rmse["before"])
        sa = soc_errors(final, split, train_rmse["after"])
        if sb is not None and sa is not None:
            before_d["soc_rmse"], after_d["soc_rmse"] = sb["soc_rmse"], sa["soc_rmse"]
            soc_info = {"estimator": "ekf", "voltage_sd": train_rmse, "note": "EKF voltage noise = the model's "
                        "training-part RMSE; current noise 1 % of C; SOC scored on the held-out part"}
        else:
            soc_info = {"note": "no reference SOC in the held-out data: SOC error not reported"}
    domain = {"before": held_out_domain(base, split), "after": held_out_domain(final, split)}
    t_end = _time.perf_counter()
    seconds = {"fit": t_fit - t0, "search": t_search - t_fit, "soc": t_end - t_search, "total": t_end - t0}
    return Diagnosis(model_name, base, final, steps, rounds, before_d, after_d, split, fit_info, seconds, soc_info,
                     domain)


def held_out_domain(model, split: Split) -> dict:
    """The domain report (:func:`socbench.domain.domain_report`) of ``model`` on the held-out profiles, each
    simulated from its start as the held-out scores are (segment by segment where a record has several)."""
    from ..domain import merge

    reports = []
    for prof, _ in split.held:
        sim = model.simulate(prof, soc0=initial_soc(model, prof))
        reports.append({**sim.domain, "segments": sim.domain.get("segments", 1)})
    out = merge(reports)
    out["segments"] = sum(r["segments"] for r in reports)
    return out
