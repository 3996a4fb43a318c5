"""What the search leaves: the held-out residual after the last step, against the voltage noise, split by what it
follows.

The search names only the effects of its catalogue. What none of them explains is still information: a residual that
follows the SOC points at the equilibrium curve (an OCV read from a few rest points, between which the curve bends) or
at anything as slow as the SOC; one that follows the current points at a resistance the model has wrong. On the
held-out residual ``e`` (every block scored by the fold that did not see it), each record's own mean removed (an
offset between records is not structure)::

    structure  = √max(RMSE² − σ_n², 0)               σ_n the voltage noise the search measured
    SOC share  = Σ_b n_b ē_b² / Σ e²                 ē_b the mean over SOC bins b of SOC_BIN_WIDTH (bins with at
                                                     least MIN_BIN_SAMPLES samples): the correlation ratio η²
    current share = corr(e, I − Ī)²                  Ī each record's mean current

with the SOC and the current from the final model run open loop over each record. An SOC shape finer than a few
bins (a period under about six, 30 % of SOC) varies within the bins and is read in part only. The two shares overlap
where the SOC and the current move together (a steady discharge), and the SOC share takes up any error as slow as the
SOC: they say where to look, not what it is. With an OCV from rest points the report gives the widest SOC gap between
them within the SOC range the records visited.

What the records cannot show. A capacity fade ``f`` (the cell holds ``(1 − f)·Q``, ``Q`` the fit test's) moves the
SOC by ``Ah/Q · f/(1 − f)`` after ``Ah`` discharged, and the voltage by ``U'(z)`` times that; each record's mean removed
(the base refit's voltage offset takes it), its RMS over the records is ``RMS(U'·Ah/Q) · f/(1 − f)``. Below the voltage
noise ``σ_n`` the records hardly tell it from the noise (over the randomised benchmark's nine runs an effect whose
footprint lies within the noise is named first in 14 % of its cases, docs/undeclared_effects_pooled.md), so the
fade whose footprint equals ``σ_n``::

    f* = c/(1 + c),   c = σ_n / RMS(U'(z)·Ah/Q)

is the largest the records cannot show: on a flat curve (LFP's plateau) a record that does not reach the knee hides
fades of tens of percent, and the report says so where nothing named a fade (:data:`FADE_HINT`).
"""

from __future__ import annotations

import numpy as np

#: width of the SOC bins of the correlation ratio
SOC_BIN_WIDTH = 0.05
#: a SOC bin with fewer samples does not count
MIN_BIN_SAMPLES = 10
#: the report suggests measuring the OCV between its points when at least this share of what is left follows the SOC
#: (most of it) …
OCV_HINT_SHARE = 0.5
#: … and the OCV's widest gap is wider than this (the 5–10 % steps of a standard HPPC)
OCV_HINT_GAP = 0.1
#: the report says the records cannot show a fade where the largest they hide (``f*``) is at least this
FADE_HINT = 0.05


def _demeaned(x: np.ndarray, sizes) -> np.ndarray:
    """``x`` (records one after another, of ``sizes``) with each record's mean removed."""
    out = np.array(x, dtype=float)
    k = 0
    for n in sizes:
        out[k:k + n] -= out[k:k + n].mean() if n else 0.0
        k += n
    return out


def soc_share(e: np.ndarray, z: np.ndarray) -> float:
    """The correlation ratio η² of ``e`` over SOC bins of :data:`SOC_BIN_WIDTH` (``e`` centred)."""
    total = float(np.sum(e * e))
    if total <= 0:
        return 0.0
    bins = np.floor(np.clip(z, 0.0, 1.0) / SOC_BIN_WIDTH).astype(int)
    between = 0.0
    for b in np.unique(bins):
        sel = bins == b
        if sel.sum() >= MIN_BIN_SAMPLES:
            between += float(sel.sum()) * float(e[sel].mean()) ** 2
    return min(between / total, 1.0)


def current_share(e: np.ndarray, i: np.ndarray) -> float:
    """``corr(e, i)²`` (both centred)."""
    den = float(np.sum(e * e) * np.sum(i * i))
    return float(np.sum(e * i)) ** 2 / den if den > 0 else 0.0


def ocv_gap(ocv_soc, z: np.ndarray | None = None) -> float | None:
    """The widest SOC gap between the OCV curve's points, within ``[min z, max z]`` (the part the records visited; a
    gap counts by its overlap with it) or, without ``z``, over all of them; None without two points."""
    if ocv_soc is None or len(ocv_soc) < 2 or (z is not None and z.size == 0):
        return None
    pts = np.sort(np.asarray(ocv_soc, dtype=float))
    lo, hi = (float(pts[0]), float(pts[-1])) if z is None else (float(np.min(z)), float(np.max(z)))
    overlap = np.minimum(pts[1:], hi) - np.maximum(pts[:-1], lo)
    return float(max(np.max(overlap), 0.0))


def hidden_fade(ocv_slope, amp_hours, capacity_ah: float, sizes, noise_sd: float) -> float:
    """``f*`` of the module docstring: the largest capacity fade (a fraction of ``capacity_ah``) whose voltage the
    records (one after another, of ``sizes``; ``ocv_slope`` U'(z) [V per unit SOC] along them, ``amp_hours`` the
    charge each has delivered since its start) cannot show above ``noise_sd``; 1 where the OCV is flat along them."""
    x = _demeaned(np.asarray(ocv_slope, dtype=float) * np.asarray(amp_hours, dtype=float) / capacity_ah, sizes)
    rms = float(np.sqrt(np.mean(x * x))) if x.size else 0.0
    if not rms > 0:
        return 1.0
    c = float(noise_sd) / rms
    return c / (1.0 + c)


def leftover(residual: np.ndarray, soc, current, sizes, noise_sd: float, ocv_soc=None, fade: float | None = None) \
        -> dict:
    """The module docstring's measures of the held-out ``residual`` [V] (records one after another, of ``sizes``),
    with the final model's ``soc`` and the measured ``current`` on the same samples; ``ocv_soc``: the SOC points of an
    OCV read from rests (None otherwise); ``fade``: :func:`hidden_fade` of the records, kept as ``hidden_fade``
    (None: not measured, or a fade is in the model)."""
    r = np.asarray(residual, dtype=float)
    ok = np.isfinite(r)
    z, i = np.asarray(soc, dtype=float), np.asarray(current, dtype=float)
    e = _demeaned(np.where(ok, r, 0.0), sizes)[ok]
    rmse = float(np.sqrt(np.mean(r[ok] ** 2))) if ok.any() else 0.0
    out = {"rmse_v": rmse, "noise_v": float(noise_sd),
           "structure_v": float(np.sqrt(max(rmse ** 2 - noise_sd ** 2, 0.0))),
           "soc_share": soc_share(e, z[ok]), "current_share": current_share(e, _demeaned(i, sizes)[ok])}
    gap = ocv_gap(ocv_soc, z[ok])
    if gap is not None:
        out["ocv_points"] = int(len(ocv_soc))
        out["ocv_widest_gap"] = gap
    if fade is not None:
        out["hidden_fade"] = float(fade)
    return out


def suggests_ocv(left: dict) -> bool:
    """Whether what is left points at the OCV: most of it follows the SOC (:data:`OCV_HINT_SHARE`) and the OCV's
    widest gap is wider than :data:`OCV_HINT_GAP`."""
    return bool(left) and left["soc_share"] >= OCV_HINT_SHARE and left.get("ocv_widest_gap", 0.0) > OCV_HINT_GAP


def sentence(left: dict) -> str:
    """One line for ``diagnosis.md``."""
    s = (f"held-out RMSE {1000 * left['rmse_v']:.1f} mV against {1000 * left['noise_v']:.1f} mV of voltage noise: "
         f"{1000 * left['structure_v']:.1f} mV of structure no candidate took; "
         f"{100 * left['soc_share']:.0f} % of the residual's variance follows the SOC (bins of "
         f"{100 * SOC_BIN_WIDTH:g} %), {100 * left['current_share']:.0f} % the current")
    if "ocv_widest_gap" in left:
        s += (f"; the OCV was read at {left['ocv_points']} points, the widest gap within the SOC range of the "
              f"records {100 * left['ocv_widest_gap']:.0f} % of SOC")
        if suggests_ocv(left):
            s += (" — between its points the curve is interpolated, and most of what is left follows the SOC: a slow "
                  "OCV test (given to `--fit` beside the HPPC) or finer HPPC steps would measure it")
    if left.get("hidden_fade", 0.0) >= FADE_HINT:
        s += (f"; a capacity fade of up to {100 * left['hidden_fade']:.0f} % would move these records' voltage by "
              "less than their noise (the OCV's slope along the SOC they cover): they can hardly show one; a "
              "capacity test, or a record that reaches the end-of-discharge knee, would")
    return s
