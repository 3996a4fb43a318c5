"""The compiled path (socbench.kernels) against the numpy reference, to 1e-9: every registered model (values and
Jacobians of step/output, every parameter form incl. temperature tables and parameter batches), every effect, the
open loop of the fits, the counter-based random numbers, the small linear algebra, and every registered estimator
(new ones are picked up from the registry: equal to their numpy engine when they have a kernel, a clean fallback
with a note when they have none)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from socbench.errors import ConfigError, ModelError
from socbench.estimators import SensorNoise, estimator_class, estimator_names, make_estimator
from socbench.estimators import draws as D
from socbench.estimators.safety import repair_psd
from socbench.kernels import jit
from socbench.kernels.lowering import NotLowerable, lower
from socbench.models import Constant, Lookup, Polynomial, make_model, model_names, paper_params
from socbench.models.effects import ModelError as ModelErrorEffect
from socbench.models.effects import ResistanceOffset, augment
from socbench.models.params import TemperatureTable
from socbench.profile import Profile, ProfileMeta

from .model_points import random_points
from .test_effects import CASES, EFFECTS
from .test_temperature_params import temperature_params

pytestmark = pytest.mark.skipif(not jit.available(), reason="numba is not installed")

TOL = 1e-9
FIELDS = ("soc", "soc_std", "v_pred", "innovation", "innovation_var", "x", "P_diag")
NOISE = SensorNoise(voltage_sd=0.01, current_sd=0.2)


# ================================================================================================ models
def _compiled_points(model, x, i, dt, temp, jac=True):
    """``(x⁺, F, B, y, H, D)`` of the compiled interpreter at every point (variant p of a parameter batch at p)."""
    from socbench.kernels.evaluate import eval_points

    L = lower(model)
    n = model.n_states
    P = x.shape[0]
    out = (np.empty((P, n)), np.empty((P, n, n)), np.empty((P, n)), np.empty(P), np.empty((P, n)), np.empty(P))
    status = np.zeros(P, dtype=np.int64)
    has_temp = temp is not None
    eval_points(L.im, L.fm, x, i, dt, np.zeros(P) if temp is None else temp, has_temp, jac, *out, status)
    assert not status.any()
    return out


def _assert_points_equal(model, x, i, dt, temp):
    xn, F, B = model.step(x, i, dt, temp, jac=True)
    y, H, D_ = model.output(x, i, temp, jac=True)
    got = _compiled_points(model, x, i, dt, temp)
    for name, ref, c in zip(("x+", "F", "B", "y", "H", "D"), (xn, F, B, y, H, D_), got):
        scale = 1.0 + np.abs(ref)
        assert np.all(np.abs(c - ref) <= TOL * scale), f"{name}: max |diff| {np.max(np.abs(c - ref)):.3g}"
    # the value-only path (the open loop, the PF) gives the same values
    vals = _compiled_points(model, x, i, dt, temp, jac=False)
    assert np.allclose(vals[0], xn, rtol=0, atol=TOL) and np.allclose(vals[3], y, rtol=0, atol=TOL)
    _assert_cloud_equal(model, x, i, dt, temp)


def _assert_cloud_equal(model, x, i, dt, temp):
    """The cloud path (the particle filter's: every point's parameters together, model_step_points and
    model_output_points) against numpy, at the first point's step and temperature, each point at its own current
    for the step and all at the first point's current for the output (one measured current per sample)."""
    from socbench.kernels.evaluate import eval_cloud

    L = lower(model)
    if L.n_variants != 1:
        return  # a parameter batch: one model per point, not a cloud of one model
    P, n = x.shape
    tc = None if temp is None else np.full(P, temp[0])
    xn = model.step(x, i, dt[0], tc)[0]
    y, _, D_ = model.output(x, np.full(P, i[0]), tc, jac=True)
    XN, Y, D = np.empty((P, n)), np.empty(P), np.empty(P)
    st = eval_cloud(L.im, np.ascontiguousarray(L.fm[0]), np.ascontiguousarray(x), np.ascontiguousarray(i), float(i[0]),
                    float(dt[0]), 0.0 if temp is None else float(temp[0]), temp is not None, XN, Y, D)
    assert st == 0
    for name, ref, c in (("cloud x+", xn, XN), ("cloud y", y, Y), ("cloud D", D_, D)):
        assert np.all(np.abs(c - ref) <= TOL * (1.0 + np.abs(ref))), f"{name}: max |diff| {np.max(np.abs(c - ref)):.3g}"


def _points(model, n, seed, wide=False):
    rng = np.random.default_rng(seed)
    x, i, dt, temp = random_points(model, n, rng)
    if wide:  # SOC outside [0, 1] and outside the OCV's rest points (extrapolation, clips, held parameters)
        x[: n // 4, 0] = rng.uniform(-0.3, 1.3, n // 4)
        temp[: n // 3] = rng.uniform(-40.0, 60.0, n // 3)  # outside every table's measured range
    return x, i, dt, temp


@pytest.mark.parametrize("name", model_names())
def test_every_model_compiled_equals_numpy(name):
    m = make_model(name, paper_params(name))
    x, i, dt, temp = _points(m, 400, 1, wide=True)
    _assert_points_equal(m, x, i, dt, temp)
    _assert_points_equal(m, x, i, dt, None)  # no temperature input: the reference temperature


@pytest.mark.parametrize("name", model_names())
def test_every_model_with_temperature_tables(name):
    m = make_model(name, temperature_params(name))
    x, i, dt, temp = _points(m, 400, 2, wide=True)
    temp[::7] = -20.0  # exactly at a measured temperature: the node's own numbers
    temp[1::7] = 25.0
    _assert_points_equal(m, x, i, dt, temp)
    _assert_points_equal(m, x, i, dt, None)


def _as_form(f, form: str):
    zg = np.linspace(0.0, 1.0, 9)
    if form == "lookup":
        return Lookup(tuple(zg), tuple(np.broadcast_to(f(zg), zg.shape)))
    return Constant(float(np.median(np.broadcast_to(f(zg), zg.shape))))


@pytest.mark.parametrize("form", ["lookup", "constant"])
@pytest.mark.parametrize("name", model_names())
def test_every_model_with_lookup_and_constant_parameters(name, form):
    p = paper_params(name)
    m = make_model(name, p.replace(values={k: _as_form(v, form) for k, v in p.values.items()}))
    x, i, dt, temp = _points(m, 300, 3, wide=True)
    x[:20, 0] = np.linspace(0.0, 1.0, 9).repeat(3)[:20]  # exactly on the breakpoints (np.interp's node rule)
    _assert_points_equal(m, x, i, dt, temp)


@pytest.mark.parametrize("name", ["thevenin", "dp", "esc", "nrc"])
def test_temperature_tables_whose_nodes_mix_forms(name):
    """A fit setting chosen per temperature (``fit_temperatures(per_record=)``) gives tables whose nodes are of
    different forms: a polynomial at one temperature, a lookup at the next, a constant at a third."""
    p = temperature_params(name)
    forms = ("lookup", None, "constant")  # None: the node as it is (the paper's polynomial or constant)
    values = {k: TemperatureTable(t.temps, tuple(n if f is None else _as_form(n, f) for n, f in zip(t.nodes, forms)),
                                  t.scale) for k, t in p.values.items()}
    m = make_model(name, p.replace(values=values))
    x, i, dt, temp = _points(m, 400, 6, wide=True)
    temp[::5] = 0.0  # at the middle node
    _assert_points_equal(m, x, i, dt, temp)


@pytest.mark.parametrize("name", ["dp", "improved_rc", "esc", "fang", "nrc"])
def test_parameter_batches_lower_to_one_variant_per_point(name):
    """A parameter batch (the fits' form) lowers to one row of numbers per variant over one structure."""
    p = paper_params(name)
    rng = np.random.default_rng(4)
    V = 24

    def batch(f):
        if isinstance(f, Polynomial):
            c = np.asarray(f.coeffs)
            return Polynomial(c * (1.0 + 0.05 * rng.standard_normal((V, c.size))))
        zg = np.linspace(0.0, 1.0, 9)
        return Constant(np.median(np.broadcast_to(f(zg), zg.shape)) * (1.0 + 0.05 * rng.standard_normal(V)))

    m = make_model(name, p.replace(values={k: batch(v) for k, v in p.values.items()}))
    assert lower(m).n_variants == V
    x, i, dt, temp = _points(m, V, 5)
    _assert_points_equal(m, x, i, dt, temp)


def _model_error(seed=0, n_temps=3, n_soc=6):
    """The noise recipe's ModelError effect with random scale grids (temperatures × SOC, uneven nodes)."""
    rng = np.random.default_rng(seed)
    temps = np.sort(rng.choice(np.arange(-20.0, 45.0, 5.0), n_temps, replace=False))
    soc = np.array([0.5]) if n_soc == 1 else np.sort(np.concatenate([[0.0, 1.0], rng.uniform(0.05, 0.95, n_soc - 2)]))
    grid = lambda scale: scale * rng.uniform(0.2, 2.0, (n_temps, n_soc))  # noqa: E731
    tau_slow = rng.uniform(100, 2000)
    return ModelErrorEffect(temps=tuple(temps), soc=tuple(soc), sd_slow=grid(0.01), sd_fast=grid(0.003),
                            sd_r=grid(0.005), tau_slow=tau_slow, tau_fast=rng.uniform(1, 20),
                            tau_r=rng.uniform(100, 2000), tau_mid=np.sqrt(10.0 * tau_slow))


@pytest.mark.parametrize("grid", [(3, 6), (1, 2), (2, 1)])
@pytest.mark.parametrize("base", ["dp", "esc", "nernst"])
def test_the_model_error_effect_compiled_equals_numpy(base, grid):
    """The noise recipe's ModelError effect (not in the effect registry: no physical effect) on several bases, with
    temperature × SOC grids of several shapes (one temperature, one SOC node: held scales), SOC beyond its grid."""
    seed = sum(map(ord, base)) + 7 * grid[0] + grid[1]
    m = augment(make_model(base, paper_params(base)), [_model_error(seed, *grid)])
    x, i, dt, temp = _points(m, 400, 9, wide=True)
    _assert_points_equal(m, x, i, dt, temp)
    _assert_points_equal(m, x, i, dt, None)
    mt = augment(make_model(base, temperature_params(base)), [EFFECTS["current_bias"](), _model_error(4, *grid)])
    x, i, dt, temp = _points(mt, 400, 10, wide=True)
    _assert_points_equal(mt, x, i, dt, temp)


@pytest.mark.parametrize("case", sorted(CASES) + ["dp+r0_offset+bias"])
def test_every_effect_compiled_equals_numpy(case):
    if case == "dp+r0_offset+bias":
        m = augment(make_model("dp", paper_params("dp")), [ResistanceOffset(dR0=1e-3), EFFECTS["current_bias"]()])
    else:
        base, names = CASES[case]
        m = augment(make_model(base, paper_params(base)), [EFFECTS[n]() for n in names])
    x, i, dt, temp = _points(m, 400, 6, wide=True)
    _assert_points_equal(m, x, i, dt, temp)
    _assert_points_equal(m, x, i, dt, None)


def test_effect_parameter_batches_lower_to_one_variant_per_point():
    """Effect values batched, one variant per point (as the diagnosis' fits simulate them): the capacity effect's
    resistance growth zero in some variants (the output untouched there) and composed with the temperature's
    Arrhenius factor in the others."""
    from socbench.models.effects import Capacity, Temperature

    rng = np.random.default_rng(11)
    V = 60
    growth = np.where(rng.random(V) < 0.3, 0.0, rng.uniform(0.0, 1.0, V))
    m = augment(make_model("dp", paper_params("dp")), [
        Temperature(Ea=rng.uniform(0.0, 60e3, V), dUdT=rng.uniform(-2e-3, 2e-3, V), t_ref=20.0),
        Capacity(cap0=rng.uniform(0.8, 1.4, V), r_growth=growth)])
    assert lower(m).n_variants == V
    x, i, dt, temp = _points(m, V, 12, wide=True)
    _assert_points_equal(m, x, i, dt, temp)
    _assert_points_equal(m, x, i, dt, None)


def test_effects_on_a_temperature_table_set():
    m = augment(make_model("dp", temperature_params("dp")), [e() for e in EFFECTS.values()])
    x, i, dt, temp = _points(m, 400, 7, wide=True)
    _assert_points_equal(m, x, i, dt, temp)


def test_what_does_not_lower_says_why():
    with pytest.raises(NotLowerable, match="strict"):
        lower(make_model("dp", paper_params("dp", mode="strict")))
    from socbench.models.effects import Effect

    class Unknown(Effect):
        name = "unknown"

    with pytest.raises(NotLowerable, match="unknown"):
        lower(augment(make_model("dp", paper_params("dp")), [Unknown()]))
    batched = ModelErrorEffect(sd_slow=np.full((3, 1, 2), 0.01))  # a batch of scale grids: no compiled layout
    with pytest.raises(NotLowerable, match="model_error"):
        lower(augment(make_model("dp", paper_params("dp")), [batched]))
    est = make_estimator("ekf", augment(make_model("dp", paper_params("dp")), [batched]), NOISE)
    assert est.engine_plan()[0] is None and "model_error" in est.engine_plan()[1]  # auto: numpy, and says why


# ================================================================================================ open loop (fits)
@pytest.mark.parametrize("name", model_names())
def test_compiled_open_loop_equals_the_step_loop(name):
    from socbench.kernels.openloop import open_loop

    m = make_model(name, temperature_params(name))
    rng = np.random.default_rng(8)
    T = 300
    t = np.cumsum(rng.choice([0.5, 1.0, 5.0], T)) - 0.5
    cur = np.repeat(rng.uniform(-15, 40, T // 10), 10)
    temp = np.linspace(-5.0, 30.0, T)
    jumps = np.zeros(T)
    jumps[[50, 200]] = [-0.01, 0.02]  # charge a record's current column misses
    x0 = m.x0(np.array([0.9, 0.5, 0.15]), (3,))
    ref_states, ref_v = m.open_loop_stepwise(x0, t, cur, temp, jumps)
    states, v = open_loop(m, x0, t, cur, temp, jumps, states=True)
    np.testing.assert_allclose(v, ref_v, rtol=0, atol=TOL)
    np.testing.assert_allclose(states, ref_states, rtol=0, atol=TOL)


def test_fits_use_the_compiled_open_loop_and_land_where_numpy_does():
    from socbench.identify import fit_model, lsq
    from socbench.loads import hppc

    truth = make_model("thevenin", paper_params("thevenin"))
    prof = hppc(truth.capacity_ah, dt=1.0)
    sim = truth.simulate(prof, soc0=1.0)
    data = Profile(prof.time_s, prof.current_a, voltage_v=sim.voltage_v, soc_ref=sim.soc,
                   meta=ProfileMeta(name="hppc", capacity_ah=truth.capacity_ah))
    fit_c = fit_model("thevenin", data, mode="constant", ocv=truth.ocv)
    orig = lsq.simulate_voltage
    try:
        lsq.simulate_voltage = lambda *a, **k: orig(*a, **{**k, "engine": "numpy"})
        fit_n = fit_model("thevenin", data, mode="constant", ocv=truth.ocv)
    finally:
        lsq.simulate_voltage = orig
    for k, v in fit_n.values.items():
        assert fit_c.values[k] == pytest.approx(v, rel=1e-5), k


@pytest.mark.parametrize("what", ["open_loop", "ukf", "pf"])
def test_a_batch_split_over_threads_equals_one_thread(what, monkeypatch):
    """``parallel_runs`` hands slices of a batch to a kept thread pool (conftest runs the suite on one thread): the
    same numbers, bit for bit, on two threads as on one, and the pool is the process' own and reused."""
    import os

    from socbench.kernels import engine
    from socbench.kernels.openloop import open_loop

    model = make_model("dp", paper_params("dp"))
    rng = np.random.default_rng(12)
    R = 16  # four slices of four runs per thread: min_runs and SLICES_PER_THREAD both act
    soc0 = rng.uniform(0.2, 0.95, R)
    p = _record(model, R=R)

    def run():
        if what == "open_loop":
            return open_loop(model, model.x0(soc0, (R,)), p.time_s, p.current_a)[1]
        est = make_estimator(what, model, NOISE, **_options(what))
        e = est.run(p, soc0=soc0, seed=3)
        assert e.info["engine"] == "compiled"
        return np.stack([e.soc, e.soc_std])

    monkeypatch.setenv("SOCBENCH_THREADS", "1")
    one = run()
    monkeypatch.setenv("SOCBENCH_THREADS", "2")
    two = run()
    pool = engine._POOLS.get((os.getpid(), 2))
    assert pool is not None
    assert np.array_equal(one, two)
    run()
    assert engine._POOLS[(os.getpid(), 2)] is pool  # kept, not started again


# ================================================================================================ random numbers
def test_counter_based_numbers_are_identical_in_numpy_and_compiled_code():
    from socbench.kernels.pf import normal, prefix, uniform0

    rng = np.random.default_rng(9)
    for _ in range(50):
        seed, stream, k = int(rng.integers(0, 2**63)), int(rng.integers(0, 40)), int(rng.integers(0, 10**6))
        runs = rng.integers(0, 10**5, 3)
        pre = D.prefix(seed, stream, k, runs)
        u = D.uniforms(pre, 1)[:, 0]
        z = D.normals(pre, 7)
        s = D.seed_u64(seed)
        for j, r in enumerate(runs):
            p = prefix(s, stream, k, int(r))
            assert p == pre[j]
            assert uniform0(np.uint64(p)) == u[j]
            np.testing.assert_allclose([normal(np.uint64(p), c) for c in range(7)], z[j], rtol=0, atol=1e-15)


def test_counter_based_normals_and_uniforms_have_their_distributions():
    from scipy import stats

    pre = D.prefix(123, D.CURRENT, 5, np.arange(500))
    z = D.normals(pre, 400).ravel()
    u = D.uniforms(pre, 400).ravel()
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.01  # neighbouring counters independent
    z2 = D.normals(D.prefix(123, D.CURRENT, 6, np.arange(500)), 400).ravel()
    assert abs(np.corrcoef(z, z2)[0, 1]) < 0.01  # neighbouring samples independent


# ================================================================================================ linear algebra
@functools.cache
def _linalg_entry():
    """Test entry points into the compiled linear algebra (arrays in, pointers inside)."""
    from socbench.kernels.evaluate import ptr
    from socbench.kernels.jit import kernel
    from socbench.kernels.linalg import eigh_jacobi
    from socbench.kernels.linalg import repair_psd as repair_c

    @kernel
    def eig(A, w, V, work):
        eigh_jacobi(ptr(A), A.shape[0], ptr(w), ptr(V), ptr(work))

    @kernel
    def repair(P, w, V, work, abs_floor, rel_floor):
        return repair_c(ptr(P), P.shape[0], abs_floor, rel_floor, ptr(w), ptr(V), ptr(work))

    return eig, repair


def test_jacobi_eigen_decomposition_and_psd_repair_equal_numpy():
    eig, repair = _linalg_entry()
    rng = np.random.default_rng(10)
    acted = 0
    for trial in range(300):
        n = int(rng.integers(1, 8))
        G = rng.standard_normal((n, n)) * 10.0 ** rng.uniform(-6, 1, n)
        A = G @ G.T
        if trial % 2:  # indefinite or nearly singular: the repair acts
            A = A - np.eye(n) * (rng.uniform(0.5, 2.0) * np.linalg.eigvalsh(A)[0] + 1e-13)
        A = 0.5 * (A + A.T)
        scale = max(1.0, np.abs(A).max())
        w, V, work = np.empty(n), np.empty((n, n)), np.empty((n, n))
        eig(A.copy(), w, V, work)
        np.testing.assert_allclose(np.sort(w), np.linalg.eigvalsh(A), rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose((V * w) @ V.T, A, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(n), rtol=0, atol=1e-12)
        P = A.copy()
        did = repair(P, w, V, work, 1e-15, 1e-12)
        ref, rep = repair_psd(A[None], 1e-15, 1e-12)
        assert bool(did) == bool(rep[0])
        acted += bool(did)
        np.testing.assert_allclose(P, ref[0], rtol=0, atol=1e-12 * scale)
    assert 50 < acted < 250


# ================================================================================================ estimators
def _record(model, T=160, R=4, temp=False, soc_true=0.6, seed=11):
    rng = np.random.default_rng(seed)
    seg = rng.integers(5, 40, size=T)
    cur = np.repeat(rng.uniform(-15.0, 60.0, size=T), seg)[:T]
    t = np.arange(T, dtype=float)
    tc = np.linspace(5.0, 35.0, T) if temp else None
    sim = model.simulate(Profile(t, cur, temperature_c=tc), soc0=soc_true)
    v = sim.voltage_v + 0.01 * rng.standard_normal((R, T))
    i = cur + 0.2 * rng.standard_normal((R, T))
    v[:, min(40, T - 1)] += 0.5  # an outlier: the gate acts
    return Profile(t, i, voltage_v=v, temperature_c=None if tc is None else np.broadcast_to(tc, (R, T)),
                   soc_ref=np.tile(sim.soc, (R, 1)), meta=ProfileMeta(name="kernels", capacity_ah=model.capacity_ah))


def _options(name):
    return {"n_particles": 48} if name in ("pf", "rbpf") else {}


def _compare(a, b, spread=None):
    """``a`` (numpy) and ``b`` equal to 1e-9 relative, or within 10× ``spread`` (:func:`_rounding_spread`) where the
    numpy engine itself moves further than that under a rounding-level change of its input."""
    for f in FIELDS:
        ra, rb = getattr(a, f), getattr(b, f)
        if ra is None:
            assert rb is None, f
            continue
        tol = TOL * (1.0 + np.abs(ra))
        if spread is not None:
            tol = np.maximum(tol, 10.0 * spread[f])
        assert np.all(np.abs(ra - rb) <= tol), f"{f}: max |diff| {np.max(np.abs(ra - rb)):.3g}"
    for f in ("gated", "clamped", "failed", "failed_at", "failed_reason"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    for key in ("r_hat", "q_hat_soc", "capacity_ah", "capacity_ah_3sigma", "r0_ohm", "r0_ohm_3sigma"):
        if key in a.info:  # the adaptive and joint filters' own outputs
            ra, rb = np.asarray(a.info[key]), np.asarray(b.info[key])
            assert np.all(np.abs(ra - rb) <= TOL * (1.0 + np.abs(ra))), key
    # counters: on every run, or, where the numpy engine itself is chaotic (spread), on the runs it is not
    stable = np.ones(a.n_runs, dtype=bool) if spread is None else spread["soc"].ravel() <= TOL
    for key in ("psd_repairs", "resampled", "tempered", "theta_capped"):
        if key in a.info:
            np.testing.assert_array_equal(np.asarray(a.info[key])[stable], np.asarray(b.info[key])[stable],
                                          err_msg=key)


MODEL_CASES = {
    "dp": lambda: make_model("dp", paper_params("dp")),
    "improved_rc": lambda: make_model("improved_rc", paper_params("improved_rc")),
    "esc+temperature tables": lambda: make_model("esc", temperature_params("esc")),
    "tremblay2": lambda: make_model("tremblay2", paper_params("tremblay2")),
    "thevenin+hysteresis+bias+capacity": lambda: augment(make_model("thevenin", paper_params("thevenin")), [
        EFFECTS["hysteresis"](), EFFECTS["current_bias"](), EFFECTS["capacity"]()]),
    # the temperature effect scales the feedthrough D, which R reads (the particle filter's model output has no
    # Jacobians but needs D)
    "dp+temperature effect": lambda: augment(make_model("dp", paper_params("dp")), [EFFECTS["temperature"]()]),
}


#: estimators whose recursion amplifies rounding on these records: compared to 1e-9 or 10× numpy's own spread (none
#: since the H∞ filter's prior cap: test_the_hinf_prior_cap_ends_its_rounding_chaos)
CHAOTIC = ()


def _rounding_spread(estimator, profile, soc0, a, seed=5):
    """Per field, per run: the largest change of the numpy engine's output ``a`` when every voltage sample moves by
    ±1 or ±2 parts in 2⁵² (rounding-level changes). For a stable recursion this is ~1e-15; a recursion that amplifies
    rounding (the H∞ posterior held at its feasibility cap, ``P⁺_zz = 2 P_K,zz`` on every update) grows it by orders
    of magnitude over a record, and then no two orders of summation — numpy's BLAS and the compiled loop — can agree
    to 1e-9 either. Several perturbations, because one samples a chaotic run's sensitivity once: the compiled loop's
    summation order is another perturbation, and on one run the four moved numpy by 0.004–0.023 of SOC. Eight, since
    four undersampled it: with numpy 2.4 the compiled loop moved one run (the noise recipe's dp with scheduling) by
    0.20 of SOC where ±1, ±2 parts moved numpy by at most 0.016 and ±3, ±4 parts by 0.069."""
    spread = {f: None for f in FIELDS}
    for k in (1, -1, 2, -2, 3, -3, 4, -4):
        p2 = Profile(profile.time_s, profile.current_a, voltage_v=profile.voltage_v * (1.0 + k * 2.0**-52),
                     temperature_c=profile.temperature_c, soc_ref=profile.soc_ref, meta=profile.meta)
        a2 = estimator.run(p2, soc0=soc0, seed=seed)
        for f in FIELDS:
            if getattr(a, f) is not None:
                d = np.max(np.abs(getattr(a, f) - getattr(a2, f)), axis=tuple(range(1, getattr(a, f).ndim)),
                           keepdims=True)
                spread[f] = d if spread[f] is None else np.maximum(spread[f], d)
    return spread


def _refuses_alike(name, model, noise, opts, exc) -> None:
    """A filter that cannot take a model at all (a joint filter adding a state the model already has) must refuse it
    the same way on every engine: nothing to compare, but the refusal itself is checked, not skipped."""
    assert "appears twice" in str(exc), exc
    with pytest.raises(ConfigError) as again:
        make_estimator(name, model, noise, engine="compiled", **opts)
    assert str(again.value) == str(exc)


def _pair(name, model, profile, soc0, **options):
    """``(numpy estimate, auto estimate, auto estimator, rounding spread or None)``, or None when the filter refuses the
    model on every engine alike (:func:`_refuses_alike`)."""
    opts = {**_options(name), "store_states": True, **options}
    try:
        numpy_engine = make_estimator(name, model, NOISE, engine="numpy", **opts)
    except ConfigError as exc:
        _refuses_alike(name, model, NOISE, opts, exc)
        return None
    a = numpy_engine.run(profile, soc0=soc0, seed=5)
    auto = make_estimator(name, model, NOISE, **opts)
    b = auto.run(profile, soc0=soc0, seed=5)
    # the spread is only read for the chaotic recursions (CHAOTIC): eight more numpy runs are not spent on the others
    return a, b, auto, _rounding_spread(numpy_engine, profile, soc0, a) if name in CHAOTIC else None


@pytest.mark.parametrize("case", sorted(MODEL_CASES))
@pytest.mark.parametrize("name", estimator_names())
def test_every_estimator_compiled_equals_numpy(name, case):
    """Every registered estimator: equal to its numpy engine to 1e-9 when it runs compiled (outputs, states, flags,
    counters), else a numpy run that says why (new filters without a kernel are picked up here)."""
    model = MODEL_CASES[case]()
    temp = "temperature" in case
    p = _record(model, temp=temp)
    soc0 = np.array([0.6, 0.75, 0.02, 0.45])  # a far-off start (gating), one near empty (clamping)
    pair = _pair(name, model, p, soc0)
    if pair is None:
        return
    a, b, est, spread = pair
    assert a.info["engine"] == "numpy"
    lowered, why = est.engine_plan()
    if lowered is None:
        assert b.info["engine"] == "numpy" and b.info["engine_note"] == why and why
        _compare(a, b)  # the same engine ran
        return
    assert b.info["engine"] == "compiled"
    _compare(a, b, spread if name in CHAOTIC else None)
    if name != "coulomb":
        assert a.gated.any(), "the record should exercise the gate"


@pytest.mark.parametrize("name", estimator_names())
def test_every_estimator_freezes_a_divergence_like_numpy(name):
    """Runs that fail (at the first sample, in the middle) keep their last values, as the numpy Recorder does."""
    model = make_model("dp", paper_params("dp"))
    p = _record(model, T=120)
    v = p.voltage_v.copy()
    v[1, 70:] += 3.0  # a run that goes far off: its NIS explodes
    p = Profile(p.time_s, p.current_a, voltage_v=v, soc_ref=p.soc_ref, meta=p.meta)
    opts = {"nis_max": 1e3, "var_max": 0.5}
    pair = _pair(name, model, p, np.array([0.6, 0.6, 0.6, 0.6]), **opts)
    if pair is None:
        return
    a, b, est, spread = pair
    _compare(a, b, spread if name in CHAOTIC else None)
    if name not in ("coulomb",) and est.engine_plan()[0] is not None:
        assert a.failed.any()


@pytest.mark.parametrize("name", ["ekf", "ukf", "pf", "coulomb"])
def test_noise_forms_compiled(name):
    """A random walk per state, a Q override matrix and an R override, and a widened particle-weight likelihood: the
    forms the compiled noise supports."""
    model = make_model("thevenin", paper_params("thevenin"))
    p = _record(model, T=100)
    walk = SensorNoise(voltage_sd=0.01, current_sd=0.2, current_bias_sd=0.05, soc_walk_sd=1e-4, state_walk_sd=2e-3,
                       dt=2.0)
    wide = SensorNoise(voltage_sd=0.01, current_sd=0.2, weight_extra_var=0.05 ** 2)
    for noise, opts in ((walk, {}), (NOISE, {"Q": np.diag([1e-8, 1e-6]), "R": 2e-4}), (wide, {})):
        o = {**_options(name), "store_states": True, **opts}
        a = make_estimator(name, model, noise, engine="numpy", **o).run(p, soc0=0.6, seed=2)
        b = make_estimator(name, model, noise, engine="compiled", **o).run(p, soc0=0.6, seed=2)
        _compare(a, b)


#: on the recipe's record the particle filter is rounding-sensitive too: its particles carry four near-deterministic
#: error states, and ±1 part in 2⁵² of the voltage moves numpy's own state means by 2e-8 (as far as the compiled loop
#: lies from it), while SOC, band and innovations agree to 1e-10
RECIPE_CHAOTIC = CHAOTIC + ("pf",)

#: estimators without a compiled kernel (the square-root UKF; the iterated EKF, whose update the EKF kernel does not
#: iterate; the Rao–Blackwellised PF): they run numpy and say why
NUMPY_ONLY = ("srukf", "iekf", "rbpf")


@pytest.mark.parametrize("schedule", [True, False])
@pytest.mark.parametrize("name", estimator_names())
def test_the_noise_recipe_runs_compiled_like_numpy(name, schedule):
    """What `socbench estimate` runs by default: the model with the ModelError states and a SensorNoise whose walk_sd
    drives them, parameter scheduling on (estimators.model_error.apply; base.scheduled_jacobian/scheduled_step), on a
    record with a temperature column; and the same without scheduling."""
    eff = _model_error(21)
    model = augment(make_model("dp", temperature_params("dp")), [eff])
    model.schedule_soc = schedule
    p = _record(model, T=200, temp=True)
    walk = np.zeros(model.n_states)
    walk[-eff.n_states:] = np.sqrt(eff.walk_var(1.0))
    noise = SensorNoise(voltage_sd=0.01, current_sd=0.2, walk_sd=tuple(walk))
    o = {**_options(name), "store_states": True}
    try:
        numpy_engine = make_estimator(name, model, noise, engine="numpy", **o)
    except ConfigError as exc:
        _refuses_alike(name, model, noise, o, exc)
        return
    a = numpy_engine.run(p, soc0=0.55, seed=4)
    est = make_estimator(name, model, noise, **o)
    b = est.run(p, soc0=0.55, seed=4)
    _compare(a, b, _rounding_spread(numpy_engine, p, 0.55, a, seed=4) if name in RECIPE_CHAOTIC else None)
    if name not in NUMPY_ONLY:
        assert b.info["engine"] == "compiled", b.info.get("engine_note")


def test_engine_option():
    model = make_model("dp", paper_params("dp"))
    with pytest.raises(ConfigError, match="engine"):
        make_estimator("ekf", model, engine="fast")
    strict = make_model("dp", paper_params("dp", mode="strict"))
    p = _record(strict, T=40)
    with pytest.raises(ConfigError, match="strict"):
        make_estimator("ekf", strict, engine="compiled").run(p, soc0=0.6)
    est = make_estimator("ekf", strict).run(p, soc0=0.6)  # auto: numpy, with the reason
    assert est.info["engine"] == "numpy" and "strict" in est.info["engine_note"]
    callable_q = make_estimator("ekf", model, Q=lambda B, dt: np.zeros(B.shape + B.shape[-1:])).run(p, soc0=0.6)
    assert callable_q.info["engine"] == "numpy" and "callable" in callable_q.info["engine_note"]


def test_a_model_error_is_raised_by_the_numpy_engine_the_kernel_hands_back_to():
    p = paper_params("improved_rc")
    bad = make_model("improved_rc", p.with_values(R1=Constant(1e-3), R2=Constant(-2e-3)))
    prof = _record(make_model("improved_rc", p), T=20)
    with pytest.raises(ModelError, match="R1 \\+ R2"):
        make_estimator("ekf", bad, engine="compiled").run(prof, soc0=0.6)


def test_a_subclass_that_changes_a_hook_runs_numpy():
    ekf = estimator_class("ekf")

    class Inflated(ekf):
        def process_cov(self, x, B, dt):
            return 4.0 * super().process_cov(x, B, dt)

    est = Inflated(make_model("dp", paper_params("dp")), NOISE)
    lowered, why = est.engine_plan()
    assert lowered is None and "process_cov" in why


def test_the_hinf_prior_cap_ends_its_rounding_chaos():
    """Without its prior cap (``prior_cap=False``) the H∞ filter at the feasibility cap doubles the SOC's Riccati term
    on every update and amplifies rounding: a one-ulp change of the voltages moves the numpy engine itself by > 1e-7,
    and no two orders of summation can agree to 1e-9. With the cap (the default) the same runs stay at rounding level
    and the compiled kernel equals numpy to 1e-9 on every run, as every other filter."""
    model = MODEL_CASES["dp"]()
    p = _record(model)
    soc0 = np.array([0.6, 0.75, 0.02, 0.45])
    spreads = {}
    for cap in (False, True):
        opts = {**_options("hinf"), "store_states": True, "theta": 1e3, "prior_cap": cap}
        numpy_engine = make_estimator("hinf", model, NOISE, engine="numpy", **opts)
        a = numpy_engine.run(p, soc0=soc0, seed=5)
        b = make_estimator("hinf", model, NOISE, engine="compiled", **opts).run(p, soc0=soc0, seed=5)
        assert b.info["engine"] == "compiled" and (a.info["theta_capped"] > 0).any()
        spread = _rounding_spread(numpy_engine, p, soc0, a)
        spreads[cap] = spread["soc"].max()
        _compare(a, b, None if cap else spread)  # without the cap: within 10× numpy's own spread, as before
    assert spreads[False] > 1e-7 and spreads[True] < 1e-12, spreads


# ================================================================================================ memory
_LARGE_CLOUD = """
import sys
import numpy as np
from socbench.estimators import SensorNoise, make_estimator
from socbench.models import make_model, paper_params
from socbench.profile import Profile
m = make_model("thevenin", paper_params("thevenin"))
t = np.arange(40.0)
cur = np.where(t % 10 < 5, 30.0, 0.0)
sim = m.simulate(Profile(t, cur), soc0=0.7)
p = Profile(t, cur, voltage_v=sim.voltage_v)
e = make_estimator("pf", m, SensorNoise(voltage_sd=0.01, current_sd=0.2), n_particles=3000, engine=sys.argv[1])
np.save(sys.argv[2], e.run(p, soc0=0.6, seed=5).soc)
"""


def test_a_large_particle_cloud_runs_from_the_kernel_cache(tmp_path):
    """A 3000-particle cloud, compiled, in two fresh processes (the first compiles or loads, the second loads the
    cached kernel), equals numpy. The kernels write through pointers to scratch arrays; numba freed those arrays after
    their last use as arrays (the ``ptr`` call), so the cached PF wrote into freed, unmapped memory and segfaulted from
    about 1250 particles up (evaluate.keep_alive)."""
    import subprocess
    import sys

    script = tmp_path / "cloud.py"
    script.write_text(_LARGE_CLOUD)
    out = {}
    for tag, engine in (("first", "compiled"), ("cached", "compiled"), ("numpy", "numpy")):
        done = subprocess.run([sys.executable, str(script), engine, str(tmp_path / f"{tag}.npy")], capture_output=True,
                              text=True, timeout=600)
        assert done.returncode == 0, (tag, done.returncode, done.stderr[-2000:])
        out[tag] = np.load(tmp_path / f"{tag}.npy")
    np.testing.assert_array_equal(out["first"], out["cached"])
    np.testing.assert_allclose(out["cached"], out["numpy"], rtol=0, atol=TOL)


_CACHE_PROBE = """
import sys
import numpy as np
import socbench
assert socbench.__file__.startswith(sys.argv[1]), socbench.__file__
from socbench.kernels.pf import prefix
prefix(np.uint64(7), 3, 5, 11)
print(sum(prefix.stats.cache_hits.values()), sum(prefix.stats.cache_misses.values()))
"""


def test_a_copy_of_the_same_sources_loads_the_kernels_compiled_before(tmp_path):
    """The cache is keyed on the sources' content (jit.fingerprint), not on where they lie or when they were
    written: a second copy of the package, its files newer, loads the kernel the first copy compiled (numba's own
    locators would compile it again: another path, another modification time); an edited copy compiles afresh."""
    import os
    import shutil
    import subprocess
    import sys
    import time

    package = jit.PACKAGE
    env = {**os.environ, "SOCBENCH_NUMBA_CACHE": str(tmp_path / "cache")}

    def run(copy):
        root = tmp_path / copy
        if not root.exists():
            shutil.copytree(package, root / "socbench", ignore=shutil.ignore_patterns("__pycache__"))
        done = subprocess.run([sys.executable, "-c", _CACHE_PROBE, str(root)], capture_output=True, text=True,
                              timeout=600, env={**env, "PYTHONPATH": str(root)}, cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-2000:]
        return tuple(map(int, done.stdout.split()[-2:]))  # (cache hits, cache misses)

    assert run("first") == (0, 1)  # compiled (and cached)
    time.sleep(1.1)  # the copy's files are newer than the first's
    assert run("second") == (1, 0)  # loaded
    edited = tmp_path / "third" / "socbench"
    shutil.copytree(package, edited, ignore=shutil.ignore_patterns("__pycache__"))
    (edited / "kernels" / "linalg.py").write_text((edited / "kernels" / "linalg.py").read_text() + "\n# edited\n")
    assert run("third") == (0, 1)  # another fingerprint: compiled afresh
