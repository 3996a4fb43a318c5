"""The sensor model: what the BMS measures of the true current, voltage and temperature.

A channel (current, voltage or temperature) has steady characteristics (white noise, offset, gain error, random-walk
drift, ADC quantisation with saturation; ``bits = 0`` means no ADC) and a list of timed faults. Internally the
characteristics are faults with onset 0, so there is one code path; every fault acts from ``onset_s`` (until
``end_s``) and faults combine in this order::

    x_m = (1 + Σ gains) · x_true + Σ offsets + Σ drifts + Σ noises       analogue errors
    x_m = quantise(x_m)            (bits over range, saturating at its ends)
    x_m = stuck(x_m)               value frozen at the onset sample (or at a given value)
    x_m = hold-last(x_m)           dropouts: the last valid sample is repeated and the sample is flagged

Sampling: the sensors sample every ``dt`` seconds; with ``jitter_sd_s`` each sample is taken at ``t_k + δ_k``,
``δ_k ~ N(0, jitter_sd_s²)`` (clipped to ±dt/2) but stamped ``t_k``. Initial-condition errors: the SOC handed to the
estimators is ``z_true(0) + soc0_error + N(0, soc0_error_sd²)``; the declared capacity is ``(1 + capacity_mismatch)``
× the true one. A temperature-sensor offset is ``temperature.offset``.

Randomness: run ``r`` with seed ``s`` draws from ``SeedSequence(s, spawn_key=(scenario key, channel, fault))`` — the
same seed gives the same data whatever else is in the batch, different seeds and different faults are independent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import build, require

CHANNELS = ("current", "voltage", "temperature")
FAULT_KINDS = ("noise", "offset", "gain", "drift", "dropout", "stuck")


@dataclass(frozen=True)
class Fault:
    """One impairment acting on ``[onset_s, end_s)``.

    kind     noise (value = SD), offset (value, units of the channel), gain (value = relative error),
             drift (value = random-walk SD per √s), dropout (value = probability that a sample starts a dropout of
             ``length_s``), stuck (value = the stuck reading; omitted: frozen at the onset sample)
    """

    kind: str
    value: float | None = None
    onset_s: float = 0.0
    end_s: float | None = None
    length_s: float = 0.0

    def __post_init__(self):
        require(self.kind in FAULT_KINDS, "kind", f"must be one of {', '.join(FAULT_KINDS)}, got {self.kind!r}")
        require(self.value is not None or self.kind == "stuck", "value", f"a {self.kind} fault needs a value")
        require(np.isfinite(self.onset_s) and self.onset_s >= 0, "onset_s", f"must be >= 0, got {self.onset_s}")
        require(self.end_s is None or self.end_s > self.onset_s, "end_s", "must be after onset_s")
        require(self.length_s >= 0, "length_s", f"must be >= 0, got {self.length_s}")
        if self.kind in ("noise", "drift"):
            require(self.value >= 0, "value", f"a {self.kind} SD must be >= 0, got {self.value}")
        if self.kind == "gain":
            require(self.value > -1, "value", f"a gain error must be > -1, got {self.value}")
        if self.kind == "dropout":
            require(0 <= self.value <= 1, "value", f"a dropout probability must be in [0, 1], got {self.value}")

    def active(self, t: np.ndarray) -> np.ndarray:
        end = np.inf if self.end_s is None else self.end_s
        return (t >= self.onset_s) & (t < end)


@dataclass(frozen=True)
class Channel:
    """Steady characteristics of one sensor channel plus its timed faults."""

    noise_sd: float = 0.0
    offset: float = 0.0
    gain: float = 0.0
    drift_sd: float = 0.0
    bits: int | None = None
    range: tuple | None = None
    faults: tuple = ()

    def __post_init__(self):
        require(self.noise_sd >= 0, "noise_sd", f"must be >= 0, got {self.noise_sd}")
        require(self.drift_sd >= 0, "drift_sd", f"must be >= 0, got {self.drift_sd}")
        require(self.gain > -1, "gain", f"must be > -1, got {self.gain}")
        require(self.bits is None or 0 <= self.bits <= 32, "bits", f"must be in 0..32 (0 = no ADC), got {self.bits}")
        if self.range is not None:
            ok = len(self.range) == 2 and all(isinstance(v, (int, float)) for v in self.range)
            require(ok and self.range[0] < self.range[1], "range", f"must be [low, high] with low < high, "
                                                                  f"got {self.range}")
        require(not self.bits or self.range is not None, "range", "quantisation (bits) needs a range")

    @property
    def steady_faults(self) -> tuple:
        out = []
        for kind, value in (("gain", self.gain), ("offset", self.offset), ("drift", self.drift_sd),
                            ("noise", self.noise_sd)):
            if value:
                out.append(Fault(kind, value))
        return tuple(out)

    @property
    def lsb(self) -> float:
        """Quantisation step (0 without an ADC)."""
        if not self.bits:
            return 0.0
        return (self.range[1] - self.range[0]) / 2.0**self.bits

    @property
    def white_sd(self) -> float:
        """SD of the white part of the error: noise and quantisation (LSB²/12)."""
        return float(np.sqrt(self.noise_sd**2 + self.lsb**2 / 12.0))


@dataclass(frozen=True)
class SensorSpec:
    """The whole sensor suite of a scenario plus the initial-condition errors handed to the estimators."""

    current: Channel = field(default_factory=Channel)
    voltage: Channel = field(default_factory=Channel)
    temperature: Channel = field(default_factory=Channel)
    dt: float = 1.0
    jitter_sd_s: float = 0.0
    soc0_error: float = 0.0
    soc0_error_sd: float = 0.0
    capacity_mismatch: float = 0.0

    def __post_init__(self):
        require(self.dt > 0, "dt", f"must be > 0, got {self.dt}")
        require(0 <= self.jitter_sd_s < self.dt, "jitter_sd_s", f"must be in [0, dt), got {self.jitter_sd_s}")
        require(-1 < self.soc0_error < 1, "soc0_error", f"must be in (-1, 1), got {self.soc0_error}")
        require(self.soc0_error_sd >= 0, "soc0_error_sd", f"must be >= 0, got {self.soc0_error_sd}")
        require(self.capacity_mismatch > -1, "capacity_mismatch", f"must be > -1, got {self.capacity_mismatch}")

    @classmethod
    def from_table(cls, table: dict, file: str, section: str = "sensors") -> SensorSpec:
        """Build from a TOML table; any problem is one ConfigError line naming ``file`` and the dotted key."""
        from ..errors import ConfigError

        if not isinstance(table, dict):
            raise ConfigError(f"{file}: key '{section}': must be a table")
        table = dict(table)
        channels = {}
        for name in CHANNELS:
            sub = table.pop(name, {})
            if not isinstance(sub, dict):
                raise ConfigError(f"{file}: key '{section}.{name}': must be a table")
            sub = dict(sub)
            faults = sub.pop("faults", [])
            if not isinstance(faults, list):
                raise ConfigError(f"{file}: key '{section}.{name}.faults': must be an array of tables")
            faults = tuple(build(Fault, f, f"{section}.{name}.faults[{j}]", file) for j, f in enumerate(faults))
            if isinstance(sub.get("range"), list):
                sub["range"] = tuple(sub["range"])
            channels[name] = build(Channel, sub, f"{section}.{name}", file, skip=("faults",), faults=faults)
        return build(cls, table, section, file, skip=CHANNELS, **channels)

    def without_faults(self) -> SensorSpec:
        """The same sensors with their steady characteristics only (the lab characterisation test)."""
        from dataclasses import replace

        return replace(self, current=replace(self.current, faults=()), voltage=replace(self.voltage, faults=()),
                       temperature=replace(self.temperature, faults=()))


def _generators(seeds, key: int, channel: int, fault: int):
    return [np.random.default_rng(np.random.SeedSequence(int(s), spawn_key=(key, channel, fault))) for s in seeds]


def _hold_last(x: np.ndarray, dropped: np.ndarray) -> np.ndarray:
    """Replace dropped samples by the last valid one (a dropout at the first sample keeps its value)."""
    idx = np.where(dropped, 0, np.arange(x.shape[-1]))
    np.maximum.accumulate(idx, axis=-1, out=idx)
    return np.take_along_axis(x, idx, axis=-1)


def apply_channel(x_true: np.ndarray, t: np.ndarray, channel: Channel, seeds, key: int, index: int):
    """Measured values ``(R, T)`` of one channel and the dropout flags ``(R, T)``.

    ``x_true`` is ``(T,)`` or ``(R, T)``; ``t`` the sample stamps ``(T,)``; ``index`` the channel number (streams).
    """
    seeds = list(seeds)
    R, T = len(seeds), t.size
    x_true = np.broadcast_to(np.asarray(x_true, dtype=float), (R, T))
    dt = np.diff(t, prepend=t[0])
    gain = np.zeros(T)
    add = np.zeros((R, T))
    faults = channel.steady_faults + tuple(channel.faults)
    for j, f in enumerate(faults):
        on = f.active(t)
        if f.kind == "gain":
            gain = gain + f.value * on
        elif f.kind == "offset":
            add += f.value * on
        elif f.kind in ("noise", "drift"):
            draws = np.stack([g.standard_normal(T) for g in _generators(seeds, key, index, j)])
            if f.kind == "noise":
                add += f.value * draws * on
            else:
                add += np.cumsum(f.value * np.sqrt(dt) * draws * on, axis=-1)
    x = (1.0 + gain) * x_true + add
    if channel.bits:
        lo, hi = channel.range
        q = channel.lsb
        x = np.clip(lo + np.round((x - lo) / q) * q, lo, hi)
    dropped = np.zeros((R, T), dtype=bool)
    for j, f in enumerate(faults):
        on = f.active(t)
        if f.kind == "stuck" and on.any():
            k0 = int(np.argmax(on))
            value = x[:, k0:k0 + 1] if f.value is None else np.full((R, 1), f.value)
            x = np.where(on, value, x)
        elif f.kind == "dropout":
            dt_med = float(np.median(np.diff(t))) if T > 1 else 1.0
            length = max(int(round(f.length_s / dt_med)), 1)
            starts = np.stack([g.random(T) < f.value for g in _generators(seeds, key, index, j)]) & on
            c = np.cumsum(starts, axis=-1)
            c_shift = np.zeros_like(c)
            c_shift[:, length:] = c[:, :-length]
            dropped |= (c - c_shift) > 0
    if dropped.any():
        x = _hold_last(x, dropped)
    return x, dropped


def jitter_offsets(t: np.ndarray, spec: SensorSpec, seeds, key: int) -> np.ndarray:
    """Sampling-time errors δ ``(R, T)`` (zero without jitter)."""
    seeds = list(seeds)
    if spec.jitter_sd_s == 0:
        return np.zeros((len(seeds), t.size))
    d = np.stack([g.standard_normal(t.size) for g in _generators(seeds, key, len(CHANNELS), 0)]) * spec.jitter_sd_s
    return np.clip(d, -spec.dt / 2, spec.dt / 2)


def initial_soc_guess(z_true0: float, spec: SensorSpec, seeds, key: int) -> np.ndarray:
    """SOC handed to the estimators ``(R,)``: the true initial SOC plus the scenario's error, clipped to [0, 1]."""
    seeds = list(seeds)
    e = np.array([g.standard_normal() for g in _generators(seeds, key, len(CHANNELS) + 1, 0)])
    return np.clip(z_true0 + spec.soc0_error + spec.soc0_error_sd * e, 0.0, 1.0)
