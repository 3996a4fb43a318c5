"""Ranking, augmentation and refit: the forward search over the effects the model lacks, scored by blocked
cross-validation.

One round, on the current model ``m`` (the base model, then the base model with what was added so far):

1. simulate ``m`` on every evaluation record and compute every effect's residual signature
   (:mod:`socbench.diagnose.signatures`): evidence (R² on all samples) and, per fold, the starting guess of its
   parameters from that fold's training samples only;
2. for the candidates (below), fit their parameters — **together with the parameters of what was added before** (the
   refit) — inside their physical bounds (:meth:`~socbench.models.effects.Effect.bounds`), once per fold and once
   on all data (:func:`socbench.diagnose.cv.fit_folds`; the base model's parameters stay as fitted on the fit data
   unless the base refit was added), from two starts (the signature's guesses and the effect's defaults), each fold
   keeping the fit of the start that fits its own training samples better (:data:`SECOND_START`);
3. judge each on its held-out residual (:func:`~socbench.diagnose.cv.cv_residual`: every block scored by the fold that
   did not see it): ``score = ln(MSE_before / MSE_after) − 2·p / n_eff`` (AIC per effective sample, ``p`` the
   parameters the candidate adds, ``n_eff = N·(1 − ρ)/(1 + ρ)`` from the lag-1 autocorrelation ρ of the residual, at
   least 100 — neighbouring residuals of a voltage fit are far from independent);
4. add the chosen candidate (:meth:`Search._choose`) if it lowers the held-out RMSE by at least ``min_gain`` (10 %)
   and the model is not already at the noise floor (held-out RMSE ≤ ``NOISE_FLOOR`` × the voltage noise of the
   averaged records, :func:`residual_noise`; ``NOISE_FLOOR_REFIT`` × once the base refit is in the model) — at the
   floor, only an effect that cuts it by ``FLOOR_GAIN`` (25 %, more than any effect cut in 99 % of null cases there)
   and, fitted jointly with the base refit, the refit's error by as much; else stop.
   The noise is measured again on the residual of the model as it grows (:meth:`Search._remeasure_noise`: a base
   model far off, in the cold, reads its own error at the current's edges as noise). Where nothing passes in the
   first round, the best-scoring effects are fitted again jointly with the base refit, and one is added when so it
   passes against the refit alone too (:meth:`Search._joint_with_refit`);
5. at the end, each SOC drift named is swapped for another when that one, fitted beside everything else added, cuts
   the held-out RMSE by ``min_gain`` (:meth:`Search._swap_drift`);
6. then each named effect the final model does not need is dropped: refitted without it (everything else jointly, every
   fold), the model is within ``min_gain`` of the final held-out RMSE (:meth:`Search._prune`, the backward half of
   stepwise selection); an effect the fit test found, no worse (:data:`FIT_TEST_KEPT`).

Candidates. The bounded fit (the expensive part) runs for the ``max_fits`` best-supported families by signature R² (at
least ``MIN_SIGNATURE_R2``); the four SOC drifts (capacity, current bias, leak, efficiency: one regressor shape up to
U(z)/U(1) and charge weighting) are one family, fitted together; the capacity effect is a fade (:data:`FADE_ONLY`),
one-sided like the leak (it only removes charge) and the efficiency (it only loses charge). Beside the effects, the
**base refit** (``BASE_REFIT``): the base model's own parameters scaled and a voltage offset per record, fitted the same
way. It stands for what a better base fit would absorb (an OCV read from unrelaxed rests, a slow branch a short pulse
cannot identify) and is never named an effect; an effect within ``PARSIMONY`` of a winning base refit is preferred to
it. For the same reason an extra RC branch whose time constant lies within ×``TWIN_TAU`` of one of the base model's
branches is not named: it cannot be told from a misfit of that branch. Nor is an extra branch named where the base
has a branch to spare (:meth:`Search.spare_branch`): two of its own branches within ×``TWIN_TAU`` of each other (a
lookup fit whose two branches swap roles over SOC, a refit that moved the slow branch next to the fast one), or one
slower than any extra branch may be (10⁴ s, the end of its range where the extra branch is itself a ramp: its
capacitor takes the charge the records move without relaxing; a DP fitted on a test that shows no slow branch, short
pulses or the step discharges logged in a gap, leaves its second branch there). An extra branch found beside such a
base is the spare branch put back: it is scored as any candidate and, where a round adopts it, kept in the model as
base-fit error, like the base refit, and never named (``Candidate.base_branch``). With both base branches in one place
the search cannot tell a missing branch from the misplaced one, and it does not guess; but the branch belongs in the
model. Named as an effect, the spare pair's branch was three of the five extra branches named in seed 47's null
cases; scored out instead (the pair first, the ramp at stop 73), its share stayed in the residual for another effect
to take, or was left. Over the randomised benchmark's eight reported runs (1440 cases), kept against scored out: nulls
273 → 275 of 288, named first 581 → 583 of 864, cut ≥ 30 % 655 → 658, SOC not worse 1353 → 1356, an effect named that
is not there 128 → 126, pairs unchanged (135); in 43 cases the effects named or the held-out error moved (seed 2026
case 13, a fade beside a DP whose slow branch the fit left as a ramp, has its fade named again). Its costs: a hidden
branch beside a spare is kept unnamed (seed 5150 case 76, where a hysteresis was then named beside it), and a better
voltage model can make the SOC estimate worse. A null case (seed 47 case 111, a gapped HPPC) falls 12.2 → 7.3 mV
held-out with the branch kept while its EKF SOC error rises 0.62 → 1.46 %: the filters' voltage noise, read from the
held-out residual, falls from 0.29–0.45 V (a coulomb count) to 23–66 mV, and the filter then follows an OCV read from
the gapped HPPC's rests. Once the base refit is in the model the branches
are those the refit made (``τ_j·s_Rj·s_Cj``, the refit's scales of the candidate's own fit): beside a refitted branch, a
twin buys the branch the freedom the refit's scaling lacks — a new SOC shape of its resistance (a constant twin beside
a looked-up branch), a time constant beyond the refit's bounds — which is base-fit error, not a branch the structure
lacks. Nested tests
against the refit (:meth:`Search._beyond_refit`): an effect that wins a round in which the refit also cut the error is
named only if, fitted jointly with the refit, it cuts the refit's error by ``min_gain`` (else the refit is taken; an
SOC drift that passes gives way to another drift of its round that, fitted jointly with the refit too, explains the
records ``min_gain`` better, :data:`DRIFT_BESIDE_REFIT`); after
a refit is adopted, the ``CARRY`` best-scoring effects of its round are fitted again jointly with it, whatever their
signature on the refitted residual (the refit took up part of their shape).

A fit at the end of a range is not the effect's own shape: an SOC drift at the limit of its physical range
(``DRIFT_AT_BOUND``), a hysteresis at Plett's γ floor or a branch at the longest time constant (``SLOW_END``: a state
that never settles within the records, a slow offset or a ramp) stands in for an OCV or SOC-axis error and is not
scored. So is a temperature whose resistances do not move with it (activation energy below
``TEMPERATURE_EA_MIN``): its entropic term alone is an offset the temperature column indexes; and a temperature or a
hysteresis at the upper end of its activation energy or gap (``FAR_END``: as much as its range allows).

The current sensor gets evidence of its own: where the records hold rests (at least ``FIELD_REST_MIN_S`` below C/20
whose spread is the sensor's noise), the true current is zero, so the measured rest current *is* the offset. ``b`` is
bounded to that median ± 3 standard errors (± ``REST_BOUND_C`` of 1C beside them; where the rests read one level of
an undithered sensor, its step over √12 stands for the standard error); with at least ``REST_EVIDENCE_S`` of
rests a clear offset puts the current bias first — added whatever the voltage says of it, a measurement rather than an
inference (on a cold record the temperature's error hides it until both are in the model) — a null one rules it out.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass, field

import numpy as np

from ..identify.fit import branch_time_constants
from ..identify.fit_test_effect import BOUND_TOL, bound_hit
from ..identify.hppc import quantisation_step, reading_level
from ..metrics import lag1_autocorrelation
from ..models.effects import EFFECTS, augment, make_effect, n_cells
from ..models.scaling import refittable_params, scaled_model
from ..segments import restart_soc
from .cv import FoldFit, cv_residual, fit_folds, simulate_records
from .data import Folds
from .signatures import Trajectory, signatures

#: a rest: at least this long, current below C/20 and steady (within C/200 of its mean)
REST_MIN_S = 30.0
#: a rest of the field records that measures the current sensor: at least this long. A vehicle waiting at a light or a
#: stop draws a small steady auxiliary current (below C/20, as steady as a rest) for a minute or two; a parked cell
#: rests for many minutes. Shorter quiet spells would read the auxiliary load as a sensor offset.
FIELD_REST_MIN_S = 300.0
MIN_N_EFF = 100.0
#: a candidate whose signature explains less of the residual variance is not fitted
MIN_SIGNATURE_R2 = 0.01
#: candidates tied (within 0.01) with the last one fitted are fitted too when their R² is at least this
TIE_R2 = 0.1
#: rests this long in total decide whether the current sensor reads an offset
REST_EVIDENCE_S = 600.0
#: a rest current above this share of 1C (and four standard errors) is a current-sensor offset
REST_OFFSET_C = 5e-4
#: the least half-width of the offset's bounds about what the rests read, as a share of 1C (a noise-free reading
#: still leaves the fit a range)
REST_BOUND_C = 1e-5
#: the rest current's standard error includes the scatter of the rests' levels beyond their noise (rest_current)
REST_SPREAD = True
#: the standard error of a median of normal noise over that of a mean (√(π/2))
MEDIAN_SE = 1.2533
#: no effect is added once the held-out RMSE is within this factor of the measured voltage noise. A base model fitted
#: on its own record leaves some error of its own beside the noise (the fit is not exact), and near the noise any
#: flexible effect can take up part of it. The factor was set as the critical value of that null distribution on
#: synthetic cases without a hidden effect (seeds neither the tests nor the benchmark use); the randomised benchmark's
#: null cases (socbench.diagnose.randomized) measure what it lets through.
NOISE_FLOOR = 2.5
#: the floor once the base refit is part of the model: the base model's own error has then been refitted on the
#: evaluation data (every later candidate is fitted jointly with it), so what stands above the noise is structure a
#: refit of the base cannot take. Half the noise's own level of headroom is left for the refit's bounded scaling.
NOISE_FLOOR_REFIT = 1.5
#: below its noise floor the search goes on only for an effect that cuts the held-out RMSE by this share (None: the
#: floor stops it). The floor is set for the base model's own error, which a flexible effect can take part of near the
#: noise; a cut this large is more than such an effect takes. The share is the 99th percentile, rounded up to 0.05, of
#: the largest cut any effect made at the floor in 200 null cases of the randomised generator's seeds 9101–9105, which
#: neither the tests nor the benchmark's reported runs use (``python benchmarks/floor_gain.py --seeds 9101 9102 9103
#: 9104 9105``): 0.23; the largest 0.30, and 2 of the 200 reach 0.25. Never the base refit (below the floor the error
#: it takes is the base fit's own); and the effect, fitted jointly with the base refit, must cut the refit's error by
#: this share too, with no exemption for a measured temperature (:meth:`_beyond_refit`). With ``min_gain`` asked there
#: instead, the randomised benchmark's seven runs named 5 more of 744 hidden effects first and one more pair, but a
#: null record read 8–15 K warmer than its fit test with an OCV offset of 1.2–1.8 × the noise
#: (``tests/test_diagnose_floor_gain.py``) got a hysteresis in 1 of 12 draws (its state, fitted fold by fold, took the
#: offset), and with the temperature exempt too, an effect in 2 of the test's 6.
FLOOR_GAIN = 0.25
#: the effects that drift the SOC (one family of signatures)
SOC_DRIFT = ("capacity", "current_bias", "coulombic_efficiency", "self_discharge")
#: the pseudo-candidate "the base model's own parameters (scaled) and each record's voltage offset, refitted on the
#: evaluation data": what a refit of the base absorbs is not an effect (it is never named as one)
BASE_REFIT = "base_refit"
#: the base refit scales each base parameter by at most this factor's e-power either way (ln 4: ×0.25…×4)
BASE_SCALE = float(np.log(4.0))
#: the base refit's voltage offset per record is at most this per cell (an OCV read from rests too short to relax)
BASE_OFFSET_V = 0.05
#: an effect is preferred to the base refit when its held-out RMSE is within this share of the refit's
PARSIMONY = 0.10
#: … and only when it would be added itself (score above zero, the search's gain): an effect short of the gain, chosen
#: over a refit that passed, ended the search, and was never fitted again beside the refit (seed 2026 case 12)
PARSIMONY_ACCEPTED = True
#: an extra RC branch whose time constant lies within this factor of one of the base model's is that branch misfitted
TWIN_TAU = 3.0
#: whether a step the fit test found (:meth:`Search.fit_test_step`) is held to the noise floor like the effects the
#: search fits on the evaluation data. It is not: the floor is set for the base model's own error, which an effect
#: fitted on the evaluation records can take up near the noise; a fit-test step has no parameter fitted there but a
#: state's initial value (the same row in every fold), so a 10 % held-out gain of it is the fit test's evidence
#: confirmed, not base-fit error taken up. On the randomised benchmark's development seeds, against the floor held
#: (stop 62): hidden effect named first 2026 80 → 81 of 120, 31 48 → 49 of 72, 47 unchanged, 777 81 → 82 of 120,
#: 4242 78 → 80 of 120 (every one a hysteresis beside a slow OCV test, 0.3–1.1 × the noise beyond the base, its
#: held-out SOC error lower too), one pair more with its hysteresis named (777 case 83), nulls and effects named that
#: are not there unchanged; held-out seeds 5150 and 6007 every rate unchanged; offered alone (``--oracle``, seed
#: 2026) the hidden effect added in 84 → 85 of 120
FIT_TEST_FLOORED = False
#: a fit-test step that passed the search's gain (:meth:`Search.fit_test_step`, ``bar="gain"``: the effect fitted on
#: the fit test, the evaluation records predicted ``min_gain`` better with nothing of it fitted on them) is dropped at
#: the end (:meth:`Search._prune`) only where the model without it is no worse, not within ``min_gain``: that model
#: still holds the base refit, fitted on the evaluation records themselves, which can take most of its share there
#: without being the cell's (False: the ``min_gain`` bar of every searched effect). On the randomised benchmark's
#: development seeds (840 cases), against that bar (stop 64): two more hysteresis singles named first (seed 2026
#: case 17, seed 777 case 189, each dropped before with the records 5-10 % worse without it); one pair (seed 47 case
#: 33, an offset and a hysteresis) kept a slow branch the fit test found beside the offset, not in the truth; every
#: other outcome unchanged
FIT_TEST_KEPT = True
#: a measured temperature this far from the fit's [K] is evidence of a temperature effect (Search._choose)
T_EVIDENCE_K = 5.0
#: effects fitted again beside the base refit in the round after it was adopted (the best-scoring ones)
CARRY = 2
#: the lower bound of the capacity effect's ``cap0 = Q_model/Q_true`` in the search. The base model's SOC axis (its OCV
#: curve and every record's counted SOC) is counted with the capacity of the fit test, measured on the same cell: what
#: the evaluation records can show is a fade since then (ageing, the cold), ``cap0 ≥ 1`` — a one-sided drift like the
#: leak (``rate ≥ 0``) and the efficiency (``η_c ≤ 1``). Below 1, a cell that gained charge, the capacity effect was the
#: only SOC drift that could slow the SOC down, and what it took there was the OCV curve's own error:
#: ``U(z₀ + cap·(z − z₀))`` is a function of the counted SOC ``z`` alone, a stretch of the OCV's SOC axis about the
#: start, which takes up any OCV misfit that correlates with the charge moved since the start.
FADE_ONLY = 1.0
#: whether the search fits the capacity effect's resistance growth ``r_growth`` (ageing grows the over-potential with
#: the fade) by default. Off: on the randomised benchmark's development seeds (31, 47; 120 cases) fitting it named the
#: aged cells' growth where the base refit had taken it, but named no more hidden effects first and fewer pairs (a
#: capacity that takes the grown over-potential leaves the model under the noise floor without the refit, whose lower
#: floor let a second, smaller effect in); with the base refit bounded by the fit's standard errors, fewer still.
#: ``Search(resistance_growth=True)`` (``diagnose(…, resistance_growth=True)``) fits it.
RESISTANCE_GROWTH = False
#: every fitted candidate is fitted from a second start, its parameters at the effect's defaults, and each group (fold,
#: all-data fit) keeps the row of the start that fits its own training samples better (:meth:`Search._better`). A
#: bounded fit of ``max_nfev`` evaluations stays near its start, and each fold's signature guess, read off its own
#: training samples, can start it far from where that fold belongs: one fold left astray spoils the held-out score of
#: an effect that is there (a hysteresis fitted beside the base refit, its parameters right to 10 %: held-out 3.8 →
#: 3.7 mV from the guesses, → 2.4 mV with the second start). On the randomised benchmark, against one start: seed 2026
#: named first 71 → 73 of 120 (the hysteresis above, a fade a leak had taken), pairs, cuts and nulls unchanged, three
#: single-effect cases with a false second effect; development seed 31 both of a pair named 8 → 10 of 24 (one false
#: second effect), seed 47 unchanged; CPU +65 % (slowest diagnosis 6.4 → 12.4 s).
SECOND_START = True
#: effects of a round that would stop (none passed alone) fitted again jointly with the base refit
#: (:meth:`Search._joint_with_refit`), the best-scoring ones
JOINT_TRIES = 2
#: where an SOC drift wins a round in which the base refit also cut the error, and passes the nested test against the
#: refit (:meth:`Search._beyond_refit`), the round's other drifts are fitted jointly with the refit too, and one that
#: lies ``min_gain`` below the winner, alone and beside the refit, is the step instead, jointly with the refit
#: (:meth:`Search._drift_beside_refit`). The four drifts leave nearly the same residual; which one the records hold
#: shows once the base's own error is taken out beside it: alone, a leak can lose to a fade whose Ah-shaped drift took
#: up part of a base error the refit fixes (resistances off at the cold, after the temperature effect).
#: On the randomised benchmark's development seeds (2026, 31, 47, 777, 4242; 840 cases), against the search without
#: it (stop 63): a fade named in place of a leak where the fade was hidden (seed 777 case 18: 82 → 83 of 120 named
#: first there), both effects named in two more pairs (a leak beside a cold cell's temperature, seed 47 case 43; a
#: Butler–Volmer term found beside a fade once the refit is in, seed 2026 case 83), one wrong drift for another in a
#: pair (seed 2026 case 112, 6.1 → 3.3 mV); nulls, SOC not worse and every other case unchanged. Held to beat the
#: winner's joint fit alone (not its fit alone too) it swapped a leak for a fade in a leak's case (seed 47 case 119)
DRIFT_BESIDE_REFIT = True
#: an SOC drift (not a measured input) whose all-data fit rests on a bound of its physical range is not scored
#: (:meth:`Search._scored`): at a 5 %/h leak, an efficiency of 0.9, 1.6 × the capacity, an offset of 5 % of 1C, the
#: fit wanted more than any cell holds, so the drift stands in for something else (seed 2026 of the randomised
#: benchmark: a fade named instead of a leak at its bound, one efficiency at its bound no longer named beside a leak,
#: every other rate unchanged; development seeds 31 and 47: every rate unchanged; in two pairs another wrong drift is
#: named instead of a wrong efficiency, one of them now naming its Butler–Volmer term and a wrong branch too)
DRIFT_AT_BOUND = True
#: a state effect whose all-data fit rests at the slow end of its rate's range is not scored (:meth:`Search._scored`),
#: the rule the fit test's refit is held to (:func:`socbench.identify.fit_test_effect.fit_with_effect`): a hysteresis at
#: Plett's γ floor settles over a whole capacity of charge moved, a slow offset; a branch at the longest time constant
#: charges over hours, a ramp. Either takes up an OCV or SOC-axis error rather than showing its own shape. On the
#: randomised benchmark (seeds 2026, 31, 47, 777; the OCV refined on every HPPC), against the search without it:
#: effects named that are not there 71 → 56 of 512 cases, nulls 125 → 126 of 128 (seed 31's case 0: a hysteresis at
#: γ = 1.0001), hidden effect named first 248 → 251 of 384; its cost, three true states fitted at the slow end and no
#: longer named (a hysteresis beside a slow test, a pair's hysteresis, a pair's branch) and one Butler–Volmer term
#: named behind a branch at 10⁴ s. The tolerance is :data:`~socbench.identify.fit_test_effect.BOUND_TOL` of the
#: range's width (γ ≤ 1.5), not the fit test's ratio. Parameter, and the end of its range that is slow (0 the lower,
#: 1 the upper)
SLOW_END = {"hysteresis": ("gamma", 0), "extra_rc": ("log10_tau", 1)}
#: whether :data:`SLOW_END` applies
SLOW_END_RULE = True
#: a temperature effect whose all-data fit has an activation energy below this [J/mol] is not scored
#: (:meth:`Search.resistance_unmoved`): its resistances barely move with the temperature (below 0.7 %/K at 25 °C), so
#: what it fits is its entropic term ``dU/dT·(T − T_ref)``, on a record held near one temperature a voltage offset,
#: which the temperature column merely indexes: an OCV offset or a second instrument's voltage offset, not the cell's
#: temperature dependence, which moves the over-potential first. The value lies below every apparent activation energy
#: fitted on the Panasonic 18650PF's temperature pairs by more than a factor of two (12–44 kJ/mol,
#: ``benchmarks/closing_the_loop.py``) and at a quarter of the randomised benchmark's lower end (20 kJ/mol). None: off
TEMPERATURE_EA_MIN = 5e3
#: an effect whose all-data fit puts this parameter at the upper end of its range is not scored
#: (:meth:`Search.at_far_end`), as an SOC drift at the limit of its range is not: the effect is taking up as much as
#: its bounds allow of something else.
#:
#: * a temperature's activation energy at 100 kJ/mol: a record whose temperature moves a few kelvin (a C/5 discharge
#:   warming by 2 K) lets the steepest Arrhenius factor scale the resistances as far as the fit wants — on the CMU
#:   eVTOL cells' capacity checks (``benchmarks/evtol_fade.py``) one was named beside or instead of the fade; the
#:   Panasonic 18650PF's temperature pairs fit 12–44 kJ/mol (``benchmarks/closing_the_loop.py``), the randomised
#:   benchmark draws 20–50 kJ/mol;
#: * a hysteresis gap ``M`` of 100 mV per cell: four times the widest LFP gap the randomised benchmark draws (and the
#:   fit test's refit refuses it there already, :func:`~socbench.identify.fit_test_effect.bound_hit`) — on a whole
#:   eVTOL life record whose counted charge drifts, it took up a drift of volts
FAR_END = {"temperature": "Ea", "hysteresis": "M"}
#: whether :data:`FAR_END` applies
FAR_END_RULE = True
#: relative change of the held-out RMSE below which an effect fitted alone counts as fitted to its null
NULL_FIT_TOL = 1e-3
#: compression of the training record for the fits (the held-out part is scored on every sample)
FIT_COMPRESS = {"max_step_s": 60.0}


@dataclass
class Candidate:
    effect: str
    score: float
    rmse_before: float
    rmse_after: float
    params: dict
    signature_r2: float
    evidence: str
    effects: tuple = ()  # the fitted effects (all of them, all-data parameters) if this candidate were added
    seconds: float = 0.0
    held_residual: np.ndarray | None = field(default=None, repr=False)
    fold_sse: np.ndarray | None = field(default=None, repr=False)
    fit: FoldFit | None = field(default=None, repr=False)
    layout: tuple = ()  # ((effect, param names), ...) of the fitted θ
    #: the largest ratio, over the blocks, of the held-out squared error after to before (reported: a real effect
    #: lowers the error wherever it shows, one that takes up base-fit error often makes some block worse)
    fold_ratio: float = float("nan")
    #: found on the fit test (:mod:`socbench.identify.fit_test_effect`), not by a round of the search
    fit_test: bool = False
    #: an extra RC branch that puts back a branch the base fit left spare (:meth:`Search.spare_branch`: a ramp, or two
    #: branches at one time constant): base-fit error, kept in the model like the base refit and, like it, never named
    base_branch: bool = False

    @property
    def named(self) -> bool:
        """Whether this step names an effect (not the base refit, nor a base branch put back)."""
        return self.effect != BASE_REFIT and not self.base_branch

    def to_dict(self) -> dict:
        score = round(float(self.score), 6) if np.isfinite(self.score) else None  # None: not fitted (valid JSON)
        return {"effect": self.effect, "score": score, "evidence": self.evidence,
                "signature_r2": round(float(self.signature_r2), 6), "rmse_v_before": self.rmse_before,
                "rmse_v_after": self.rmse_after, "params": self.params, "seconds": round(self.seconds, 3),
                "worst_block_mse_ratio": round(float(self.fold_ratio), 4) if np.isfinite(self.fold_ratio) else None}


def added_alone(c: Candidate, min_gain: float) -> bool:
    """Whether candidate ``c`` would be added by its own round: a score above zero and a held-out RMSE ``min_gain``
    below the model's before it."""
    return bool(c.score > 0 and c.rmse_after <= (1.0 - min_gain) * c.rmse_before)


def noise_floor(noise_sd: float, refitted: bool = False) -> float:
    """The search's noise floor for a voltage noise ``noise_sd``: :data:`NOISE_FLOOR` × it, :data:`NOISE_FLOOR_REFIT` ×
    once the base refit is in the model (``refitted``)."""
    return (NOISE_FLOOR_REFIT if refitted else NOISE_FLOOR) * noise_sd


def initial_soc(model, profile) -> float:
    """The reference SOC at the start when the data carry one, else the SOC the model reads off the first voltage
    (:func:`socbench.segments.restart_soc`)."""
    return float(restart_soc(profile, 0, model))


def effective_samples(r: np.ndarray) -> float:
    """``N (1 − ρ)/(1 + ρ)`` with ρ the lag-1 autocorrelation, floored at :data:`MIN_N_EFF`."""
    rho = lag1_autocorrelation(r)
    return float(min(r.size, max(MIN_N_EFF, r.size * (1 - rho) / (1 + rho))))


def robust_sd(x) -> float:
    """``1.4826·MAD(x)``: the standard deviation of the bulk of ``x``, blind to a minority of outliers."""
    x = np.asarray(x, dtype=float)
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else 0.0


#: a voltage reading whose ADC step is at least this share of the noise read off it is quantised (residual_noise)
QUANTISED = 0.5


def interpolation_deviation(t, e) -> np.ndarray:
    """Each inner sample's deviation from the straight line through its two neighbours, scaled to the sd of white
    noise in ``e``, on any spacing (a logger's time stamps jitter):

        d_k = e_k − (h₂·e_{k−1} + h₁·e_{k+1}) / (h₁ + h₂),   h₁ = t_k − t_{k−1},  h₂ = t_{k+1} − t_k
        var d_k = σ²·(1 + (h₁² + h₂²)/(h₁ + h₂)²)             (white noise of sd σ)

    returned as ``d_k / √(1 + (h₁² + h₂²)/(h₁ + h₂)²)``; on a uniform grid that is ``−Δ²e/√6``, the second difference
    over √6. A signal that is linear over the three samples leaves nothing."""
    t, e = np.asarray(t, dtype=float), np.asarray(e, dtype=float)
    h1, h2 = t[1:-1] - t[:-2], t[2:] - t[1:-1]
    span = h1 + h2
    with np.errstate(invalid="ignore", divide="ignore"):
        d = e[1:-1] - (h2 * e[:-2] + h1 * e[2:]) / span
        d = d / np.sqrt(1.0 + (h1 * h1 + h2 * h2) / (span * span))
    return d[np.isfinite(d) & (span > 0)]


def residual_noise(model, profiles, soc0s=None) -> float:
    """Voltage noise sd in the data: the robust sd of ``model``'s open-loop residual's deviation from the line through
    each sample's neighbours (:func:`interpolation_deviation`: the second difference over √6 on a uniform grid, any
    spacing allowed; before, only exactly uniform triples counted, and a logger whose time stamps jitter by 0.01 %
    left almost none: 3 % of the Panasonic US06 samples, none on a record jittered by ±2 %).

    A model error is smooth at the sample scale except at current edges, a minority the median ignores; what the
    deviation keeps is the sensor's white noise (and the current sensor's, through the model's ``R0``). Run on the
    records as measured, before any averaging. A voltage read in ADC steps ``q`` larger than its noise repeats its
    values, most deviations are 0 or a lattice step and their median deviation jumps with the lattice: where the step
    is at least :data:`QUANTISED` × the noise read, the noise is the plain sd of the deviations within 5 spreads of
    their median, and at least the rounding's ``q/√12`` (``q`` the largest step among the records; an unquantised
    reading's is negligible, and its noise is read as before)."""
    d, q = [], 0.0
    for r, p in enumerate(profiles):
        if p.n < 3:
            continue
        z0 = soc0s[r] if soc0s is not None else initial_soc(model, p)
        d.append(interpolation_deviation(p.time_s, p.voltage_v - model.simulate(p, soc0=z0).voltage_v))
        q = max(q, quantisation_step(p.voltage_v))
    d = np.concatenate(d) if d else np.zeros(0)
    if d.size < 50:
        return 0.0
    sigma = robust_sd(d)
    if q >= QUANTISED * sigma:
        # the deviations of a quantised reading lie on a lattice of q/2 steps, and their median deviation jumps with
        # the lattice (from 0 to 0.6 q): the plain sd of the bulk instead, within 5 spreads of its median
        mid = float(np.median(d))
        spread = max(sigma, q)
        sigma = float(np.std(d[np.abs(d - mid) <= 5.0 * spread]))
    return max(sigma, q / np.sqrt(12.0))


def rest_current(profiles, capacity_ah: float, quiet_a: float | None = None, min_s: float = REST_MIN_S):
    """``(median, standard error, seconds)`` of the measured current over the rests of ``profiles`` (one or a list),
    or None without rests. The standard error is the median's, widened by the scatter of the rests' own levels where
    they disagree beyond their noise (:data:`REST_SPREAD`).

    A rest: at least ``min_s`` below ``quiet_a`` (default C/20) whose spread (robust sd) is within C/200 plus
    three times the current sensor's own noise (the robust sd of successive differences over the quiet samples,
    ``/√2``): a noisy sensor's rest is still a rest, a slow taper is not."""
    vals, weights = [], []
    quiet_a = capacity_ah / 20.0 if quiet_a is None else quiet_a
    for profile in [profiles] if hasattr(profiles, "current_a") else profiles:
        i = profile.current_a
        quiet = np.abs(i) < quiet_a
        both = quiet[1:] & quiet[:-1]
        sensor = robust_sd(np.diff(i)[both]) / np.sqrt(2.0) if both.sum() >= 10 else 0.0
        edges = np.flatnonzero(np.diff(np.r_[0, quiet.astype(int), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a < 2:
                continue
            seg = i[a:b]
            dur = profile.time_s[b - 1] - profile.time_s[a]
            if dur >= min_s and robust_sd(seg) <= capacity_ah / 200.0 + 3.0 * sensor:
                vals.append(seg)
                weights.append(dur)
    if not vals:
        return None
    allv = np.concatenate(vals)
    # the median: a rest that begins or ends with a few seconds of load (a stop's auxiliary current before the
    # vehicle is switched off) would pull a mean; read through its dither when the sensor is quantised, whose plain
    # median sticks to a level and reads a sub-step offset as none (reading_level). The standard error is that of
    # the median of normal noise
    level, sd = reading_level(allv)
    se = float(MEDIAN_SE * sd / np.sqrt(allv.size)) if allv.size > 1 else 0.0
    if REST_SPREAD and len(vals) >= 2:
        # an offset reads the same in every rest: rests whose levels scatter beyond their own noise (Cochran's Q above
        # its 99th percentile) are not all rests (a vehicle creeping on its auxiliary load under a noisy sensor passes
        # for one), and the level is known only to that scatter (the between-rest variance in excess of the
        # within-rest, as a random effect). Rests that agree within their noise leave the error as it was
        from scipy.stats import chi2

        each = [reading_level(v) for v in vals]
        levels = np.array([m for m, _ in each])
        within = np.array([max((MEDIAN_SE * sd_k) ** 2 / v.size, 1e-30) for (_, sd_k), v in zip(each, vals)])
        q_stat = float(np.sum((levels - level) ** 2 / within))
        if q_stat > chi2.ppf(0.99, len(vals) - 1):
            excess = max(0.0, float(np.var(levels, ddof=1)) - float(np.mean(within)))
            se = float(np.sqrt(se * se + excess / len(vals)))
    return level, se, float(sum(weights))


class Search:
    """The forward search on one base model, scored by blocked cross-validation (see the module docstring)."""

    def __init__(self, base, folds: Folds, t_ref: float, candidates=None, min_gain: float = 0.10,
                 max_nfev: int = 15, max_steps: int = 3, max_fits: int = 3, h_ref: float = 0.0,
                 noise_sd: float = 0.0, raw=None, base_refit: bool = True, noise_scale: float = 0.0,
                 resistance_growth: bool = RESISTANCE_GROWTH):
        self.base = base
        self.folds = folds
        self.t_ref = float(t_ref)
        self.candidates = list(candidates or EFFECTS) + ([BASE_REFIT] if base_refit else [])
        self.base_params = refittable_params(base)
        self.n_cells = n_cells(base)
        self.min_gain = min_gain
        self.max_nfev = max_nfev
        self.max_steps = max_steps
        self.max_fits = max_fits
        self.h_ref = float(h_ref)
        self.soc0s = [initial_soc(base, p) for p in folds.records]
        self.groups = tuple(range(folds.k)) + (None,)  # the folds, then the all-data fit
        self.bounds = {name: EFFECTS[name]().bounds(base) for name in EFFECTS}
        # the capacity effect is a fade (see FADE_ONLY): cap0 = Q_fit/Q_use ≥ 1; its resistance growth is fitted
        # only when asked for (RESISTANCE_GROWTH): a parameter without bounds here stays at its default
        cap = self.bounds["capacity"]
        self.bounds["capacity"] = {"cap0": (max(cap["cap0"][0], FADE_ONLY), cap["cap0"][1]),
                                   **({"r_growth": cap["r_growth"]} if resistance_growth else {})}
        measured = folds.records if raw is None else raw  # the records as the sensor read them
        self.bias_rest = rest_current(measured, base.capacity_ah, min_s=FIELD_REST_MIN_S)
        self.noise_sd = noise_sd
        #: the raw records' noise → the averaged records' (0: the noise is not measured again as the model improves)
        self.noise_scale = float(noise_scale)
        self.raw = raw
        n_all = np.concatenate([np.ones(p.n, dtype=bool) for p in folds.records])
        self.rows = {j: np.concatenate([folds.train_mask(r, j) for r in range(len(folds.records))])
                     for j in range(folds.k)}
        self.rows[None] = n_all
        #: the evaluation records' measured temperature lies ``T_EVIDENCE_K`` or more from the fit's for a tenth of
        #: their samples or more: direct evidence of a temperature effect (at one ambient a base refit scaling every
        #: resistance mimics the Arrhenius factor, and would be taken for base-fit error)
        self.temperature_measured = bool(all(p.temperature_c is not None for p in folds.records) and np.mean(
            np.concatenate([np.abs(p.temperature_c - self.t_ref) >= T_EVIDENCE_K for p in folds.records])) >= 0.1)
        #: what the rests say about the current sensor: True (it reads an offset), False (it reads none), None (too
        #: few rests to tell)
        self.bias_measured = None
        #: effects added as the fit test's rests show them (:meth:`fit_test_step` with ``bar="not worse"``)
        self.shown_on_fit_test = set()
        #: effects added as the fit test found them and the evaluation records confirmed (:meth:`fit_test_step` with
        #: ``bar="gain"``): dropped at the end only where the model without them is no worse (:data:`FIT_TEST_KEPT`)
        self.found_on_fit_test = set()
        if self.bias_rest is not None:
            mean, se, seconds = self.bias_rest
            lo, hi = self.bounds["current_bias"]["b0"]
            # the rests' own uncertainty (an undithered ADC reads a rest as one level, no scatter: the offset is
            # known to its step, not to zero): wider bounds (0.2 % of 1C beside it until stop 47, 0.05 % until stop
            # 65) let the offset take up another SOC drift of the base (a capacity a few per cent off, a slow branch
            # it lacks), and the offset named is not the sensor's (tests/test_rest_offset_bound.py)
            known = se
            if known <= 0.0:
                known = max(quantisation_step(p.current_a) for p in measured) / np.sqrt(12.0)
            half = 3.0 * known + base.capacity_ah * REST_BOUND_C
            self.bounds["current_bias"] = {"b0": (max(lo, mean - half), min(hi, mean + half))}
            if seconds >= REST_EVIDENCE_S:
                self.bias_measured = bool(abs(mean) > max(4.0 * se, base.capacity_ah * REST_OFFSET_C))

    # ------------------------------------------------------------------ pieces
    def _settings(self, name):
        if name == "temperature":
            return {"t_ref": self.t_ref}
        if name == "hysteresis":
            return {"h_ref": self.h_ref}
        return {}

    def applicable(self, name: str) -> str | None:
        """Why ``name`` cannot be a candidate here (None when it can)."""
        if name == "temperature" and any(p.temperature_c is None for p in self.folds.records):
            return "no temperature column in the data"
        if name == "current_bias" and self.bias_measured is False:
            mean, _, seconds = self.bias_rest
            return (f"the rests ({seconds / 60:.0f} min) read {1000 * mean:.2f} mA: no current-sensor offset beyond "
                    f"{100 * REST_OFFSET_C:g} % of 1C")
        try:
            augment(self.base, [make_effect(name)])
        except Exception as exc:  # a state the base model already has (e.g. hysteresis in ESC)
            return str(exc)
        return None

    def params_of(self, name):
        """``(parameter names, lower, upper, defaults)`` of an effect, or of the base refit."""
        if name == BASE_REFIT:
            names = [f"log_{p}" for p in self.base_params] + [f"offset_{r}" for r in range(len(self.folds.records))]
            v = BASE_OFFSET_V * self.n_cells
            lo = [-BASE_SCALE] * len(self.base_params) + [-v] * len(self.folds.records)
            hi = [BASE_SCALE] * len(self.base_params) + [v] * len(self.folds.records)
            return names, lo, hi, {n: 0.0 for n in names}
        b = self.bounds[name]
        fitted = [p for p in EFFECTS[name].param_names if p in b]  # the search's bounds name what it fits
        return fitted, [b[p][0] for p in fitted], [b[p][1] for p in fitted], EFFECTS[name].defaults

    def builder(self, names, initial_sd=None):
        """``(build, layout, lower, upper)`` for the effects ``names`` fitted jointly (and the base refit when
        :data:`BASE_REFIT` is among them): ``build(θ (…, P))`` gives ``(model, per-record voltage offsets or None)``
        with the parameters at θ (a leading batch axis gives one variant per row). ``initial_sd`` maps an effect to the
        filter SDs of its states (:meth:`~socbench.models.effects.Effect.initial_sd`)."""
        layout, lo, hi = [], [], []
        for name in names:
            pnames, plo, phi, _ = self.params_of(name)
            layout.append((name, tuple(pnames)))
            lo += plo
            hi += phi
        initial_sd = initial_sd or {}

        def build(theta):
            theta = np.asarray(theta, dtype=float)
            effects, j, base, offsets = [], 0, self.base, None
            for name, params in layout:
                if name == BASE_REFIT:
                    nb = len(self.base_params)
                    base = scaled_model(self.base, self.base_params, np.exp(theta[..., j:j + nb]))
                    offsets = theta[..., j + nb:j + len(params)]
                else:
                    vals = {p: theta[..., j + m] for m, p in enumerate(params)}
                    effects.append(make_effect(name, **vals, **self._settings(name),
                                               initial_sd=initial_sd.get(name)))
                j += len(params)
            return (augment(base, effects) if effects else base), offsets

        return build, tuple(layout), np.asarray(lo), np.asarray(hi)

    def fit(self, names, theta0):
        """Fit the effects ``names`` once per fold and once on all data; ``theta0`` is ``(P,)`` or one row per
        group (:attr:`groups`). Returns ``(FoldFit, build, layout)``."""
        build, layout, lo, hi = self.builder(names)
        fit = fit_folds(build, self.folds, theta0, lo, hi, self.soc0s, groups=self.groups,
                        names=[f"{n}.{p}" for n, ps in layout for p in ps], compress=FIT_COMPRESS,
                        max_nfev=self.max_nfev)
        return fit, build, layout

    def trajectories(self, build, thetas):
        """``{group: [Trajectory per record]}`` of the current model of every group (``build`` None: the base)."""
        if build is None:
            same = [Trajectory.simulate(self.base, p, z0) for p, z0 in zip(self.folds.records, self.soc0s)]
            return {g: same for g in self.groups}
        model, offsets = build(thetas)  # one variant per group
        out = {g: [] for g in self.groups}
        for r, (p, z0) in enumerate(zip(self.folds.records, self.soc0s)):
            sim = model.simulate(p, x0=model.x0(z0, (len(self.groups),)))
            u, du = self.base.ocv.value_and_slope(sim.soc)
            y = sim.voltage_v + (0.0 if offsets is None else offsets[:, r:r + 1])
            for b, g in enumerate(self.groups):
                out[g].append(Trajectory(p, y[b], sim.soc[b], u[b], du[b]))
        return out

    def _to_fit(self, ready, r2s, carried=()):
        """The candidates whose bounded fit is run: the ``max_fits`` best-supported families by signature R²
        (at least ``MIN_SIGNATURE_R2``), where the SOC-drift effects (:data:`SOC_DRIFT`, one regressor shape up to
        U(z)/U(1) and charge weighting, which their signatures cannot rank) with R² of ``TIE_R2`` or more are one family
        fitted together; a weaker one takes a slot of its own (one slot for every drift was tried: on the randomised
        benchmark's seeds 31 and 47 no rate moved, on 2026 one pair lost its capacity and one wrong efficiency went);
        and the base refit, which has no signature."""
        chosen, families = [], 0
        drift = [n for n, r2 in zip(ready, r2s) if n in SOC_DRIFT and r2 >= max(MIN_SIGNATURE_R2, TIE_R2)]
        for name, r2 in zip(ready, r2s):
            if name == BASE_REFIT:
                chosen.append(name)
            elif families < self.max_fits and r2 >= MIN_SIGNATURE_R2 and name not in chosen:
                group = drift if name in drift else [name]
                chosen += group
                families += 1
        if self.bias_measured and "current_bias" in ready and "current_bias" not in chosen:
            chosen.append("current_bias")  # the rests measure an offset: direct evidence, whatever the signature says
        chosen += [n for n in carried if n in ready and n not in chosen]
        return chosen

    # ------------------------------------------------------------------ the search
    def fit_test_step(self, name: str, values: dict, plain, evidence: str, bar: str | None = "gain"):
        """The effect ``name`` at ``values``, fitted with the base on the fit test (:mod:`~socbench.identify.
        fit_test_effect`), as a step: the same row in every fold, so no parameter of it is fitted on the evaluation
        data and every block is held out. Scored against ``plain``, the base model fitted without it. None when the
        search would not add it: short of ``bar``, or a branch the search refuses (:meth:`twin_branch`); ``plain``
        within the noise floor does not stop it (:data:`FIT_TEST_FLOORED`). ``bar``: ``"gain"``, the search's score
        and cut; ``"not worse"``, the held-out RMSE not above ``plain``'s — for a branch the fit test's rests show
        (:mod:`socbench.identify.rest_relaxation`), a measurement on the test that the evaluation records need only
        not contradict, which no later step then drops (:meth:`_prune`); None, not held to either (the
        caller judges it beside later steps, :func:`socbench.diagnose.core.search_beside`)."""
        r_before, sse_before, _ = cv_residual(plain, self.folds, self.soc0s)
        rmse_before = float(np.sqrt(np.mean(r_before * r_before)))
        if FIT_TEST_FLOORED and rmse_before <= self.floor() and bar != "not worse":
            return None
        build, layout, lo, hi = self.builder([name])
        pnames = layout[0][1]
        row = np.clip([values[p] for p in pnames], lo, hi)
        thetas = np.tile(row, (len(self.groups), 1))
        # a state's initial value is the record's, not the fit test's: it alone is fitted, fold by fold
        free = [m for m, p in enumerate(pnames) if p in EFFECTS[name].initial_params.values()]
        if free:
            def with_fixed(theta_free):
                full = np.broadcast_to(row, theta_free.shape[:-1] + row.shape).copy()
                full[..., free] = theta_free
                return build(full)

            states = fit_folds(with_fixed, self.folds, row[free], lo[free], hi[free], self.soc0s, groups=self.groups,
                               names=[f"{name}.{pnames[m]}" for m in free], compress=FIT_COMPRESS,
                               max_nfev=self.max_nfev)
            thetas[:, free] = states.thetas
        fit = FoldFit(thetas, self.groups, tuple(f"{name}.{p}" for p in pnames), 0, 0, 0.0)
        c = self._scored(name, fit, build, layout, None, rmse_before, effective_samples(r_before), 0.0)
        if not np.isfinite(c.score) or bar == "gain" and not (c.score > 0 and c.rmse_after
                                                                <= (1.0 - self.min_gain) * rmse_before):
            return None
        if bar == "not worse" and c.rmse_after > rmse_before:
            return None
        if bar == "not worse":
            self.shown_on_fit_test.add(name)
        elif bar == "gain" and FIT_TEST_KEPT:
            self.found_on_fit_test.add(name)
        return dataclasses.replace(c, fit_test=True, fold_ratio=self.worst_block(c, sse_before), evidence=(
            f"{evidence}; held-out RMSE {1000 * rmse_before:.1f} → {1000 * c.rmse_after:.1f} mV (no parameter fitted "
            "on the evaluation data)"))

    def run(self, start: Candidate | None = None):
        """``(final model, steps, rounds, before)``: steps = accepted candidates (effects, and the base refit when it
        was adopted), rounds = every round's list, ``before`` the base model's held-out RMSE (it has no parameter
        fitted on the evaluation data). ``start``: a first step found before the search (:meth:`fit_test_step`)."""
        names, thetas, build = [], None, None  # what was added so far, its rows per group, its builder
        model = self.base
        r_now, sse_now, _ = cv_residual(self.base, self.folds, self.soc0s)
        rmse_now = float(np.sqrt(np.mean(r_now * r_now)))
        before = rmse_now
        self.offsets = None
        steps, rounds, carried = [], [], {}
        if start is not None:
            steps = [start]
            names, thetas, build, model, rmse_now, r_now, sse_now = self._adopt(start)
        for _ in range(self.max_steps + 1):  # max_steps effects, and the base refit once
            # a base branch put back counts (it adds parameters fitted on the records), as it did when it was named
            if sum(st.effect != BASE_REFIT for st in steps) >= self.max_steps:
                break
            trajs = self.trajectories(build, thetas)
            sigs_all = signatures(self.base, trajs[None], self.bounds, self.t_ref)
            n_eff = effective_samples(r_now)
            cands, ready = [], []
            for name in self.candidates:
                if name in names:
                    continue
                why = None if name == BASE_REFIT else self.applicable(name)
                if why is not None:
                    cands.append(Candidate(name, -np.inf, rmse_now, rmse_now, {}, 0.0, f"not applicable: {why}"))
                else:
                    ready.append(name)
            ready.sort(key=lambda n: sigs_all[n].r2 if n in sigs_all else 0.0, reverse=True)
            r2s = [sigs_all[n].r2 if n in sigs_all else 0.0 for n in ready]
            fit_now = self._to_fit(ready, r2s, carried)
            fold_sigs = None
            for name, r2 in zip(ready, r2s):
                sig = sigs_all.get(name)
                if name in fit_now:
                    if fold_sigs is None:  # each fold's starting guesses from its own training samples only
                        fold_sigs = {g: signatures(self.base, trajs[g], self.bounds, self.t_ref, self.rows[g])
                                     for g in self.groups if g is not None}
                        fold_sigs[None] = sigs_all
                    cand = self._try(name, names, thetas, fold_sigs, sig, rmse_now, n_eff)
                    if name in carried:  # a second start: the effect where it was alone, the refit at identity
                        cand = self._better(cand, self._try(name, names, thetas, fold_sigs, sig, rmse_now, n_eff,
                                                            start=self._carried_start(carried[name], names)), sig,
                                            n_eff)
                    guessed = any(fold_sigs[g][name].guess for g in self.groups if name in fold_sigs.get(g, {}))
                    if SECOND_START and guessed:  # the effect at its defaults (see SECOND_START)
                        cand = self._better(cand, self._try(name, names, thetas, {}, sig, rmse_now, n_eff), sig,
                                            n_eff)
                    cands.append(cand)
                else:
                    cands.append(Candidate(name, -np.inf, rmse_now, rmse_now, {}, r2,
                                           f"residual signature {'' if sig is None else sig.regressor} explains "
                                           f"{100 * r2:.1f} % of the residual variance: not fitted"))
            for c in cands:
                c.fold_ratio = self.worst_block(c, sse_now)
            cands.sort(key=lambda c: (c.score, c.signature_r2), reverse=True)
            rounds.append({"candidates": cands, "signatures": sigs_all, "trajectory": trajs[None], "model": model})
            best = self._choose(cands)
            # a current offset the rests measure is a measurement, not an inference from the voltage: it is added
            # first (fitted within the rests' bounds) whatever it does to the held-out error — on a record whose
            # error another effect dominates (a cold cell) it cuts nothing until that effect is added beside it
            measured = best is not None and best.effect == "current_bias" and bool(self.bias_measured)
            at_floor = rmse_now <= self.floor(BASE_REFIT in names)
            # at the floor only an effect that cuts the error by FLOOR_GAIN goes on
            strong = [c for c in cands if c.effect != BASE_REFIT and np.isfinite(c.score) and c.score > 0
                      and c.rmse_after <= (1.0 - FLOOR_GAIN) * rmse_now] \
                if at_floor and not measured and FLOOR_GAIN is not None else []
            below_floor = bool(strong)
            if below_floor:
                best, at_floor = max(strong, key=lambda c: c.score), False
            if best is None or not np.isfinite(best.score) or not measured and (
                    best.score <= 0 or best.rmse_after > (1.0 - self.min_gain) * rmse_now or at_floor):
                joint = None if at_floor else self._joint_with_refit(cands, names, fold_sigs, sigs_all, rmse_now,
                                                                     n_eff)
                if joint is None:
                    break
                best = joint
            else:
                best = self._beyond_refit(best, cands, names, fold_sigs, sigs_all, n_eff, below_floor)
                if below_floor and best.effect == BASE_REFIT:  # the refit explains it as well: the floor holds
                    break
            steps.append(best)
            # after the base refit, the effects that scored best beside it are fitted again, jointly with it, whatever
            # their signature on the refitted residual: the refit takes up part of an effect (a scaled resistance is
            # an Arrhenius factor at one temperature, a slow branch rescaled is part of a missing one), so what is
            # left shows little of its shape, while the joint fit says whether the effect explains more than the refit
            carried = {c.effect: c for c in [c for c in cands if c.effect != BASE_REFIT and np.isfinite(c.score)
                                             and c.score > 0 and c.fit is not None][:CARRY]} \
                if best.effect == BASE_REFIT else {}
            names, thetas, build, model, rmse_now, r_now, sse_now = self._adopt(best)
        if steps:
            steps = self._prune(self._swap_drift(steps, r_now), r_now)
            model, self.offsets = self.builder([n for n, _ in steps[-1].layout])[0](steps[-1].fit.row(None))
        return model, steps, rounds, before

    def _adopt(self, step: Candidate):
        """The search's state with ``step`` in the model: ``(names, rows per group, builder, all-data model, held-out
        RMSE, held-out residual, per-block squared error)``; the records' voltage offsets are set and the noise
        measured again on the model's residual."""
        names = [n for n, _ in step.layout]
        build = self.builder(names)[0]
        model, self.offsets = build(step.fit.row(None))
        self._remeasure_noise(model)
        return names, step.fit.thetas, build, model, step.rmse_after, step.held_residual, step.fold_sse

    def _swap_drift(self, steps, r_now):
        """``steps`` with each SOC drift it named (:data:`SOC_DRIFT`) exchanged for another when that one, fitted
        jointly with everything else the search added, cuts the held-out RMSE by :attr:`min_gain` (a swap step of
        stepwise selection, among effects with one parameter each, held to the same gain as an addition: where the
        two explain about as well, the records do not tell them apart and the first stays).

        The four drifts leave nearly the same residual, and the one that wins a round alone can owe its lead to
        what it took up of a later step's share (a fade comes with grown resistances, which the base refit takes
        later; a leak at its bound mimics a fade on a record that discharges steadily). Fitted beside the later
        steps, the drift the records hold explains more."""
        last = steps[-1]
        n_eff = effective_samples(r_now)
        empty = {g: {} for g in self.groups}
        # a current offset the rests measure is direct evidence (no model needed): it is never swapped away
        for e in [n for n, _ in last.layout if n in SOC_DRIFT and not self.measured_input(n)]:
            rest, thetas = self._without(steps[-1], e)
            names = [n for n, _ in steps[-1].layout]
            best = steps[-1]
            for d in SOC_DRIFT:
                if d in names or d not in self.candidates or self.applicable(d) is not None:
                    continue
                cand = self._try(d, rest, thetas, empty, None, best.rmse_after, n_eff)
                if np.isfinite(cand.score) and cand.rmse_after <= (1.0 - self.min_gain) * best.rmse_after:
                    best = cand
            if best is steps[-1]:
                continue
            i = next(k for k, st in enumerate(steps) if st.effect == e)
            steps = list(steps)
            note = (f"; {best.effect} fitted in place of {e} beside the later steps: held-out RMSE "
                    f"{1000 * steps[-1].rmse_after:.1f} → {1000 * best.rmse_after:.1f} mV (swapped)")
            steps[i] = dataclasses.replace(steps[i], effect=best.effect, evidence=steps[i].evidence + note,
                                           params=best.params if i == len(steps) - 1 else steps[i].params)
            steps[-1] = dataclasses.replace(steps[-1], rmse_after=best.rmse_after, held_residual=best.held_residual,
                                            fold_sse=best.fold_sse, fit=best.fit, layout=best.layout,
                                            effects=best.effects)
        return steps

    def measured_input(self, name: str) -> bool:
        """Whether the records measure effect ``name`` directly (a current offset their rests read, a temperature that
        differs from the fit's): such an effect is evidence, not an inference, and no later step takes it away."""
        return (name == "current_bias" and bool(self.bias_measured)) or (name == "temperature"
                                                                         and self.temperature_measured)

    def alike(self, step: Candidate, rounds) -> list:
        """The other SOC drifts the records hardly tell from the drift ``step`` names: in the last round that fitted
        ``step``'s drift (the round it was added in; for a drift swapped in at the end, :meth:`_swap_drift`, the last
        one that tried it), each other drift fitted there beside what was added before whose held-out RMSE the named
        drift's does not undercut by :attr:`min_gain` (the bar any effect must clear to be added).
        ``[{"effect", "rmse_v_after", "named_rmse_v_after"}]``; empty for any other step, and for a drift the records
        measure (:meth:`measured_input`), on either side.

        The four drifts move the SOC along nearly the same path (charge moved, time, charge put in), and the search
        names one by rules beyond the held-out error (the nested test against the base refit, the swap beside it,
        the bounds); where another explains the records within the gain, which one the cell has is not settled by
        them: a rest of hours (a leak goes on, a fade does not) or a capacity test is. Reported, not acted on."""
        if step.effect not in SOC_DRIFT or not step.named or self.measured_input(step.effect):
            return []
        for rnd in reversed(rounds):
            own = next((c for c in rnd["candidates"] if c.effect == step.effect and np.isfinite(c.score)), None)
            if own is not None:
                break
        else:
            return []
        return [{"effect": c.effect, "rmse_v_after": float(c.rmse_after), "named_rmse_v_after": float(own.rmse_after)}
                for c in rnd["candidates"] if c.effect in SOC_DRIFT and c.effect != step.effect
                and not self.measured_input(c.effect) and np.isfinite(c.score)
                and own.rmse_after > (1.0 - self.min_gain) * c.rmse_after]

    @staticmethod
    def _columns(layout) -> list:
        """The slice of the parameter row (θ's columns) that each ``(name, params)`` entry of ``layout`` holds, in
        order."""
        ends = np.cumsum([0] + [len(ps) for _, ps in layout])
        return [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])]

    @staticmethod
    def _without(step: Candidate, effect: str):
        """``(names, rows)``: what ``step`` fitted, without ``effect`` — the other names and their columns of every
        group's θ (None when nothing is left)."""
        kept = [(n, sl) for (n, _), sl in zip(step.layout, Search._columns(step.layout)) if n != effect]
        if not kept:
            return [], None
        cols = np.concatenate([np.arange(sl.start, sl.stop) for _, sl in kept])
        return [n for n, _ in kept], step.fit.thetas[:, cols]

    def _prune(self, steps, r_now):
        """``steps`` without the named effects the final model does not need: the backward half of stepwise
        selection. Each named effect is refitted out (everything else fitted jointly again, every fold); the one whose
        removal costs least goes when the model without it is within :attr:`min_gain` of the final held-out RMSE
        (``RMSE_final ≥ (1 − min_gain)·RMSE_without``, the forward acceptance read backwards); then again on what is
        left. An effect that won an early round by taking up what a later one explains better (a leak standing in for a
        fade before the base refit took the aged cell's grown resistances) adds nothing beside it at the end, and a
        diagnosis should not name it. Measured inputs are never dropped (a current offset the rests measure, the
        temperature where the records' measured temperature differs from the fit's), nor a branch the fit test's rests
        show (:meth:`fit_test_step`); an effect the fit test found that predicted the evaluation records ``min_gain``
        better with nothing of it fitted on them goes only where the model without it is no worse
        (:data:`FIT_TEST_KEPT`)."""
        n_eff = effective_samples(r_now)
        empty = {g: {} for g in self.groups}
        while True:
            final = steps[-1]
            names = [n for n, _ in final.layout]
            droppable = [n for n in names if n != BASE_REFIT and not self.measured_input(n)
                         and n not in self.shown_on_fit_test]
            trials = []
            for e in droppable:
                rest, rows = self._without(final, e)
                if not rest:  # the only thing added: the forward step already measured it against the base model
                    continue
                c = self._try(rest[-1], rest[:-1], None, empty, None, final.rmse_after, n_eff, start=rows)
                if c.fit is not None and np.isfinite(c.rmse_after):
                    trials.append((c.rmse_after, e, c))
            if not trials:
                return steps
            # each effect's bar: within min_gain of the final RMSE; an effect the fit test found, no worse
            trials = [t for t in trials if (t[0] <= final.rmse_after if t[1] in self.found_on_fit_test
                                            else final.rmse_after >= (1.0 - self.min_gain) * t[0])]
            if not trials:
                return steps
            rmse_without, e, c = min(trials, key=lambda x: x[0])
            steps = [st for st in steps if st.effect != e]
            if not steps:
                return steps
            bar = "no worse" if e in self.found_on_fit_test else f"less than {100 * self.min_gain:.0f} % worse"
            note = (f"; {e} dropped at the end: refitted without it, held-out RMSE {1000 * final.rmse_after:.1f} → "
                    f"{1000 * c.rmse_after:.1f} mV ({bar})")
            steps[-1] = dataclasses.replace(steps[-1], evidence=steps[-1].evidence + note, rmse_after=c.rmse_after,
                                            held_residual=c.held_residual, fold_sse=c.fold_sse, fit=c.fit,
                                            layout=c.layout, effects=c.effects)

    @staticmethod
    def worst_block(c: Candidate, sse_before) -> float:
        """The largest ratio over the blocks of ``c``'s held-out squared error to ``sse_before`` (NaN unfitted)."""
        if c.fold_sse is None or sse_before is None:
            return float("nan")
        return float(np.max(c.fold_sse / np.maximum(sse_before, 1e-30)))

    def _remeasure_noise(self, model):
        """The voltage noise measured again on the residual of ``model`` (what was added so far, all-data fit), kept
        when lower. The second difference of the residual keeps, beside the sensor's white noise, the model's error
        where the current changes from sample to sample (a drive cycle's current moves every second): a base model
        whose resistances are far off (the cold) reads that error as noise, and the floor it sets then stops the search
        while the error is many times the noise. The better model reads less of it."""
        if self.raw is None or self.noise_scale <= 0:
            return
        try:
            sigma = residual_noise(model, self.raw)
        except Exception:  # an augmented model the raw records drive out of its domain: keep the noise as it was
            return
        if sigma > 0:
            self.noise_sd = min(self.noise_sd, sigma * self.noise_scale)

    def floor(self, refitted: bool = False) -> float:
        """No effect is added once the held-out RMSE is at or below this (:func:`noise_floor` of the noise measured
        so far), but for one that cuts it by :data:`FLOOR_GAIN`."""
        return noise_floor(self.noise_sd, refitted)

    def _choose(self, cands):
        """The best-scoring candidate, except that an effect within :data:`PARSIMONY` of a winning base refit is
        preferred (a named effect with fewer parameters explains the same) where it would be added itself
        (:data:`PARSIMONY_ACCEPTED`), and that a current-sensor offset the
        rests measure comes first when it explains a share of the residual of its own (:attr:`min_gain`): the rest
        current *is* the offset (direct evidence, no model needed), while a leak or a fade reads none. The same for
        the temperature when the records' measured temperature differs from the fit's (:data:`T_EVIDENCE_K`)."""
        ok = [c for c in cands if np.isfinite(c.score)]
        if not ok:
            return cands[0] if cands else None
        best = max(ok, key=lambda c: c.score)
        if self.bias_measured:  # the rests measure the offset: it is taken whatever the voltage says of it
            bias = [c for c in ok if c.effect == "current_bias"]
            if bias:
                return bias[0]
        if self.temperature_measured:  # likewise the measured temperature: a base refit would only mimic it
            temp = [c for c in ok if c.effect == "temperature" and added_alone(c, self.min_gain)]
            if temp:
                return temp[0]
        if best.effect == BASE_REFIT:
            rivals = [c for c in ok if c.effect != BASE_REFIT and c.rmse_after <= (1.0 + PARSIMONY) * best.rmse_after
                      and (added_alone(c, self.min_gain) if PARSIMONY_ACCEPTED else c.score > 0)]
            if rivals:
                return max(rivals, key=lambda c: c.score)
        return best

    def _beyond_refit(self, best, cands, names, fold_sigs, sigs_all, n_eff, below_floor: bool = False):
        """``best``, or the base refit when ``best`` is an effect that explains no more than the refit does.

        Where the base refit also cut the error this round, a base-fit error is part of the residual, and a flexible
        effect may have taken it up instead. The effect is fitted jointly with the refit (nested): unless it cuts the
        refit's held-out RMSE by :attr:`min_gain`, what it explained is what a better base fit explains, and the
        refit is taken (never named; the effect is fitted again beside it in the next round). Effects whose evidence
        is a measured input are exempt: the temperature (the measured temperature differs from the fit's) and a
        current offset the rests measure. ``below_floor`` (the search goes on below its noise floor,
        :data:`FLOOR_GAIN`): none is, and the effect must cut the refit's error by ``FLOOR_GAIN`` instead of
        :attr:`min_gain` — what a flexible effect takes there beyond the refit can be an offset the refit's per-record
        offset takes too (a measured temperature's entropic term, a hysteresis state fitted fold by fold)."""
        if best.effect == BASE_REFIT or BASE_REFIT in names or not below_floor and (
                best.effect == "temperature" or (best.effect == "current_bias" and self.bias_measured)):
            return best
        refit = next((c for c in cands if c.effect == BASE_REFIT and np.isfinite(c.score)
                      and added_alone(c, self.min_gain)), None)
        if refit is None or fold_sigs is None:
            return best
        gain = FLOOR_GAIN if below_floor else self.min_gain
        joint = self._try(best.effect, names + [BASE_REFIT], refit.fit.thetas, fold_sigs, sigs_all.get(best.effect),
                          refit.rmse_after, n_eff)
        best.evidence += (f"; fitted jointly with the base refit: held-out RMSE {1000 * refit.rmse_after:.1f} → "
                          f"{1000 * joint.rmse_after:.1f} mV")
        if np.isfinite(joint.score) and joint.rmse_after <= (1.0 - gain) * refit.rmse_after:
            if DRIFT_BESIDE_REFIT and best.effect in SOC_DRIFT and not self.measured_input(best.effect):
                return self._drift_beside_refit(best, joint, cands, names, refit, fold_sigs, sigs_all, n_eff)
            return best
        refit.evidence += (f"; {best.effect} explained no more than this refit (jointly with it "
                           f"{1000 * joint.rmse_after:.1f} mV)")
        return refit

    def _joint_with_refit(self, cands, names, fold_sigs, sigs_all, rmse_now, n_eff):
        """The best of the :data:`JOINT_TRIES` best-scoring effects of a round that would stop, each fitted jointly
        with the base refit (from where it was fitted alone, the refit at identity), when it cuts the held-out RMSE by
        :attr:`min_gain` below both the current model's and the refit's alone; else None. Only in the first round
        (nothing added yet).

        An effect the HPPC fit took part of into the base's own parameters can fail alone (the base holds that part
        already, wrongly shaped) while the refit fails alone too (it cannot make what the structure lacks): a hidden
        branch part of which went to R0 and the base's branch; a branch slower than the HPPC's rests, which depresses
        every OCV point the fit reads at the rests' ends. Fitted together, each takes its own share. The test is the
        nested test of :meth:`_beyond_refit` (the effect must cut the refit's error by ``min_gain``), asked where
        neither passes alone.

        On the randomised benchmark (against the search without it): seed 2026, named first 73 → 75 of 120, cut
        ≥ 30 % 86 → 88, nulls and pairs unchanged (39/40, 14/40), one wrong name where nothing was named (an
        efficiency for a hidden branch), SOC not worse 187 → 185 of 200 (two cases whose filter, on the better model,
        trusts a voltage whose residual is still structured); development seed 31 named first 42 → 46 of 72 and cut
        ≥ 30 % 52 → 55, nothing else changed; seed 47 named first unchanged, two wrong names where nothing was named
        (a leak for an efficiency within the noise, a hysteresis in a pair), SOC not worse 114 → 113 of 120. Asked
        in later rounds too it added two false second effects on seed 47 for one pair more: it is asked in the first
        round only."""
        if names or BASE_REFIT not in self.candidates or fold_sigs is None:
            return None
        refit = next((c for c in cands if c.effect == BASE_REFIT and np.isfinite(c.score)), None)
        bar = (1.0 - self.min_gain) * min(rmse_now, refit.rmse_after if refit is not None else rmse_now)
        # an effect fitted to its null alone (a drift at zero: the held-out error unchanged) is, beside the refit,
        # the refit alone, which failed already: the tries go to effects the fit moved
        tried = [c for c in cands if c.effect != BASE_REFIT and np.isfinite(c.score) and c.fit is not None
                 and not self.measured_input(c.effect)
                 and abs(c.rmse_after - rmse_now) > NULL_FIT_TOL * rmse_now][:JOINT_TRIES]
        refit_penalty = self._refit_penalty(n_eff)
        best = None
        for alone in tried:
            joint = self._try(alone.effect, names + [BASE_REFIT], None, fold_sigs, sigs_all.get(alone.effect),
                              rmse_now, n_eff, start=self._carried_start(alone, names))
            joint.score -= refit_penalty
            if np.isfinite(joint.score) and joint.score > 0 and joint.rmse_after <= bar \
                    and (best is None or joint.score > best.score):
                best = dataclasses.replace(joint, evidence=joint.evidence + (
                    f"; fitted jointly with the base refit, where neither cut the error by "
                    f"{100 * self.min_gain:.0f} % alone ({1000 * alone.rmse_after:.1f} mV alone, the refit "
                    f"{'not fitted' if refit is None else f'{1000 * refit.rmse_after:.1f} mV'})"))
        return best

    def _drift_beside_refit(self, best, joint, cands, names, refit, fold_sigs, sigs_all, n_eff):
        """``best``, an SOC drift that passed the nested test against the base refit (``joint``: it fitted jointly
        with ``refit``), or another drift of its round fitted jointly with the refit the same way, where that one lies
        :attr:`min_gain` below both ``best`` and ``joint`` in held-out RMSE (see :data:`DRIFT_BESIDE_REFIT`): that
        joint fit is the step."""
        rival = None
        for c in cands:
            if c.effect not in SOC_DRIFT or c.effect == best.effect or not np.isfinite(c.score) or c.fit is None \
                    or self.measured_input(c.effect):
                continue
            j = self._try(c.effect, names + [BASE_REFIT], refit.fit.thetas, fold_sigs, sigs_all.get(c.effect),
                          best.rmse_before, n_eff)
            if np.isfinite(j.score) and (rival is None or j.rmse_after < rival.rmse_after):
                rival = j
        # below the winner as it would be added (alone) and as it was fitted beside the refit
        if rival is None or rival.rmse_after > (1.0 - self.min_gain) * min(best.rmse_after, joint.rmse_after):
            return best
        rival.score -= self._refit_penalty(n_eff)
        return dataclasses.replace(rival, evidence=rival.evidence + (
            f"; fitted jointly with the base refit in place of {best.effect}, which won the round alone "
            f"({1000 * best.rmse_after:.1f} mV) but beside the refit explains less ({1000 * joint.rmse_after:.1f} "
            f"against {1000 * rival.rmse_after:.1f} mV)"))

    def _refit_penalty(self, n_eff: float) -> float:
        """What a joint step pays in score for the base refit's parameters beside its effect (a candidate's own score
        counts the effect's alone): ``2·p_refit/n_eff``, the AIC-like term of :meth:`_scored`."""
        return 2.0 * len(self.params_of(BASE_REFIT)[0]) / n_eff

    def _carried_start(self, alone: Candidate, names) -> np.ndarray:
        """Rows ``(groups, P)`` for the joint fit of ``alone``'s effect beside the refit adopted after it: what was
        added before and the effect as fitted without the refit, the refit at identity (zero log-scales and
        offsets)."""
        n_refit = len(self.params_of(BASE_REFIT)[0])
        p_effect = len(alone.layout[-1][1])
        rows = alone.fit.thetas
        return np.hstack([rows[:, :rows.shape[1] - p_effect], np.zeros((rows.shape[0], n_refit)),
                          rows[:, rows.shape[1] - p_effect:]])

    def _better(self, a: Candidate, b: Candidate, sig, n_eff) -> Candidate:
        """Of two fits of the same candidate from different starts, each group's (fold's, and the all-data fit's)
        parameter row from the start whose fit has the lower error on that group's *training* samples — never chosen
        by the held-out score — and the candidate scored again on the rows so chosen (``sig``, ``n_eff`` as for
        :meth:`_try`). A start that suits one fold may lose another (each fold's guess comes from its own training
        samples, and a bounded fit of few evaluations stays near its start)."""
        if b.fit is None:
            return a
        if a.fit is None:
            return b
        sa, sb = self._group_sse(a), self._group_sse(b)
        pick = sb < sa
        if not pick.any():
            return a
        if pick.all():
            return b
        fit = dataclasses.replace(a.fit, thetas=np.where(pick[:, None], b.fit.thetas, a.fit.thetas),
                                  nfev=a.fit.nfev + b.fit.nfev, njev=a.fit.njev + b.fit.njev,
                                  seconds=a.fit.seconds + b.fit.seconds)
        build = self.builder([n for n, _ in a.layout])[0]
        return self._scored(a.effect, fit, build, a.layout, sig, a.rmse_before, n_eff,
                            a.seconds + b.seconds)

    def _group_sse(self, c: Candidate) -> np.ndarray:
        """``(groups,)``: each group's row of ``c``'s fit, its squared error on that group's training samples (a
        non-finite prediction counts 1 V² a sample)."""
        build = self.builder([n for n, _ in c.layout])[0]
        ys = simulate_records(build, c.fit.thetas, self.folds.records, self.soc0s)
        e = np.concatenate([y - p.voltage_v for y, p in zip(ys, self.folds.records)], axis=1)
        e2 = np.where(np.isfinite(e), e, 1.0) ** 2
        return np.array([float(np.sum(e2[k, self.rows[g]])) for k, g in enumerate(self.groups)])

    def _try(self, name, names, thetas, fold_sigs, sig, rmse_now, n_eff, start=None) -> Candidate:
        t0 = _time.perf_counter()
        pnames, _, _, defaults = self.params_of(name)
        if start is not None:
            theta0 = start
        else:
            start = np.array([[fold_sigs[g][name].guess.get(p, defaults[p]) if name in fold_sigs.get(g, {})
                               else defaults[p] for p in pnames] for g in self.groups])
            theta0 = start if thetas is None else np.hstack([thetas, start])
        try:
            fit, build, layout = self.fit(names + [name], theta0)
        except Exception as exc:  # a failed fit scores nothing but is reported
            return self._failed(name, sig, rmse_now, exc, _time.perf_counter() - t0)
        return self._scored(name, fit, build, layout, sig, rmse_now, n_eff, _time.perf_counter() - t0)

    @staticmethod
    def _failed(name, sig, rmse_now, exc, seconds) -> Candidate:
        """The candidate ``name`` whose fit or scoring raised ``exc``: no score, the error as its evidence."""
        return Candidate(name, -np.inf, rmse_now, rmse_now, {}, 0.0 if sig is None else sig.r2,
                         f"fit failed: {type(exc).__name__}: {exc}", seconds=seconds)

    def _scored(self, name, fit, build, layout, sig, rmse_now, n_eff, seconds) -> Candidate:
        """The candidate ``name`` with the fitted rows ``fit``: held-out residual, score and evidence."""
        t0 = _time.perf_counter()
        pnames = self.params_of(name)[0]
        r2 = 0.0 if sig is None else sig.r2
        try:
            r_after, sse, _ = cv_residual(build, self.folds, self.soc0s, fit.folds())
        except Exception as exc:  # a failed fit scores nothing but is reported
            return self._failed(name, sig, rmse_now, exc, seconds + _time.perf_counter() - t0)
        rmse_after = float(np.sqrt(np.mean(r_after * r_after)))
        p = len(pnames)
        score = float(np.log(rmse_now**2 / max(rmse_after**2, 1e-30)) - 2.0 * p / n_eff)
        final, offsets = build(fit.row(None))
        row = fit.row(None)
        params = {k: float(v) for k, v in zip(pnames, row[self._columns(layout)[-1]])}
        if name == BASE_REFIT:
            params = {**{k[4:]: float(np.exp(v)) for k, v in params.items() if k.startswith("log_")},
                      **{k: v for k, v in params.items() if k.startswith("offset_")}}
            evidence = (f"the base model's parameters scaled ({format_params(params)}) and each record's voltage "
                        f"offset, refitted on the evaluation data: held-out RMSE {1000 * rmse_now:.1f} → "
                        f"{1000 * rmse_after:.1f} mV ({100 * (1 - rmse_after / rmse_now):.0f} % lower)")
        else:
            regressor = "" if sig is None else sig.regressor
            evidence = (f"residual signature {regressor}: explains {100 * r2:.0f} % of the residual variance; "
                        f"fitted in bounds ({format_params(params)}): held-out RMSE {1000 * rmse_now:.1f} → "
                        f"{1000 * rmse_after:.1f} mV ({100 * (1 - rmse_after / rmse_now):.0f} % lower)")
        if name == "current_bias" and self.bias_rest is not None:
            evidence += f"; rests read {1000 * self.bias_rest[0]:.1f} mA (bounds b to it)"
        at_bound = bound_hit(params, self.bounds[name], params) if name in SOC_DRIFT \
            and not self.measured_input(name) else None
        if DRIFT_AT_BOUND and at_bound is not None:  # a drift at the end of its physical range stands in for another
            score = -np.inf
            evidence += f"; {at_bound}: a drift at the limit of its physical range stands in for something else"
        slow = self.at_slow_end(name, params) if SLOW_END_RULE else None
        if slow is not None:
            score = -np.inf
            evidence += f"; {slow}: a state that never settles within the records stands in for a drift"
        unmoved = self.resistance_unmoved(name, params)
        if unmoved is not None:
            score = -np.inf
            evidence += f"; {unmoved}: its entropic term alone, an offset the temperature indexes, stands in for it"
        far = self.at_far_end(name, params) if FAR_END_RULE else None
        if far is not None:
            score = -np.inf
            evidence += f"; {far}: as much as its range allows, it stands in for something else"
        base_branch = False
        if name == "extra_rc":
            refit = dict(zip(dict(layout).get(BASE_REFIT, ()), self._refit_row(layout, row)))
            twin = self.twin_branch(10.0 ** params["log10_tau"], refit)
            spare = self.spare_branch(refit) if twin is None else None
            if twin is not None:  # not an effect the structure lacks: a branch it has, misfitted
                score = -np.inf
                evidence += (f"; its τ = {10.0 ** params['log10_tau']:.0f} s lies within ×{TWIN_TAU:g} of the base "
                             f"model's branch {twin[0]} (τ = {twin[1]:.0f} s{', as refitted' if refit else ''}): a "
                             "misfit of that branch, left to the base refit")
            elif spare is not None:  # the base's own branch put back: kept (scored as it is), never named
                base_branch = True
                (b1, t1), other = spare
                as_refitted = ", as refitted" if refit else ""
                where = (f"branch {b1} lies at τ = {t1:.3g} s{as_refitted}, slower than any branch (a ramp)"
                         if other is None else
                         f"branches {b1} and {other[0]} lie within ×{TWIN_TAU:g} of each other (τ = {t1:.0f} and "
                         f"{other[1]:.0f} s{as_refitted})")
                evidence += (f"; the base model's {where}: one of its branches is spare, and this branch is where it "
                             "belongs, a misfit of the base, kept in the model as base-fit error and not named")
        return Candidate(name, score, rmse_now, rmse_after, params, r2, evidence,
                         tuple(getattr(final, "effects", ())), seconds + _time.perf_counter() - t0, r_after, sse, fit,
                         layout, base_branch=base_branch)

    def at_slow_end(self, name: str, params: dict) -> str | None:
        """Where effect ``name``'s fitted ``params`` rest at the slow end of its rate's range (:data:`SLOW_END`, within
        :data:`~socbench.identify.fit_test_effect.BOUND_TOL` of the range), that as a phrase; else None."""
        if name not in SLOW_END or not params:
            return None
        p, end = SLOW_END[name]
        lo, hi = self.bounds[name][p]
        if abs(params[p] - (lo, hi)[end]) > BOUND_TOL * (hi - lo):
            return None
        return f"{p} = {params[p]:.4g} at the {('lower', 'upper')[end]} end of [{lo:.4g}, {hi:.4g}]"

    def at_far_end(self, name: str, params: dict) -> str | None:
        """Where effect ``name``'s fitted ``params`` rest at the upper end of the range of its :data:`FAR_END`
        parameter (within :data:`~socbench.identify.fit_test_effect.BOUND_TOL` of the range), that as a phrase; else
        None."""
        if name not in FAR_END or not params:
            return None
        p = FAR_END[name]
        lo, hi = self.bounds[name][p]
        if params[p] < hi - BOUND_TOL * (hi - lo):
            return None
        return f"{p} = {params[p]:.4g} at the upper end of [{lo:.4g}, {hi:.4g}]"

    @staticmethod
    def resistance_unmoved(name: str, params: dict) -> str | None:
        """Where the temperature effect's fitted ``params`` move no resistance (``Ea`` below
        :data:`TEMPERATURE_EA_MIN`), that as a phrase; else None."""
        if name != "temperature" or not params or TEMPERATURE_EA_MIN is None or params["Ea"] >= TEMPERATURE_EA_MIN:
            return None
        return (f"Ea = {params['Ea']:.3g} J/mol < {TEMPERATURE_EA_MIN:.3g}: the resistances barely move with the "
                "temperature")

    @staticmethod
    def _refit_row(layout, row) -> np.ndarray:
        """The base refit's entries of the parameter row ``row`` (empty when the refit is not in ``layout``)."""
        for (name, _), sl in zip(layout, Search._columns(layout)):
            if name == BASE_REFIT:
                return np.asarray(row[sl])
        return np.zeros(0)

    def twin_branch(self, tau: float, refit: dict | None = None):
        """``(branch, τ_j)`` of a base-model RC branch whose time constant (``R_j·C_j`` at SOC 0.5, times
        ``exp(log_Rj + log_Cj)`` of the base refit's parameters ``refit`` when given) lies within ×``TWIN_TAU`` of
        ``tau``, or None: a further branch there cannot be told from a misfit of that one."""
        refit = refit or {}
        for branch, tj in self.refitted_taus(refit).items():
            if tj > 0 and abs(np.log(tau / tj)) <= np.log(TWIN_TAU):
                return branch, tj
        return None

    def refitted_taus(self, refit: dict | None = None) -> dict:
        """``{branch: τ_j}`` of the base model's RC branches (``R_j·C_j`` at SOC 0.5), times ``exp(log_Rj + log_Cj)`` of
        the base refit's parameters ``refit`` when given."""
        refit = refit or {}
        out = {}
        for branch, tj in branch_time_constants(self.base.params, self.base.required_params()).items():
            j = branch[1:branch.index("C")]
            out[branch] = tj * float(np.exp(refit.get(f"log_R{j}", 0.0) + refit.get(f"log_C{j}", 0.0)))
        return out

    def spare_branch(self, refit: dict | None = None):
        """``((branch, τ), (branch, τ))``: two of the base model's RC branches (as the base refit made them, see
        :meth:`refitted_taus`) within ×``TWIN_TAU`` of each other; ``((branch, τ), None)``: a branch slower than any
        extra branch may be (the upper end of its ``log10_tau`` range, where the extra branch itself is a ramp,
        :data:`SLOW_END`); else None. Two branches at one time constant are one branch, and a branch slower than that
        is a ramp (its capacitor takes the charge a record moves without relaxing): either way the structure has a
        branch to spare, and an extra branch the search finds is where that one belongs (base-fit error, not a branch
        the structure lacks). A fit test that shows no slow branch (short pulses, its step discharges logged in a gap)
        leaves a DP fit's second branch there."""
        items = [(b, t) for b, t in self.refitted_taus(refit).items() if t > 0]
        slowest = 10.0 ** self.bounds["extra_rc"]["log10_tau"][1] if "extra_rc" in self.bounds else np.inf
        for b, t in items:
            if t > slowest:  # a ramp, not a branch: the structure's branch is unused
                return (b, t), None
        for a in range(len(items)):
            for b in range(a + 1, len(items)):
                if abs(np.log(items[a][1] / items[b][1])) <= np.log(TWIN_TAU):
                    return items[a], items[b]
        return None

    def fold_models(self, step: Candidate, layout=None, initial_sd=None, fold: int | None = None):
        """``(model, offsets)`` of every fold after ``step`` (one variant per fold on a leading batch axis of shape
        ``layout``, default ``(k,)``), or of fold ``fold`` alone."""
        build = self.builder([n for n, _ in step.layout], initial_sd)[0]
        th = step.fit.folds()
        if fold is not None:
            return build(th[fold])
        return build(th.reshape((layout or (th.shape[0],)) + th.shape[1:]))


def format_params(params: dict) -> str:
    """``name=value, …`` of the evidence texts."""
    return ", ".join(f"{k}={v:.4g}" for k, v in params.items())
