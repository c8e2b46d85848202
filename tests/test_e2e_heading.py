"""End to end, the heading the daemon publishes (issue 16 item 6): `azimuthd sim` and `azimuthd run`
as separate OS processes over UDP on loopback, the daemon's own outputs against the simulator's
truth log (the harness reads the truth; the daemon never sees it).

GIVEN the default scenario shortened (inclined rail, 20 s on the launcher, a boost, a climb-out,
      a 120-deg turn, level flight)
      with the FC's yaw trusted on the launcher and method A solving in flight
WHEN  the daemon runs against the simulator
THEN  the yaw of its ATTITUDE and the attitude quaternion of its ODOMETRY (what the FC's EKF fuses)
      are within the measured error plus a stated margin of the true yaw, ODOMETRY's yaw variance
      covers the error (>= 95 % of the samples within 3 sigma), and a heading is published for
      most of the flight.

ATTITUDE and ODOMETRY carry the FC time of their solution (time_boot_ms / time_usec): each is
compared with the truth at that time, so a busy machine (the simulator slower than SPEED, the
daemon behind) changes how many samples arrive, never what is compared.
"""
import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import Sitl, angle_diff_rad  # noqa: E402

SPEED = 2.0
REST_S = 20.0
LEGS = [{"type": "climb", "alt_m": 60.0, "rate_m_s": 5.0},
        {"type": "turn", "by_deg": 120.0, "bank_deg": 30.0},
        {"type": "level", "duration_s": 30.0}]
FLIGHT_S = REST_S + 45.0
"""The default scenario shortened: 20 s on the rail, the boost, a 12 s climb-out, a 120-deg turn
at 30 deg of bank (~9 s, what method A needs to solve), then level flight."""
HANG_S = 900.0
"""Only a hang detector: the flight takes what the machine gives it."""
DRAIN_QUIET_S = 10.0
"""After the simulator's end the daemon works off what it has queued: it is done when its ATTITUDE
reaches the simulator's last FC time (DRAIN_END_S), or, when it lost the tail of the input, when
no ATTITUDE came for this long (a hang detector: nothing is counted per wall-clock second)."""
DRAIN_END_S = 0.5
"""The daemon has worked off its queue when its newest ATTITUDE is this close to the FC time of
the simulator's last truth row (ATTITUDE goes out at 50 Hz of the daemon's clock)."""

MAX_HEADING_RMS_DEG = 2.1
MAX_HEADING_ERR_DEG = 4.2
"""Bounds on the published heading vs truth over the whole flight. Measured on 2026-12-02 at load
20-26 (3 flights of this scenario family, seed 5: 130/140 s flights at 4x and this 65 s one at
2x): ATTITUDE yaw RMS 1.39 / 1.52 / 1.61 deg, worst 2.66 / 2.65 / 2.66 deg; ODOMETRY (the first
flight; in the others the daemon ran behind and held them back) RMS 1.41, worst 2.66 deg, 100 %
within 3 sigma, median sigma 1.47 deg. Bound = the worst measured + a margin: +0.5 deg on the RMS,
+1.5 deg (one median published sigma) on the worst error."""
MIN_WITHIN_3SIGMA = 0.95
MIN_HEADING_COVERAGE = 0.9
"""Share of the ATTITUDE after the first heading that carries a yaw (a NaN yaw: no heading)."""


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from geofence import write_scenario_toml
    from sim.scenario import read_scenario_source
    wd = tmp_path_factory.mktemp("e2e-heading")
    sc = read_scenario_source("inclined_rail")   # the scenario file as written (no None defaults)
    sc["launcher"]["rest_s"], sc["legs"], sc["scenario"]["duration_s"] = REST_S, LEGS, FLIGHT_S
    path = write_scenario_toml(sc, wd / "scenario.toml")
    with Sitl(scenario=str(path), speed=SPEED, seed=5, tap=True, workdir=wd) as s:
        finished = s.wait_for(lambda: s.sim.poll() is not None, HANG_S)
        t_end_fc = s.truth()["time_boot_s"][-1] - DRAIN_END_S if finished else math.inf
        n, t_quiet = -1, time.monotonic()
        while time.monotonic() - t_quiet < DRAIN_QUIET_S and s.daemon.poll() is None:
            att = s.listener.attitude
            if att and att[-1][0] >= t_end_fc:
                break
            if len(att) != n:
                n, t_quiet = len(att), time.monotonic()
            time.sleep(0.1)
    assert finished and s.sim.returncode == 0, f"simulator hung or failed; see {s.workdir}"
    return s


def _truth_yaw_at(truth: dict, t_boot_s: np.ndarray) -> np.ndarray:
    idx = np.clip(np.searchsorted(truth["time_boot_s"], t_boot_s), 0, len(truth["time_boot_s"]) - 1)
    return truth["yaw_rad"][idx]


def _yaw_of_q(q) -> float:
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def test_attitude_yaw_follows_the_true_heading(flight):
    truth = flight.truth()
    att = np.array([row[:4] for row in flight.listener.attitude], float).reshape(-1, 4)
    assert len(att) > 100, f"{len(att)} ATTITUDE reached the ground-station listener"
    has = np.isfinite(att[:, 3])
    assert has.any(), "no ATTITUDE carried a yaw"
    first = np.argmax(has)
    coverage = float(np.mean(has[first:]))
    err = np.degrees(np.abs(angle_diff_rad(att[has, 3], _truth_yaw_at(truth, att[has, 0]))))
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"ATTITUDE yaw: n={has.sum()} rms={rms:.2f} max={err.max():.2f} deg coverage={coverage:.3f}")
    assert coverage >= MIN_HEADING_COVERAGE
    assert rms <= MAX_HEADING_RMS_DEG
    assert err.max() <= MAX_HEADING_ERR_DEG
    # the heading really changed in flight (the 120-deg turn): a frozen yaw would not pass
    launch = truth["launch_time_boot_s"]
    flown = has & (att[:, 0] > launch)
    assert np.ptp(np.unwrap(att[flown, 3])) > math.radians(100.0)


def test_odometry_yaw_and_its_variance(flight):
    truth = flight.truth()
    odo = flight.tap.sent_by_daemon("ODOMETRY")
    late = flight.log("daemon").count("event=odometry_late")
    if len(odo) <= 50 and late:
        # the daemon held its ODOMETRY back because it ran behind its input (an FC would fuse the
        # yaw misdated: mavlink_io/output_gate.py); what it did send is still checked below
        if not odo:
            pytest.skip(f"no ODOMETRY: the daemon ran behind its input and held them back "
                        f"({late} odometry_late warnings); a busy machine, see {flight.workdir}")
    else:
        assert len(odo) > 50, f"{len(odo)} ODOMETRY sent by the daemon and none held back as late"
    t = np.array([m.time_usec * 1e-6 for m in odo])
    yaw = np.array([_yaw_of_q(m.q) for m in odo])
    var = np.array([m.pose_covariance[20] for m in odo])
    err_rad = np.abs(angle_diff_rad(yaw, _truth_yaw_at(truth, t)))
    err = np.degrees(err_rad)
    rms = float(np.sqrt(np.mean(err ** 2)))
    within3 = float(np.mean(err_rad <= 3.0 * np.sqrt(var)))
    print(f"ODOMETRY yaw: n={len(odo)} rms={rms:.2f} max={err.max():.2f} deg within 3 sigma {within3:.3f} "
          f"median sigma {np.degrees(np.median(np.sqrt(var))):.2f} deg")
    assert np.all(np.isfinite(yaw)) and np.all(var > 0.0)
    assert rms <= MAX_HEADING_RMS_DEG
    assert err.max() <= MAX_HEADING_ERR_DEG
    assert within3 >= MIN_WITHIN_3SIGMA
