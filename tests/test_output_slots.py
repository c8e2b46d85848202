"""MAVLink output slots on the FC's clock (issue 19 item 5: ATTITUDE at the configured rate under load).

The busy bench (bench/speed.py --busy-only, 300 s at load 16-17.6) lost no IMU sample but sent ATTITUDE
at 49.24 of 50 Hz: the slots were on the local clock, and a loop that woke more than a period late
re-synchronised, so that slot was gone. Now each message belongs to a slot of the FC's time (slot k of a
message at f Hz: FC time [k/f, (k+1)/f)), taken by the first solution whose IMU sample falls in it, sent
with that solution's own values and stamp. What is asserted here, with the daemon's own dispatch and a
stub Pipeline (one solution per sample at the sample's FC time), on a simulated clock (no timing):

- a backlog worked off at once sends exactly the slots the FC-time schedule defines, each its own
  sample's solution, stamps strictly increasing; of the slots older than CATCH_UP_MAX_LAG_S against
  the FC's clock no ODOMETRY is sent and the others at most at their rate of the local clock, the rest
  counted in slots_late;
- the same input sends the same messages whether it is worked off on arrival or after a stall within
  the cap (live and replay agree);
- an idle stream gives the configured rates, each message sent while its own sample is handled;
- an FC reboot starts the slots again; the counters reach the health topic and the stopped line.
"""
from __future__ import annotations

import logging
import math
import types

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.link import LinkEvent
from mavlink_io.outputs import CATCH_UP_MAX_LAG_S, SLOT_EPSILON, OutputScheduler
from mavlink_io.samples import ImuSample
from test_outputs_rates import solution

IMU_HZ = 400.0
TRANSPORT_S = 0.004
"""FC time -> local receive time offset of an undelayed sample (the link's transport delay)."""


class _Link:
    """What the daemon's publishing needs from MavlinkLink: send() and our system id. Each message is
    recorded with the FC time of the sample being handled when it was sent."""

    def __init__(self, current):
        self.sent: list[tuple[float, object]] = []
        self.current = current
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)

    def send(self, msg):
        self.sent.append((self.current[0], msg))
        return True


class _Pipe:
    """What dispatch needs from the Pipeline: one solution per IMU sample, at its FC time."""

    def __init__(self, counters, current):
        self.counters, self.current = counters, current

    def on_imu(self, s):
        self.current[0] = s.time_fc_s
        return solution(t_fc=s.time_fc_s, t_rx=s.time_rx_s, rates=(0.0, 0.0, 0.1))

    def step_imu(self, s):   # the daemon's message path (Pipeline.step_imu: on_imu, with the hot path)
        return self.on_imu(s)

    def propagated_solution(self):
        return None

    def drain_events(self):
        return []

    vehicle = types.SimpleNamespace(pending=False)  # the reboot asks the FC's parameters again

    def on_fc_reboot(self):
        pass


@pytest.fixture(scope="module")
def base_daemon(tmp_path_factory):
    from service.config import validate
    from service.daemon import Daemon
    cfg = validate({"site": {"lat_deg": 47.0, "lon_deg": 8.0}, "zenoh": {"enabled": False},
                    "service": {"state_dir": str(tmp_path_factory.mktemp("state"))},
                    "azimuth": {"solve_in_background": False},
                    "outputs": {"attitude_hz": 50.0, "odometry_hz": 10.0, "attitude_to_fc": True}})
    d = Daemon(cfg)
    yield d
    d.pipeline.solver.close()


@pytest.fixture
def daemon(base_daemon):
    """The daemon with a fresh scheduler, lag meter and stub Pipeline on a simulated clock."""
    from mavlink_io.output_gate import FcLagMeter
    d = base_daemon
    clock, current = [0.0], [math.nan]
    real = (d.pipeline, d.clock)
    d.clock = lambda: clock[0]
    d.pipeline = _Pipe(real[0].counters, current)
    d.link = _Link(current)
    d.scheduler = OutputScheduler(dict(d.scheduler.rates_hz))
    d.scheduler.odometry_allowed = True
    d.fc_lag = FcLagMeter()
    d.last_solution, d._offered_sol, d._last_sent_sol = None, None, None
    d._last_sent_fc_s, d._last_solution_s = -math.inf, -math.inf
    d.test_clock = clock
    yield d
    d.pipeline, d.clock = real
    d.link = None


def _run(d, t_fc: np.ndarray, handled_at) -> None:
    """Each sample received TRANSPORT_S after its FC time and dispatched at local time handled_at(k),
    followed by the loop's own step-end publishing (Daemon.step)."""
    for k, t in enumerate(t_fc):
        d.test_clock[0] = handled_at(k)
        d.dispatch(ImuSample(float(t), float(t) + TRANSPORT_S, np.zeros(3), np.zeros(3), None, "RAW_IMU"))
        d._publish_due(d.test_clock[0])


def _stamps_ms(d, msg_type: str) -> list[int]:
    return [m.time_boot_ms if hasattr(m, "time_boot_ms") else m.time_usec // 1000
            for _, m in d.link.sent if m.get_type() == msg_type]


def _first_in_each_slot(t_fc: np.ndarray, rate_hz: float) -> dict[int, float]:
    """The FC-time schedule, computed here on its own: slot -> FC time of its first sample."""
    out: dict[int, float] = {}
    for t in t_fc:
        out.setdefault(math.floor(t * rate_hz + SLOT_EPSILON), float(t))
    return out


def test_an_idle_stream_gives_the_configured_rates_each_message_sent_with_its_own_sample(daemon):
    # GIVEN 400 Hz samples for 2 s, each handled as it arrives
    t_fc = 100.0 + np.arange(int(2.0 * IMU_HZ)) / IMU_HZ
    _run(daemon, t_fc, lambda k: t_fc[k] + TRANSPORT_S)
    # THEN 50 Hz ATTITUDE, 10 Hz ODOMETRY: exactly one per slot, the slot's first sample
    att = _stamps_ms(daemon, "ATTITUDE")
    assert len(att) == 100 and len(_stamps_ms(daemon, "ODOMETRY")) == 20
    assert att == [int(round(t * 1e3)) for t in _first_in_each_slot(t_fc, 50.0).values()]
    # AND each was sent while its own sample was handled (no wait for a later wake-up)
    assert all(abs(m.time_boot_ms - round(cur * 1e3)) == 0 for cur, m in daemon.link.sent
               if m.get_type() == "ATTITUDE")
    sc = daemon.scheduler
    assert sc.slots_late["ATTITUDE"] == sc.slots_gap["ATTITUDE"] == sc.slots_filled["ATTITUDE"] == 0
    assert daemon.scheduler.next_fill_s() is None  # dense samples: no output timer wakes the loop


@pytest.mark.parametrize("backlog_s", [0.5, 2.0])
def test_a_backlog_sends_exactly_the_fc_time_slots_within_the_cap_and_paces_the_rest(daemon, backlog_s):
    # GIVEN 1 s handled on arrival, then a loop stalled for backlog_s while the FC went on sending,
    # then the backlog handled at once (0.1 ms per sample), then 1 s on arrival again
    n1, nb, n2 = int(IMU_HZ), int(backlog_s * IMU_HZ), int(IMU_HZ)
    t_fc = 100.0 + np.arange(n1 + nb + n2) / IMU_HZ
    wake = t_fc[n1 + nb - 1] + TRANSPORT_S  # the loop wakes when the backlog's last sample is in

    def handled_at(k):
        if k < n1:
            return t_fc[k] + TRANSPORT_S
        if k < n1 + nb:
            return wake + (k - n1) * 1e-4
        return max(t_fc[k] + TRANSPORT_S, wake + nb * 1e-4)

    _run(daemon, t_fc, handled_at)
    # THEN the FC-time schedule, computed here: each slot's first sample; its lag = handled time
    # against the FC's clock
    sched = _first_in_each_slot(t_fc, 50.0)
    index = {float(t): k for k, t in enumerate(t_fc)}
    lag = {slot: handled_at(index[t]) - (t + TRANSPORT_S) for slot, t in sched.items()}
    fresh = {int(round(t * 1e3)) for slot, t in sched.items() if lag[slot] <= CATCH_UP_MAX_LAG_S}
    late = {int(round(t * 1e3)): handled_at(index[t]) for slot, t in sched.items() if lag[slot] > CATCH_UP_MAX_LAG_S}
    att = _stamps_ms(daemon, "ATTITUDE")
    sc = daemon.scheduler
    # every slot within the cap is sent, with its own sample's stamp; nothing else but late slots
    assert fresh <= set(att) and set(att) <= fresh | set(late)
    assert all(b > a for a, b in zip(att, att[1:]))  # strictly increasing, never two with one stamp
    # the late ones (fused by no EKF) go at most at 50 Hz of the local clock: the burst is not flooded
    # out; every slot is sent or counted
    late_sent = sorted(late[ms] for ms in set(att) & set(late))
    assert len(late_sent) >= 1 and all(b - a >= 0.02 - 1e-9 for a, b in zip(late_sent, late_sent[1:]))
    assert sc.slots_behind["ATTITUDE"] == len(late_sent) and sc.slots_gap["ATTITUDE"] == 0
    assert len(att) + sc.slots_late["ATTITUDE"] == len(sched)
    # (handling the backlog itself adds up to nb * 0.1 ms of lag)
    assert (backlog_s - CATCH_UP_MAX_LAG_S) * 50.0 - 2 <= len(late) <= \
        (backlog_s - CATCH_UP_MAX_LAG_S + nb * 1e-4) * 50.0 + 2
    # ODOMETRY: none late (the FC's EKF would misdate it), its own count as before (odometry_late)
    odo = _stamps_ms(daemon, "ODOMETRY")
    assert not set(odo) & set(late) and sc.odometry_late == sc.slots_late["ODOMETRY"] > 0
    assert sc.slots_behind["ODOMETRY"] == 0 and all(b > a for a, b in zip(odo, odo[1:]))


def test_a_stall_within_the_cap_sends_what_the_same_input_sends_on_arrival(daemon, base_daemon):
    """Live and replay send the same set: the slots depend on the FC times of the samples only."""
    t_fc = 100.0 + np.arange(int(1.5 * IMU_HZ)) / IMU_HZ
    _run(daemon, t_fc, lambda k: t_fc[k] + TRANSPORT_S)
    on_arrival = [(m.get_type(), m.time_boot_ms if hasattr(m, "time_boot_ms") else m.time_usec)
                  for _, m in daemon.link.sent]
    # the same input with the loop stalled 0.15 s in the middle (under CATCH_UP_MAX_LAG_S)
    stall_from, stall_to = 200, 260  # samples 200..259 wait for sample 259's arrival
    wake = t_fc[stall_to - 1] + TRANSPORT_S
    daemon.scheduler = OutputScheduler(dict(daemon.scheduler.rates_hz))
    daemon.scheduler.odometry_allowed = True
    daemon.link.sent.clear()
    daemon._last_sent_fc_s, daemon._offered_sol, daemon.last_solution = -math.inf, None, None
    from mavlink_io.output_gate import FcLagMeter
    daemon.fc_lag = FcLagMeter()
    _run(daemon, t_fc, lambda k: wake + (k - stall_from) * 1e-4 if stall_from <= k < stall_to
         else t_fc[k] + TRANSPORT_S + (1e-4 * (stall_to - stall_from) if k >= stall_to else 0.0))
    stalled = [(m.get_type(), m.time_boot_ms if hasattr(m, "time_boot_ms") else m.time_usec)
               for _, m in daemon.link.sent]
    assert stalled == on_arrival and daemon.scheduler.slots_late["ATTITUDE"] == 0


def test_an_fc_reboot_starts_the_slots_again(daemon, monkeypatch):
    t1 = 500.0 + np.arange(200) / IMU_HZ
    _run(daemon, t1, lambda k: t1[k] + TRANSPORT_S)
    n_before = len(_stamps_ms(daemon, "ATTITUDE"))
    # WHEN the FC reboots (its clock starts again near 0) THEN its new samples take slots at once,
    # and the restart is not counted as skipped slots
    daemon.link.fc_autopilot = None
    monkeypatch.setattr(daemon.fc_yaw_guard, "start", lambda autopilot: ((), []))
    daemon.dispatch(LinkEvent("fc_reboot", "FC time went back", 0.0))
    assert daemon.internal_faults == 0
    t2 = 1.0 + np.arange(200) / IMU_HZ
    _run(daemon, t2, lambda k: t2[k] + TRANSPORT_S)
    att = _stamps_ms(daemon, "ATTITUDE")
    assert len(att) - n_before == 25 and att[n_before] == 1000  # 0.5 s at 50 Hz, from the first sample
    assert daemon.scheduler.slots_gap["ATTITUDE"] == 0 and daemon.scheduler.slots_late["ATTITUDE"] == 0


def test_slow_samples_fill_the_slots_between_them_on_the_local_clock(daemon):
    # GIVEN 25 Hz samples (ArduPlane's stock RAW_IMU) and 50 Hz ATTITUDE, the loop ticking every 5 ms
    t_fc = 100.0 + np.arange(50) / 25.0
    for t in t_fc:
        daemon.test_clock[0] = t + TRANSPORT_S
        daemon.dispatch(ImuSample(float(t), float(t) + TRANSPORT_S, np.zeros(3), np.zeros(3), None, "RAW_IMU"))
        for tick in range(1, 8):
            daemon._publish_due(t + TRANSPORT_S + tick * 0.005)
    att = _stamps_ms(daemon, "ATTITUDE")
    # THEN the slot after each sample is filled with it (its own stamp repeated): 50 Hz
    assert len(att) == 100 and daemon.scheduler.slots_filled["ATTITUDE"] == 50
    assert all(b >= a for a, b in zip(att, att[1:])) and len(set(att)) == 50


def test_the_counters_reach_the_health_topic_and_the_stopped_line(tmp_path, caplog):
    from test_fc_yaw_loop import daemon_on_sim
    ap, d, loop, _events = daemon_on_sim(tmp_path)
    while ap.t < 2.0:
        loop.run(ap.t + 0.05)
        for it in loop.items:
            d.dispatch(it)
        loop.items.clear()
        d._publish_due(ap.t)
    d.scheduler.slots_late["ATTITUDE"] += 3  # as a late burst would

    class _Bus:
        published: list = []

        def publish(self, topic, payload):
            self.published.append((topic, payload))

        def close(self):
            pass
    d.bus = _Bus()
    d._publish_health(ap.t)
    (health,) = [p for t, p in d.bus.published if t == "health"]
    counts = health["counters_count"]
    assert counts["slots_late_ATTITUDE"] == 3 and "slots_gap_ODOMETRY" in counts
    assert counts["slots_filled_ATTITUDE"] == d.scheduler.slots_filled["ATTITUDE"]
    with caplog.at_level(logging.INFO, logger="azimuthd.daemon"):
        d.close()
    (stopped,) = [r for r in caplog.records if r.getMessage() == "stopped"]
    assert stopped.fields["slots_late_attitude"] == 3 and "slots_gap_attitude" in stopped.fields
