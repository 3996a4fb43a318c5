"""Counter-based random numbers of the particle filter: every number is a hash of where it is used.

A number is a function of ``(seed, stream, sample k, run r, counter c)`` alone — no generator state — so any engine
(the batched numpy PF, the compiled PF, the per-run reference) computes exactly the numbers of any run, step or
particle without replaying the others, whatever the batch shape::

    h(seed, stream, k, r, c) = A(A(A(A(seed, stream), k), r), c),   A(h, v) = mix64(h + (v + 1)·γ)

with ``mix64`` the splitmix64 finaliser (Steele, Lea & Flood 2014: multiply–xorshift, full avalanche) and
``γ = 0x9E3779B97F4A7C15`` (the golden-ratio increment); all arithmetic modulo 2⁶⁴. From a hash::

    uniform [0, 1)    u = ⌊h / 2¹¹⌋ · 2⁻⁵³
    normal            Box–Muller on pairs: counters 2q and 2q + 1 share u₁ = (⌊h(2q) / 2¹¹⌋ + 1)·2⁻⁵³ ∈ (0, 1] and
                      u₂ = ⌊h(2q + 1) / 2¹¹⌋·2⁻⁵³: ε_2q = √(−2 ln u₁)·cos(2π u₂), ε_2q+1 = √(−2 ln u₁)·sin(2π u₂)

``cos(2π u₂)`` and ``sin(2π u₂)`` are reduced in turns, ``u₂ = q/4 + f`` with ``q = round(4 u₂)`` and
``|f| ≤ 1/8`` (exact in floating point), then taken from the Taylor series of ``sin r`` and ``cos r`` at ``r = 2π f``,
``|r| ≤ π/4`` (:func:`sin_cos_reduced`; the first term left out is below 1e-19) and the quadrant ``q``: accurate to a
few units in the last place, and plain arithmetic, which a compiled loop vectorises (the compiled particle filter
draws a normal in ~5 ns instead of ~18 with libm's ``cos``/``sin``).

:func:`absorb` and :func:`sin_cos_reduced` are the primitives: written with operators only, they run on numpy arrays
here and are compiled as is by :mod:`socbench.kernels.pf` (the two implementations of the few lines that compose
them are checked against each other by the tests). Streams of the particle filter (``pf.py`` docstring): the initial
cloud, the resampling offset, the current noise, the additive process noise, the roughening, the hold's noise across
a logger pause, and two per tempering stage.
"""

from __future__ import annotations

import math

import numpy as np

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
M1 = np.uint64(0xBF58476D1CE4E5B9)
M2 = np.uint64(0x94D049BB133111EB)
S11, S27, S30, S31 = np.uint64(11), np.uint64(27), np.uint64(30), np.uint64(31)
ONE = np.uint64(1)
TWO_M53 = 2.0**-53
TWO_PI = 2.0 * np.pi
#: Taylor coefficients in r² of sin(r)/r and of cos(r): (−1)ᵏ/(2k + 1)! and (−1)ᵏ/(2k)!, highest first
SIN_C = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(8, -1, -1))
COS_C = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(9, -1, -1))

#: stream numbers
INITIAL, RESAMPLE, CURRENT, ADDITIVE, ROUGHEN, HOLD = 0, 1, 2, 3, 4, 5
#: tempering stage s uses streams STAGE + 2s (its resampling offset) and STAGE + 2s + 1 (its kernel noise)
STAGE = 16


def absorb(h, v):
    """``mix64(h + (v + 1)·γ)`` modulo 2⁶⁴ (``h``, ``v`` uint64 scalars or arrays)."""
    h = h + (v + ONE) * GOLDEN
    h = (h ^ (h >> S30)) * M1
    h = (h ^ (h >> S27)) * M2
    return h ^ (h >> S31)


def sin_cos_reduced(r):
    """``(sin r, cos r)`` for ``|r| ≤ π/4`` from their Taylor series in ``r²`` (Horner; scalars or arrays)."""
    r2 = r * r
    s = SIN_C[0]
    for c in SIN_C[1:]:
        s = s * r2 + c
    co = COS_C[0]
    for c in COS_C[1:]:
        co = co * r2 + c
    return s * r, co


def cos_sin_turn(u):
    """``(cos 2πu, sin 2πu)`` of uniforms ``u ∈ [0, 1)`` (arrays): quadrant ``q = round(4u)``, remainder
    ``r = 2π(u − q/4)`` (module docstring)."""
    q = np.floor(4.0 * u + 0.5)
    s, c = sin_cos_reduced((u - 0.25 * q) * TWO_PI)
    quadrant = q.astype(np.int64) & 3
    return np.choose(quadrant, [c, -s, -c, s]), np.choose(quadrant, [s, c, -s, -c])


def seed_u64(seed: int) -> np.uint64:
    return np.uint64(int(seed) % 2**64)


def prefix(seed: int, stream: int, k: int, runs) -> np.ndarray:
    """``A(A(A(seed, stream), k), r)`` for each run index in ``runs``: ``(R,)`` uint64."""
    with np.errstate(over="ignore"):
        h = absorb(absorb(seed_u64(seed), np.uint64(stream)), np.uint64(k))
        return absorb(h, np.asarray(runs, dtype=np.uint64))


def uniforms(pre: np.ndarray, count: int) -> np.ndarray:
    """``(R, count)`` uniforms in [0, 1) at counters ``0 … count − 1`` of each prefix."""
    c = np.arange(count, dtype=np.uint64)
    return (absorb(pre[:, None], c) >> S11).astype(np.float64) * TWO_M53


def normals(pre: np.ndarray, count: int) -> np.ndarray:
    """``(R, count)`` standard normals at counters ``0 … count − 1`` of each prefix (Box–Muller on pairs)."""
    q = np.arange((count + 1) // 2, dtype=np.uint64) * np.uint64(2)
    p = pre[:, None]
    u1 = ((absorb(p, q) >> S11) + ONE).astype(np.float64) * TWO_M53
    u2 = (absorb(p, q + ONE) >> S11).astype(np.float64) * TWO_M53
    rho = np.sqrt(-2.0 * np.log(u1))
    cos, sin = cos_sin_turn(u2)
    out = np.empty((pre.shape[0], 2 * q.size))
    out[:, 0::2] = rho * cos
    out[:, 1::2] = rho * sin
    return out[:, :count]


class StepDraws:
    """The particle filter's numbers for the runs ``runs`` (indices into the batch; default ``0 … R − 1``).

    ``initial()`` the initial cloud ``(R, N, n)``; ``step(k)`` → ``(u (R,), ε_I (R, N) or None, ε_Q (R, N, n) or
    None)``; ``hold(k)`` ``(R, N, n)`` (the noise of the current the hold misses across a logger pause);
    ``roughening(k, rows)`` ``(rows, N, n)``; ``stage(k, s)`` → ``(u (R,), ε (R, N, n))``. A per-run reference passes
    ``runs=[r]`` and gets exactly row ``r`` of the batch's numbers.
    """

    def __init__(self, seed, n_runs: int, n_particles: int, n_states: int, perturb_current: bool, additive: bool,
                 runs=None):
        if seed is None:
            seed = int(np.random.SeedSequence().entropy % (2**63))
        self.seed = int(seed)
        self.runs = np.arange(n_runs) if runs is None else np.asarray(runs, dtype=np.int64)
        self.N = n_particles
        self.n = n_states
        self.perturb_current = perturb_current
        self.additive = additive

    def _normals(self, stream: int, k: int, tail: tuple, rows=None) -> np.ndarray:
        """``(runs, N, *tail)`` normals; particle ``p``, entry ``d`` at counter ``p·∏tail + d``."""
        runs = self.runs if rows is None else self.runs[rows]
        with np.errstate(over="ignore"):
            out = normals(prefix(self.seed, stream, k, runs), self.N * int(np.prod(tail, dtype=int)))
        return out.reshape((runs.size, self.N) + tail)

    def _uniform(self, stream: int, k: int) -> np.ndarray:
        with np.errstate(over="ignore"):
            return uniforms(prefix(self.seed, stream, k, self.runs), 1)[:, 0]

    def initial(self) -> np.ndarray:
        return self._normals(INITIAL, 0, (self.n,))

    def step(self, k: int):
        eps_i = self._normals(CURRENT, k, ()) if self.perturb_current else None
        eps_q = self._normals(ADDITIVE, k, (self.n,)) if self.additive else None
        return self._uniform(RESAMPLE, k), eps_i, eps_q

    def hold(self, k: int) -> np.ndarray:
        return self._normals(HOLD, k, (self.n,))

    def roughening(self, k: int, rows=None) -> np.ndarray:
        return self._normals(ROUGHEN, k, (self.n,), rows)

    def stage(self, k: int, s: int):
        return self._uniform(STAGE + 2 * s, k), self._normals(STAGE + 2 * s + 1, k, (self.n,))
