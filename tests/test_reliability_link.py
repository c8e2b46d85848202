"""Link faults end to end (issue 10): the simulator's fault switches against the daemon process.

GIVEN the simulator (real time) with 10 % of its packets dropped, 1 % corrupted, 1 % duplicated,
1 % reordered, a 3 s outage on the launcher, a 10 s outage in flight (no traffic either way) and an FC reboot later in flight (2 s silence, time_boot restarts,
stream rates back to the defaults), a UDP tap between it and the daemon
WHEN the daemon flies it
THEN it never crashes; it reports the link lost and restored, its ATTITUDE resumes within 2 s
of the simulator's clock after the link's return and it re-requests its streams with
SET_MESSAGE_INTERVAL after the outage and after the reboot; the reboot is handled (fc_reboot event, the FC time it stamps its
ATTITUDE with never goes back) and its roll/pitch after both faults stay close to the truth;
the daemon's counts of lost and bad packets in its "stopped" line are not zero.

Nothing depends on the machine's speed: "when" is the simulator's clock (the FC time its
messages carry, which the tap records as it forwards them) and the order of messages in the
tap's one timeline; the wall clock only detects a hang. How long recovery took in wall time is
printed, a figure, not a pass mark. The one local-clock check, link_lost, cannot trip in a daemon
that was more than (outage - link_timeout_s) behind its input when the outage began (it reads its
backlog through the silence): how far behind is measured in the tap's timeline and said, and only
then are the outage's local-clock checks skipped. After the simulator's end the daemon works off
its queue before it is stopped.
"""
import re
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import Sitl, angle_diff_rad  # noqa: E402
from conftest import udp_rx_queue_bytes, wait_progressing  # noqa: E402

REST_S = 20.0
OUTAGE = (32.0, 42.0)
REBOOT_AT_S, REBOOT_SILENCE_S = 55.0, 2.0
END_S = 72.0
PRELAUNCH_OUTAGE = (8.0, 11.0)
FAULTS = ["--set", "faults.drop_rate=0.10", "--set", "faults.corrupt_rate=0.01",
          "--set", "faults.duplicate_rate=0.01", "--set", "faults.reorder_rate=0.01",
          "--set", f"faults.outages=[[{PRELAUNCH_OUTAGE[0]}, {PRELAUNCH_OUTAGE[1]}], [{OUTAGE[0]}, {OUTAGE[1]}]]",
          "--set", f"faults.reboot_at_s={REBOOT_AT_S}", "--set", f"faults.reboot_silence_s={REBOOT_SILENCE_S}",
          "--set", f"launcher.rest_s={REST_S}", "--duration", str(END_S)]


TAP_TYPES = ("ATTITUDE", "RAW_IMU", "SCALED_PRESSURE", "HEARTBEAT")
"""What the tap records of the simulator's traffic: the daemon takes any message of its FC as the link's
return (HEARTBEAT and RAW_IMU often come before the first ATTITUDE after a silence)."""


@pytest.fixture(scope="module")
def flight():
    with Sitl(scenario="inclined_rail", speed=1.0, seed=11, tap=True, sim_args=FAULTS,
              config_overrides={"launch": {}}, tap_record_to_daemon=TAP_TYPES) as s:
        finished = s.wait_for(lambda: s.sim.poll() is not None, HANG_S)
        if finished:
            # a daemon behind its input (a busy machine) works off its queue before it is stopped:
            # done when its ATTITUDE reaches the flight's last 2 s in the FC's clock (it resumes
            # after the reboot ~2 s short of the simulator's time: 70.2 s at the end, 2026-12-02),
            # or when neither its FC time nor its socket's queue moved for DRAIN_QUIET_S
            newest = lambda: s.listener.attitude[-1][0] if s.listener.attitude else None  # noqa: E731
            wait_progressing(lambda: (newest() or 0.0) >= END_S - 2.0,
                             lambda: (newest(), udp_rx_queue_bytes(s.fc_port)), "drain", stall_s=DRAIN_QUIET_S,
                             hang_s=HANG_S, stall_ok=True)
            print(f"drained: the daemon's last ATTITUDE at FC time {newest()} s")
    assert finished, f"hang: the simulator did not finish in {HANG_S:g} s; see {s.workdir}"
    return s


HANG_S = 900.0
"""Only a hang detector: the 72 s flight takes what the machine gives it."""
DRAIN_QUIET_S = 10.0
"""After the simulator's end: no newer ATTITUDE and no change in its socket's queue for this long
means the daemon has nothing left to process (a hang detector, nothing counted per wall second)."""
pytestmark = pytest.mark.timeout(HANG_S + 300)  # the flight's own hang detector decides, not the suite's 600 s


def _sim_attitude(flight) -> list:
    """(tap forward time, message) of the simulator's ATTITUDE messages."""
    return [(t, m) for t, m in flight.tap.to_daemon if m.get_type() == "ATTITUDE"]


def _tap_time_of_sim_fc(flight, pred) -> float:
    """The tap's clock when it forwarded the simulator's first ATTITUDE whose FC time (s) meets
    ``pred``: the instant the simulator had reached that FC time, in the tap's timeline."""
    return next(t for t, m in _sim_attitude(flight) if pred(m.time_boot_ms / 1000.0))


def _fc_time_s(m) -> float | None:
    """The FC time a simulator message carries (None: a HEARTBEAT carries none)."""
    if m.get_type() == "RAW_IMU":
        return m.time_usec * 1e-6
    return m.time_boot_ms / 1000.0 if hasattr(m, "time_boot_ms") else None


def _tap_time_link_back(flight, t_back_s: float) -> float:
    """The tap's clock when it forwarded the simulator's first message after a silence that ended at
    FC time ``t_back_s``: the first timed message at or after it, or the HEARTBEATs forwarded just
    before that one (a HEARTBEAT carries no time; the one before the silence is followed by 400 Hz
    RAW_IMU, and a packet the simulator's fault model held back for reordering comes after, not
    before, the first new one)."""
    rows = flight.tap.to_daemon
    i = next(i for i, (_t, m) in enumerate(rows) if (fc := _fc_time_s(m)) is not None and fc >= t_back_s - 1e-6)
    while i > 0 and rows[i - 1][1].get_type() == "HEARTBEAT":
        i -= 1
    return rows[i][0]


def _outage_hidden(flight) -> tuple[bool, float]:
    """link_lost is a local-clock timeout (link_timeout_s): a daemon more than (outage -
    link_timeout_s) behind its input when the outage began reads its backlog through the silence
    and cannot see it. Returns (hidden, how far behind in wall s): from the tap's forwarding the
    simulator's first ATTITUDE 1 s before the outage to the daemon's first ATTITUDE of that FC time
    reaching the listener (one monotonic clock, this process)."""
    with open(flight.config_path, "rb") as f:
        timeout_s = tomllib.load(f)["mavlink"]["link_timeout_s"]
    t_fc = OUTAGE[0] - 1.0
    lag_s = next(r[4] for r in flight.listener.attitude if r[0] >= t_fc) - _tap_time_of_sim_fc(flight, lambda t: t >= t_fc)
    print(f"daemon behind its input 1 s before the outage: {lag_s:.2f} s (wall)")
    return lag_s > OUTAGE[1] - OUTAGE[0] - timeout_s, lag_s


GAP_LINE = re.compile(r"IMU gap of ([\d.]+) s \(> [\d.]+ s\) at FC time ([\d.]+) s")


def _outage_events(log: str) -> str:
    """The daemon's log from its IMU gap line for the pre-launch outage to the one for the in-flight
    outage (both carry the FC time the data came back): a link_lost and a link_restored in it are
    the outage's, not the other silences' (the pre-launch one, the reboot, the simulator's end)."""
    lines = log.splitlines()

    def gap_line(t_back: float) -> int | None:
        return next((i for i, ln in enumerate(lines) if (m := GAP_LINE.search(ln))
                     and t_back <= float(m.group(2)) < t_back + 0.5), None)
    i0, i1 = gap_line(PRELAUNCH_OUTAGE[1]), gap_line(OUTAGE[1])
    return "\n".join(lines[i0 + 1:i1 + 1]) if i0 is not None and i1 is not None else ""


def _daemon_after(flight, t0: float, t1: float = float("inf"), command: int | None = None, mtype="COMMAND_LONG"):
    return [m for t, m in flight.tap.from_daemon
            if t0 < t < t1 and m.get_type() == mtype and (command is None or m.command == command)]


def test_no_crash_and_faults_counted(flight):
    log = flight.log("daemon")
    assert "Traceback" not in log
    assert flight.daemon.returncode == 0
    m = re.search(r"msg=stopped .*link_seq_lost=(\d+) link_bad_data=(\d+) link_stale_drops=(\d+) "
                  r"link_losses=(\d+) fc_reboots=(\d+)", log)
    assert m, "no stopped line with link counters"
    seq_lost, bad, stale, losses, reboots = map(int, m.groups())
    print(f"daemon link counters: seq_lost {seq_lost} bad_data {bad} stale_drops {stale} link_losses {losses} "
          f"fc_reboots {reboots}")
    # link_lost is a local-clock timeout (link_timeout_s 2 s): the 10 s outage trips it unless the
    # daemon was more than 8 s behind its input when it began (_outage_hidden: measured and said);
    # the 3 s and the 2 s silences trip it only when the daemon is not behind, so they are checked
    # in the FC's clock (test_prelaunch_outage_...)
    hidden, lag_s = _outage_hidden(flight)
    assert seq_lost > 1000 and bad > 10 and stale > 10 and reboots == 1
    assert losses >= 1
    assert "event=link_lost" in _outage_events(log) or hidden, \
        f"the {OUTAGE[1] - OUTAGE[0]:g} s outage not reported (daemon {lag_s:.2f} s behind)"


def test_prelaunch_outage_levelling_still_done(flight):
    """A 3 s outage on the launcher (pre-launch): reported, and the daemon still levels and
    detects the launch."""
    log = flight.log("daemon")
    gaps = [(float(g), float(t)) for g, t in GAP_LINE.findall(log)]
    span_s = PRELAUNCH_OUTAGE[1] - PRELAUNCH_OUTAGE[0]
    assert any(span_s <= g < span_s + 0.5 and PRELAUNCH_OUTAGE[1] <= t < PRELAUNCH_OUTAGE[1] + 0.5 for g, t in gaps), gaps
    assert "event=levelled" in log and "msg=launch event=phase" in log


def test_outage_reported_recovered_within_2_s_and_streams_rerequested(flight):
    log = flight.log("daemon")
    att = flight.listener.attitude
    back = [r for r in att if r[0] >= OUTAGE[1]]
    assert back, "no ATTITUDE after the outage"
    assert back[0][0] < OUTAGE[1] + 2.0, f"ATTITUDE resumed at FC time {back[0][0]:.2f} s (link back at {OUTAGE[1]})"
    hidden, lag_s = _outage_hidden(flight)
    log = _outage_events(log)
    if hidden and "event=link_lost" not in log:
        pytest.skip(f"the daemon was {lag_s:.1f} s behind its input when the outage began (a busy machine): "
                    f"it read its backlog through the silence, so its local-clock link_lost and the "
                    f"re-request on link_restored could not happen; see {flight.workdir}")
    assert "event=link_lost" in log and "event=link_restored" in log
    t_return = _tap_time_link_back(flight, OUTAGE[1])
    t_3s_later = _tap_time_of_sim_fc(flight, lambda t: OUTAGE[1] + 3.0 <= t < REBOOT_AT_S)
    print(f"outage recovery: ATTITUDE {back[0][4] - t_return:.3f} s (wall) after the link returned")
    assert _daemon_after(flight, t_return, t_3s_later, command=511), \
        "streams not re-requested within 3 s of the simulator's clock after the outage"


def test_fc_reboot_handled_not_integrated_as_a_jump(flight):
    log = flight.log("daemon")
    assert "event=fc_reboot" in log
    att = flight.listener.attitude
    t = np.array([r[0] for r in att])
    back = np.nonzero(np.diff(t) < 0)[0]
    assert back.size == 0, (f"the daemon's ATTITUDE time went back {back.size} times, first "
                            f"{t[back[0]]:.3f} -> {t[back[0] + 1]:.3f} s" if back.size else "")
    # the simulator's ATTITUDE stream stops at its reboot (rates back to defaults) and comes back
    # with its clock restarted only once asked again: the daemon asked after the reboot
    sim_att = [(tt, m.time_boot_ms / 1000.0) for tt, m in _sim_attitude(flight)]
    i_last_old = max(i for i, (_tt, fc) in enumerate(sim_att) if fc < REBOOT_AT_S + 0.01 and fc > REBOOT_AT_S - 1.0)
    new_boot = [(tt, fc) for tt, fc in sim_att[i_last_old + 1:] if fc < REBOOT_AT_S - 1.0]
    assert new_boot and new_boot[0][1] < REBOOT_SILENCE_S + 10.0, "the simulator's ATTITUDE never resumed after its reboot"
    t_old, t_new = sim_att[i_last_old][0], new_boot[0][0]
    assert _daemon_after(flight, t_old, t_new, command=511), "streams not re-requested after the reboot"
    # and the daemon's own ATTITUDE resumed once the new boot's data came
    resumed = _daemon_after(flight, t_new, mtype="ATTITUDE")
    assert resumed, "no ATTITUDE from the daemon after the reboot"
    rx = np.array([r[4] for r in att])
    print(f"reboot: ATTITUDE {rx[rx > t_new][0] - t_new:.3f} s (wall) after the simulator's first new-boot ATTITUDE"
          if np.any(rx > t_new) else "reboot: no ATTITUDE at the listener after the new boot")


def test_attitude_close_to_truth_after_the_faults(flight):
    """Before the outage, after it and after the reboot: roll and pitch within 3 deg of the truth
    (the daemon keeps its FC time continuous across the reboot; at speed 1 it stays on the
    simulator's time_s within the processing latency)."""
    truth = flight.truth()
    att = np.array([r[:5] for r in flight.listener.attitude])
    t = att[:, 0]
    idx = np.clip(np.searchsorted(truth["time_s"], t), 0, len(truth["time_s"]) - 1)
    d_roll = np.degrees(np.abs(angle_diff_rad(att[:, 1], truth["roll_rad"][idx])))
    d_pitch = np.degrees(np.abs(angle_diff_rad(att[:, 2], truth["pitch_rad"][idx])))
    worst = {}
    for name, (a, b) in {"before": (REST_S + 2, OUTAGE[0]), "after_outage": (OUTAGE[1] + 3, REBOOT_AT_S),
                         "after_reboot": (REBOOT_AT_S + REBOOT_SILENCE_S + 3, END_S - 1)}.items():
        w = (t >= a) & (t < b)
        assert np.count_nonzero(w) > 100, name
        worst[name] = (float(np.max(d_roll[w])), float(np.max(d_pitch[w])))
    print("worst roll/pitch error, deg:", {k: (round(a, 2), round(b, 2)) for k, (a, b) in worst.items()})
    for name, (r, p) in worst.items():
        assert r < 3.0 and p < 3.0, f"{name}: roll {r:.2f} pitch {p:.2f} deg"
