"""HPPC analysis: the current sensor's rest level, rests and pulses, OCV points, the SOC axis and pulse resistances;
OCV curves from a slow (C/20) test.

An HPPC record (ECM_SPEC §1; Panasonic 18650PF, Kollmeyer 2018, doi:10.17632/wykht8y7tg.1; ORNL Nissan Leaf cell,
Wiggins, Allu & Wang) is a sequence of pulse *sets*, one per SOC level, separated by discharge steps (or, in the
Panasonic files, by a gap in the record during which the step happened) and long rests. Real instruments add noise, an
offset and quantisation to the current and log at 0.1–60 s, so nothing below is a fixed fraction of the peak current
or a fixed duration where the record can tell. The analysis

1. **measures the current sensor on the rests** (:func:`rest_level`): at rest the cell carries no current, so the
   sensor reads its offset ``b`` plus noise. With ``P = max|I|`` and the *near-zero band* ``|I| ≤ 5 % P``:

   * rough level ``b₀ = median(I)`` over the band;
   * noise ``σ = max(1.4826·median|I − b₀|, 1.4826·median|ΔI|/√2)`` over the band (robust standard deviations: the
     first from the levels, right for coloured noise too; the second from sample-to-sample differences);
   * quantisation step ``q``: the smallest spacing between distinct current values in the band (0 when all are
     equal, negligible for an unquantised reading);
   * thresholds ``θ_lo = max(4σ, 1.5 q, 0.5 % P)`` and ``θ_hi = 1.5 θ_lo`` (the 0.5 % floor is what a noise-free
     record needs, and was the whole rule before);
   * offset ``b``: the *mean* current over the rest samples ``|I − b₀| ≤ θ_lo`` away from any edge (the mean, not the
     median: it is unbiased for a quantised, dithered reading);

2. **splits the record into rests and active runs, with hysteresis**: a sample with ``|I − b| ≤ θ_lo`` may be rest;
   a run of the other samples is active only if one of them reaches beyond ``θ_hi``, so noise that crosses ``θ_lo``
   stays rest. *Blips* — active runs shorter than :data:`MIN_PULSE_S` or of at most two samples, that peak below
   ``2 θ_hi`` — are merged into the surrounding rest (a short run of a large current stays: the Panasonic cells at
   −20 °C hit their voltage limit 1–1.5 s into the 11.6 A pulses, and those aborted pulses are real). An active run
   is cut into *phases* where ``I − b`` changes sign (a charge pulse that runs straight into a discharge step, as in
   the ORNL Leaf HPPC); a phase shorter than :data:`MIN_PULSE_S` joins its neighbour;
3. puts every sample on the **SOC axis** ``z = 1 − (Ah − Ah_full)/Q``. ``Ah`` is the charge discharged since the
   first sample: ``I − b`` integrated under zero-order hold or, when the record has gaps whose charge only the
   reference SOC knows, that reference (:func:`discharged_ah`). ``Ah_full`` is its minimum, the most charged point:
   an HPPC starts full, and the ORNL Leaf files first discharge to empty and charge to full — phases before the
   record first comes within :data:`FULL_TOL` of full are pre-conditioning, not part of the test; where most held
   phases lie before that point, it is a charge back after the test that went beyond where the test started (a
   count's drift over a day-long test, the charge a cell takes beyond what it gave), and full is the most charged
   point before the first of them. An HPPC in the
   *charge direction* (its levels reached by charge steps, up to full: the SOC of its held phases rises over the
   record) is the whole record up to full (``steps = "charge"``: its rest points lie on the charge branch). ``Q`` is the
   capacity (default: the charge discharged from full to the most discharged point — ECM_SPEC §2 recommends the
   HPPC's own Ah). Where the record's own reference SOC says the test spans less than full to empty (it stops at
   20 %, or starts part charged), the reference places it: ``Q`` is the charge moved over the reference's span and
   the most charged point sits where the reference puts it (:func:`reference_placement`);
   **Pulses counted alike.** A cycler logging every 5–10 s sees a 10–18 s pulse as one or two samples: counted
   under zero-order hold, each pulse moves the charge of a whole number of sample periods, up to a period too much
   or too little, and as the sampling phase slides along the schedule those errors run into a bulge of up to a few
   points of SOC between full and empty, which the OCV read at the rest points carries. An HPPC repeats one pulse:
   where the pulses of one direction (the held ones: every sample at the level, so a logger that averages its
   interval, whose edge samples carry part of the pulse and count its charge exactly, is left alone) are at least
   :data:`PULSE_COUNT_MIN` and their counted lengths lie within :data:`PULSE_COUNT_SPREAD` sample periods of each
   other — one length seen through the sampling — while a period is at least :data:`PULSE_COUNT_FRAC` of that
   length, each pulse's charge is taken as its current × their mean counted length (unbiased over a phase that
   slides; the pulse's own count, one or two samples, is off by up to a period), the difference added to the count
   where the pulse ends (:func:`pulse_count_correction`, ``HPPCAnalysis.count_correction_ah``;
   :func:`socbench.identify.fit.setup_fit` adds it to the fitted record's SOC as it adds a gap's charge). The mean's
   own error stays (a drift along the test, which a capacity counted from full to empty takes up); the bulge goes:
   ``python benchmarks/hppc_pulse_count.py`` (400 draws of each generator), records sampled every 5–10 s, the
   spread of the rest points' SOC error median 0.35 → 0.21 points, largest 2.54 → 1.34 (the tests' generator),
   largest 3.96 → 2.33 (``benchmarks/foreign_records.py``'s; at 10 s its 5 s pulses fall between samples half the
   time, which no count recovers); below 1 s nothing moves. Not where the charge comes from the reference SOC,
   which counted it;

4. **tells pulses from steps**: a *pulse* is a phase that

   * starts from a rest at least half as long as itself (an HPPC rests before every pulse; a drive cycle only
     crosses zero for a moment);
   * holds its current: median absolute deviation from its median within ``max(θ_lo, 15 %)`` of it (driving is not
     held; a pulse held at a voltage limit, which decays by up to 30 %, is);
   * carries at least ``3 θ_hi`` (stands clear of the rest level: a drive cycle's near-zero band, without true rests,
     makes the thresholds as wide as its currents);
   * lasts at most ``max_pulse_s``. By default that bound is read from the record: the sorted durations of the phases
     that pass the tests above are split at their largest ratio between neighbours when it is at least
     :data:`DURATION_GAP` (4: pulses of seconds against steps of minutes, while the pulses of one record differ by
     less — 30 s discharge and 10 s regen pulses in the ORNL Leaf test, or a pulse that coarse sampling makes one or
     two samples long) and at least two phases lie below it; without such a split (a file whose steps fall in gaps)
     every phase up to :data:`MAX_PULSE_S` is a pulse.

   Anything else (steps, a CV charge, driving) is a step;
5. groups pulses into **sets**: a new set starts whenever charge moved between two pulses other than by the pulses
   themselves (more than :data:`SET_SPLIT` of Q) — and, where no bound finds an HPPC that way (SOC steps as long as
   the pulses or shorter are pulses under every bound, so no charge moves between "pulses"), also after every rest
   of ``min_rest_s`` (:func:`analyze_hppc`);
6. takes an **OCV point** at the end of the rest before each set, when that rest lasts ``min_rest_s`` (default
   :data:`MIN_OCV_REST_S`, 4 min) or is the record's initial rest (the cell rested before the test began), and at the
   end of a final rest after a last discharge step. The test ends with that rest: when the record then charges the
   cell back to full (a cycler's script), the charge back is post-conditioning, not part of the test
   (``end_index``). The point is the end of the least-squares line through the voltage over the rest's last
   ``min(60 s, 10 % of the rest)`` — noise averaged, without the lag of a mean behind a voltage still relaxing —
   never reaching back across a gap in the record longer than that window. A record is an
   HPPC test when it has at least two OCV points and rests before at least half of its pulse sets
   (:data:`REST_SHARE`); otherwise (a drive cycle, a constant discharge, a flight) :func:`analyze_hppc` raises one
   :class:`DataError` line. Once a record is read as an HPPC, a rest of ``min_rest_s`` after a discharge step (in
   the charge direction, a charge step) that no pulse set follows gives a point too, and so does the rest at full
   before the first step: a logger every 5–10 s misses a 5–10 s pulse half the time, and the level it opened has no
   set in the file. Such a rest runs on through the pulse no sample caught, so its point is read before the voltage
   first falls (``_with_step_rests``, ``tests/test_hppc_step_rests.py``);
7. estimates per pulse the **instantaneous resistance** ``r_inst = −ΔV/ΔI`` across the leading edge (one sample: under
   the ZOH convention ``y_k = h(x_k, I_k)`` this is exactly the model's ``R0(z)`` plus the decay of the RC states over
   one sample), the same across the trailing edge, the **pulse resistance** ``(V_before − V_end)/I`` at the end of
   the pulse (``V_before`` the end of the rest before it, as in 6), and the **relaxation time constant**: the time the
   voltage needs, in the rest after the pulse, to recover ``1 − 1/e`` of what it recovers by the end of that rest
   (after the instantaneous jump), and a slow one, a third of the time to recover 95 % (both equal τ for a single
   exponential). An edge resistance needs a pulse of at least :data:`MIN_EDGE_SAMPLES` samples and an edge that
   carries at least half the pulse current: with a sample period near the pulse length, or a ramping edge, ``ΔV/ΔI``
   would measure polarisation, not ``R0``; such edges give NaN and a note says so.

A record whose pulses *raise* the voltage under the current it calls discharge (median pulse resistance below 0) was
read with the current's sign flipped — read that way, a test down from full looks like one up to full with the OCV
falling as the SOC rises — and gets one :class:`DataError` line naming the current column.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import isotonic_regression

from ..errors import DataError
from ..metrics import lag1_autocorrelation
from ..ocv import OCVCurve, monotone_points
from ..profile import Profile, run_medians, samples_fingerprint, true_runs
from ..socaxis import reference_capacity

#: relative disagreement between the integrated current and the reference SOC above which the reference is used
#: (when jumps across the record's gaps explain it)
AH_MISMATCH = 5e-3
#: a step where the reference and the counted current move apart by more than this fraction of the record's charge is
#: a jump (charge the current column does not carry: a gap in the record)
JUMP_FRAC = 1e-3
#: the reference is a record of gaps when its jumps explain at least this share of its disagreement with the current
JUMP_SHARE = 0.75
#: a step moving more than this fraction of Q between two pulses starts a new pulse set
SET_SPLIT = 2e-3
#: the test starts where the record first comes within this fraction of its charge of its most charged point (what
#: comes before is pre-conditioning: the ORNL Leaf files discharge to empty and charge to full first)
FULL_TOL = 0.02
#: the near-zero band where the rest level and the sensor noise are measured, as a fraction of max|I|
REST_BAND_FRAC = 0.05
#: rest threshold θ_lo in robust standard deviations of the current noise; θ_hi = HYSTERESIS × θ_lo
REST_K = 4.0
HYSTERESIS = 1.5
#: θ_lo is at least this fraction of max|I − b| (a noise-free record) and this many quantisation steps
REST_FLOOR_FRAC = 5e-3
QUANT_K = 1.5
#: a blip: an active run shorter than MIN_PULSE_S [s] (or of at most two samples) that peaks below BLIP_K θ_hi; a
#: phase shorter than MIN_PULSE_S is a transition and joins its neighbour
MIN_PULSE_S = 2.0
BLIP_K = 2.0
#: a held pulse: median absolute deviation of its current within max(θ_lo, this fraction of its level); loose enough
#: for a pulse the cycler holds at a voltage limit (the ORNL Leaf regen pulse at full charge decays by 30 %)
PULSE_FLATNESS = 0.15
#: a pulse's current is at least PULSE_SNR θ_hi, and the rest before it at least PULSE_REST_RATIO × its duration
PULSE_SNR = 3.0
PULSE_REST_RATIO = 0.5
#: pulse/step split: the largest ratio between neighbouring sorted phase durations, when at least this
DURATION_GAP = 4.0
#: longest pulse when the durations show no split [s]
MAX_PULSE_S = 120.0
#: edge resistances need this many samples in the pulse and an edge carrying EDGE_FRACTION of the pulse current
MIN_EDGE_SAMPLES = 3
EDGE_FRACTION = 0.5
#: a record's own reference SOC places the test on the SOC axis (:func:`reference_placement`) when it spans at least
#: this much between the test's most charged and most discharged points: over a shorter span a reference read to a
#: point (a BMS in whole percent) gives the capacity no better than the count from full does
REFERENCE_MIN_SPAN = 0.2
#: the rests whose slope of the reference SOC measures the reference's drift are at least this long [s]
REFERENCE_REST_S = 60.0
#: a test that reaches empty ends in the OCV's end-of-discharge knee: its lowest OCV step is at least this many times
#: steeper than the median of its others, and at least this steep per cell [V per unit SOC] (:func:`end_knee`)
KNEE_RATIO = 2.0
KNEE_SLOPE_V = 1.0
#: the note (and the fit command's warning) for a test whose lowest step shows no knee starts with this
NO_KNEE = "no end-of-discharge knee"
#: pulses counted alike (module docstring, 3): at least this many held pulses of one direction, whose counted lengths
#: lie within this many sample periods of each other, sampled at periods of at least this share of their mean length
PULSE_COUNT_MIN = 3
PULSE_COUNT_SPREAD = 1.5
PULSE_COUNT_FRAC = 0.1
#: ... and only where that moves the SOC axis somewhere by at least this share of the capacity (less is within the
#: count's own rounding: a schedule on the sampling grid counts every pulse alike already)
PULSE_COUNT_MIN_MOVE = 1e-4
#: the analysis' note where pulses were counted alike contains this (``socbench fit`` prints it)
COUNTED_ALIKE = "counted alike"
#: shortest rest before a pulse set that gives an OCV point [s]: HPPC protocols rest 5 min to 2 h (4 min leaves room
#: for a coarse sampling of a 5 min rest); after a shorter rest most of the polarisation is still there, and drive
#: cycles stop for a minute or two
MIN_OCV_REST_S = 240.0
#: a rest of ``min_rest_s`` or more inside the test that follows a step of at least this share of the capacity (a
#: held phase longer than the pulses, in the test's direction) gives an OCV point even where no pulse set follows it:
#: a logger every 5–10 s misses 5–10 s pulses (the sample falls before or after them), and a step-and-rest test
#: has none; the rest after the step relaxed all the same (module docstring, 6)
STEP_REST_MIN_SOC = 0.02
#: … read before the voltage first falls by this many times its sample-to-sample noise, and at least
#: :data:`REST_DROP_MIN_V`, from one sample to the next (a pulse between two samples; :func:`_undisturbed_stop`)
REST_DROP_SIGMAS = 6.0
REST_DROP_MIN_V = 1e-3
#: a record that starts this far (SOC) above its highest rest point gets its OCV continued to its top
#: (:attr:`HPPCAnalysis.ocv_top_extension`)
TOP_EXTENSION_MIN = 0.01
#: a test whose most discharged point, reached by a step (a held discharge longer than the pulses) rather than a
#: rest, lies this far (SOC) below its lowest rest point gets its OCV continued down to it
#: (:attr:`HPPCAnalysis.ocv_bottom_extension`)
BOTTOM_EXTENSION_MIN = 0.01
#: whether a test that stops under load below its lowest rest point gets the bottom extension (off: the line through
#: its two lowest rest points, as before stop 49)
BOTTOM_EXTENSION = True
#: SOC bins of the bottom extension's trace
BOTTOM_BIN = 0.005
#: points of the rest points' curve kept inside its lowest interval when the bottom extension is added
BOTTOM_HELD = 8
#: an HPPC rests (≥ min_rest_s) before at least this share of its pulse sets; a drive cycle with stops does not
REST_SHARE = 0.5
#: OCV point: line through the voltage over the last min(OCV_WINDOW_S, OCV_WINDOW_FRAC × duration) of a rest
OCV_WINDOW_S = 60.0
OCV_WINDOW_FRAC = 0.1


@dataclass(frozen=True)
class Rest:
    start: int  # first rest sample
    stop: int  # one past the last rest sample
    duration_s: float
    soc_end: float
    v_end: float  # voltage at the rest's end, from a line through its last window (module docstring, 6)


@dataclass(frozen=True)
class Pulse:
    start: int  # first sample with the pulse current
    stop: int  # first sample after the pulse (a rest, or the next phase)
    current_a: float  # charge-weighted mean current, offset removed (A, positive = discharge)
    duration_s: float
    soc: float  # SOC at the pulse start
    level: int  # index of the pulse set
    r_inst: float  # leading edge  −ΔV/ΔI  [Ω] (nan where the edge is not resolved)
    r_inst_off: float  # trailing edge −ΔV/ΔI [Ω] (nan where the edge is not resolved)
    r_pulse: float  # (V_before − V_end)/I at the end of the pulse [Ω]
    tau_s: float  # relaxation time constant in the following rest [s] (nan if the rest is too short)
    tau_slow_s: float = float("nan")  # a third of the time to recover 95 % (the slow process) [s]


@dataclass(frozen=True)
class RestLevel:
    """The current sensor as the rests show it (module docstring, 1); all in A."""

    offset_a: float  # b
    noise_a: float  # σ
    step_a: float  # quantisation step q (0: none seen)
    lo_a: float  # θ_lo
    hi_a: float  # θ_hi
    peak_a: float  # max|I − b₀|

    def describe(self) -> str:
        q = f", quantisation step {self.step_a:.3g} A" if self.step_a > 1e-3 * self.lo_a else ""
        return (f"current sensor at rest: offset {self.offset_a:+.3g} A, noise {self.noise_a:.3g} A{q}; rest where "
                f"|I - b| <= {self.lo_a:.3g} A (hysteresis {self.hi_a:.3g} A)")


@dataclass(frozen=True, eq=False)
class HPPCAnalysis:
    """Result of :func:`analyze_hppc`. ``soc`` and ``ah`` are per sample of the analysed profile; ``ah`` counts the
    current with the sensor offset ``sensor.offset_a`` removed (or comes from the reference SOC, ``ah_source``)."""

    rests: tuple
    pulses: tuple
    ocv_soc: np.ndarray
    ocv_voltage: np.ndarray
    capacity_ah: float
    soc: np.ndarray
    ah: np.ndarray
    ah_source: str
    level_soc: np.ndarray
    notes: tuple = field(default_factory=tuple)
    sensor: RestLevel | None = None
    max_pulse_s: float = float("nan")  # the pulse/step bound used [s]
    #: the OCV the first sample reads when the record starts at its top: its voltage plus the instantaneous drop
    #: r_inst·I of its current (offset removed), r_inst the median leading-edge resistance of the pulses [V]; NaN when
    #: the record reaches its top later (a charge first) or no pulse edge was resolved
    start_ocv_v: float = float("nan")
    #: the sample where the test starts: the record's first approach to its top (0 when it starts there; later when
    #: a charge to full comes first, whose SOC is counted back from full through a charge of unknown efficiency); 0
    #: for a test in the charge direction
    start_index: int = 0
    #: how the test moves between its SOC levels: "discharge" (down from full, the usual HPPC) or "charge" (up to
    #: full): the hysteresis branch its rest points lie on
    steps: str = "discharge"
    #: one past the test's last sample: the record's length, or the end of the rest after a test's most discharged
    #: point when the record charges back to full after it (None: the record's length)
    end_index: int | None = None
    #: ``((z, OCV), ...)`` by rising SOC, read along the step that ends at the test's most discharged point when a step
    #: (not a rest) ends there below the lowest rest point, once its over-potential has settled: the voltage plus the
    #: current times the pulse resistance of the lowest pulse set (``r_pulse``: what the pulses there dropped by their
    #: end), medians on SOC bins of :data:`BOTTOM_BIN`; None otherwise (:attr:`ocv_bottom_extension`)
    bottom_point: tuple | None = None
    #: per sample, the charge [Ah] added to the count in the step into the sample where a pulse counted under
    #: zero-order hold is taken as its current × the mean counted length of its kind (:func:`pulse_count_correction`;
    #: included in ``ah`` and ``soc``); None where no pulse was corrected
    count_correction_ah: np.ndarray | None = None
    #: the current [A] the test's recorded discharge steps hold (held discharge phases longer than the longest pulse,
    #: median of their levels, offset removed): what moved the charge of a record gap
    #: (:mod:`socbench.identify.gap_fill`); NaN where no step is recorded (the Panasonic files: every step falls in a
    #: gap) or the test steps by charging
    step_current_a: float = float("nan")

    @property
    def current_offset_a(self) -> float:
        """The current sensor's offset measured on the rests [A] (0 when unknown)."""
        return self.sensor.offset_a if self.sensor is not None else 0.0

    def ocv(self, source: str = "") -> OCVCurve:
        """Monotone PCHIP through the OCV points (made monotone by isotonic regression first), continued to the
        record's top SOC when it starts above its highest rest point (:attr:`ocv_top_extension`) and down to the
        test's most discharged point when a step ends there below its lowest one (:attr:`ocv_bottom_extension`)."""
        z, v = monotone_points(self.ocv_soc, self.ocv_voltage)
        if self.ocv_bottom_extension is not None and z.size >= 2:
            below = [(zb, vb) for zb, vb in self.bottom_point if zb < z[0] - BOTTOM_EXTENSION_MIN]
            # above the lowest rest point the curve stays the one the rest points give: its values on a few points
            # of the lowest interval hold the interpolant's slope there, which the steep trace below would bend
            held = np.linspace(z[0], z[1], BOTTOM_HELD + 2)[1:-1]
            z, v = monotone_points(np.r_[[p[0] for p in below], z[0], held, z[1:]],
                                   np.r_[[p[1] for p in below], v[0], OCVCurve(z, v)(held), v[1:]])
        ext = self.ocv_top_extension
        if ext is not None and z.size >= 2:
            z_top = ext[1]
            if np.isfinite(self.start_ocv_v):
                v_top = max(self.start_ocv_v, float(v[-1]))
            else:
                v_top = v[-1] + (v[-1] - v[-2]) / (z[-1] - z[-2]) * (z_top - z[-1])
            z, v = np.append(z, z_top), np.append(v, v_top)
        return OCVCurve(z, v, source or "HPPC rest points")

    @property
    def ocv_top_extension(self) -> tuple[float, float] | None:
        """``(z_highest_rest_point, z_top)`` when the record starts more than :data:`TOP_EXTENSION_MIN` above its
        highest OCV point (no rest at full before the first pulse set), else None. There the curve continues up to the
        record's top SOC: the rising OCV of a charged cell, where a curve held flat beyond its end leaves the whole
        first step tens of mV off. The top point is the OCV the first sample reads (:attr:`start_ocv_v`: its voltage
        plus the instantaneous drop of its current; nothing else has built up at a load's first sample), else the line
        through the two highest points (an LFP cell's knee at full lies far above any line from its plateau: on the
        independent generator's records the line missed the top by a median 130 mV there, the first sample by 4 mV)."""
        if self.ocv_soc.size < 2:
            return None
        z_hi = float(np.max(self.ocv_soc))
        z_top = float(min(1.0, np.max(self.soc)))
        return (z_hi, z_top) if z_top > z_hi + TOP_EXTENSION_MIN else None

    @property
    def ocv_bottom_extension(self) -> tuple[float, float] | None:
        """``(z_bottom, z_lowest_rest_point)`` when the test's most discharged point, reached by a step, lies more
        than :data:`BOTTOM_EXTENSION_MIN` below its lowest OCV point (the test stops at the cut-off under load,
        without a rest at the bottom), else None. There the curve continues down to :attr:`bottom_point`: the knee
        at empty lies far below any line from the points above it (the Nissan Leaf HPPC at 25 °C ends at 3.0 V under
        C/3, its lowest rest point at z = 0.058 reads 3.53 V, the line through the two lowest 3.43 V at z = 0, the
        bottom point 3.04 V), and a record that runs there (the same cell's 10 °C HPPC, which starts from empty)
        read the line: 282 mV RMS below z = 0.1."""
        if self.bottom_point is None or self.ocv_soc.size < 2:
            return None
        z_lo = float(np.min(self.ocv_soc))
        z_bot = self.bottom_point[0][0]
        return (z_bot, z_lo) if z_bot < z_lo - BOTTOM_EXTENSION_MIN else None

    def resistance_table(self) -> dict:
        """Per pulse set: SOC and the median pulse resistances ``{"soc", "r_inst", "r_pulse", "tau_s"}`` (arrays;
        NaN where no pulse of the set measured it)."""
        lv = np.array([p.level for p in self.pulses])
        out = {"soc": [], "r_inst": [], "r_pulse": [], "tau_s": []}
        for j in np.unique(lv):
            ps = [p for p in self.pulses if p.level == j]
            out["soc"].append(ps[0].soc)
            out["r_inst"].append(_finite_median([p.r_inst for p in ps]))
            out["r_pulse"].append(_finite_median([p.r_pulse for p in ps]))
            out["tau_s"].append(_finite_median([p.tau_s for p in ps]))
        return {k: np.asarray(v) for k, v in out.items()}

    def medians(self) -> dict:
        """Record-wide medians used as fitting scales: ``r_inst``, ``r_pulse``, ``tau_s``, ``tau_slow_s``."""
        return {
            "r_inst": _finite_median([p.r_inst for p in self.pulses]),
            "r_pulse": _finite_median([p.r_pulse for p in self.pulses]),
            "tau_s": _finite_median([p.tau_s for p in self.pulses]),
            "tau_slow_s": _finite_median([p.tau_slow_s for p in self.pulses]),
        }


def _finite_median(xs) -> float:
    xs = [x for x in xs if np.isfinite(x)]
    return float(np.median(xs)) if xs else float("nan")


# ------------------------------------------------------------------------------------------------ SOC axis
def _counted_ah(profile: Profile, current_offset_a: float = 0.0) -> np.ndarray:
    """``∫(I − b) dt`` since the first sample [Ah], zero-order hold."""
    if current_offset_a == 0.0:
        return profile.amp_hours()
    return profile.with_(current_a=profile.current_a - current_offset_a).amp_hours()


def _reference_ah(profile: Profile) -> np.ndarray | None:
    """The reference SOC as discharged charge since the first sample [Ah] (None without a reference or a capacity).
    A reference given but refused (far outside [0, 1]) raises here: this is where it is used."""
    soc_ref = profile.get("soc_ref")
    if soc_ref is None or not profile.meta.capacity_ah:
        return None
    return (soc_ref[0] - soc_ref) * float(profile.meta.capacity_ah)


def discharged_ah(profile: Profile, current_offset_a: float = 0.0) -> tuple[np.ndarray, str]:
    """Charge discharged since the first sample [Ah] and where it came from (``"current"`` or ``"soc_ref"``).

    The integrated current (zero-order hold, the sensor offset ``current_offset_a`` removed) is used unless the
    profile's reference SOC (with ``meta.capacity_ah``) disagrees with it by more than 0.5 % of the record's charge
    *in jumps*: the steps where the two move apart by more than :data:`JUMP_FRAC` of the record's charge, added to
    the integrated current, explain at least 3/4 of the disagreement. Then the record has gaps whose charge only the
    reference knows (the Panasonic HPPC files omit the discharges between pulse sets), and the reference is used.
    A reference that drifts away a little at every step (counted from another capacity, or from a sensor with an
    offset) is not a record of gaps: the current is used. A reference given but refused (far outside [0, 1]) raises
    here.
    """
    ah = _counted_ah(profile, current_offset_a)
    ref = _reference_ah(profile)
    if ref is not None:
        scale = max(float(np.max(np.abs(ref))), float(np.max(np.abs(ah))), 1e-12)
        mismatch = float(np.max(np.abs(ref - ah)))
        if mismatch > AH_MISMATCH * scale:
            d = np.diff(ref) - np.diff(ah)
            jumps = np.where(np.abs(d) > JUMP_FRAC * scale, d, 0.0)
            filled = ah + np.concatenate([[0.0], np.cumsum(jumps)])
            if float(np.max(np.abs(ref - filled))) <= (1.0 - JUMP_SHARE) * mismatch:
                return ref, "soc_ref"
    return ah, "current"


def gap_step_ah(ah: np.ndarray, frac: float = JUMP_FRAC) -> float:
    """The charge [Ah] beyond which one step of the count ``ah`` is a record gap rather than a sample's own charge:
    ``frac`` of the record's charge (a rest moves none; a gap whose charge the reference holds moves a step's)."""
    return frac * max(float(np.max(np.abs(ah))), 1e-12)


def spans_gap(ah: np.ndarray, start: int, stop: int, jump: float) -> bool:
    """Whether the rest ``[start, stop)`` runs across a record gap: the discharged charge ``ah`` (which holds a gap's
    charge from the reference) moves over it by more than ``jump`` (:func:`gap_step_ah`), where a rest moves none."""
    return abs(float(ah[stop - 1] - ah[start])) > jump


def unrecorded_charge(profile: Profile, threshold_frac: float = JUMP_FRAC,
                      current_offset_a: float = 0.0) -> np.ndarray:
    """Per sample, the charge [Ah] discharged in the step *into* the sample that the current column does not carry
    (0 where the column, less the offset ``current_offset_a``, and the reference agree to ``threshold_frac`` of the
    record's charge; non-zero only where :func:`discharged_ah` takes the reference, i.e. across gaps)."""
    ah, src = discharged_ah(profile, current_offset_a)
    out = np.zeros(profile.n)
    if src != "soc_ref":
        return out
    extra = np.diff(ah) - np.diff(_counted_ah(profile, current_offset_a))
    thr = gap_step_ah(ah, threshold_frac)
    out[1:] = np.where(np.abs(extra) > thr, extra, 0.0)
    return out


def gap_soc_jumps(profile: Profile, capacity_ah: float) -> np.ndarray | None:
    """Per sample, the SOC (on the axis of a cell of ``capacity_ah``) that the step into it moves beyond what the
    current column carries: ``−unrecorded_charge / capacity`` (:func:`unrecorded_charge`, the ``soc_jumps`` of
    :meth:`~socbench.models.base.Model.open_loop`), or None where the record has no reference or none is missing.
    The charge a cell delivered while the logger was off (the Panasonic HPPC files leave out the step discharges), as
    the fit, the noise recipe and the simulation carry it."""
    if profile.get("soc_ref") is None:
        return None
    extra = unrecorded_charge(profile)
    return -extra / capacity_ah if np.any(extra) else None


# ------------------------------------------------------------------------------------------------ the sensor
def _robust_sd(x: np.ndarray) -> float:
    """1.4826 × the median absolute value: the standard deviation of zero-mean Gaussian samples, robustly."""
    return 1.4826 * float(np.median(np.abs(x))) if x.size else 0.0


def quantisation_step(x) -> float:
    """The smallest spacing between distinct values of ``x`` (0 when all are equal): a sensor's ADC step, negligible
    for an unquantised reading."""
    levels = np.unique(np.asarray(x, dtype=float))
    return float(np.min(np.diff(levels))) if levels.size > 1 else 0.0


def _grouped_median(x: np.ndarray, levels: np.ndarray, counts: np.ndarray, q: float) -> float:
    """The median of quantised values interpolated within its level (the median of grouped data):
    ``L + (n/2 − F)/f · q``, ``L`` the lower edge of the level holding the n/2-th sample, ``F`` the samples below it,
    ``f`` the samples at it."""
    below = np.cumsum(counts) - counts
    k = int(np.searchsorted(np.cumsum(counts), 0.5 * x.size))
    return float(levels[k] - 0.5 * q + (0.5 * x.size - below[k]) / counts[k] * q)


def reading_level(x) -> tuple[float, float]:
    """``(level, sd)`` of a sensor reading that should be constant (the current over a rest).

    The median and the robust sd: blind to a minority of samples off the level (a load's last seconds at the start
    of a rest). A *quantised* reading (its values repeat: at least four samples per distinct value) carries a
    sub-step level in the shares of its levels, which the plain median cannot see: it sticks to a level (a current
    sensor 0.3 % of 1C off, read with a 1 %-of-1C step and dithered by its noise, has a median of 0). Its level is
    the *skipped mean* instead::

        m ← mean{x_k : |x_k − m| ≤ 3 s},   s = max(robust sd, q),   from m = the median interpolated within its level

    iterated to its fixed point (unbiased for a dithered reading, still blind to samples beyond 3 s), and its sd the
    plain sd of the samples kept."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return 0.0, 0.0
    levels, counts = np.unique(x, return_counts=True)
    if levels.size < 2 or 4 * levels.size > x.size:
        med = float(np.median(x))
        return med, _robust_sd(x - med)
    q = quantisation_step(levels)
    m = _grouped_median(x, levels, counts, q)
    s = max(_robust_sd(x - m), q)
    for _ in range(50):
        kept = x[np.abs(x - m) <= 3.0 * s]
        m_next = float(np.mean(kept))
        if abs(m_next - m) <= 1e-9 * max(s, 1e-300):
            break
        m = m_next
    return m_next, float(np.std(kept))


def rest_level(current, i_rest: float | None = None) -> RestLevel:
    """The current sensor's offset, noise and quantisation, and the rest thresholds (module docstring, 1).

    ``i_rest`` fixes ``θ_lo = θ_hi = i_rest`` instead of the noise-derived thresholds (the offset is still measured).
    """
    i = np.asarray(current, dtype=float)
    peak = float(np.max(np.abs(i), initial=0.0))
    band = np.abs(i) <= REST_BAND_FRAC * peak
    b0 = float(np.median(i[band])) if band.any() else 0.0
    sigma = step = 0.0
    if band.any():
        both = band[:-1] & band[1:]
        sigma = max(_robust_sd(i[band] - b0), _robust_sd(np.diff(i)[both]) / np.sqrt(2.0))
        step = quantisation_step(i[band])
    peak_b = float(np.max(np.abs(i - b0), initial=0.0))
    if i_rest is not None:
        lo = hi = float(i_rest)
    else:
        lo = max(REST_K * sigma, QUANT_K * step, REST_FLOOR_FRAC * peak_b)
        hi = HYSTERESIS * lo
    rest = np.abs(i - b0) <= lo
    inner = rest.copy()
    inner[1:] &= rest[:-1]
    inner[:-1] &= rest[1:]
    pick = inner if inner.any() else rest
    b = float(np.mean(i[pick])) if pick.any() else 0.0
    return RestLevel(b, sigma, step, lo, hi, peak_b)


# ------------------------------------------------------------------------------------------------ structure
def _active_mask(t_after: np.ndarray, t: np.ndarray, dev: np.ndarray, lev: RestLevel) -> tuple[np.ndarray, int]:
    """Samples in active runs (hysteresis, blips merged into rests) and the number of blips merged."""
    active = dev > lev.lo_a
    blips = 0
    for a, b in true_runs(active):
        peak = float(np.max(dev[a:b]))
        short = (t_after[b - 1] - t[a]) < MIN_PULSE_S or (b - a) <= 2
        if peak <= lev.hi_a or (short and peak < BLIP_K * lev.hi_a):
            active[a:b] = False
            blips += peak > lev.hi_a  # a run that reached θ_hi yet was dropped: a blip
    return active, blips


def _phases(a: int, b: int, sign: np.ndarray, t_after: np.ndarray, t: np.ndarray) -> list[tuple[int, int]]:
    """The run ``[a, b)`` cut where the sign of ``I − b`` changes; phases under MIN_PULSE_S join a neighbour."""
    cuts = (a + 1 + np.flatnonzero(sign[a + 1:b] != sign[a:b - 1])).tolist()
    bounds = [a] + cuts + [b]
    phases = [(bounds[k], bounds[k + 1]) for k in range(len(bounds) - 1)]
    merged = []
    for p in phases:
        if merged and t_after[p[1] - 1] - t[p[0]] < MIN_PULSE_S:
            merged[-1] = (merged[-1][0], p[1])  # a transition: part of the phase before
        elif merged and t_after[merged[-1][1] - 1] - t[merged[-1][0]] < MIN_PULSE_S:
            merged[-1] = (merged[-1][0], p[1])  # the run opened with a transition: part of this phase
        else:
            merged.append(p)
    return merged


def _pulse_bound(durations: np.ndarray) -> float:
    """Longest pulse: the largest ratio gap of the sorted durations (≥ DURATION_GAP, two or more below it), or
    MAX_PULSE_S (module docstring, 3)."""
    d = np.sort(durations[durations > 0])
    if d.size >= 3:
        ratio = d[1:] / d[:-1]
        ratio[:1] = 0.0  # at least two durations below the split
        k = int(np.argmax(ratio))
        if ratio[k] >= DURATION_GAP and d[k] <= MAX_PULSE_S:
            return float(d[k])
    return MAX_PULSE_S


def _rest_end_voltage(t: np.ndarray, v: np.ndarray, start: int, stop: int, duration_s: float) -> float:
    """The voltage at the end of the rest ``[start, stop)``: the least-squares line through the samples of its last
    ``min(OCV_WINDOW_S, OCV_WINDOW_FRAC × duration)`` (not reaching back across a gap in the record longer than
    that window), evaluated at the last sample. The line, not the mean: a still-relaxing voltage would pull a mean
    back by half the window's drift; the line's end keeps the noise averaging (variance ``4σ²/N`` instead of ``σ²``)
    without that lag."""
    w = min(OCV_WINDOW_S, OCV_WINDOW_FRAC * duration_s)
    k = stop - 1
    first = max(int(np.searchsorted(t, t[k] - w, side="left")), start)
    gaps = np.flatnonzero(np.diff(t[first:stop]) > w)
    if gaps.size:
        first += int(gaps[-1]) + 1
    if stop - first < 3:
        return float(np.mean(v[first:stop]))
    x = t[first:stop] - t[k]
    slope, intercept = np.polyfit(x, v[first:stop], 1)
    return float(intercept)


#: the log-time window of :func:`relaxation_curve`'s running mean: a sample's neighbours within this factor of its
#: time since the rest began
RELAXATION_WINDOW = 1.1


def relaxation_curve(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The rest voltage ``v`` (at times ``t``) without its noise, for reading recovery times off:

    1. each sample averaged with its neighbours whose time since the rest began lies within a factor
       :data:`RELAXATION_WINDOW` of its own (a relaxation changes on a log-time scale, so the window widens as it
       slows: the first seconds stay sharp, the slow end, where 95 % of the recovery is read, averages many samples);
    2. the least-squares monotone fit of that (isotonic regression), rising where the rest ends above its start,
       falling where it ends below: a relaxation after a pulse runs one way.

    Read off the samples themselves, the first one whose noise lifted it over ``1 − 1/e`` of a recovery as small as
    the noise gave the time: a 29 s branch recovering 9 mV under 4.6 mV of voltage noise read 0.03 s. No shape is
    imposed (a diffusion tail is no exponential); on noise-free records the window moves the readings by −7 to +1 %
    (60 random draws of tests/hppc_records.py, seeds 47 000+)."""
    if v.size < 4 or not np.all(np.isfinite(v)):
        return v
    k = max(1, v.size // 10)
    rising = float(np.mean(v[-k:])) >= float(np.mean(v[:k]))
    s = t - t[0]
    csum = np.concatenate([[0.0], np.cumsum(v - v[0])])
    lo = np.searchsorted(s, s / RELAXATION_WINDOW, side="left")
    hi = np.searchsorted(s, s * RELAXATION_WINDOW, side="right")
    smooth = v[0] + (csum[hi] - csum[lo]) / (hi - lo)
    return np.asarray(isotonic_regression(smooth, increasing=rising).x, dtype=float)


def _recovery_tau(t: np.ndarray, v: np.ndarray, level: float = 1.0 - np.exp(-1.0)) -> float:
    """Time for ``v − v[0]`` to reach ``level`` (default ``1 − 1/e``) of ``v[-1] − v[0]`` (linear interpolation)."""
    if v.size < 4:
        return float("nan")
    rec = v - v[0]
    final = rec[-1]
    if not np.isfinite(final) or abs(final) < 1e-9:
        return float("nan")
    frac = rec / final
    k = int(np.argmax(frac >= level))
    if k == 0:
        return float("nan")
    f0, f1 = frac[k - 1], frac[k]
    w = 0.0 if f1 == f0 else (level - f0) / (f1 - f0)
    return float(t[k - 1] + w * (t[k] - t[k - 1]) - t[0])


#: the longest pulse tried when the one read from the record's phase durations finds no HPPC, or one with fewer
#: than :data:`FEW_OCV_POINTS` OCV points (:func:`analyze_hppc`): the upper end of each group of the record's held
#: phases (from a rest) whose lengths lie within this ratio of the next, up to :data:`LADDER_MAX_S`
LADDER_RATIO = 1.15
#: … or lie more than this many sample periods apart: a phase's length is measured to a sample period at each edge, so
#: lengths further apart are different phases however close their ratio (an independent generator's HPPC: 42.5 s
#: discharge pulses and 48.6 s SOC steps sampled every 0.23 s, one group by the ratio alone, and no bound between them)
LADDER_SAMPLES = 4.0
LADDER_MAX_S = 600.0
#: an analysis with fewer OCV points than this (a straight line through the first and last rest) has the ladder tried
FEW_OCV_POINTS = 3


def analyze_hppc(profile: Profile, capacity_ah: float | None = None, i_rest: float | None = None,
                 max_pulse_s: float | None = None, min_rest_s: float = MIN_OCV_REST_S,
                 soc_start: float | None = None) -> HPPCAnalysis:
    """Analyse an HPPC record (see the module docstring). Raises :class:`DataError` (one line) when the record is not
    an HPPC test: no pulse, fewer than two OCV rest points, or rests before fewer than half of its pulse sets.

    ``i_rest`` fixes the rest threshold [A] (default: from the sensor noise); ``max_pulse_s`` the longest pulse
    (default: from the record's phase durations); ``min_rest_s`` the shortest rest that gives an OCV point;
    ``soc_start`` the SOC of the record's first sample, where the user knows it (a test started part charged: its
    rest points lie that much lower; :func:`socbench.identify.fit.setup_fit` with ``soc0``); default: the record's
    most charged point is full (SOC 1).

    Where the longest pulse read from the record's phase durations finds no HPPC, or one with fewer than
    :data:`FEW_OCV_POINTS` OCV points, every bound of :func:`pulse_bound_ladder` is tried and the one that finds the
    most OCV points (then the most pulses) is kept when it finds more; where none finds that many, the record's own
    bound and the ladder's up to :data:`MAX_PULSE_S` are tried again with the sets split at every OCV rest too
    (module docstring, 5). The durations mislead in three layouts: charge
    and discharge pulses of lengths four times apart (a 55 s discharge beside a 10 s charge pulse: the gap between
    them looks like the one between pulses and SOC steps; where the sets open with the charge pulse, the top set,
    which has none, opens with the discharge pulse), and SOC steps shorter than :data:`MAX_PULSE_S` and less
    than :data:`DURATION_GAP` times longer than the pulses (2–5 % at 1–2 C: 40–180 s), taken for pulses, so that no
    charge moves between the "pulses" and every set merges into one level (an "HPPC" of two OCV points, the first
    rest and the last); and steps as long as the pulses or shorter (55 s steps beside 60 s pulses), pulses under every
    bound, whose sets only the OCV rests tell apart. A record whose own bound finds three OCV points or more is
    analysed as before.

    The analysis of a record is kept (:data:`MEMO_SIZE` records, keyed on their samples, all their metadata and
    the arguments): a diagnosis fits one HPPC in several modes, models and effect sets, and each fit analysed it again
    (in the 42 slowest tests, fits analysed records 2 313 times, 5 % of their time). The key holds this module's
    settings too (a setting changed, as a study of a rule does, analyses again). Its arrays are read-only; an error
    is raised again as it was.
    """
    key = (samples_fingerprint(profile), json.dumps(profile.meta.to_dict(), sort_keys=True, default=str),
           str(profile.soc_ref_error), capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start, _settings())
    with _MEMO_LOCK:
        hit = _MEMO.get(key)
        if hit is not None:
            _MEMO.move_to_end(key)
    if hit is None:
        try:
            hit = _read_only(_with_step_rests(
                _analyze_with_ladder(profile, capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start),
                profile, min_rest_s))
        except DataError as exc:
            hit = exc
        with _MEMO_LOCK:
            _MEMO[key] = hit
            while len(_MEMO) > MEMO_SIZE:
                _MEMO.popitem(last=False)
    if isinstance(hit, DataError):
        raise hit.with_traceback(None)
    return hit


#: records whose analysis :func:`analyze_hppc` keeps
MEMO_SIZE = 16
_MEMO: OrderedDict = OrderedDict()
_MEMO_LOCK = threading.Lock()


def _settings() -> tuple:
    """This module's settings as they are now: every upper-case name bound to a number, string, bool or tuple."""
    return tuple((k, v) for k, v in globals().items()
                 if k.isupper() and isinstance(v, (bool, int, float, str, tuple)))


def _read_only(analysis: HPPCAnalysis) -> HPPCAnalysis:
    """``analysis`` with its per-sample and OCV arrays made read-only (a kept analysis is shared by every caller)."""
    for name in ("ocv_soc", "ocv_voltage", "soc", "ah", "level_soc", "count_correction_ah"):
        arr = getattr(analysis, name)
        if isinstance(arr, np.ndarray):
            arr.flags.writeable = False
    return analysis


def _analyze_with_ladder(profile, capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start) -> HPPCAnalysis:
    """:func:`analyze_hppc` without its memo: the record's own pulse bound, then the ladder."""
    durations = []
    try:
        first = _analyze_hppc(profile, capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start, durations)
        if max_pulse_s is not None or first.ocv_soc.size >= FEW_OCV_POINTS:
            return first
        why = f"{first.ocv_soc.size} OCV points"
    except DataError as exc:
        if max_pulse_s is not None or exc.column is not None:  # a bound asked for, or a bad column: say so
            raise
        first, why = exc, exc.message
    period = float(np.median(np.diff(profile.time_s))) if profile.n > 1 else 0.0
    ladder = pulse_bound_ladder(durations, period)
    best = _best_on_ladder(profile, capacity_ah, i_rest, min_rest_s, soc_start, ladder)
    if best is None or best.ocv_soc.size < FEW_OCV_POINTS:
        # the last resort: the sets split at every OCV rest too, under the record's own bound and the ladder's up to
        # MAX_PULSE_S (steps as long as the pulses or shorter are pulses under every bound that keeps the pulses; a
        # longer bound would take a field record's minutes-long charges and drives between its rests for pulses)
        best = _best_on_ladder(profile, capacity_ah, i_rest, min_rest_s, soc_start,
                               [None, *(b for b in ladder if b <= MAX_PULSE_S)], rest_sets=True)
    if best is None or best.ocv_soc.size < FEW_OCV_POINTS or (
            isinstance(first, HPPCAnalysis) and best.ocv_soc.size <= first.ocv_soc.size):
        if isinstance(first, DataError):
            raise first
        return first
    note = (f"the longest pulse read from the record's phase durations found no HPPC with {FEW_OCV_POINTS} OCV "
            f"points or more ({why}); pulses of at most {best.max_pulse_s:.3g} s find {best.ocv_soc.size} (of the "
            "bounds between the lengths of its held phases, the one that finds the most)")
    return replace(best, notes=tuple(n for n in best.notes if not n.startswith("pulses: held phases")) + (note,))


def _best_on_ladder(profile, capacity_ah, i_rest, min_rest_s, soc_start, bounds, rest_sets: bool = False):
    """Of the analyses under each of ``bounds`` (None: the record's own), the one with the most OCV points, then the
    most pulses, among those whose pulse sets repeat (:func:`_sets_repeat`: a day of drives and flights between rests
    makes "pulse sets" of a minute, ten seconds and ten minutes); None when no bound finds an HPPC."""
    found = []
    for bound in bounds:
        try:
            a = _analyze_hppc(profile, capacity_ah, i_rest, bound, min_rest_s, soc_start, rest_sets=rest_sets)
        except DataError:  # a bound that finds nothing (or "pulses" read upside down) is not the record's
            continue
        if _sets_repeat(a):
            found.append(a)
    return max(found, key=lambda a: (a.ocv_soc.size, len(a.pulses)), default=None)


def pulse_bound_ladder(durations, dt: float = 0.0) -> list[float]:
    """The longest pulses :func:`analyze_hppc` tries: the upper end of each group of ``durations`` (sorted; a group
    ends where the next is more than :data:`LADDER_RATIO` longer, or, on a record sampled every ``dt`` seconds, more
    than :data:`LADDER_SAMPLES` sample periods longer), up to :data:`LADDER_MAX_S`. Every bound between two groups
    gives the same analysis, so one per group is enough."""
    d = np.sort(np.asarray(durations, dtype=float))
    d = d[(d > 0) & (d <= LADDER_MAX_S)]
    if d.size == 0:
        return []
    step = np.diff(d)
    ends = np.flatnonzero((d[1:] > LADDER_RATIO * d[:-1]) | ((dt > 0) & (step > LADDER_SAMPLES * dt)))
    return [float(x) for x in np.append(d[ends], d[-1])]


def reference_placement(profile: Profile, ah: np.ndarray, k_full: int, k_empty: int,
                        capacity_ah: float | None = None, rests=()) -> tuple | None:
    """``(capacity [Ah], SOC of the most charged point, note)`` where the record's own reference SOC says the test
    does not run from full to empty; None where it does (within its counting error), where the record has no reference
    of its own, or where the reference cannot place it.

    Without a capacity, the count from full takes the charge from the most charged point (sample ``k_full``) to the
    most discharged (``k_empty``) as the capacity: an HPPC that stops at 20 % (many protocols end at 10–30 %, or at a
    voltage limit above empty) or starts part charged gets a capacity short by that much, and an SOC axis that runs a
    fifth too fast — every SOC a filter reports on it is off by up to that fifth. The record's reference SOC says where
    the test ran. Its drift ``d`` first: a reference a cycler counts from its own current sensor carries that
    sensor's offset, which ``Ah`` (the offset measured on the rests removed) does not — read as a place on the axis,
    it would move the test's end by the offset times the test's hours. On a rest no charge moves, so the reference's
    slope there *is* its drift: ``d`` is the median slope over the test's ``rests`` (:class:`Rest`, at least
    :data:`REFERENCE_REST_S` and three samples each), weighted by their durations (0 without such rests). A rest
    across a record gap (Panasonic: the step's discharge missing from the file, its charge only in the reference and
    so in ``Ah``) is not one: its reference falls by the step, a "drift" of the step over the rest's hours (on the
    tests' generator, seeds 0–799, it put 15 of 206 such records from full to empty at capacities 26–385 % too large,
    and missed the placement of nearly every one that stops above empty); a rest over which ``Ah`` moves by more than
    :data:`JUMP_FRAC` of the record's charge is left out. Then, over the test's samples (between
    the two points) with the reference inside (0, 1), least squares

        z_ref − d·(t − t₀) ≈ c₀ − Ah/Q_ref

    gives the capacity ``Q_ref`` the reference counts with (a joint fit of ``d`` beside it is ill-conditioned: in an
    HPPC the charge moves almost in step with time). The test then spans ``ΔAh/Q_ref`` (``ΔAh`` the charge counted
    between the two points), and its most charged point sits at the reference's drift-free value there,
    ``c₀ − Ah_full/Q_ref``. A span within :data:`FULL_TOL` of 1 or more (a reference counted with a smaller capacity,
    or one that runs past full or empty) is a test from full to empty: the count decides, as without a reference. The
    span is placed inside [0, 1], nearest the reference; a top within :data:`FULL_TOL` of full is full. With a
    capacity given (``capacity_ah``: the user's, the record's declared one, or a refit's on the axis placed before) the
    reference places the test's top alone, the span being ``ΔAh`` over that capacity: a refit that passes the capacity
    of a placed axis gets the same axis.

    Only a reference that is the record's own statement of SOC: a loader that counts the reference from full with a
    capacity of its own (``meta.extra["soc_ref_capacity_ah"]``, Panasonic, CALCE) declares a different axis, which
    :mod:`socbench.socaxis` converts; and a reference spanning less than :data:`REFERENCE_MIN_SPAN` is not used."""
    soc_ref = profile.get("soc_ref")
    if soc_ref is None or reference_capacity(profile) is not None:
        return None
    lo, hi = sorted((k_full, k_empty))
    test = slice(lo, hi + 1)
    time = profile.time_s - profile.time_s[lo]
    z, a, t = soc_ref[test], ah[test], time[test]
    inside = (z > 0.0) & (z < 1.0)
    moved = float(ah[k_empty] - ah[k_full])
    if np.count_nonzero(inside) < 10 or not moved > 0:
        return None
    slopes, weights = [], []
    jump = gap_step_ah(ah)
    for r in rests:
        if r.start >= lo and r.stop <= hi + 1 and r.duration_s >= REFERENCE_REST_S and r.stop - r.start >= 3 \
                and not spans_gap(ah, r.start, r.stop, jump):
            slopes.append(float(np.polyfit(time[r.start:r.stop], soc_ref[r.start:r.stop], 1)[0]))
            weights.append(r.duration_s)
    drift = _weighted_median(slopes, weights) if slopes else 0.0
    design = np.column_stack([np.ones(a.size), a])[inside]
    (c0, slope), *_ = np.linalg.lstsq(design, (z - drift * t)[inside], rcond=None)
    if not slope < 0:
        return None  # a reference that does not fall as charge leaves: not a count of this record's charge
    q_ref = -1.0 / float(slope)
    if not moved / q_ref >= REFERENCE_MIN_SPAN or moved / q_ref >= 1.0 - FULL_TOL:
        return None  # a reference from full to empty within its counting error: the count decides, as without it
    q = float(capacity_ah) if capacity_ah else q_ref
    span = min(moved / q, 1.0)
    top = float(c0 + slope * ah[k_full])
    # a top within the count's tolerance of full is full (a reference read to a point or two, not a part charge)
    z_top = 1.0 if top >= 1.0 - FULL_TOL else float(np.clip(top, span, 1.0))
    note = (f"the record's reference SOC places the test: its most charged point at z = {z_top:.3f}, its most "
            f"discharged at {z_top - span:.3f} (the reference counts with {q_ref:.4g} Ah; at the most charged point "
            f"it reads {top:.3f} without its drift)")
    if not capacity_ah:
        note += f"; capacity {q_ref:.4g} Ah, where a count from full to empty would take the {moved:.4g} Ah moved"
    return q, z_top, note


def declared_capacity(profile: Profile, declared: float | None,
                      full_to_empty: str = "declared") -> tuple[float | None, str | None]:
    """``(capacity for the SOC axis or None, note or None)`` of an HPPC record whose metadata declare ``declared`` Ah
    (a canonical CSV's sidecar, a loader's table). None means: the HPPC's own charge (the count from full to its most
    discharged point).

    * A test that moves less charge between its most charged and most discharged points than the declared capacity,
      by more than :data:`FULL_TOL`, stops above empty (10–30 % is common): the declared capacity places it where it
      ran.
    * One that moves more, by more than :data:`FULL_TOL`, would run the axis below empty (a nominal capacity of a cell
      that holds more, or a wrong sidecar): None, and a note says so.
    * One that moves the declared charge within :data:`FULL_TOL` ran from full to empty: ``full_to_empty`` says which
      the caller keeps, ``"declared"`` (``socbench diagnose``, as it always has) or ``"count"`` (``socbench fit``,
      as it always has: exact for its own record, where a rounded declaration may end a little past empty).

    None, without a note, where nothing is declared or the record is not an HPPC (the fit says why)."""
    if not declared:
        return None, None
    try:
        a = analyze_hppc(profile, capacity_ah=declared)
    except DataError:
        return None, None
    test = a.soc[a.start_index:a.end_index]
    span = float(np.max(test) - np.min(test))  # the charge the test moves, in units of the declared capacity
    if span > 1.0 + FULL_TOL:
        return None, (f"the HPPC moves {span * declared:.4g} Ah between its most charged and most discharged points, "
                      f"more than the {declared:.4g} Ah its metadata declare: the capacity is the charge it moves")
    if span < 1.0 - FULL_TOL or full_to_empty == "declared":
        return float(declared), None
    return None, None


def end_knee(ocv_z, ocv_v, n_series: int = 1) -> tuple | None:
    """``(ratio, slope)`` of the lowest step between OCV points (by SOC): how many times steeper it is than the median
    of the others, and its slope per cell [V per unit SOC]. Every Li-ion chemistry ends in a knee (the anode's last
    stage, the cathode's end of lithiation): its last 5–10 % above empty falls several times steeper than the middle
    of the curve and by a volt per unit SOC or more (NMC/NCA 2–5 V; LFP, after a plateau of 0.05–0.1 V, tens of
    volts), so a test that reaches empty shows it (Panasonic 18650PF at 25 °C: 2.3 ×, 2.1 V; ORNL Leaf cell: 3.3–4 ×,
    1.7–2 V) and one that stops at 10–40 % does not. None with fewer than four points."""
    z, v = np.asarray(ocv_z, dtype=float), np.asarray(ocv_v, dtype=float)
    if z.size < 4:
        return None
    order = np.argsort(z)
    dz, dv = np.diff(z[order]), np.diff(v[order])
    if np.any(dz <= 0):
        return None
    slopes = dv / dz
    rest = float(np.median(slopes[1:]))
    return (float(slopes[0] / rest) if rest > 0 else float("inf")), float(slopes[0]) / max(int(n_series), 1)


def _weighted_median(values, weights) -> float:
    """The value below and above which half the weight lies."""
    order = np.argsort(values)
    v, w = np.asarray(values, dtype=float)[order], np.asarray(weights, dtype=float)[order]
    return float(v[np.searchsorted(np.cumsum(w), 0.5 * np.sum(w))])


def _soc_axis(ah: np.ndarray, ah_full: float, q: float, soc_start: float | None) -> np.ndarray:
    """SOC per sample of the charge count ``ah`` [Ah discharged]: 1 at the most charged point ``ah_full``, or, given
    ``soc_start``, that at the first sample."""
    z = 1.0 - (ah - ah_full) / q
    return z if soc_start is None else z + (soc_start - float(z[0]))


def _sets_repeat(a: HPPCAnalysis) -> bool:
    """Whether the first pulses of ``a``'s sets last within :data:`DURATION_GAP` of each other, the test's first set
    aside when two or more follow it: where the test starts (full; empty for a test in the charge direction) a protocol
    skips the pulse the cell cannot take (a cycler cannot charge a full cell; the USABC HPPC at 100 % SOC has no regen
    pulse), so where that pulse opens the other sets the first set opens with another one."""
    firsts = {}
    for p in a.pulses:
        firsts.setdefault(p.level, p.duration_s)
    d = np.array(list(firsts.values()))
    d = d[1:] if d.size > 2 else d
    return d.size > 0 and float(np.max(d)) <= DURATION_GAP * max(float(np.min(d)), 1e-9)


def _analyze_hppc(profile: Profile, capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start=None,
                  durations: list | None = None, rest_sets: bool = False,
                  count_correction: np.ndarray | None = None) -> HPPCAnalysis:
    """:func:`analyze_hppc` with a given (or the record-read, for None) longest pulse; the lengths of the held
    phases from a rest (the pulse candidates, before the bound) are appended to ``durations`` when it is a list.
    ``rest_sets``: a pulse after a rest of ``min_rest_s`` or more opens a new set too (module docstring, 5).
    ``count_correction``: per sample, charge [Ah] added to the count (:func:`pulse_count_correction`); None: the
    pulses found are counted alike where they qualify, and the record analysed again on that count."""
    if profile.batched:
        raise DataError("analyze_hppc needs a plain profile", file=profile.meta.source or profile.name)
    profile.require("voltage_v")
    src = profile.meta.source or profile.name
    t, i, v = profile.time_s, profile.current_a, profile.voltage_v
    n = t.size
    # a sample's interval ends at the next time stamp; the last one lasts the median step
    t_after = np.append(t[1:], t[-1] + (float(np.median(np.diff(t))) if n > 1 else 0.0))
    lev = rest_level(i, i_rest)
    notes = [lev.describe()]
    di = i - lev.offset_a
    active, blips = _active_mask(t_after, t, np.abs(di), lev)
    if blips:
        notes.append(f"{blips} current blip(s) shorter than {MIN_PULSE_S:g} s or at the noise level merged into rests")

    ah, ah_source = discharged_ah(profile, lev.offset_a)
    if count_correction is not None:
        ah = ah + np.cumsum(count_correction)
    ref = _reference_ah(profile)
    if ah_source == "current" and ref is not None:
        scale = max(float(np.max(np.abs(ref))), float(np.max(np.abs(ah))), 1e-12)  # as discharged_ah
        off = float(np.max(np.abs(ref - ah))) / scale
        if off > AH_MISMATCH:
            notes.append(f"the reference SOC departs from the counted current by up to {100 * off:.2g} % of the "
                         "charge, not in jumps at gaps (another capacity, or counting error): the SOC axis follows "
                         "the current")
    # full: the most charged point; the test starts where the record first comes within FULL_TOL of it (charge
    # pulses at full may return to it or beyond, and noise and coarse sampling blur the count by tenths of a percent)
    ah_full, k_full, q = _full_point(ah, capacity_ah)
    if not q > 0:
        raise DataError("the record discharges no charge: cannot place it on the SOC axis", file=src)
    soc = _soc_axis(ah, ah_full, q, soc_start)

    # a rest's end voltage (a line through its last window) is read where it is used, once: a drive cycle has
    # thousands of moments at zero current, and a record that is no HPPC uses hardly any of them
    v_ends: dict = {}

    def v_end(r: Rest) -> float:
        if r.start not in v_ends:
            v_ends[r.start] = _rest_end_voltage(t, v, r.start, r.stop, r.duration_s)
        return v_ends[r.start]

    rests = []
    for a, b in true_runs(~active):
        dur = float(t_after[b - 1] - t[a]) if b < n else float(t[b - 1] - t[a])
        rests.append(Rest(a, b, dur, float(soc[b - 1]), float("nan")))
    rest_by_stop = {r.stop: r for r in rests}  # (their lengths: the SOC axis is final further down)

    # pulse candidates: held phases that start from a rest and end inside the record
    sign = np.sign(di)
    candidates = []
    held = []  # (duration, level) of every held phase from a rest: the pulses, and the steps a record shows
    # the first phase of each active run, where it ends inside the record: a phase that starts from a rest
    from_rest = [ph for a, b in true_runs(active) if a > 0
                 for ph in _phases(a, b, sign, t_after, t)[:1] if ph[1] < n]
    levels = run_medians(di, from_rest)
    spread = np.zeros_like(di)  # |I − level| over each such phase, for its median absolute deviation
    for (pa, pb), level in zip(from_rest, levels):
        spread[pa:pb] = np.abs(di[pa:pb] - level)
    for (pa, pb), level, mad in zip(from_rest, levels.tolist(), run_medians(spread, from_rest).tolist()):
        dur = float(t[pb] - t[pa])
        if mad > max(lev.lo_a, PULSE_FLATNESS * abs(level)):
            continue  # not a held current (driving, a ramp)
        if abs(level) < PULSE_SNR * lev.hi_a:
            continue  # hardly above the rest threshold: a wobble of a current that has no clear rest level
        held.append((dur, level))
        before = rest_by_stop.get(pa)
        if before is None or before.duration_s < PULSE_REST_RATIO * dur:
            continue  # an HPPC rests before every pulse; a drive cycle crosses zero for a moment
        candidates.append((pa, pb, dur))
    # which way the test steps: down from full (the usual HPPC: what comes before full is pre-conditioning) or up to
    # it (an HPPC in the charge direction, whose levels are reached by charging: the whole record before full is the
    # test). Decided by the SOC of the held phases over time, the steps among them
    ascending = len(candidates) >= 2 and float(np.polyfit(t[[c[0] for c in candidates]],
                                                          soc[[c[0] for c in candidates]], 1)[0]) > 0.0
    if not ascending and 2 * sum(c[1] <= k_full for c in candidates) > len(candidates):
        # most held phases lie before the record's most charged point: that point is a charge back after the test
        # to beyond where the test started (a count that drifts over a day-long test, the charge a cell takes beyond
        # what it gave, a test started a little below full). The test down from full starts at the most charged
        # point before its first held phase; what follows it is post-conditioning (_test_end)
        ah_full, k_full, q = _full_point(ah, capacity_ah, stop=candidates[0][0] + 1)
        soc = _soc_axis(ah, ah_full, q, soc_start)
        notes.append(f"the record charges back {float(ah_full - np.min(ah)):.3g} Ah beyond where its test started: "
                     "full is the most charged point before the test, not the charge back's end")
    start = 0 if ascending else k_full
    candidates = [c for c in candidates if c[1] > start]
    if ascending:
        notes.append("an HPPC in the charge direction (its SOC levels are reached by charging): the rest points lie "
                     "on the charge branch of any hysteresis")
        if not capacity_ah:  # the charge from the most discharged point up to full, not what follows full
            q = float(np.max(ah) - ah_full)
            soc = _soc_axis(ah, ah_full, q, soc_start)
    placed = None if soc_start is not None else reference_placement(
        profile, ah, k_full, int(np.argmax(ah)) if ascending else k_full + int(np.argmax(ah[k_full:])), capacity_ah,
        rests)
    if placed is not None:
        q, z_top, note = placed
        soc = _soc_axis(ah, ah_full, q, None) - (1.0 - z_top)
        notes.append(note)
    # the rests' SOC on the final axis (recounted in the charge direction, or placed by the reference)
    rests = [replace(r, soc_end=float(soc[r.stop - 1])) for r in rests]
    rest_by_start = {r.start: r for r in rests}
    rest_by_stop = {r.stop: r for r in rests}
    shift = float(soc[0]) - float(_soc_axis(ah[:1], ah_full, q, None)[0])
    if abs(shift) > 1e-9 and placed is None:
        notes.append(f"the record starts at SOC {soc_start:g} (given): its most charged point at {1.0 + shift:.4g}, "
                     "the HPPC rest points on that axis")
    if durations is not None:
        durations.extend(c[2] for c in candidates)
    if max_pulse_s is None:
        max_pulse_s = _pulse_bound(np.array([c[2] for c in candidates])) if candidates else MAX_PULSE_S
        notes.append(f"pulses: held phases from a rest of at most {max_pulse_s:.3g} s (read from the record)")

    if rest_sets:
        notes.append(f"pulse sets: a new one after every rest of {min_rest_s:g} s or more, as well as where charge "
                     "moved between pulses")
    pulses = []
    level = -1
    last_stop_ah = None
    unresolved = 0
    gap_jump = gap_step_ah(ah)
    for a, b, dur in candidates:
        if dur > max_pulse_s:
            continue
        rested = rest_sets and a in rest_by_stop and rest_by_stop[a].duration_s >= min_rest_s
        if last_stop_ah is None or abs(ah[a - 1] - last_stop_ah) > SET_SPLIT * q or rested:
            level += 1
        last_stop_ah = ah[b]
        dts = t[a + 1:b + 1] - t[a:b]
        cur = float(np.sum(di[a:b] * dts) / np.sum(dts))
        resolved = b - a >= MIN_EDGE_SAMPLES
        unresolved += not resolved
        d_on, d_off = i[a] - i[a - 1], i[b - 1] - i[b]
        r_inst = float((v[a - 1] - v[a]) / d_on) if resolved and abs(d_on) >= EDGE_FRACTION * abs(cur) else np.nan
        r_off = float((v[b] - v[b - 1]) / d_off) if resolved and abs(d_off) >= EDGE_FRACTION * abs(cur) else np.nan
        before = rest_by_stop.get(a)
        v_before = v_end(before) if before is not None else float(v[a - 1])
        r_pulse = float((v_before - v[b - 1]) / cur)
        nxt = rest_by_start.get(b)
        tau = tau_slow = float("nan")
        if nxt is not None and nxt.stop - nxt.start >= 4:
            tr, vr = t[nxt.start:nxt.stop], v[nxt.start:nxt.stop]
            # a rest with a record gap in it holds two rests at two SOCs, which a monotone fit would join into one
            # (a 6 s branch read 1800 s): its samples are read as they are
            if not spans_gap(ah, nxt.start, nxt.stop, gap_jump):
                vr = relaxation_curve(tr, vr)
            tau = _recovery_tau(tr, vr)
            tau_slow = _recovery_tau(tr, vr, 0.95) / 3.0
        pulses.append(Pulse(a, b, cur, dur, float(soc[a - 1]), level, r_inst, r_off, r_pulse, tau, tau_slow))
    if not pulses:
        raise DataError(f"not an HPPC test: no pulse found (a held current of at most {max_pulse_s:.3g} s that "
                        "starts from a rest)", file=src)
    if np.nanmedian([p.r_pulse for p in pulses]) < 0:  # the voltage rises under discharge: a test read upside down
        raise DataError("current sign looks flipped: the voltage rises under the pulses the current calls discharge "
                        "(positive = discharge)", file=src, column="current_a")
    if unresolved:
        period = float(np.median(np.diff(t))) if n > 1 else float("nan")
        notes.append(f"{unresolved} of {len(pulses)} pulses span fewer than {MIN_EDGE_SAMPLES} samples (sample "
                     f"period {period:.3g} s): their edge resistances are not measured")

    # OCV points: end of the rest before each set's first pulse, and a final rest after a last step
    ocv_z, ocv_v = [], []
    firsts = {}
    for p in pulses:
        firsts.setdefault(p.level, p)
    unrested = []
    for p in firsts.values():
        r = rest_by_stop.get(p.start)
        if r is not None and r.start == 0 and r.duration_s < min_rest_s:
            # the record starts at rest: the cell rested before the test began (HPPC protocol), keep the point
            notes.append(f"pulse set at z={p.soc:.3f}: OCV point from the record's initial rest ({r.duration_s:g} s)")
        elif r is None or r.duration_s < min_rest_s:
            unrested.append(p.soc)
            continue
        ocv_z.append(r.soc_end)
        ocv_v.append(v_end(r))
    n_sets, n_rested = len(firsts), len(ocv_z)
    if unrested:
        notes.append(f"{len(unrested)} of {n_sets} pulse sets (at z = {', '.join(f'{z:.3f}' for z in unrested[:5])}"
                     f"{', ...' if len(unrested) > 5 else ''}) follow a rest shorter than {min_rest_s:g} s: no OCV "
                     "point")
    end = _test_end(pulses, rests, ah, q, ascending)
    last = next((r for r in rests if r.stop == end), None)
    if last is not None and last.duration_s >= min_rest_s:
        # after a last step (charge moved since the last pulse; with the sets split at every rest, the last "pulse"
        # may be that step: charge moved since the last set began)
        since = ah[firsts[pulses[-1].level].start - 1] if rest_sets else ah[pulses[-1].stop]
        if abs(ah[end - 1] - since) > SET_SPLIT * q:
            ocv_z.append(last.soc_end)
            ocv_v.append(v_end(last))
    if end < n:
        notes.append(f"the test ends at the rest after its most discharged point (z = {soc[end - 1]:.3f}): the "
                     f"{(t[-1] - t[end - 1]) / 3600:.2g} h of charge back that follow are not part of it")
    if len(ocv_z) < 2 or n_rested < REST_SHARE * n_sets:
        raise DataError(f"not an HPPC test: {n_rested} of {n_sets} pulse set(s) follow a rest of {min_rest_s:g} s or "
                        f"more, {len(ocv_z)} OCV rest point(s) in all (an HPPC rests before most of its pulse sets; "
                        "an OCV curve needs 2 points)", file=src)
    knee = end_knee(ocv_z, ocv_v, profile.meta.n_series or 1)
    if knee is not None and not (knee[0] >= KNEE_RATIO and knee[1] >= KNEE_SLOPE_V) and not capacity_ah \
            and placed is None and soc_start is None:
        notes.append(f"{NO_KNEE}: the lowest OCV step falls {knee[1]:.2g} V per unit SOC per cell, {knee[0]:.2g} × "
                     f"the median step (a test that reaches empty ends in a step {KNEE_RATIO:g} × steeper or more, "
                     f"and {KNEE_SLOPE_V:g} V or more): the test may stop above empty, and the capacity counted from "
                     f"full to its most discharged point ({q:.4g} Ah) is then short of the cell's, its SOC axis too "
                     "fast; give the capacity, the start SOC, or a reference SOC column")
    level_soc = np.array([p.soc for p in firsts.values()])
    r_inst = _finite_median([p.r_inst for p in pulses])
    start_ocv = float(v[0] + r_inst * di[0]) if k_full == 0 and r_inst > 0 else float("nan")
    bottom = (None if ascending or not BOTTOM_EXTENSION
              else _bottom_point(t, v, di, ah, soc, pulses, start, end, lev, max_pulse_s))
    if count_correction is None and ah_source == "current":
        correction = pulse_count_correction(t, di, pulses, lev)
        moved_ah = 0.0 if correction is None else float(np.max(np.abs(np.cumsum(correction))))
        if correction is not None and moved_ah >= PULSE_COUNT_MIN_MOVE * q:
            again = _analyze_hppc(profile, capacity_ah, i_rest, max_pulse_s, min_rest_s, soc_start,
                                  rest_sets=rest_sets, count_correction=correction)
            moved = moved_ah / again.capacity_ah
            note = (f"{int(np.count_nonzero(correction))} pulses sampled in a few samples each, {COUNTED_ALIKE} (their "
                    f"current × the mean counted length of their direction): the SOC axis moves by up to "
                    f"{100 * moved:.2g} points")
            return replace(again, notes=again.notes + (note,))
    rests = [replace(r, v_end=v_end(r)) for r in rests]
    steps = [level for dur, level in held if dur > max_pulse_s and level > 0.0]
    step_current = float(np.median(steps)) if steps and not ascending else float("nan")
    return HPPCAnalysis(tuple(rests), tuple(pulses), np.asarray(ocv_z), np.asarray(ocv_v), q, soc, ah, ah_source,
                        level_soc, tuple(notes), lev, float(max_pulse_s), start_ocv, start,
                        "charge" if ascending else "discharge", end, bottom, count_correction, step_current)


def pulse_count_correction(t: np.ndarray, di: np.ndarray, pulses, lev: RestLevel) -> np.ndarray | None:
    """Per sample, the charge [Ah] to add to the zero-order-hold count in the step into the sample (at each
    corrected pulse's first sample after it) when the pulses of one direction are counted alike (module docstring,
    3): ``I_k·(D̄ − D_k)/3600`` for pulse ``k`` of current ``I_k`` and counted length ``D_k``, ``D̄`` the mean over
    the held pulses of its direction (``di``: the current less the sensor offset; held: every sample within
    ``max(θ_lo, 5 %)`` of the pulse's current). None where no direction qualifies."""
    out = np.zeros(t.size)
    for direction in (1.0, -1.0):
        kind = [p for p in pulses if np.sign(p.current_a) == direction and p.stop < t.size
                and float(np.max(np.abs(di[p.start:p.stop] - p.current_a))) <= max(lev.lo_a, 0.05 * abs(p.current_a))]
        if len(kind) < PULSE_COUNT_MIN:
            continue
        lengths = np.array([p.duration_s for p in kind])
        period = float(np.median([p.duration_s / (p.stop - p.start) for p in kind]))
        mean = float(np.mean(lengths))
        if period < PULSE_COUNT_FRAC * mean or float(np.ptp(lengths)) > PULSE_COUNT_SPREAD * period:
            continue
        for p, length in zip(kind, lengths):
            out[p.stop] += p.current_a * (mean - length) / 3600.0
    return out if np.any(out) else None


def _bottom_point(t, v, di, ah, soc, pulses, start: int, end: int, lev: RestLevel, max_pulse_s: float):
    """The trace :attr:`HPPCAnalysis.bottom_point` of a test down from full whose most discharged sample ends a
    discharge step, else None. ``di`` is the current with the sensor's offset removed."""
    k = start + int(np.argmax(ah[start:end]))
    if di[k] <= lev.hi_a:  # at rest there (a final rest is a rest point of its own) or not discharging
        return None
    quiet = np.flatnonzero(di[start:k] <= lev.hi_a)  # the step began after the last sample at rest before it
    a = start + int(quiet[-1]) + 1 if quiet.size else start
    if t[k] - t[a] <= max_pulse_s:  # a pulse took the test lowest: its rest point stands for the bottom
        return None
    lowest = max(p.level for p in pulses)
    r = _finite_median([p.r_pulse for p in pulses if p.level == lowest])
    if not (np.isfinite(r) and r > 0):
        return None
    # the trace of the step once its over-potential has settled (three of the slowest relaxation times the pulses'
    # rests read, at least the pulse length): v + I·r, on SOC bins of BOTTOM_BIN
    tau = _finite_median([p.tau_slow_s for p in pulses])
    settle = max(3.0 * tau, max_pulse_s) if np.isfinite(tau) else max_pulse_s
    keep = np.arange(a, k + 1)[t[a:k + 1] >= t[a] + settle]
    if keep.size == 0:
        keep = np.array([k])
    zs, us = soc[keep], v[keep] + di[keep] * r
    edges = np.arange(float(zs.min()), float(zs.max()) + BOTTOM_BIN, BOTTOM_BIN)
    idx = np.clip(np.searchsorted(edges, zs, side="right") - 1, 0, max(edges.size - 1, 0))
    pts = [(float(np.median(zs[idx == j])), float(np.median(us[idx == j]))) for j in np.unique(idx)]
    return tuple(sorted(pts))


def _full_point(ah: np.ndarray, capacity_ah, stop: int | None = None) -> tuple[float, int, float]:
    """``(Ah_full, k_full, Q)``: the most charged point of the count ``ah`` among its samples before ``stop`` (all
    by default), the first sample within :data:`FULL_TOL` of it (:func:`_first_approach`), and the capacity: the given
    one, else the charge from there to the most discharged point after it."""
    head = ah[:stop]
    ah_full = float(np.min(head))
    k_full = _first_approach(head, ah_full, ah)
    q = float(capacity_ah) if capacity_ah else float(np.max(ah[k_full:]) - ah_full)
    return ah_full, k_full, q


def _first_approach(x: np.ndarray, extreme: float, ah: np.ndarray) -> int:
    """The first sample of ``x`` within :data:`FULL_TOL` of the record's charge (``ptp(ah)``) of its ``extreme``:
    where a count first reaches full or its most discharged point (noise and a rest's offset move it by tenths of a
    percent)."""
    return int(np.argmax(np.abs(x - extreme) <= FULL_TOL * max(float(np.ptp(ah)), 1e-12)))


def _test_end(pulses, rests, ah, q: float, ascending: bool) -> int:
    """One past the last sample of a test down from full: the end of the rest after its most discharged point when
    the record then charges back (a cycler's script returning the cell to full: post-conditioning, as the charge
    before full is pre-conditioning); the record's length otherwise, and for a test in the charge direction."""
    n = ah.size
    if ascending or not pulses:
        return n
    tail = ah[pulses[-1].stop:]
    k_bottom = pulses[-1].stop + _first_approach(tail, float(np.max(tail)), ah)
    after = next((r for r in rests if r.start >= k_bottom - 1), None)
    if after is None or after.stop >= n or ah[after.stop - 1] - float(np.min(ah[after.stop:])) <= SET_SPLIT * q:
        return n
    return after.stop


def _with_step_rests(analysis: HPPCAnalysis, profile: Profile, min_rest_s: float) -> HPPCAnalysis:
    """``analysis`` (of ``profile``) with an OCV point at the end of each rest of ``min_rest_s``
    or more inside the test that follows a step and gives no point yet (:data:`STEP_REST_MIN_SOC`): the active run
    before it lasts longer than the pulse bound and moves at least that share of the capacity in the test's direction
    (discharge down from full, charge in the charge direction: the branch of the other rest points). A test down from
    full also gets the rest at full before its first step, where it rested ``min_rest_s`` or more. A rest across a
    gap in the record is left out (the step may have happened in the gap), and so is one within half that share of
    SOC of a point (the rest after the first pulses at full). Such a rest ends where the next level's pulse fell
    between two samples, if it did: its point is read before the voltage first falls (:func:`_undisturbed_stop`), not
    in the relaxation after that pulse. Added to the analysis :func:`analyze_hppc` settles on,
    not counted in deciding whether a record is an HPPC or which pulse bound reads it: a drive with long stops is
    no HPPC for having them."""
    ah, q, rests = analysis.ah, analysis.capacity_ah, analysis.rests
    t, v = profile.time_s, profile.voltage_v
    start = analysis.start_index
    end = analysis.end_index if analysis.end_index is not None else ah.size
    down = analysis.steps != "charge"
    gap_jump = gap_step_ah(ah)
    candidates = []
    top = next((r for r in rests if r.stop > start and r.duration_s >= min_rest_s), None) if down else None
    if top is not None and abs(ah[max(top.start, start)] - ah[start]) <= SET_SPLIT * q:
        candidates.append(top)  # the rest at full before the first step
    for before, r in zip(rests, rests[1:]):
        if r.start < start or r.stop > end or r.duration_s < min_rest_s or r.stop >= ah.size:
            continue
        moved = (ah[r.start] - ah[before.stop]) * (1.0 if down else -1.0)
        if t[r.start] - t[before.stop] > analysis.max_pulse_s and moved >= STEP_REST_MIN_SOC * q \
                and not spans_gap(ah, r.start, r.stop, gap_jump):
            candidates.append(r)
    points = [(-1, float(z), float(v)) for z, v in zip(analysis.ocv_soc, analysis.ocv_voltage)]
    added = []
    for r in candidates:
        stop = _undisturbed_stop(v, r.start, r.stop)
        rested = float(t[stop - 1] - t[r.start])
        if rested < min_rest_s or min(abs(r.soc_end - z) for _, z, _ in points) < STEP_REST_MIN_SOC / 2:
            continue
        point_v = r.v_end if stop == r.stop else _rest_end_voltage(t, v, r.start, stop, rested)
        points.append((r.start, r.soc_end, point_v))
        added.append(r.soc_end)
    if not added:
        return analysis
    # in the order of the record: each measured point at the rest it ends
    at = {(r.soc_end, r.v_end): r.start for r in rests}
    points = sorted((at.get((z, v), k), z, v) for k, z, v in points)
    note = (f"{len(added)} OCV point(s) from rests at full or after a step that no pulse set follows (at z = "
            f"{', '.join(f'{z:.3f}' for z in added[:5])}{', ...' if len(added) > 5 else ''}): pulses shorter than the "
            "sample period, or a step-and-rest test")
    return replace(analysis, ocv_soc=np.array([z for _, z, _ in points]),
                   ocv_voltage=np.array([v for _, _, v in points]), notes=analysis.notes + (note,))


def _undisturbed_stop(v: np.ndarray, start: int, stop: int) -> int:
    """One past the last sample of the rest ``[start, stop)`` before its voltage first falls from one sample to the
    next by :data:`REST_DROP_SIGMAS` times its sample-to-sample noise (robust: 1.4826 × the median absolute difference
    / √2) and at least :data:`REST_DROP_MIN_V`: a discharge pulse no sample caught. A rest after a discharge only
    rises as it relaxes; ``stop`` when nothing falls."""
    dv = np.diff(v[start:stop])
    if dv.size < 2:
        return stop
    sigma = 1.4826 * float(np.median(np.abs(dv - np.median(dv)))) / np.sqrt(2.0)
    falls = np.flatnonzero(dv < -max(REST_DROP_SIGMAS * sigma, REST_DROP_MIN_V))
    return start + int(falls[0]) + 1 if falls.size else stop


def ocv_from_hppc(profile: Profile, capacity_ah: float | None = None, **options) -> OCVCurve:
    """The OCV curve through the HPPC rest points (:func:`analyze_hppc`), monotone PCHIP (ECM_SPEC §3.3)."""
    a = analyze_hppc(profile, capacity_ah=capacity_ah, **options)
    return a.ocv(source=f"HPPC rest points of {profile.meta.source or profile.name} ({a.ocv_soc.size} points, "
                        f"Q = {a.capacity_ah:.4g} Ah)")


# ------------------------------------------------------------------------------------------------ slow test
@dataclass(frozen=True, eq=False)
class SlowOCV:
    """OCV from a slow constant-current test: the discharge branch, the charge branch (None if the test has no
    charge) and their mean (None without a charge branch). ``capacity_ah`` is the discharged charge of the test."""

    discharge: OCVCurve
    charge: OCVCurve | None
    mean: OCVCurve | None
    capacity_ah: float

    @property
    def best(self) -> OCVCurve:
        """The mean of both branches when there are two, else the discharge branch."""
        return self.mean if self.mean is not None else self.discharge


def _binned(z: np.ndarray, *columns: np.ndarray, n_bins: int) -> tuple[np.ndarray, ...]:
    """``(z̄, c̄ for c in columns)``: the means of ``z`` and of each column over ``n_bins`` equal bins of ``z``
    (empty bins left out)."""
    edges = np.linspace(z.min(), z.max(), n_bins + 1)
    k = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, n_bins - 1)
    cnt = np.bincount(k, minlength=n_bins)
    ok = cnt > 0
    return tuple(np.bincount(k, weights=c, minlength=n_bins)[ok] / cnt[ok] for c in (z, *columns))


#: a slow test's branch runs on across a dip below its threshold this short [s] (a noisy sensor's sample or two, a
#: pause), never across the test's rests of half an hour and more
SLOW_GAP_S = 600.0


def _closed(mask: np.ndarray, t: np.ndarray, max_gap_s: float) -> np.ndarray:
    """``mask`` with its runs of False shorter than ``max_gap_s`` between two runs of True set True."""
    out = mask.copy()
    for a, b in true_runs(~mask):
        if a > 0 and b < mask.size and t[b] - t[a - 1] <= max_gap_s:
            out[a:b] = True
    return out


def _slow_branches(profile: Profile, capacity_ah: float | None, i_min: float | None):
    """``(discharge, charge or None, q)``: each branch of a slow test as ``(z, v, t)`` per sample (the SOC counted as
    :func:`ocv_from_slow_test` says, the voltage, the time) and the charge ``q`` its SOC is counted over. A branch
    runs on across a dip of the current below ``i_min`` shorter than :data:`SLOW_GAP_S`."""
    profile.require("voltage_v")
    src = profile.meta.source or profile.name
    i, v, t = profile.current_a, profile.voltage_v, profile.time_s
    ah = profile.amp_hours()
    if i_min is None:
        i_min = 0.2 * float(np.max(np.abs(i)))
    dis = _closed(i > i_min, t, SLOW_GAP_S)
    if not dis.any():
        raise DataError("no discharge in the slow OCV test", file=src, column="current_a")
    runs = true_runs(dis)
    a, b = max(runs, key=lambda r: ah[r[1] - 1] - ah[r[0]])
    q_dis = float(ah[b - 1] - ah[a])
    q = float(capacity_ah) if capacity_ah else q_dis
    discharge = (1.0 - (ah[a:b] - ah[a]) / q, v[a:b], t[a:b])
    chg = _closed(i < -i_min, t, SLOW_GAP_S) & (np.arange(i.size) >= b)
    charge = None
    if chg.any():
        c0, c1 = max(true_runs(chg), key=lambda r: r[1] - r[0])
        charge = (1.0 - (ah[c0:c1] - ah[a]) / q, v[c0:c1], t[c0:c1])  # the same charge count as the discharge
    return discharge, charge, q


def ocv_from_slow_test(profile: Profile, capacity_ah: float | None = None, n_points: int = 101,
                       i_min: float | None = None) -> SlowOCV:
    """Pseudo-OCV branches of a slow (e.g. C/20) discharge and, when present, the following charge.

    SOC: the discharge branch runs from 1 (its start) to 0 (its end) over ``Q`` = its discharged charge (or
    ``capacity_ah``); the charge branch continues the same charge count, climbing with the charged Ah (coulombic
    efficiency 1). Each branch is averaged into ``n_points`` SOC bins and made monotone. The mean curve is
    the average of the branches where both exist; above the top of the charge branch (a charge that stops at the
    voltage limit before the full capacity) it is the discharge branch shifted by half the gap at the top of the
    overlap.
    """
    (z_d, v_d, _), chg, q = _slow_branches(profile, capacity_ah, i_min)
    src = profile.meta.source or profile.name
    zd, vd = monotone_points(*_binned(z_d, v_d, n_bins=n_points))
    discharge = OCVCurve(zd, vd, f"C/20 discharge branch of {src}")
    charge = mean = None
    if chg is not None:
        zc, vc = monotone_points(*_binned(chg[0], chg[1], n_bins=n_points))
        charge = OCVCurve(zc, vc, f"C/20 charge branch of {src}")
        grid = zd
        top = zc.max()
        inside = grid <= top
        half_gap_top = 0.5 * (float(charge(top)) - float(discharge(top)))
        vm = np.where(inside, 0.5 * (discharge(grid) + charge(np.minimum(grid, top))), discharge(grid) + half_gap_top)
        zm, vm = monotone_points(grid, vm)
        mean = OCVCurve(zm, vm, f"mean of the C/20 branches of {src}")
    return SlowOCV(discharge, charge, mean, q)


#: the SOC range whose branch gap :func:`slow_test_count_error` reads (away from the ends, where the resistances
#: rise and the branches have not settled)
COUNT_ERROR_SOC = (0.2, 0.9)


def slow_test_count_error(profile: Profile, capacity_ah: float | None = None, n_points: int = 101,
                          i_min: float | None = None) -> tuple[float, float] | None:
    """``(e, se)`` [A]: the current offset still in a slow test's charge count, read from how its two branches
    disagree, and its standard error; None without a charge branch or an OCV slope to read it by.

    A count off by ``e`` reads, at the time ``t`` (from the discharge's start), the SOC ``ẑ = z − e·t/Q``. Each
    branch then lies at ``V(ẑ) ≈ U(ẑ) + U'(ẑ)·e·t(ẑ)/Q ∓ I·R``, ``t(ẑ)`` the time the branch passes ``ẑ``. The
    charge branch passes every SOC later than the discharge, so the gap between them is::

        V_c(ẑ) − V_d(ẑ) = G + e · U'(ẑ)·(t_c(ẑ) − t_d(ẑ))/Q

    ``G`` the branches' polarisation (``(I_d + I_c)·R``, no SOC dependence assumed over :data:`COUNT_ERROR_SOC`). The
    regression of the gap on that term and a constant gives ``e``. On a flat OCV (``U' ≈ 0``) the branches do not
    show it, and neither does the OCV: the standard error is then large. Over a C/20 test's forty hours an offset of
    0.1 % of 1C moves the charge branch by 4 % of SOC; the rests, which measure the offset directly, leave an error of
    the current noise over √(rest samples)."""
    dis, chg, q = _slow_branches(profile, capacity_ah, i_min)
    if chg is None:
        return None
    zd, vd, td = _binned(*dis, n_bins=n_points)
    zc, vc, tc = _binned(*chg, n_bins=n_points)
    lo = max(COUNT_ERROR_SOC[0], zd.min(), zc.min())
    hi = min(COUNT_ERROR_SOC[1], zd.max(), zc.max())
    grid = zd[(zd >= lo) & (zd <= hi)]
    if grid.size < 5:
        return None
    v_c, v_d = np.interp(grid, zc, vc), np.interp(grid, zd, vd)
    gap = v_c - v_d
    mean = OCVCurve(*monotone_points(grid, 0.5 * (v_c + v_d)), "")
    k = mean.slope(grid) * (np.interp(grid, zc, tc) - np.interp(grid, zd, td)) / (3600.0 * q)
    x = np.column_stack([np.ones_like(k), k])
    coef, *_ = np.linalg.lstsq(x, gap, rcond=None)
    r = gap - x @ coef
    dof = max(grid.size - 2, 1)
    cov = np.linalg.pinv(x.T @ x) * float(r @ r) / dof
    # neighbouring bins share their error (a smooth misfit, not noise): the standard error of so many fewer samples
    rho = lag1_autocorrelation(r, max_rho=0.99)
    se = float(np.sqrt(max(cov[1, 1], 0.0) * (1.0 + rho) / (1.0 - rho)))
    return (float(coef[1]), se) if np.isfinite(se) and se > 0 else None


def edge_resistance(profile: Profile, frac: float = 0.2) -> float:
    """Median ``−ΔV/ΔI`` over the sample-to-sample current steps larger than ``frac`` × the largest step: an
    instantaneous-resistance scale for any record (used when a record has no HPPC pulses)."""
    profile.require("voltage_v")
    di = np.diff(profile.current_a)
    dv = np.diff(profile.voltage_v)
    big = np.abs(di) >= frac * np.max(np.abs(di), initial=0.0)
    big &= np.abs(di) > 0
    if not big.any():
        raise DataError("the record has no current steps to estimate a resistance from",
                        file=profile.meta.source or profile.name)
    return float(np.median(-dv[big] / di[big]))
