"""A heading of our own: the FC's yaw excluded ([heading] use_fc_yaw = false, or
Pipeline.exclude_fc_yaw at run time), through the daemon's own Pipeline on a simulated flight.

GIVEN the simulated inclined-rail flight (consumer IMU, 100 Hz, the FC's ATTITUDE streamed and
trusted) fed from 60 s after the launch (started in flight: method A is off), WHEN the FC's yaw
is excluded THEN no published heading uses the FC ('fc' never a source), the heading comes from
methods B/C (the magnetometer), and it is within its published sigma against the simulator's
truth (>= 90 % of the samples within 2 sigma, NEES-like ratio bounded), with a small RMS.
GIVEN the same flight WHEN the magnetometer starts reading 0.87 G against the model's ~0.5 G
THEN it is rejected with a named reason (event and ``mag_status``) and the heading sigma grows
while the filters coast on the gyros, still covering the error.
"""
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from sitl import feed_pipeline, scenario_site  # noqa: E402

from mavlink_io.samples import FcAttitude, FcHeartbeat, ImuSample, PressureSample  # noqa: E402
from service.config import validate  # noqa: E402
from service.pipeline import Pipeline  # noqa: E402
from sim.offline import simulate  # noqa: E402

RATE_HZ = 100.0
FEED_FROM_S = 60.0
FEED_S = 45.0
BAD_MAG_FROM_S = FEED_FROM_S + 30.0
BAD_MAG_GAUSS = 0.87


@pytest.fixture(scope="module")
def run():
    return simulate(scenario="inclined_rail", seed=3, imu_grade="consumer", imu_rate_hz=RATE_HZ,
                    duration_s=FEED_FROM_S + FEED_S, overrides={"launcher": {"rest_s": 5.0}})


@pytest.fixture(scope="module")
def flown(run):
    """FC yaw excluded; the magnetometer reads 0.87 G from BAD_MAG_FROM_S on (good before)."""
    scale = BAD_MAG_GAUSS / float(np.median(np.linalg.norm(run.mag_gauss, axis=1)))
    return fly(run, {"use_fc_yaw": False}, mag_scale_after=(BAD_MAG_FROM_S, scale))


def fly(run, heading_cfg, mag_scale_after=None, exclude_at_s=None, feed_s=FEED_S):
    """Feed the flight from FEED_FROM_S (FC ATTITUDE, pressure, HEARTBEAT armed at 1 Hz); the
    magnetometer scaled by ``mag_scale_after`` = (time, factor) from that time on."""
    items = []
    for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss):
        m = m.copy()
        if mag_scale_after is not None and t >= mag_scale_after[0]:
            m = m * mag_scale_after[1]
        items.append((t, 2, ImuSample(t, t, g.copy(), a.copy(), m, "RAW_IMU", 0)))
    for t, p, d, k in zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                          run.temperature_k.tolist()):
        items.append((t, 1, PressureSample(t, t, p, d, k)))
    for t, e in zip(run.fc_time_s.tolist(), run.fc_euler_rad):
        items.append((t, 0, FcAttitude(t, t, float(e[0]), float(e[1]), float(math.remainder(e[2], 2 * math.pi)),
                                       np.zeros(3))))
    for t in np.arange(FEED_FROM_S, FEED_FROM_S + FEED_S, 1.0).tolist():
        items.append((t, -1, FcHeartbeat(t, 1, 1, "ardupilot", 1, 129, 0, 4, True)))
    items = sorted((x for x in items if FEED_FROM_S <= x[0] < FEED_FROM_S + feed_s), key=lambda x: (x[0], x[1]))
    site = scenario_site("inclined_rail")
    s = run.site
    site["site"].update(lat_deg=s["lat_deg"], lon_deg=s["lon_deg"], alt_m=s["alt_m"], decimal_year=s["decimal_year"])
    p = Pipeline(validate({**site, "mavlink": {"imu_rate_hz": RATE_HZ}, "heading": heading_cfg}))
    sols, events = [], []
    # the FC's yaw is excluded just before the first item at or after exclude_at_s
    cut = len(items) if exclude_at_s is None else next((k for k, x in enumerate(items) if x[0] >= exclude_at_s),
                                                       len(items))
    sols += [(sol, p.mag_status) for sol in feed_pipeline(p, [it for _t, _o, it in items[:cut]], events)]
    if cut < len(items):
        p.exclude_fc_yaw("test: the FC's yaw is our own fed back")
        sols += [(sol, p.mag_status) for sol in feed_pipeline(p, [it for _t, _o, it in items[cut:]], events)]
    return p, sols, events


def heading_errors(run, sols, t_from=-math.inf, t_to=math.inf):
    """(time, error deg, sigma deg, source) of every solution with a valid heading in [t_from, t_to)."""
    out = []
    for s, _ in sols:
        if not s.heading_valid or not t_from <= s.time_fc_s < t_to:
            continue
        k = min(int(np.searchsorted(run.time_s, s.time_fc_s - 1e-9)), len(run.time_s) - 1)
        err = math.degrees(math.remainder(s.heading_rad - run.truth.euler_rad[k][2], 2 * math.pi))
        out.append((s.time_fc_s, err, math.degrees(s.heading_sigma_rad), s.heading_source))
    return out


def test_given_fc_yaw_excluded_when_magnetometer_good_then_heading_from_b_c_within_sigma(run, flown):
    p, sols, events = flown
    good = [x for x in sols if x[0].time_fc_s < BAD_MAG_FROM_S]
    errs = heading_errors(run, good)
    assert len(errs) > 0.9 * len(good)                       # a heading nearly all the time
    sources = {e[3] for e in errs}
    assert not any("fc" in s.split("+") for s in sources), sources
    assert sources <= {"synthetic_ahrs", "heading_filter", "coast"}, sources
    e = np.array([x[1] for x in errs])
    sig = np.array([x[2] for x in errs])
    within2 = float(np.mean(np.abs(e) <= 2 * sig))
    rms = float(np.sqrt(np.mean(e * e)))
    assert within2 >= 0.90, (within2, rms)
    assert rms < 3.0, rms
    assert all(m == "usable" for _, m in good[-100:])


def test_given_run_time_exclusion_then_fc_leaves_the_heading_with_an_event(run):
    p, sols, events = fly(run, {}, exclude_at_s=FEED_FROM_S + 20.0, feed_s=25.0)
    before = [s.heading_source for s, _ in sols if s.time_fc_s < FEED_FROM_S + 20.0 and s.heading_valid]
    after = [s.heading_source for s, _ in sols if s.time_fc_s >= FEED_FROM_S + 20.5 and s.heading_valid]
    assert any("fc" in s.split("+") for s in before)
    assert after and not any("fc" in s.split("+") for s in after)
    assert [d for k, d in events if k == "fc_yaw_excluded"] == [
        "the FC's yaw is no longer used: test: the FC's yaw is our own fed back"]


def test_given_magnetometer_reading_0p87_gauss_then_rejected_named_and_sigma_grows(run, flown):
    p, sols, events = flown
    model = float(np.linalg.norm(p.field.e_ned_gauss))
    rej = [d for k, d in events if k == "magnetometer" and d.startswith("rejected")]
    assert len(rej) == 1 and rej[0].startswith("rejected (field norm ") and f"the model's {model:.3f} G" in rej[0], rej
    # once the window holds only bad samples, the status names the figure (the sensor's norm
    # varies with its hard iron and the attitude: +-0.03 G about the scaled median)
    m = re.match(r"rejected: field norm (\d\.\d{3}) G vs the model's (\d\.\d{3}) G", p.mag_status)
    assert m and abs(float(m.group(1)) - BAD_MAG_GAUSS) < 0.03 and float(m.group(2)) == round(model, 3), p.mag_status
    assert sols[-1][0].flags["magnetometer"] == p.mag_status
    # the sigma grows from the rejection on (the filters coast on the gyros) and still covers the error
    after = heading_errors(run, sols, BAD_MAG_FROM_S + 2.5)
    assert after, "the heading must coast, not vanish, right after the rejection"
    sig = np.array([x[2] for x in after])
    per_s = sig[::50]                                      # once a second (50 Hz solutions)
    assert np.all(np.diff(per_s) > 0.0), per_s             # (a tilt update may trim it by < 0.001 deg)
    assert sig[-1] > sig[0] + 0.3, (sig[0], sig[-1])
    e = np.array([x[1] for x in after])
    assert float(np.mean(np.abs(e) <= 2 * sig)) >= 0.9


def test_kf2_reference_update_without_yaw_pulls_roll_pitch_and_leaves_the_heading():
    """GIVEN KF2 at roll 0, pitch 0, heading 30 deg WHEN the FC says roll 2, pitch -1, yaw 70 deg
    with use_yaw False THEN roll/pitch move toward the FC's and the heading does not move at all;
    with use_yaw True (the default) the heading is pulled toward the FC's."""
    from estimators.ahrs_kf2 import Kf2Params, kf2_euler_and_cov, kf2_init, kf2_update_reference
    from estimators.rotations import quat_from_euler
    kf = kf2_init(quat_from_euler(0.0, 0.0, math.radians(30.0)), Kf2Params(), sigma_tilt_rad=math.radians(3.0),
                  sigma_heading_rad=math.radians(30.0))
    ref = np.radians([2.0, -1.0, 70.0])
    no_yaw, d = kf2_update_reference(kf, ref, 0.0, math.radians(0.5), math.radians(1.5), use_yaw=False)
    e, _ = kf2_euler_and_cov(no_yaw)
    assert d.fused and abs(math.degrees(e[2]) - 30.0) < 0.05
    assert abs(math.degrees(e[0]) - 2.0) < 0.2 and abs(math.degrees(e[1]) + 1.0) < 0.2
    with_yaw, _ = kf2_update_reference(kf, np.radians([2.0, -1.0, 35.0]), 0.0, math.radians(0.5), math.radians(1.5))
    assert abs(math.degrees(kf2_euler_and_cov(with_yaw)[0][2]) - 35.0) < 0.5
