"""A daemon killed in flight and restarted (what systemd's Restart=on-failure does), end to end.

GIVEN the simulator flying the default scenario and the daemon as processes
WHEN the daemon is SIGKILLed 15 s after the launch and started again 2 s later (RestartSec=2s)
THEN the new daemon knows it starts in flight (the FC says armed and the pitot says airspeed):
     it reports ``started_in_flight``, does not level on the moving vehicle, reports no launch
     and no method-A solution, and the roll/pitch it sends stay within 4 deg of the truth in
     the first 20 s and within 2 deg after (a daemon that levelled on the climb would be off by
     the climb angle).

"15 s after the launch" is the simulator's clock, not the wall clock: the launch's FC time is
the one on the daemon's ATTITUDE when it logs the launch, the simulator's live FC time the one on
its ATTITUDE as the tap forwards it (a daemon that is behind would be killed late otherwise); and the flight goes on until the restarted daemon has sent AFTER_RESTART_FC_S of
it (however long its start took on a busy machine): a busy machine slows the flight, not the
test's meaning. Wall-clock deadlines only detect a hang.
"""
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import ROOT, Sitl, angle_diff_rad  # noqa: E402

SPEED = 4.0
AFTER_RESTART_FC_S = 45.0
"""FC seconds of the restarted daemon's ATTITUDE compared: the first 20 s and 25 s after."""
FIRST_20S_BOUND_DEG = 4.0
"""Measured 2.7-3.2 deg in the first seconds: the restarted daemon has no at-rest gyro bias and
starts from the FC's attitude (trusted here); C then pulls it in."""
AFTER_20S_BOUND_DEG = 2.0
"""As the first 60 s of a normal flight (tests/test_e2e_sitl.py); measured <= 1.3 deg."""
HANG_S = 900.0
"""Only a hang detector."""
pytestmark = pytest.mark.timeout(HANG_S + 300)  # the flight's own hang detectors decide, not the suite's 600 s


def _latest_fc_s(s) -> float:
    """FC time of the newest ATTITUDE the daemon sent the listener (-inf before the first)."""
    att = s.listener.attitude
    return att[-1][0] if att else float("-inf")


@pytest.fixture(scope="module")
def restarted():
    with Sitl(scenario="inclined_rail", speed=SPEED, seed=6, sim_args=["--duration", "0"], tap=True,
              tap_record_to_daemon=("ATTITUDE",)) as s:
        assert s.wait_for(lambda: "msg=launch event=phase" in s.log("daemon"), HANG_S)
        t_launch_logged = _latest_fc_s(s)
        assert s.wait_for(lambda: bool(s.tap.to_daemon)
                          and s.tap.to_daemon[-1][1].time_boot_ms / 1000.0 >= t_launch_logged + 15.0, HANG_S)
        s.daemon.send_signal(signal.SIGKILL)
        s.daemon.wait(10)
        killed_at = time.monotonic()
        time.sleep(2.0)
        out = open(s.workdir / "daemon2.log", "w")
        s.daemon = subprocess.Popen(s.daemon_cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)
        restarted_att = lambda: [r[0] for r in s.listener.attitude if r[4] > killed_at]  # noqa: E731
        assert s.wait_for(lambda: len(restarted_att()) > 1 and restarted_att()[-1] - restarted_att()[0]
                          >= AFTER_RESTART_FC_S, HANG_S), "hang: the restarted daemon's ATTITUDE did not cover the flight"
        restarted_log = (s.workdir / "daemon2.log").read_text()
    return s, killed_at, restarted_log


def test_the_restarted_daemon_knows_it_is_in_flight(restarted):
    _s, _k, log = restarted
    assert "event=started_in_flight" in log, log[-3000:]
    assert "event=levelled" not in log
    assert "msg=launch event=phase" not in log
    assert "level=error" not in log


def test_attitude_after_the_restart_stays_near_the_truth(restarted):
    s, killed_at, _log = restarted
    truth = s.truth()
    att = np.array([row for row in s.listener.attitude if row[4] > killed_at])
    assert len(att) > 100, "the restarted daemon sent too little ATTITUDE"
    t = att[:, 0]
    idx = np.clip(np.searchsorted(truth["time_boot_s"], t), 0, len(truth["time_boot_s"]) - 1)
    d_roll = np.degrees(np.abs(angle_diff_rad(att[:, 1], truth["roll_rad"][idx])))
    d_pitch = np.degrees(np.abs(angle_diff_rad(att[:, 2], truth["pitch_rad"][idx])))
    for lo in range(0, int(t[-1] - t[0]) + 1, 5):
        w = (t >= t[0] + lo) & (t < t[0] + lo + 5)
        if w.any():
            print(f"  +{lo:3d}..{lo + 5:3d} s: roll max {d_roll[w].max():.2f}, pitch max {d_pitch[w].max():.2f} deg")
    print(f"after restart: {len(att)} ATTITUDE, roll max {d_roll.max():.2f} deg, pitch max {d_pitch.max():.2f} deg, "
          f"first at FC time {t[0]:.1f} s (launch {truth['launch_time_boot_s']:.1f} s)")
    assert t[0] > truth["launch_time_boot_s"] + 15.0  # it really restarted in flight
    early = t < t[0] + 20.0
    assert d_roll[early].max() < FIRST_20S_BOUND_DEG and d_pitch[early].max() < FIRST_20S_BOUND_DEG
    assert np.count_nonzero(~early) > 100
    assert d_roll[~early].max() < AFTER_20S_BOUND_DEG and d_pitch[~early].max() < AFTER_20S_BOUND_DEG
