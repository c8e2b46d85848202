"""The operator's first run: the README's sim + run pair works as written (this test runs the
commands it shows, and stands where QGroundControl would, on UDP 14550), and `make run`'s summary
tells the truth (its verdict and the daemon's counters, from bench/live_demo.py's own functions)."""
from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
import live_demo  # noqa: E402

WAIT_S = 150.0  # a bound for a busy machine, never a timing assertion
MARKER = "<!-- first-run:"


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    start = text.index(MARKER)
    block = re.search(r"```sh\n(.*?)```", text[start:], re.S)
    assert block, "no ```sh block after the first-run marker in README.md"
    return [ln for ln in block.group(1).splitlines() if ln.strip() and not ln.startswith("#")]


def test_readme_pair_as_written_reaches_a_ground_station(tmp_path):
    cmds = readme_commands()
    assert [c.split()[0] for c in cmds] == ["sed", "azimuthd", "azimuthd"], cmds
    (tmp_path / "systemd").symlink_to(ROOT / "systemd")  # the commands run from a checkout
    # the example config leaves state_dir empty: $STATE_DIRECTORY, else ~/.local/state/azimuthd (the
    # tester's own): the daemon's calibrations go to this test's directory instead
    env = dict(os.environ, PATH=f"{ROOT / '.venv' / 'bin'}{os.pathsep}{os.environ['PATH']}",
               STATE_DIRECTORY=str(tmp_path / "state"))
    subprocess.run(cmds[0], shell=True, cwd=tmp_path, env=env, check=True, timeout=60)

    # the ground station: where QGroundControl listens
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:14550", source_system=255, source_component=190)
    seen: dict[tuple[int, int, str], int] = {}
    procs, logs = [], []
    try:
        for i, cmd in enumerate(cmds[1:]):
            logs.append(open(tmp_path / f"cmd{i}.log", "w"))
            procs.append(subprocess.Popen(shlex.split(cmd), cwd=tmp_path, env=env, stdout=logs[-1],
                                          stderr=subprocess.STDOUT))
        # the FC, azimuthd's HEARTBEAT and its NAMED_VALUE_FLOAT (azimuth, heading sigma, phase):
        # what a ground station shows without any FC parameter set (ODOMETRY waits for the FC's
        # parameters, ATTITUDE goes to the FC link only when configured: docs/VEHICLE.md)
        wanted = {(1, 1, "HEARTBEAT"), (1, 191, "HEARTBEAT"), (1, 191, "NAMED_VALUE_FLOAT")}
        t_end = time.monotonic() + WAIT_S
        while time.monotonic() < t_end and not wanted <= set(seen):
            msg = gcs.recv_match(blocking=True, timeout=0.5)
            if msg is not None and msg.get_type() != "BAD_DATA":
                key = (msg.get_srcSystem(), msg.get_srcComponent(), msg.get_type())
                seen[key] = seen.get(key, 0) + 1
            for p, cmd in zip(procs, cmds[1:]):
                assert p.poll() is None, f"{cmd!r} exited {p.returncode}"
        # THEN the ground station sees the simulated FC and azimuthd
        assert wanted <= set(seen), f"missing {wanted - set(seen)}; seen {sorted(seen)}"
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        codes = [p.wait(30) for p in procs]
        for f in logs:
            f.close()
        gcs.close()
    text = "".join((tmp_path / f"cmd{i}.log").read_text() for i in range(len(procs)))
    assert codes == [0, 0], text
    assert "Traceback" not in text and "level=error" not in text, text


def _summary(**over) -> dict:
    base = {"simulated_flown_s": 120.0, "speed_achieved_x": 3.9, "imu_lost_fraction": 0.0,
            "roll_rms_deg": 0.6, "pitch_rms_deg": 0.2, "heading_rms_deg": 0.5, "daemon_errors": 0,
            "attitude_received_hz": 48.0, "attitude_configured_hz": 50.0}
    return {**base, **over}


def test_verdict_pass_at_the_thresholds_and_each_failure_named():
    assert live_demo.verdict(_summary(), 120.0, 4.0) == []
    assert live_demo.verdict(_summary(roll_rms_deg=1.0, heading_rms_deg=2.0, imu_lost_fraction=0.01), 120.0, 4.0) == []
    assert live_demo.verdict(_summary(attitude_received_hz=25.0), 120.0, 4.0) == []
    why = live_demo.verdict(_summary(simulated_flown_s=37.5, speed_achieved_x=0.26, imu_lost_fraction=0.103,
                                     heading_rms_deg=2.5, daemon_errors=2, attitude_received_hz=0.75), 120.0, 4.0)
    assert why == ["the simulator flew only 37.5 s of the 120 s asked (< 95%) at 0.26x instead of 4x: the machine is "
                   "too busy for this speed; try --speed 1",
                   "the daemon lost 10.3% of the IMU messages (> 1%)",
                   "heading RMS 2.50 deg > 2 deg",
                   "ATTITUDE reached the ground station at 0.8 Hz, < 50% of the configured 50 Hz",
                   "the daemon logged 2 error(s)"]
    nothing = live_demo.verdict(_summary(roll_rms_deg=None, pitch_rms_deg=None, heading_rms_deg=None,
                                         imu_lost_fraction=None), 120.0, 4.0)
    assert nothing == ["the IMU loss could not be counted (no end-of-run line from the simulator or the daemon)",
                       "no roll was received from the daemon", "no pitch was received from the daemon",
                       "no heading was received from the daemon"]


def test_a_daemon_that_died_before_the_harness_stopped_it_fails_the_verdict_with_its_last_line():
    # GIVEN the daemon exited on its own mid-flight (a crash: its stderr ends with the exception)
    crash = "Traceback (most recent call last):\n  File ...\nValueError: manoeuvre_speed_m_s must be > 0, got 0.0\n"
    last = live_demo.last_line(crash)
    # WHEN the verdict is drawn, THEN it fails and says so even though the daemon logged no error line
    why = live_demo.verdict(_summary(daemon_exited_early=True, daemon_exit_code=1, daemon_last_line=last), 120.0, 4.0)
    assert why == ["the daemon exited (code 1) before the harness stopped it: "
                   "ValueError: manoeuvre_speed_m_s must be > 0, got 0.0"]
    assert live_demo.last_line("") == ""


def test_the_daemons_own_counters_and_warnings_are_read_from_its_log():
    log = "\n".join([
        'ts=1 level=warning logger=azimuthd.daemon msg="gap: IMU gap of 0.812 s (> 0.5 s): not integrated across" event=imu_input',
        'ts=2 level=warning logger=azimuthd.daemon msg="gap: IMU gap of 3.900 s (> 0.5 s): not integrated across" event=imu_input',
        'ts=3 level=error logger=azimuthd.daemon msg="transport failed" event=transport_error',
        'ts=4 level=info logger=azimuthd.daemon msg=stopped imu_samples=100 imu_rejected=1 sent="{}" imu_messages=120 '
        'link_accepted=300 link_seq_lost=7 link_bad_data=0 link_stale_drops=2 link_losses=1 fc_reboots=0 kernel_rx_drops=2507',
    ])
    h = live_demo.daemon_health(log)
    assert (h["imu_messages"], h["link_seq_lost"], h["kernel_rx_drops"], h["link_losses"]) == (120, 7, 2507, 1)
    assert (h["imu_gaps"], h["imu_gap_max_s"], h["errors"]) == (2, 3.9, 1)
    assert h["warnings"]["imu_input"][0] == 2


def test_the_simulators_end_line_is_read():
    line = ('2026-12-01 20:51:42,000 azimuthd.sim INFO sim stopped: simulated_s=37.460 wall_s=146.300 '
            'achieved_speed=0.256 sent={"HEARTBEAT":37,"RAW_IMU":7480}')
    assert live_demo.sim_outcome(line) == {"simulated_s": 37.46, "wall_s": 146.3,
                                           "sent": {"HEARTBEAT": 37, "RAW_IMU": 7480}}
    assert live_demo.sim_outcome("nothing here") == {}
