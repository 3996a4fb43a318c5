"""Replay of the real DJI Matrice 100 flights (needs SOCBENCH_DATA_DIR with uav_dji_m100/)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from socbench.datasets import detect_format, load
from socbench.datasets.dji import CAPACITY_AH, read_segments
from socbench.scenarios import load_scenario
from socbench.scenarios.replay import held_current, replay_dataset

pytestmark = pytest.mark.realdata
DT = 2.0  # replay grid step (s); the records are ≈ 12 s apart


@pytest.fixture(scope="module")
def dji(data_dir):
    return data_dir / "uav_dji_m100"


@pytest.fixture(scope="module")
def raw(dji):
    return pd.read_csv(dji / "battery_telemetry_all_flights.csv")


@pytest.fixture(scope="module")
def replay(dji):
    return replay_dataset(dji, dt=DT)


def test_replay_covers_every_discharge_segment_with_20_samples(raw, replay):
    sizes = raw.groupby(["log_id", "battery_segment"]).size()
    expected = {f"{log}#{seg}" for (log, seg), n in sizes.items() if n >= 20}
    assert len(expected) == 144  # PROVENANCE: 144 segments with >= 20 samples
    assert set(replay.keys) == expected and replay.n_segments == 144
    # each replayed segment spans its records (held current from the first to the last one); a glitch dropped at
    # either end shortens it by at most one sampling interval
    groups = raw.groupby(["log_id", "battery_segment"])["t_s_since_first_battery_record"]
    span = groups.agg(lambda t: t.max() - t.min())
    gap = groups.agg(lambda t: np.diff(np.sort(t.to_numpy())).max(initial=0.0))
    for j, key in enumerate(replay.keys):
        log, seg = key.rsplit("#", 1)
        k = (log, int(seg))
        assert span[k] - 2 * gap[k] - DT <= (replay.n_steps[j] - 1) * DT <= span[k] + DT
        assert np.all(replay.c_rate[j, replay.n_steps[j]:] == 0.0)
    assert np.all(np.isfinite(replay.voltage_v)) and np.all(replay.active.sum(axis=1) >= 20)


def test_logged_glitches_are_rejected_and_counted(dji, raw):
    segments, dropped = read_segments(dji)
    # PROVENANCE: 35 records with 0 % SOC at a charged-pack voltage, 9 records at 0.0 °C
    assert dropped["soc_zero_at_high_voltage"] == 35
    assert dropped["temperature_zero"] == 9
    kept = sum(s.n for s in segments)
    assert kept == len(raw) - sum(dropped.values())
    for s in segments:
        assert not np.any(s.temperature_c == 0.0)
        assert not np.any((s.soc_bms == 0.0) & (s.voltage_v > 21.0))


def test_current_is_held_between_records_and_scaled_by_c_rate(dji, replay):
    segments, _ = read_segments(dji, min_samples=20)
    s = segments[0]
    amps, phases = held_current(s, DT)
    for k in (1, s.n // 2, s.n - 2):  # between record k and k+1 the current is record k's
        g = int(np.floor((s.time_s[k] + s.time_s[k + 1]) / 2 / DT))  # a grid point between the two records
        if s.time_s[k] <= g * DT < s.time_s[k + 1]:
            assert amps[g] == s.current_a[k]
    j = replay.keys.index(s.key)
    n = amps.size
    assert np.allclose(replay.c_rate[j, :n], amps / CAPACITY_AH)
    live = replay.active[j, :n]
    assert np.allclose(replay.current_a[j, :n][live], amps[live] / CAPACITY_AH * 22.0)
    # flight-mode events give the phases; on the ground the current is below 5 A
    assert {"ground", "cruise"} <= set(phases)
    assert np.all(amps[phases == "ground"] < 5.0)


def test_dji_log_format_loads_the_whole_file(dji, raw):
    path = dji / "battery_telemetry_all_flights.csv"
    assert detect_format(path) == "dji-log"
    p = load(path)
    assert p.n == len(raw) - 44
    assert p.meta.capacity_ah == pytest.approx(CAPACITY_AH) and p.meta.n_series == 6
    assert p.soc_ref.min() >= 0 and p.soc_ref.max() <= 1
    assert len(p.meta.extra["segments"]) == raw.groupby(["log_id", "battery_segment"]).ngroups
    assert np.all(p.current_a >= 0)  # positive = discharge as logged


def test_scenario_can_replay_real_segments(tmp_path, dji, monkeypatch):
    monkeypatch.setenv("SOCBENCH_DATA_DIR", str(dji.parent))
    segments, _ = read_segments(dji, min_samples=20)
    keys = [segments[0].key]
    f = tmp_path / "real.toml"
    f.write_text('extends = "dji-m100-replay"\n[replay]\nsource = "data"\nsegments = ' + str(keys).replace("'", '"')
                 + "\n")
    p = load_scenario(f).realize([0])
    i = p.meta.extra["truth"]["current_a"]
    first = held_current(segments[0], 1.0)[0] / CAPACITY_AH * 22.0
    start = int(np.argmax(i > 0))  # after the recorded rest
    n = min(first.size, i.size - start)
    assert np.allclose(i[start:start + n], first[:n])
