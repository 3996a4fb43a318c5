"""A multirotor mission: electrical power per time step from rotor momentum theory, drawn as a constant-power load.

One sortie is ground idle → take-off → climb → hover → cruise (with gusts) → hover → descent → landing; the pattern
repeats until the truth pack reaches its under-voltage limit or a landing-reserve SOC. Shaft power (Leishman,
*Principles of Helicopter Aerodynamics*, ch. 2–5; momentum theory with a figure of merit)::

    v_h²  = T / (2 ρ A)                                      hover induced velocity, A = n_rotors · π D²/4
    v_i²  = (−V² + √(V⁴ + 4 v_h⁴)) / 2                        Glauert induced velocity at airspeed V (level flight)
    P_ind = κ · T · (V_c/2 + √(V_c²/4 + v_i²)) / FM           climb (V_c > 0) / descent (V_c < 0)
    P_par = D · V,   D = ½ ρ V² (CdA_frame + CdA_payload),   T = √(W² + D²)
    P_el  = (P_ind + P_par) / η_drive + P_avionics

κ = 1 in hover and vertical flight, ``cruise_induced_factor`` in forward flight. The descent branch uses the same
formula as a smooth approximation (momentum theory does not hold in the vortex-ring state). Gusts: a first-order
(Dryden-like) Ornstein–Uhlenbeck airspeed disturbance with SD ``gust_sd_ms`` and correlation time ``gust_tau_s``,
one fixed realisation per scenario (``gust_seed``) so that every Monte Carlo run flies the same mission.

Vehicle calibration (documented assumptions; the paper names no airframe): momentum theory gives P ∝ m^{3/2}, so a
+10 kg payload that roughly doubles the current (ECM_SPEC §1) needs an all-up mass without payload of about 15–17 kg;
a 10 kg hexacopter would draw 2^{3/2} ≈ 2.8× the power. Defaults: 16 kg including the 2.40 kg pack, six 30-inch
(0.762 m) rotors, ρ = 1.225 kg/m³ (ISA sea level); assumed, not measured: FM = 0.70 (full-scale rotors reach
0.7–0.8, small propellers are usually quoted at 0.5–0.7), η_drive = 0.80 (motor ≈ 0.85 × ESC ≈ 0.95), avionics 40 W,
idle 60 W, CdA 0.25 m² frame + 0.10 m² payload, κ_cruise = 1.15 (a typical induced-power factor), cruise 8 m/s.
On the truth pack at 25 °C this gives (measured, ``socbench scenarios --details``) 50.5 A mean for 24.6 min without
payload and 111.5 A for 11.1 min with 10 kg: 2.2× the current, 0.45× the flight time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import require

G = 9.80665


@dataclass(frozen=True)
class Vehicle:
    """The airframe and drivetrain (see the module docstring for the sources of the defaults)."""

    empty_mass_kg: float = 16.0  # all-up without payload, including the 2.40 kg pack (calibrated assumption)
    n_rotors: int = 6
    rotor_diameter_m: float = 0.762
    air_density: float = 1.225
    figure_of_merit: float = 0.70
    drive_efficiency: float = 0.80
    avionics_w: float = 40.0
    idle_w: float = 60.0  # armed on the ground, rotors at idle
    frame_cda_m2: float = 0.25
    payload_cda_m2: float = 0.10  # added when a payload is carried
    cruise_induced_factor: float = 1.15

    def __post_init__(self):
        for name in ("empty_mass_kg", "rotor_diameter_m", "air_density"):
            require(getattr(self, name) > 0, name, f"must be > 0, got {getattr(self, name)}")
        require(self.n_rotors >= 1, "n_rotors", f"must be >= 1, got {self.n_rotors}")
        for name in ("figure_of_merit", "drive_efficiency"):
            require(0 < getattr(self, name) <= 1, name, f"must be in (0, 1], got {getattr(self, name)}")
        for name in ("avionics_w", "idle_w", "frame_cda_m2", "payload_cda_m2"):
            require(getattr(self, name) >= 0, name, f"must be >= 0, got {getattr(self, name)}")
        require(self.cruise_induced_factor >= 1, "cruise_induced_factor", "must be >= 1")

    @property
    def disk_area_m2(self) -> float:
        return self.n_rotors * np.pi * self.rotor_diameter_m**2 / 4.0

    def electrical_power(self, payload_kg: float, airspeed, climb_rate=0.0, forward: bool = False):
        """Electrical power [W] at ``airspeed`` (m/s) and ``climb_rate`` (m/s, negative = descent)."""
        v = np.abs(np.asarray(airspeed, dtype=float))
        cda = self.frame_cda_m2 + (self.payload_cda_m2 if payload_kg > 0 else 0.0)
        drag = 0.5 * self.air_density * v**2 * cda
        weight = (self.empty_mass_kg + payload_kg) * G
        thrust = np.sqrt(weight**2 + drag**2)
        vh2 = thrust / (2.0 * self.air_density * self.disk_area_m2)
        vi2 = 0.5 * (-(v**2) + np.sqrt(v**4 + 4.0 * vh2**2))
        vc = np.asarray(climb_rate, dtype=float)
        kappa = self.cruise_induced_factor if forward else 1.0
        p_ind = kappa * thrust * (vc / 2.0 + np.sqrt(vc**2 / 4.0 + vi2)) / self.figure_of_merit
        return (p_ind + drag * v) / self.drive_efficiency + self.avionics_w


@dataclass(frozen=True)
class Mission:
    """One sortie's pattern (durations in s, speeds in m/s), repeated until the stop condition."""

    payload_kg: float = 0.0
    ground_s: float = 10.0
    takeoff_s: float = 5.0
    climb_s: float = 30.0
    climb_rate_ms: float = 2.0
    hover_s: float = 30.0
    cruise_s: float = 240.0
    cruise_speed_ms: float = 8.0
    hover2_s: float = 20.0
    descent_s: float = 40.0
    descent_rate_ms: float = 1.5
    landing_s: float = 10.0
    landing_rate_ms: float = 0.5
    gust_sd_ms: float = 1.5
    gust_tau_s: float = 5.0
    gust_seed: int = 2023
    reserve_soc: float = 0.0
    max_duration_s: float = 4 * 3600.0

    def __post_init__(self):
        for name, value in self.__dict__.items():
            if name.endswith(("_s", "_ms", "_kg")) and name != "gust_tau_s":
                require(value >= 0, name, f"must be >= 0, got {value}")
        require(self.gust_tau_s > 0, "gust_tau_s", f"must be > 0, got {self.gust_tau_s}")
        require(0 <= self.reserve_soc < 1, "reserve_soc", f"must be in [0, 1), got {self.reserve_soc}")
        require(self.max_duration_s > 0, "max_duration_s", "must be > 0")
        require(self.sortie_s > 0, "cruise_s", "the sortie has zero length")

    @property
    def sortie_s(self) -> float:
        return (self.ground_s + self.takeoff_s + self.climb_s + self.hover_s + self.cruise_s + self.hover2_s
                + self.descent_s + self.landing_s)

    def phases(self) -> list[tuple[str, float]]:
        return [("ground", self.ground_s), ("takeoff", self.takeoff_s), ("climb", self.climb_s),
                ("hover", self.hover_s), ("cruise", self.cruise_s), ("hover", self.hover2_s),
                ("descent", self.descent_s), ("landing", self.landing_s)]

    def power_pattern(self, vehicle: Vehicle, dt: float = 1.0) -> tuple[np.ndarray, list]:
        """Electrical power of one sortie on a ``dt`` grid ``(n,)`` and its phases ``[(name, start_s), ...]``.

        Gusts are drawn per sortie from ``gust_seed`` (the k-th repetition uses the k-th block of the stream) — see
        :meth:`power`.
        """
        return self.power(vehicle, 0, dt)

    def power(self, vehicle: Vehicle, sortie: int, dt: float = 1.0) -> tuple[np.ndarray, list]:
        """Power ``(n,)`` [W] and phases of repetition ``sortie`` (0-based) of the pattern."""
        names, speeds, climbs, forward = [], [], [], []
        phases, t0 = [], 0.0
        for name, seconds in self.phases():
            n = int(round(seconds / dt))
            if n == 0:
                continue
            phases.append((name, t0))
            t0 += n * dt
            names += [name] * n
            ramp = np.linspace(0.0, 1.0, n, endpoint=False)
            if name == "ground":
                speeds.append(np.zeros(n))
                climbs.append(np.zeros(n))
            elif name == "takeoff":  # spin-up and acceleration to the climb rate
                speeds.append(np.zeros(n))
                climbs.append(self.climb_rate_ms * ramp)
            elif name == "climb":
                speeds.append(np.zeros(n))
                climbs.append(np.full(n, self.climb_rate_ms))
            elif name == "cruise":
                speeds.append(np.full(n, self.cruise_speed_ms))
                climbs.append(np.zeros(n))
            elif name == "descent":
                speeds.append(np.zeros(n))
                climbs.append(np.full(n, -self.descent_rate_ms))
            elif name == "landing":
                speeds.append(np.zeros(n))
                climbs.append(np.full(n, -self.landing_rate_ms))
            else:  # hover
                speeds.append(np.zeros(n))
                climbs.append(np.zeros(n))
            forward.append(np.full(n, name == "cruise"))
        speed = np.concatenate(speeds)
        climb = np.concatenate(climbs)
        fwd = np.concatenate(forward)
        airspeed = speed + self.gusts(speed.size, dt, sortie)
        power = np.where(fwd, vehicle.electrical_power(self.payload_kg, airspeed, climb, forward=True),
                         vehicle.electrical_power(self.payload_kg, airspeed, climb, forward=False))
        ground = np.array([n == "ground" for n in names])
        power = np.where(ground, vehicle.idle_w, power)
        return power, phases

    def gusts(self, n: int, dt: float, sortie: int) -> np.ndarray:
        """Ornstein–Uhlenbeck airspeed disturbance ``(n,)`` [m/s], exact discretisation, stationary start."""
        rng = np.random.default_rng(np.random.SeedSequence(self.gust_seed, spawn_key=(sortie,)))
        a = np.exp(-dt / self.gust_tau_s)
        w = rng.standard_normal(n) * self.gust_sd_ms * np.sqrt(1.0 - a * a)
        g = np.empty(n)
        g_prev = rng.standard_normal() * self.gust_sd_ms
        for k in range(n):  # a scalar recursion of a few hundred steps per sortie
            g_prev = a * g_prev + w[k]
            g[k] = g_prev
        return g


def fly(cell, x0: np.ndarray, mission: Mission, vehicle: Vehicle, dt: float, ambient_c: float):
    """Fly ``mission`` on the truth ``cell`` from state ``x0`` ``(R, 6)`` as a constant-power load.

    Each step solves ``I_k·y(x_k, I_k) = P_k`` with the truth model's own voltage, so the current rises as the pack
    sags. Stops at the first sample whose terminal voltage is below the pack's under-voltage limit (in any run) or
    whose true SOC is below ``mission.reserve_soc``; that sample is the last one. Returns a
    :class:`~socbench.scenarios.schedule.Record`.
    """
    from .schedule import Record

    x = np.array(x0, dtype=float)
    currents, volts, states, phases = [], [], [], []
    k, sortie, reason = 0, 0, "max_duration"
    n_max = int(mission.max_duration_s / dt)
    done = False
    while not done and k < n_max:
        power, ph = mission.power(vehicle, sortie, dt)
        phases += [(name, (k * dt) + t0) for name, t0 in ph]
        for p in power:
            i, y = cell.current_for_power(x, p)
            currents.append(i)
            volts.append(y)
            states.append(x)
            k += 1
            x = cell.step(x, i, dt, ambient_c)
            if np.any(y < cell.uv_limit_v):
                reason, done = "under_voltage", True
                break
            if np.any(states[-1][..., 0] < mission.reserve_soc):
                reason, done = "reserve_soc", True
                break
            if k >= n_max:
                break
        sortie += 1
    return Record(np.arange(k) * dt, np.stack(currents, axis=-1), np.stack(volts, axis=-1),
                  np.stack(states, axis=-2), [p for p in phases if p[1] < k * dt], reason, x)
