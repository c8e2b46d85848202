"""Calibration store for KF1: atomic file, checksum, corrupt handling, one-flight-old rule."""
import json
import math

import numpy as np

from estimators.mag_error_kf import Kf1Params, kf1_init, kf1_step
from estimators.rotations import dcm_from_euler
from service.calibration_store import (CalibrationHistory, CalibrationStore, begin_flight,
                                       estimate_for_flight, learning_start, next_flight_id,
                                       update_current)

FIELD = np.array([0.2, 0.01, 0.42])


def learnt(n=50, seed=0, offset=0.0):
    rng = np.random.default_rng(seed)
    st = kf1_init()
    for k in range(n):
        t = offset + 0.1 * k
        C = dcm_from_euler(0.3 * math.sin(0.2 * t), 0.2 * math.cos(0.13 * t), 0.4 * t)
        m = C.T @ FIELD + np.array([0.03, -0.02, 0.01]) + rng.normal(0, 0.002, 3)
        st, _ = kf1_step(st, m, C, FIELD, np.zeros(3), t, Kf1Params())
    return st


def test_roundtrip_is_exact(tmp_path):
    store = CalibrationStore(tmp_path / "cal.json")
    assert store.load().status == "missing"
    h = update_current(begin_flight(CalibrationHistory(), 1, 1000.0), 1, learnt(), 1001.5)
    assert store.save(h)
    back = store.load()
    assert back.status == "loaded"
    assert np.array_equal(back.current.kf1.x, h.current.kf1.x)
    assert np.array_equal(back.current.kf1.P, h.current.kf1.P)
    assert back.current.wall_time_s == 1001.5 and back.current.flight_id == 1
    assert not list(tmp_path.glob(".cal.json.tmp.*"))


def test_split_run_through_store_equals_unbroken_run(tmp_path):
    """Persistence: KF1 saved to the file mid-flight, reloaded (restart), continued == unbroken."""
    rng = np.random.default_rng(11)
    data = []
    for k in range(400):
        t = 0.1 * k
        C = dcm_from_euler(0.5 * math.sin(0.1 * t), 0.3 * math.sin(0.07 * t), 0.3 * t)
        data.append((t, C.T @ FIELD * 1.02 + np.array([0.02, 0.01, -0.03]) + rng.normal(0, 0.002, 3), C))
    full = kf1_init()
    for t, m, C in data:
        full, _ = kf1_step(full, m, C, FIELD, np.zeros(3), t)
    store = CalibrationStore(tmp_path / "cal.json")
    part = kf1_init()
    for t, m, C in data[:233]:
        part, _ = kf1_step(part, m, C, FIELD, np.zeros(3), t)
    assert store.save(update_current(begin_flight(CalibrationHistory(), 4, 0.0), 4, part, 5.0))
    resumed = learning_start(CalibrationStore(tmp_path / "cal.json").load(), 4)
    for t, m, C in data[233:]:
        resumed, _ = kf1_step(resumed, m, C, FIELD, np.zeros(3), t)
    assert np.array_equal(resumed.x, full.x) and np.array_equal(resumed.P, full.P)


def test_truncated_or_tampered_file_is_set_aside(tmp_path):
    p = tmp_path / "cal.json"
    store = CalibrationStore(p)
    h = update_current(begin_flight(CalibrationHistory(), 1, 0.0), 1, learnt(), 1.0)
    assert store.save(h)
    good = p.read_bytes()
    p.write_bytes(good[: len(good) // 2])                 # truncated (power cut, no atomic write)
    st = store.load()
    assert st.status.startswith("corrupt") and st.current is None and st.completed == ()
    assert not p.exists() and (tmp_path / "cal.json.corrupt").read_bytes() == good[: len(good) // 2]
    doc = json.loads(good)
    doc["payload"]["current"]["kf1"]["x"][0] += 1e-9     # silent bit-rot: checksum catches it
    p.write_text(json.dumps(doc))
    st = store.load()
    assert "checksum" in st.status and (tmp_path / "cal.json.corrupt.1").exists()
    doc = json.loads(good)
    doc["version"] = 99
    p.write_text(json.dumps(doc))
    assert "version" in store.load().status
    p.write_bytes(b"\xff\xfe\x00garbage")
    assert store.load().status.startswith("corrupt")
    assert store.save(h) and store.load().status == "loaded"   # and the store works again


def test_crash_before_replace_keeps_old_file_and_failed_save_reports(tmp_path):
    p = tmp_path / "cal.json"
    store = CalibrationStore(p)
    h1 = update_current(begin_flight(CalibrationHistory(), 1, 0.0), 1, learnt(), 1.0)
    assert store.save(h1)
    (tmp_path / ".cal.json.tmp.999").write_bytes(b'{"format": "azimuthd-synth')  # crash mid-write
    back = store.load()
    assert back.status == "loaded" and back.current.wall_time_s == 1.0
    assert not (tmp_path / ".cal.json.tmp.999").exists()
    (tmp_path / "not_a_dir").write_text("x")
    bad = CalibrationStore(tmp_path / "not_a_dir" / "cal.json")
    assert not bad.save(h1) and bad.last_error


def test_one_flight_old_rule_and_restart_in_flight():
    h = CalibrationHistory()
    assert next_flight_id(h) == 1 and estimate_for_flight(h, 1) is None
    h = begin_flight(h, 1, 0.0)
    e1 = learnt(seed=1)
    h = update_current(h, 1, e1, 10.0)
    assert estimate_for_flight(h, 1) is None           # own flight's estimate never used
    h = begin_flight(h, 2, 20.0)                       # flight 1 completes implicitly
    assert h.current is None and h.completed[-1].flight_id == 1
    assert h.completed[-1].kf1.flight_count == 1
    assert np.array_equal(learning_start(h, 2).x, e1.x)
    e2 = learnt(seed=2, offset=100.0)
    h = update_current(h, 2, e2, 30.0)
    use = estimate_for_flight(h, 2)
    assert use.flight_id == 1 and np.array_equal(use.kf1.x, e1.x)   # the one-flight-old estimate
    assert begin_flight(h, 2, 40.0) is h               # restart during flight 2 resumes it
    assert np.array_equal(learning_start(h, 2).x, e2.x)
    for f in (3, 4, 5, 6):
        h = update_current(begin_flight(h, f, 50.0 + f), f, learnt(seed=f), 60.0 + f)
    assert [fe.flight_id for fe in h.completed] == [3, 4, 5]   # keep_completed = 3
    assert estimate_for_flight(h, 6).flight_id == 5 and next_flight_id(h) == 7
