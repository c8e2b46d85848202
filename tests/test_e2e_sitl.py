"""End to end: `azimuthd sim` and `azimuthd run` as separate OS processes over UDP on loopback.

GIVEN the default scenario (inclined rail, 60 s on the launcher, then a boost and a climb)
WHEN the daemon runs against the simulator
THEN the daemon's HEARTBEAT reaches the autopilot, it requests its streams with
     SET_MESSAGE_INTERVAL, and the ATTITUDE it sends stays within 2 deg of the truth in roll and
     pitch on the launcher and over the first 60 s of the flight after launch, wherever it has
     seen every IMU interval so far; after an interval it reports not seen (its own "IMU gap"
     events, FC time) within the re-levelling bound below.

The machine may be busy (the simulator then flies slower than SPEED and the daemon may fall
behind): the flight is waited for to its end (a wall-clock deadline only detects a hang), and
nothing is counted per wall-clock second. A daemon that falls behind loses datagrams in its full
socket buffer (seconds of IMU at once on a loaded machine: 2-6 s gaps measured on 2026-12-02 at
load ~25); what it lost is read from its own log, never guessed from timing.
"""
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import Sitl, angle_diff_rad  # noqa: E402

SPEED = 2.0
"""Twice real time: 400 RAW_IMU per second, which the daemon processes in ~0.6 of a core (its
Pipeline costs 1.2-1.4 ms CPU per 200 Hz IMU sample: 1188 us at 7d57775, 1363 us at 34ab8a8, measured
2026-12-02 by replaying this flight's recorded input). At 4x (800 per second) it needs more than the
whole core and drops seconds of input at once from its full socket buffer even on an idle machine:
the tilt errors of 2.1-4.2 deg seen in session 3 and 4 (see MAX_TILT_AFTER_GAP_DEG)."""
FLIGHT_S = 130.0   # 60 s at rest + 70 s of flight
HANG_S = 900.0
"""Only a hang detector: the flight takes what the machine gives it (65 s idle, minutes busy)."""
pytestmark = pytest.mark.timeout(HANG_S + 300)  # the flight's own hang detector decides, not the suite's 600 s


@pytest.fixture(scope="module")
def flight():
    with Sitl(scenario="inclined_rail", speed=SPEED, seed=3, tap=True,
              sim_args=["--duration", str(FLIGHT_S)]) as s:
        finished = s.wait_for(lambda: s.sim.poll() is not None, HANG_S)
    assert finished and s.sim.returncode == 0, f"simulator hung or failed; see {s.workdir}"
    return s


def _sim_account(flight) -> dict:
    """The simulator's own account of the flight (its ``sim stopped`` line)."""
    m = re.search(r"sim stopped: simulated_s=([\d.]+) .* sent=(\{.*\})", flight.log("sim"))
    assert m, "no 'sim stopped' line in the simulator's log"
    return {"simulated_s": float(m.group(1)), "sent": json.loads(m.group(2))}


def test_the_whole_flight_was_flown(flight):
    own = _sim_account(flight)
    assert own["simulated_s"] == pytest.approx(FLIGHT_S, abs=0.05)
    # 200 Hz of its clock from the daemon's request (within its first seconds) to the end
    assert 200 * (FLIGHT_S - 10.0) <= own["sent"]["RAW_IMU"] <= 200 * FLIGHT_S + 1


def test_daemon_heartbeat_reaches_the_autopilot(flight):
    times = [t for t, m in flight.tap.from_daemon if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191]
    hb = [m for m in flight.tap.sent_by_daemon("HEARTBEAT") if m.get_srcComponent() == 191]
    assert len(hb) >= 3
    # 1 Hz of the daemon's clock: never faster (a late loop only makes it slower; the rate itself
    # is tests/test_mavlink_link.py's); one interval of slack for the tap's own receive delays
    assert len(hb) - 1 <= times[-1] - times[0] + 1.0
    assert hb[0].type == 18 and hb[0].autopilot == 8  # ONBOARD_CONTROLLER, INVALID
    assert hb[0].get_srcSystem() == 1  # the vehicle's system id, learned from the FC


def test_daemon_requested_its_streams(flight):
    cmds = [m for m in flight.tap.sent_by_daemon("COMMAND_LONG") if m.command == 511]  # SET_MESSAGE_INTERVAL
    requested = {int(m.param1): m.param2 for m in cmds}
    assert requested.get(27) == pytest.approx(5000.0)      # RAW_IMU at 200 Hz: 5000 us
    assert requested.get(29) == pytest.approx(20000.0)     # SCALED_PRESSURE at 50 Hz
    assert 30 in requested                                 # the FC's ATTITUDE


MAX_TILT_ERR_DEG = 2.0
"""Worst roll/pitch error of what the daemon sent while it had seen every IMU interval (at rest, and
after the launch up to its first reported gap). The same pipeline replayed offline on everything
the simulator sent in a flight whose daemon lost 6953 datagrams: worst 1.64 deg roll / 1.45 deg
pitch in the 60 s after launch, 0.97 / 1.01 deg at rest (measured 2026-12-02 by recording what the
simulator sent and replaying it offline through the Pipeline); 2.0 deg = that plus 0.36 deg of margin."""
MAX_TILT_AFTER_GAP_DEG = 5.0
"""After an IMU interval the daemon did not see (seconds lost to a full socket buffer), method C has
no attitude propagation over it: its covariance is widened (polar_attitude_unseen) and roll/pitch
are re-levelled on the specific force, which in this climb-out's turbulence carries 0.1-0.45 m/s^2
of 2-s-mean vehicle acceleration (truth log), i.e. up to 2.6 deg, on top of the 1 deg accelerometer
bias the rest levelling cannot separate. Measured after 2-6 s gaps: 4.15 deg (gaps of 2.0, 3.5, 3.8
and 5.9 s) and 2.88 deg (2.6 and 3.4 s) on 2026-12-02; 5.0 deg = the worst plus 0.85 deg."""
GAP_RE = re.compile(r"IMU gap of ([\d.]+) s \(> [\d.]+ s\) at FC time ([\d.]+) s")


def _reported_gaps(flight) -> list[tuple[float, float]]:
    """The IMU intervals (FC time, s) the daemon reports it did not see: its time_gap events."""
    return [(float(end) - float(gap), float(end)) for gap, end in GAP_RE.findall(flight.log("daemon"))]


def test_attitude_within_2_deg_of_truth(flight):
    truth = flight.truth()
    att = np.array([row[:4] for row in flight.listener.attitude]).reshape(-1, 4)
    assert len(att) > 0, "no ATTITUDE from the daemon reached the ground-station listener"
    t = att[:, 0]
    idx = np.clip(np.searchsorted(truth["time_boot_s"], t), 0, len(truth["time_boot_s"]) - 1)
    launch = truth["launch_time_boot_s"]
    assert 55.0 < launch < 65.0
    d_roll = np.degrees(np.abs(angle_diff_rad(att[:, 1], truth["roll_rad"][idx])))
    d_pitch = np.degrees(np.abs(angle_diff_rad(att[:, 2], truth["pitch_rad"][idx])))
    gaps = _reported_gaps(flight)
    first_gap = min((g0 for g0, _ in gaps), default=np.inf)
    rest = (t >= t[0]) & (t < launch)
    flight60 = (t >= launch) & (t <= launch + 60.0)
    # ATTITUDE goes out at [outputs] attitude_hz of the daemon's clock: enough to compare
    assert np.count_nonzero(rest) > 100, f"{np.count_nonzero(rest)} ATTITUDE at rest"
    assert np.count_nonzero(flight60) > 100, f"{np.count_nonzero(flight60)} ATTITUDE in flight"
    print(f"IMU gaps the daemon reported (FC s): {gaps}")
    for name, window, bound in (("all seen", (rest | flight60) & (t < first_gap), MAX_TILT_ERR_DEG),
                                ("after a gap", flight60 & (t >= first_gap), MAX_TILT_AFTER_GAP_DEG)):
        if not np.any(window):
            continue
        worst = max(np.max(d_roll[window]), np.max(d_pitch[window]))
        print(f"{name}: {np.count_nonzero(window)} ATTITUDE, worst roll {np.max(d_roll[window]):.2f} deg, "
              f"pitch {np.max(d_pitch[window]):.2f} deg")
        assert worst < bound, f"{name}: worst tilt error {worst:.2f} deg >= {bound} deg; gaps {gaps}"
    # the attitude really moved: the climb-out pitch differs from the rail's 15 deg
    assert np.ptp(np.degrees(att[flight60, 2])) > 5.0


def test_daemon_log_is_clean(flight):
    log = flight.log("daemon")
    assert "level=error" not in log
    assert "event=levelled" in log and "msg=launch event=phase" in log
