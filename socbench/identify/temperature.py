"""Fit a model at several temperatures and assemble one temperature-aware parameter set.

``fit_temperatures(name, records)`` takes identification records (HPPC tests) measured at different temperatures:

1. **Temperature of each record**: the median of its temperature column (the cell's own thermocouple for the
   Panasonic files: the 25 °C HPPC runs at a median 25.9 °C), else the ambient temperature its loader read from the
   file name (``meta.extra["ambient_temperature_c"]``); a record with neither is an error, and so are two records less
   than :data:`MIN_SPACING_C` apart.
2. **One SOC axis**. Every record is placed on the charge axis of one reference capacity ``Q_ref`` (default: the
   largest charge any record delivers, normally the warmest): ``z = 1 − Ah/Q_ref``. A colder HPPC, which reaches its
   cut-off after ``Q_T < Q_ref``, then covers ``[1 − Q_T/Q_ref, 1]``. Why not each record on its own capacity: the
   charge a cold cell delivers before the cut-off is mostly lost to resistance, not missing charge; blending two
   temperatures at equal fractions of their own capacities would blend different charge states (tens of mV of OCV
   apart in the knee).
3. **Fit** each record with :func:`~socbench.identify.fit.fit_model` on that axis (``capacity_ah=Q_ref``; each with
   its own fit setting when ``per_record`` gives one, e.g. the one that validates best at that temperature). SOC
   polynomials of a record that covers part of the axis are fitted on its range and stored clamped to it (their end
   values held), lookups hold their end values by construction: nothing is extrapolated below a cold record's range.
4. **Tables**. Each parameter becomes a :class:`~socbench.models.params.TemperatureTable` over the fitted
   temperatures: log-linear in ``T`` (``"log"``) for positive quantities (resistances, capacitances, time constants
   — their fit is logarithmic, :mod:`socbench.identify.specs`), linear otherwise; exact at every fitted
   temperature, between its two neighbours in between, the end tables held outside (with a warning from
   :func:`socbench.checks.check_temperature_range` when data leave the range).
5. **OCV(z, T)** (:class:`~socbench.ocv.TemperatureOCV`): each record's own HPPC rest points, where the data has
   them. Below a record's lowest rest point there is no data at that temperature: the curve is continued by the
   curve that reaches lowest (normally the warmest), shifted to meet the record's lowest point (so the shape comes
   from data, the level from that temperature; the note says by how much).
6. **Capacity per temperature** ``Q_T`` (each record's own discharge) is kept as data:
   :class:`~socbench.models.params.CapacityTable` (``capacity_by_temperature`` in PARAMS.json).

A single record gives a plain single-temperature set (exactly :func:`fit_model`).

**Charge transfer** (``charge_transfer=True``): the cold cell's polarisation is not linear in the current (the
Panasonic HPPCs: the 10 s polarisation per ampere at the smallest pulse is 1.0× that at 2C at 25 °C, 2.6× at
−20 °C), the Butler–Volmer signature ``U_ct = N_s(2R_gT/F)·asinh(I/2I_0)`` with an exchange current ``I_0`` that
falls steeply in the cold. The set then carries a :class:`~socbench.models.effects.ButlerVolmer` effect fitted with
the base model (docs/real_data.md §4d measures the signature), in two passes:

a. at each temperature ``T_k`` the base parameters and one ``I_0,k`` are fitted together
   (:func:`fit_model` with ``effects``; ``ΔR = 0``: the base's ``R0`` carries the linear part);
b. the Arrhenius law ``ln I_0(T) = ln I_0(T_ref) − (E_a/R_g)(1/T − 1/T_ref)`` (``T_ref`` = 25 °C) through the
   ``(1/T_k, ln I_0,k)`` by weighted least squares (:func:`arrhenius_law`: weights from each ``I_0,k``'s standard
   error, an ``I_0,k`` at a bound of its range left out; ``E_a ≥ 0``);
c. at each temperature the base parameters refitted with the law's ``I_0(T)`` held, starting from where pass (a)
   ended there (only ``I_0`` moved), so every node of the tables was fitted with the exchange current the set will
   use (the law is looked up at the measured cell temperature, sample by sample, like every table).

Pass (a)'s ``I_0,k`` and the law are in :attr:`TemperatureFit.extra` (``"charge_transfer"``) and the notes.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..models.base import T_REF_C
from ..models.effects import KELVIN, R_GAS, ButlerVolmer
from ..models.params import CapacityTable, ModelParams, TemperatureTable
from ..ocv import OCVCurve, TemperatureOCV, monotone_points
from ..profile import Profile
from .fit import FitResult, fit_model
from .hppc import analyze_hppc
from .specs import Guess, param_spec

#: two identification records closer than this [K] are the same temperature (an error: which one would count?)
MIN_SPACING_C = 1.0


def record_temperature(profile: Profile) -> tuple[float, str]:
    """``(T [°C], how it was found)``: the median of the temperature column, else the file's ambient temperature."""
    src = profile.meta.source or profile.name
    if profile.temperature_c is not None:
        t = np.asarray(profile.temperature_c, dtype=float)
        return float(np.median(t)), f"median of the temperature column ({t.min():.1f}…{t.max():.1f} °C)"
    amb = profile.meta.extra.get("ambient_temperature_c")
    if amb is not None:
        return float(amb), "ambient temperature of the file (no temperature column)"
    raise DataError("no temperature column and no ambient temperature: cannot place the record in temperature",
                    file=src, column="temperature_c")


@dataclass(frozen=True, eq=False)
class TemperatureFit:
    """The assembled set and the fit of each record, coldest first."""

    name: str
    params: ModelParams
    temps: tuple
    fits: tuple  # FitResult per temperature
    capacities: tuple  # Q_T [Ah] per temperature (each record's own discharge)
    capacity_ref: float
    sources: tuple  # record names
    temperature_notes: tuple
    notes: tuple = ()
    seconds: float = 0.0
    mode: str = "paper"
    extra: dict = field(default_factory=dict)

    @property
    def rmse_v(self) -> float:
        """RMS of the per-record fit RMSEs (each over its fitted samples)."""
        return float(np.sqrt(np.mean([f.rmse_v ** 2 for f in self.fits])))

    @property
    def warnings(self) -> list:
        return [f"{t:g} °C: {w}" for t, f in zip(self.temps, self.fits) for w in f.warnings]

    def fit_summary(self) -> dict:
        """The ``"fit"`` block of PARAMS.json: one entry per temperature plus how the set was assembled."""
        return {
            "mode": self.mode,
            "rmse_v": self.rmse_v,
            "seconds": self.seconds,
            "capacity_ref_ah": self.capacity_ref,
            "by_temperature": [
                {"temperature_c": t, "record": s, "temperature_from": how, "capacity_ah": q,
                 **f.fit_summary()}
                for t, s, how, q, f in zip(self.temps, self.sources, self.temperature_notes, self.capacities,
                                           self.fits)],
            "notes": list(self.notes),
            **({"charge_transfer": self.extra["charge_transfer"]} if "charge_transfer" in self.extra else {}),
        }


def extend_ocv(curve: OCVCurve, reference: OCVCurve) -> tuple[OCVCurve, float | None]:
    """``curve`` continued below its lowest rest point by ``reference`` shifted to meet it; ``(curve, shift [V])``
    (shift None when nothing was added). Monotone: the reference is, and it ends at the junction."""
    z_lo = float(curve.soc[0])
    below = reference.soc < z_lo - 1e-9
    if not below.any():
        return curve, None
    shift = float(curve(z_lo)) - float(reference(z_lo))
    z = np.r_[reference.soc[below], curve.soc]
    v = np.r_[reference.voltage[below] + shift, curve.voltage]
    return OCVCurve(*monotone_points(z, v), source=curve.source), shift


def _table_scale(name: str, nodes) -> str:
    """"log" for a positive quantity (fitted as a logarithm) whose every node is positive, else "linear"."""
    positive = all(n.range_on_unit()[0] > 0 for n in nodes)
    return "log" if param_spec(name, Guess()).log and positive else "linear"


#: a relative standard error of a fitted ``I_0,k`` below this is taken as this in the law's weights: the fit's
#: standard errors assume white residuals and are far too small on a record of thousands of correlated samples, so
#: without a floor one temperature would decide the law alone
I0_REL_SE_FLOOR = 0.05
#: the charge-transfer term's label among a fit's values
I0_LABEL = f"{ButlerVolmer.name}.I0"


@dataclass(frozen=True)
class ArrheniusLaw:
    """``I_0(T) = i0_ref·exp[−(ea/R_g)(1/T − 1/T_ref)]`` fitted through per-temperature exchange currents."""

    i0_ref: float  # [A] at t_ref
    ea: float  # [J/mol]
    t_ref: float  # [°C]
    used: tuple  # per point: whether it entered the fit

    def __call__(self, temp_c):
        return self.effect().exchange_current(np.asarray(temp_c, dtype=float) + KELVIN)

    def effect(self) -> ButlerVolmer:
        return ButlerVolmer(I0=self.i0_ref, dR=0.0, Ea=self.ea, t_ref=self.t_ref)


def arrhenius_law(temps_c, i0, rel_se, usable=None, t_ref: float = T_REF_C) -> ArrheniusLaw:
    """Weighted least squares of ``ln I_0`` on ``x = −(1/T − 1/T_ref)/R_g``: ``ln I_0 = ln I_0(T_ref) + E_a·x``.

    Weights ``1/max(rel_se, I0_REL_SE_FLOOR)²`` (``rel_se`` the standard error of ``ln I_0``); points not ``usable``
    (at a bound of the fit's range, non-finite) are left out. With fewer than two usable temperatures, or a fitted
    ``E_a < 0`` (an exchange current that grows in the cold is no Arrhenius process), ``E_a = 0`` and ``I_0`` is the
    weighted geometric mean."""
    t = np.asarray(temps_c, dtype=float)
    y = np.log(np.asarray(i0, dtype=float))
    se = np.asarray(rel_se, dtype=float)
    ok = np.isfinite(y) & np.isfinite(se) & (np.ones(t.size, bool) if usable is None else np.asarray(usable, bool))
    if not ok.any():
        raise DataError("no usable exchange current to fit the Arrhenius law to")
    w = 1.0 / np.maximum(se[ok], I0_REL_SE_FLOOR) ** 2
    x = -(1.0 / (t[ok] + KELVIN) - 1.0 / (t_ref + KELVIN)) / R_GAS
    ea = 0.0
    if ok.sum() >= 2:
        xm, ym = np.average(x, weights=w), np.average(y[ok], weights=w)
        ea = float(np.sum(w * (x - xm) * (y[ok] - ym)) / np.sum(w * (x - xm) ** 2))
    ea = max(ea, 0.0)
    ln_ref = float(np.average(y[ok] - ea * x, weights=w))
    return ArrheniusLaw(float(np.exp(ln_ref)), ea, float(t_ref), tuple(bool(v) for v in ok))


def fit_temperatures(name: str, records, mode: str = "paper", capacity_ah: float | None = None,
                     options: dict | None = None, charge_transfer: bool = False, per_record=None,
                     **fit_kwargs) -> TemperatureFit:
    """Fit ``name`` on every record and assemble the temperature-aware set (see the module docstring).

    ``capacity_ah`` is ``Q_ref`` (default: the largest charge a record delivers); ``charge_transfer`` adds the
    Butler–Volmer term with an Arrhenius ``I_0(T)`` fitted with the base model (the module docstring);
    ``fit_kwargs`` go to :func:`fit_model` (``compress``, ``time_weighted``, ``knots``…).

    ``per_record``: one dict of :func:`fit_model` keywords per record (in the order given), laid over ``mode`` and
    ``fit_kwargs`` for that record alone — a fit setting chosen per temperature (the SOC form and the sample
    weighting that validate best at one temperature need not at another). The nodes of a table may then be of
    different forms (a polynomial at one temperature, a lookup at the next): each is evaluated on its own and the
    table interpolates their values, so nothing else changes.
    """
    t0 = _time.perf_counter()
    records = list(records)
    if not records:
        raise DataError("fit_temperatures needs at least one record")
    if per_record is None:
        per_record = [{}] * len(records)
    per_record = [dict(kw) for kw in per_record]
    if len(per_record) != len(records):
        raise DataError(f"fit_temperatures: {len(per_record)} per-record settings for {len(records)} records")
    placed = []
    for prof, kw in zip(records, per_record):
        temp, how = record_temperature(prof)
        placed.append((temp, how, prof, {"mode": mode, **fit_kwargs, **kw}))
    placed.sort(key=lambda x: x[0])
    for (ta, _, pa, _), (tb, _, pb, _) in zip(placed, placed[1:]):
        if tb - ta < MIN_SPACING_C:
            raise DataError(f"two identification records at the same temperature ({ta:.1f} and {tb:.1f} °C): "
                            f"{pa.name} and {pb.name}; give one record per temperature",
                            file=pb.meta.source or pb.name)
    analyses = [analyze_hppc(p) for _, _, p, _ in placed]
    own = [float(a.capacity_ah) for a in analyses]
    q_ref = float(capacity_ah) if capacity_ah else max(own)
    temps = tuple(t for t, _, _, _ in placed)
    modes = sorted({setting["mode"] for _, _, _, setting in placed})
    mode = modes[0] if len(modes) == 1 else "per temperature"

    def fit_all(starts=None, **kw):
        starts = starts or [None] * len(placed)
        return [fit_model(name, prof, capacity_ah=q_ref, options=options, start_fit=start, **setting, **kw)
                for (_, _, prof, setting), start in zip(placed, starts)]

    notes = [f"fitted at {len(temps)} temperatures ({', '.join(f'{t:.1f}' for t in temps)} °C) on one SOC axis "
             f"counted with Q_ref = {q_ref:.4g} Ah"]
    extra = {}
    if not charge_transfer:
        fits: list[FitResult] = fit_all()
    else:
        # (a) one exchange current per temperature with the base parameters; start at the 1C current
        first = fit_all(effects=(ButlerVolmer(I0=q_ref),))
        i0 = np.array([f.values[I0_LABEL] for f in first])
        rel_se = np.array([f.stderr[I0_LABEL] / f.values[I0_LABEL] for f in first])
        free = [I0_LABEL not in f.lsq.at_bounds for f in first]
        law = arrhenius_law(temps, i0, rel_se, free)
        # (b) every temperature refitted with the law's exchange current held (one record: pass (a) is final), from
        # where pass (a) ended there: only I0 moved. From the record's own guesses the refit can land in another
        # minimum (liu at 25 °C on the Panasonic HPPC: 5.8 mV on the HPPC against 4.7, 171 mV on its Cycle_1 run
        # against 25, a time constant at its 10^5 s bound)
        fits = first if len(first) == 1 else fit_all(effects=(law.effect(),), fit_effects=False, starts=first)
        extra["charge_transfer"] = {"temps": list(temps), "i0_fitted_a": i0.tolist(), "i0_rel_se": rel_se.tolist(),
                                    "used": list(law.used), "i0_ref_a": law.i0_ref, "ea_j_per_mol": law.ea,
                                    "t_ref_c": law.t_ref, "i0_law_a": np.atleast_1d(law(temps)).tolist(),
                                    "rmse_v_first_pass": [f.rmse_v for f in first]}
        notes.append("charge transfer (Butler–Volmer) fitted with the base model: I0 per temperature "
                     + ", ".join(f"{t:.1f} °C {v:.3g} A" + ("" if u else " (at a bound: not used)")
                                 for t, v, u in zip(temps, i0, law.used))
                     + f"; Arrhenius law I0(T) = {law.i0_ref:.3g} A at {law.t_ref:g} °C, Ea = {law.ea / 1e3:.1f} "
                       "kJ/mol; base parameters refitted with it held")
    if len(fits) == 1:
        f = fits[0]
        params = f.params.replace(notes=f.params.notes + tuple(notes))
        return TemperatureFit(name, params, temps, tuple(fits), tuple(own), q_ref,
                              tuple(p.name for _, _, p, _ in placed), tuple(h for _, h, _, _ in placed), tuple(notes),
                              _time.perf_counter() - t0, mode, extra)
    # OCV: each record's own curve, continued below its range by the curve that reaches lowest
    curves = [f.params.ocv for f in fits]
    ref = min(curves, key=lambda c: float(c.soc[0]))
    node_curves = []
    for temp, c in zip(temps, curves):
        ext, shift = extend_ocv(c, ref)
        if shift is not None:
            notes.append(f"OCV at {temp:.1f} °C below z = {c.soc[0]:.3f} (no rest points there): the lowest-reaching "
                         f"curve shifted by {1000 * shift:+.1f} mV")
        node_curves.append(ext)
    ocv = TemperatureOCV(temps, node_curves, source=f"HPPC rest points at {len(temps)} temperatures on Q_ref = "
                                                    f"{q_ref:.4g} Ah")
    values = {}
    for pname in fits[0].params.values:
        nodes = [f.params[pname] for f in fits]
        values[pname] = TemperatureTable(temps, tuple(nodes), _table_scale(pname, nodes))
    cap = CapacityTable(temps, tuple(own), source="charge each identification record discharges from full to "
                                                 "its end (HPPC: to the last pulse set)")
    base = fits[-1].params
    params = ModelParams(capacity_ah=q_ref, ocv=ocv, values=values, eta_charge=base.eta_charge,
                         options=dict(base.options), source="socbench fit (several temperatures)",
                         notes=tuple(notes) + tuple(n for f in fits for n in f.params.notes),
                         capacity_by_temperature=cap, effects=base.effects)
    return TemperatureFit(name, params, temps, tuple(fits), tuple(own), q_ref,
                          tuple(p.name for _, _, p, _ in placed), tuple(h for _, h, _, _ in placed), tuple(notes),
                          _time.perf_counter() - t0, mode, extra)
