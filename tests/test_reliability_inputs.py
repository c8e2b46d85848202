"""Bad values into the Pipeline (issue 10): NaN/inf, a saturated and a clipped sensor, a frozen
(repeating) sensor, time going backwards and a restarted clock, a 10 s gap.

GIVEN a simulated flight (inclined rail, 15 s on the launcher, 100 Hz, consumer IMU, RAW_IMU
quantisation) fed to the daemon's own Pipeline as the daemon feeds it, WHEN one fault is injected
in flight THEN it is detected and counted by kind (service/input_checks.py), reported once as an
event (not once per sample), the bad samples never reach the estimators, and the roll/pitch the
Pipeline gives afterwards stay finite and as close to the truth as in the clean run.
"""
import copy
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import feed_pipeline, pipeline_inputs, scenario_site  # noqa: E402

from mavlink_io.samples import ImuSample  # noqa: E402
from service.config import validate  # noqa: E402
from service.input_checks import RAW_GYRO_LIMIT_RAD_S, ImuInputChecks, InputCheckParams  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402

RATE_HZ = 100.0
REST_S = 15.0
DUR_S = 60.0
FAULT_T = 30.0  # in flight (launch at ~15 s)


def _make():
    run = simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ,
                   duration_s=DUR_S, overrides={"launcher": {"rest_s": REST_S}})
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    cfg = validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}})
    return run, pipeline_inputs(run), cfg


RUN, ITEMS, CFG = _make()


def _run(p, items, sols, events):
    sols.extend(feed_pipeline(p, items, events))


_PREFIX = {}


def feed(items):
    """Feed ``items`` to a Pipeline. Every fault starts at FAULT_T, so the common clean prefix is
    run once and each fault continues from a deep copy of that Pipeline (the same as a full run:
    the Pipeline is deterministic, its solver inline)."""
    split = next(i for i, it in enumerate(ITEMS) if it.time_fc_s >= FAULT_T)
    if items[:split] != ITEMS[:split]:
        raise ValueError("a fault before FAULT_T")
    if not _PREFIX:
        p0, sols0, ev0 = Pipeline(CFG), [], []
        _run(p0, ITEMS[:split], sols0, ev0)
        _PREFIX.update(p=p0, sols=sols0, events=ev0)
    p = copy.deepcopy(_PREFIX["p"])
    sols, events = list(_PREFIX["sols"]), list(_PREFIX["events"])
    _run(p, items[split:], sols, events)
    finite = all(math.isfinite(x) for s in sols[-50:] for x in (s.roll_rad, s.pitch_rad)
                 if x is not None) and all(np.all(np.isfinite(s.rates_body_rad_s)) for s in sols[-50:])
    return {"sol": sols, "events": events, "counts": dict(p.input_checks.counts), "rejected": p.counters.imu_rejected,
            "reasons": dict(p.counters.reasons), "finite": finite, "pipeline": p}


def test_prefix_copy_equals_a_full_run():
    """The shortcut in ``feed`` is exact: a deep-copied Pipeline continues as an unbroken run."""
    p, sols, ev = Pipeline(CFG), [], []
    _run(p, ITEMS, sols, ev)
    r = feed(ITEMS)
    assert len(r["sol"]) == len(sols)
    assert all(a.roll_rad == b.roll_rad and a.pitch_rad == b.pitch_rad and a.heading_rad == b.heading_rad
               for a, b in zip(r["sol"], sols))


def tilt_err_deg(r, t0, t1, t_shift=0.0):
    """Max |roll|, |pitch| error vs the truth (deg) over solutions with FC time in [t0, t1)."""
    tt = RUN.time_s
    worst = 0.0
    for s in r["sol"]:
        t = s.time_fc_s + t_shift
        if t0 <= t < t1 and s.roll_rad is not None:
            k = min(int(np.searchsorted(tt, t - 1e-9)), len(tt) - 1)
            e = RUN.truth.euler_rad[k]
            worst = max(worst, abs(math.degrees(math.remainder(s.roll_rad - e[0], 2 * math.pi))),
                        abs(math.degrees(s.pitch_rad - e[1])))
    return worst


def tilt_track(r, t0, t1, t_shift=0.0):
    """Rows (time from t0 s, |roll err|, |pitch err|, roll sigma, pitch sigma), deg, for the
    solutions with FC time + t_shift in [t0, t1)."""
    tt, out = RUN.time_s, []
    for s in r["sol"]:
        t = s.time_fc_s + t_shift
        if t0 <= t < t1 and s.roll_rad is not None:
            k = min(int(np.searchsorted(tt, t - 1e-9)), len(tt) - 1)
            e = RUN.truth.euler_rad[k]
            out.append((t - t0, abs(math.degrees(math.remainder(s.roll_rad - e[0], 2 * math.pi))),
                        abs(math.degrees(s.pitch_rad - e[1])), math.degrees(s.roll_sigma_rad),
                        math.degrees(s.pitch_sigma_rad)))
    return np.array(out)


def reconverged_after_s(a, within_deg=2.0):
    """Time (s from the start of ``a``) after which roll and pitch stay within ``within_deg``."""
    bad = np.nonzero(np.maximum(a[:, 1], a[:, 2]) >= within_deg)[0]
    if not len(bad):
        return 0.0
    return math.inf if bad[-1] + 1 >= len(a) else float(a[bad[-1] + 1, 0])


def _imu_idx(items, t0, t1):
    return [i for i, it in enumerate(items) if isinstance(it, ImuSample) and t0 <= it.time_fc_s < t1]


def _replace(items, idx, fn):
    out = list(items)
    for i in idx:
        it = out[i]
        out[i] = fn(it)
    return out


def fault_nan(items):
    idx = _imu_idx(items, FAULT_T, FAULT_T + 0.5)
    out = _replace(items, idx[::2], lambda s: ImuSample(s.time_fc_s, s.time_rx_s, np.array([np.nan, 0, 0]),
                                                        s.accel_m_s2, s.mag_gauss, s.source))
    return _replace(out, idx[1::2], lambda s: ImuSample(s.time_fc_s, s.time_rx_s, s.gyro_rad_s,
                                                        np.array([0, np.inf, -9.8]), s.mag_gauss, s.source))


def fault_saturated(items):
    """RAW_IMU gyro x at its int16 limit (32767 mrad/s) for 0.3 s."""
    idx = _imu_idx(items, FAULT_T, FAULT_T + 0.3)
    return _replace(items, idx, lambda s: ImuSample(s.time_fc_s, s.time_rx_s,
                                                    np.array([RAW_GYRO_LIMIT_RAD_S, *s.gyro_rad_s[1:]]),
                                                    s.accel_m_s2, s.mag_gauss, s.source))


def fault_clipped(items):
    """Accel x clipped at a 16 g sensor's range (156.9 m/s^2) for 0.5 s."""
    idx = _imu_idx(items, FAULT_T, FAULT_T + 0.5)
    return _replace(items, idx, lambda s: ImuSample(s.time_fc_s, s.time_rx_s, s.gyro_rad_s,
                                                    np.array([16 * 9.80665, *s.accel_m_s2[1:]]),
                                                    s.mag_gauss, s.source))


def fault_frozen(items):
    """The driver resends one sample (time advancing) for 2 s."""
    idx = _imu_idx(items, FAULT_T, FAULT_T + 2.0)
    first = items[idx[0]]
    return _replace(items, idx, lambda s: ImuSample(s.time_fc_s, s.time_rx_s, first.gyro_rad_s.copy(),
                                                    first.accel_m_s2.copy(), first.mag_gauss, s.source))


def fault_backwards(items):
    """Ten single samples whose time is 2 ms behind the previous one (a reordered/duplicated stream)."""
    idx = _imu_idx(items, FAULT_T, FAULT_T + 1.0)[::10]
    out = list(items)
    for i in reversed(idx):
        s = out[i]
        out.insert(i + 1, ImuSample(s.time_fc_s - 0.002, s.time_rx_s, s.gyro_rad_s * 5, s.accel_m_s2 * 5,
                                    s.mag_gauss, s.source))
    return out


CLOCK_BACK_S = 25.0


def fault_clock_restart(items):
    """From FAULT_T on, the FC time restarts 25 s lower (a log with an FC reboot, no link event)."""
    out = []
    for it in items:
        if it.time_fc_s >= FAULT_T:
            t = it.time_fc_s - CLOCK_BACK_S
            it = type(it)(*((t,) + tuple(getattr(it, f) for f in it.__slots__[1:])))
        out.append(it)
    return out


def fault_gap(items):
    """No sample at all for 10 s in flight."""
    return [it for it in items if not (FAULT_T <= it.time_fc_s < FAULT_T + 10.0)]


FAULTS = {"nan": fault_nan, "saturated": fault_saturated, "clipped": fault_clipped, "frozen": fault_frozen,
          "backwards": fault_backwards, "clock_restart": fault_clock_restart, "gap": fault_gap}


@pytest.fixture(scope="module")
def clean():
    return feed(ITEMS)


def _input_events(r, kind):
    return [d for k, d in r["events"] if k == "imu_input" and d.startswith(kind + ":")]


def without_corrupted(fault_items):
    """The clean flight with every sample the fault replaced simply missing (the fault builders put
    new objects in place of the samples they corrupt and insert new ones; the rest are kept)."""
    kept = {id(it) for it in fault_items}
    return [it for it in ITEMS if id(it) in kept]


def test_clean_flight_has_no_input_findings(clean):
    assert all(v == 0 for v in clean["counts"].values())
    assert clean["rejected"] == 0 and clean["finite"]
    assert tilt_err_deg(clean, 40.0, 60.0) < 2.5  # the reference the faults are compared with


@pytest.mark.parametrize("name, kind, n_rejected, reason", [
    ("nan", "non_finite", 50, "non-finite IMU sample"),
    ("saturated", "saturated", 30, "IMU saturated"),
    ("clipped", "saturated", 31, "IMU saturated"),       # detected at the 20th identical clipped value
    ("frozen", "frozen", 150, "IMU frozen"),             # detected after 0.5 s of 2 s
    ("backwards", "time_backwards", 10, "IMU time not increasing"),
])
def test_bad_values_detected_counted_reported_once_and_estimators_protected(clean, name, kind, n_rejected, reason):
    r = feed(FAULTS[name](ITEMS))
    assert r["counts"][kind] == n_rejected
    assert r["rejected"] == n_rejected and r["reasons"] == {reason: n_rejected}
    assert len(_input_events(r, kind)) == 1  # once, not once per sample
    assert r["finite"]
    assert r["sol"][-1].phase == "in-flight" and r["sol"][-1].time_fc_s > DUR_S - 0.1
    # the bad values themselves cost nothing: roll/pitch during and after the fault as good as in the
    # same flight with the corrupted samples simply missing (within 0.1 deg; measured nan 0.000,
    # frozen -0.014: the frozen samples let through before the detection cost nothing either)
    m = feed(without_corrupted(FAULTS[name](ITEMS)))
    for t0, t1 in ((FAULT_T, FAULT_T + 10.0), (FAULT_T + 10.0, DUR_S)):
        assert tilt_err_deg(r, t0, t1) < tilt_err_deg(m, t0, t1) + 0.1
        # and the samples lost cost at most 0.6 deg against the clean flight: in flight, 0.5-2 s of
        # unseen rates widen the attitude, which the specific force then re-learns without the
        # rest-time gyro-bias alignment the clean flight still carries (zero-rate, ce873d7: clean
        # 1.30 -> 0.95 deg, the nan case 1.29 -> 1.31, frozen 1.46 -> 1.49 deg over the 10 s)
        assert tilt_err_deg(r, t0, t1) < tilt_err_deg(clean, t0, t1) + 0.6
    if name == "frozen":
        assert len(_input_events(r, "frozen_end")) == 1


def test_ten_second_gap_detected_not_integrated_and_recovers(clean):
    r = feed(fault_gap(ITEMS))
    assert r["counts"]["gap"] == 1 and r["rejected"] == 0
    assert len(_input_events(r, "gap")) == 1
    assert any(k == "strapdown" and "not integrated" in d for k, d in r["events"])
    assert r["finite"]
    # the attitude filter resumes from its pre-gap state (5.6 deg off just after the gap), but its
    # covariance says so: the 10 s unseen widen roll/pitch sigma to the 30 deg prior, the
    # specific force pulls the attitude back and the sigma covers the error meanwhile.
    # Measured: before this fix sigma 0.8 deg after the gap, 34 % of the next 15 s within 3 sigma,
    # back within 2 deg for good after 10.4 s; now 100 % within 3 sigma, back after 1.4 s.
    a = tilt_track(r, FAULT_T + 10.0, FAULT_T + 25.0)
    assert a[0, 3] > 20.0 and a[0, 4] > 20.0  # honest: the state is stale
    assert np.all(a[:, 1] < 3 * a[:, 3]) and np.all(a[:, 2] < 3 * a[:, 4])
    assert reconverged_after_s(a) < 2.0
    # after 10 s unseen in flight the attitude is re-learnt from the specific force alone, so the
    # recovered error is the in-flight filter's, not the clean flight's (which still carries its
    # rest-time gyro-bias alignment, zero-rate ce873d7: clean 1.79 -> 1.19 deg over 42-55 s).
    # Absolute bounds on the recovered error, measured 1.91 / 1.71 deg before zero-rate (d538bdf)
    # and 1.90 / 1.73 after:
    assert tilt_err_deg(r, FAULT_T + 12.0, FAULT_T + 25.0) < 2.2
    assert tilt_err_deg(r, FAULT_T + 25.0, DUR_S) < 2.0


def test_restarted_clock_rejected_then_integration_restarts():
    """A log whose FC clock restarts 25 s lower without a reboot event: the samples are rejected
    (never integrated backwards), the restart reported once, and when the new clock passes the
    old one the Pipeline restarts its integration (fc_reboot) instead of integrating across the
    unseen 25 s; the 25 s not seen (receive time) widen the attitude and heading covariance, so
    the stale attitude (17 deg off) carries an honest sigma and the accelerometer pulls it back."""
    r = feed(fault_clock_restart(ITEMS))
    imu_t = [it.time_fc_s for it in ITEMS if isinstance(it, ImuSample)]
    t_last = max(t for t in imu_t if t < FAULT_T)
    n_back = sum(1 for t in imu_t if t >= FAULT_T and t - CLOCK_BACK_S <= t_last)
    assert r["counts"]["time_backwards"] == n_back and r["counts"]["time_reset"] == 1
    assert len(_input_events(r, "time_backwards")) == 1 and len(_input_events(r, "time_reset")) == 1
    assert len(_input_events(r, "time_reset_end")) == 1
    assert sum(1 for k, _d in r["events"] if k == "fc_reboot") == 1
    assert r["finite"] and r["sol"][-1].time_fc_s > DUR_S - CLOCK_BACK_S - 0.1
    assert any(k == "unseen" and d.startswith("25.0 s not seen") for k, d in r["events"])
    # measured: before this fix 17.2 deg off with sigma 0.8 deg, 0 % within 3 sigma, not back
    # within the 5 s left; now sigma 30 deg at the restart, 100 % within 3 sigma, within 2 deg
    # after 1.1 s and 1.4 deg at most from then on
    a = tilt_track(r, FAULT_T + CLOCK_BACK_S, DUR_S, t_shift=CLOCK_BACK_S)
    assert max(a[0, 1], a[0, 2]) > 10.0 and a[0, 3] > 20.0 and a[0, 4] > 20.0
    assert np.all(a[:, 1] < 3 * a[:, 3]) and np.all(a[:, 2] < 3 * a[:, 4])
    assert reconverged_after_s(a) < 1.5


def test_reports_are_rate_limited_with_a_count():
    chk = ImuInputChecks(InputCheckParams(report_interval_s=60.0))
    n_events = 0
    for k in range(400):  # a NaN every other sample for 100 s of receive time at 4 Hz
        bad = k % 2 == 0
        s = ImuSample(0.25 * k, 0.25 * k, np.array([np.nan if bad else 0.01 * k, 0, 0]), np.array([0, 0, -9.8]),
                      None, "RAW_IMU")
        v = chk.check(s)
        n_events += len(v.events)
        if bad:
            assert v.reject == "non-finite IMU sample"
    assert chk.counts["non_finite"] == 200
    assert n_events == 2  # at 0 s and at 60 s (with the count since)


def test_params_validated():
    with pytest.raises(ValueError, match="frozen_s"):
        InputCheckParams(frozen_s=0.0)
    with pytest.raises(ValueError, match="clip_repeats"):
        InputCheckParams(clip_repeats=0)


def test_daemon_publishes_input_counters_on_health_and_logs_once(tmp_path, caplog):
    """Through the daemon's dispatch: 300 NaN samples are one warning line and show in the
    ``health`` payload's counters_count."""
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.transport import NullTransport
    from service.daemon import Daemon

    class Bus:
        def __init__(self):
            self.out = []

        def publish(self, topic, payload):
            self.out.append((topic, payload))

        def publish_solution(self, sol, now, aiding=None):  # ZenohBus.publish_solution's signature
            pass

    keep = {sec: {k: v for k, v in CFG[sec].items() if v is not None} for sec in ("site", "imu", "launch")}
    cfg = validate({**keep, "mavlink": {"imu_rate_hz": RATE_HZ},
                    "service": {"state_dir": str(tmp_path)}, "zenoh": {"enabled": False},
                    "azimuth": {"solve_in_background": False}})
    d = Daemon(cfg)
    d.link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0"), transport=NullTransport(None))
    d.bus = Bus()
    caplog.set_level("WARNING", logger="azimuthd")
    imu = [it for it in ITEMS if isinstance(it, ImuSample)][:600]
    for k, s in enumerate(imu):
        if k % 2:
            s = ImuSample(s.time_fc_s, s.time_rx_s, np.array([np.nan, 0.0, 0.0]), s.accel_m_s2, s.mag_gauss, s.source)
        d.dispatch(s)
    d._publish_health(10.0)
    health = [p for t, p in d.bus.out if t == "health"][-1]
    assert health["counters_count"]["imu_input_non_finite"] == 300
    assert health["counters_count"]["imu_rejected"] == 300
    lines = [r for r in caplog.records if "non_finite" in r.getMessage()]
    assert len(lines) == 1
    events = [p for t, p in d.bus.out if t == "events" and "non_finite" in p.get("text", str(p))]
    assert len(events) == 1
    d.pipeline.solver.close()
    d.link.close()


@pytest.mark.parametrize("name", ["arducopter-flight.tlog", "px4-bench-sample.ulg", "px4-vtol-airspeed-small.ulg"])
def test_real_logs_raise_no_false_value_findings(name):
    """Real flight-controller logs (/work/shared/data): no sample is called non-finite, saturated,
    out of range, frozen or backwards (the tlog's 2 Hz telemetry IMU does show as gaps)."""
    from service.logreaders import open_log
    path = Path("/work/shared/data") / name
    chk = ImuInputChecks()
    n = 0
    for it in open_log(path).items():
        if isinstance(it, ImuSample):
            n += 1
            assert chk.check(it).reject is None
    assert n > 1000
    assert {k: v for k, v in chk.counts.items() if v and k != "gap"} == {}


def test_unseen_interval_widens_the_filters_covariance_by_the_stated_bound():
    """estimators: s = min(rate * unseen, cap) is added to the attitude error variance (each axis)
    and the heading variance; the next sample restarts the increments, whatever its time."""
    from estimators.polar_attitude import (I_ATT, PolarAttitudeParams, polar_attitude_init_at,
                                           polar_attitude_step, polar_attitude_unseen)
    from estimators.polar_heading import PolarHeadingParams, polar_heading_init, polar_heading_unseen
    pa = PolarAttitudeParams()
    st = polar_attitude_init_at(10.0, 0.1, -0.05, math.radians(1.0), pa)
    for dt_unseen, s_exp in ((0.5, math.radians(5.0)), (10.0, math.radians(30.0))):
        st2 = polar_attitude_unseen(st, dt_unseen, pa)
        grow = np.diag(st2.P[I_ATT, I_ATT] - st.P[I_ATT, I_ATT])
        assert np.allclose(grow, s_exp ** 2, rtol=1e-12)
        assert st2.time_s is None and np.array_equal(st2.q_P_from_body, st.q_P_from_body)
    st3, diag = polar_attitude_step(st2, 3.0, np.zeros(3), np.array([0.0, 0.0, -9.80665]), pa)
    assert diag.reason == "increments restarted" and st3.time_s == 3.0  # a lower, restarted clock
    ph = PolarHeadingParams()
    h = polar_heading_init(1.0, math.radians(2.0), ph)
    h2 = polar_heading_unseen(h, 2.0, ph)
    assert h2.P[0, 0] - h.P[0, 0] == pytest.approx(math.radians(40.0) ** 2, rel=1e-12)
    assert polar_heading_unseen(h, 60.0, ph).P[0, 0] - h.P[0, 0] == pytest.approx(math.pi ** 2, rel=1e-12)
    with pytest.raises(ValueError, match="unseen_s"):
        polar_attitude_unseen(st, -1.0, pa)
    with pytest.raises(ValueError, match="tilt_sigma_rad"):
        polar_attitude_init_at(0.0, 0.0, 0.0, 0.0, pa)
