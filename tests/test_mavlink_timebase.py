"""FC clock reconstruction: uint32 ms wrap, reboot (backward jump), gaps, stale packets."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavlink_io.timebase import MS_WRAP, US32_WRAP, FcTimebase, TimebaseParams

WRAP_S = MS_WRAP / 1000.0  # 4294967.296 s = 49.71 days
US32_S = US32_WRAP / 1e6  # 4294.967296 s = 71.58 min: ArduPilot's RAW_IMU micros() counter


def _feed_all(tb, seq, gap_s=None):
    out, events = [], []
    for stream, raw, unit, rx in seq:
        t, ev = tb.feed(stream, raw, unit, rx, gap_s)
        out.append(t)
        events += ev
    return out, events


def test_ms_wrap_is_unwrapped_and_reported_once():
    tb = FcTimebase()
    raws = [MS_WRAP - 20, MS_WRAP - 10, 0, 10, 20]  # 20 ms steps across the wrap
    out, events = _feed_all(tb, [("ATTITUDE", r, "ms", 1.0 + 0.010 * i) for i, r in enumerate(raws)])
    assert out == pytest.approx([WRAP_S - 0.020, WRAP_S - 0.010, WRAP_S, WRAP_S + 0.010, WRAP_S + 0.020], abs=1e-9)
    assert [e.kind for e in events] == ["time_wrap"]


def test_ms_stream_unwrapped_against_us_stream():
    # RAW_IMU (uint64 us) is past 2^32 ms; SCALED_PRESSURE (uint32 ms) has wrapped: same FC clock
    tb = FcTimebase()
    t_imu, _ = tb.feed("IMU", int((WRAP_S + 5.0) * 1e6), "us", 0.0)
    t_p, ev = tb.feed("PRESSURE", 5000 - 20, "ms", 0.0)
    assert t_imu == pytest.approx(WRAP_S + 5.0)
    assert t_p == pytest.approx(WRAP_S + 4.98, abs=1e-9)
    assert ev == []  # the first ms sample: the wrap happened before we connected
    t_p, ev = tb.feed("PRESSURE", 5000, "ms", 0.02)
    assert t_p == pytest.approx(WRAP_S + 5.0, abs=1e-9) and ev == []


def test_ardupilot_raw_imu_uint32_microsecond_wrap():
    """RAW_IMU.time_usec is uint64 but ArduPilot fills it from a uint32 us counter (71.6 min)."""
    tb = FcTimebase()
    raws = [US32_WRAP - 10_000, US32_WRAP - 5_000, 0, 5_000, 10_000]
    out, events = _feed_all(tb, [("IMU", r, "us", 4300.0 + 0.005 * i) for i, r in enumerate(raws)], gap_s=0.5)
    np.testing.assert_allclose(np.diff(out), [0.005] * 4, atol=1e-9)
    assert out[2] == pytest.approx(US32_S, abs=1e-9)
    assert [e.kind for e in events] == ["time_wrap"] and "uint32 us" in events[0].detail
    # the uint32 ms streams of the same FC agree with the unwrapped IMU time
    t_att, ev = tb.feed("ATTITUDE", int(US32_S * 1000) + 10, "ms", 4300.02)
    assert ev == [] and t_att == pytest.approx(US32_S + 0.010 - 0.000296, abs=1e-6)


def test_wrap_recognised_after_a_long_link_loss():
    tb = FcTimebase()
    tb.feed("PRESSURE", MS_WRAP - 10_000, "ms", 1000.0)  # 10 s before the 49.7-day wrap
    t, ev = tb.feed("PRESSURE", 20_000, "ms", 1030.0)  # 30 s of silence, then 20 s after the wrap
    assert [e.kind for e in ev] == ["time_wrap"]
    assert t == pytest.approx(WRAP_S + 20.0)


def test_reboot_near_the_us32_wrap_is_not_taken_for_a_wrap():
    tb = FcTimebase()
    tb.feed("IMU", US32_WRAP - 1_000_000, "us", 100.0)  # 1 s before the counter would wrap
    # 0.5 s later the FC says 2 s since boot: a wrap would mean 3 s elapsed, the local clock says 0.5
    t, ev = tb.feed("IMU", 2_000_000, "us", 100.5)
    assert [e.kind for e in ev] == ["fc_reboot"] and t == pytest.approx(US32_S - 1.0 + 0.5)
    t2, ev2 = tb.feed("IMU", 2_005_000, "us", 100.505)  # and the new boot goes on normally
    assert ev2 == [] and t2 - t == pytest.approx(0.005, abs=1e-9)


def test_reboot_just_after_a_us32_wrap_is_still_caught():
    """3 s after boot looks like 'a little later' to a wrapped uint32 us clock; the uint32 ms
    stream of the same FC (ATTITUDE) goes back 4295 s and tells the reboot."""
    tb = FcTimebase()
    _feed_all(tb, [("IMU", US32_WRAP - 5_000, "us", 10.0), ("ATTITUDE", int(US32_S * 1000) - 5, "ms", 10.0),
                   ("IMU", 5_000, "us", 10.01)])  # wrapped once
    t_imu, ev = tb.feed("IMU", 3_000_000, "us", 13.0)  # rebooted 3 s later: ambiguous on its own
    assert ev == []
    t_att, ev = tb.feed("ATTITUDE", 3_001, "ms", 13.001)
    assert [e.kind for e in ev] == ["fc_reboot"] and t_att > t_imu
    out, ev = _feed_all(tb, [("IMU", 3_000_000 + 5_000 * i, "us", 13.0 + 0.005 * i) for i in range(1, 5)])
    assert ev == [] and all(o is not None for o in out) and np.allclose(np.diff(out), 0.005, atol=1e-9)
    assert out[0] > t_imu  # never backwards
    # had the FC been silent for 10 s, the IMU stream alone would tell: 7 s behind the local clock
    tb = FcTimebase()
    _feed_all(tb, [("IMU", US32_WRAP - 5_000, "us", 10.0), ("IMU", 5_000, "us", 10.01)])
    _, ev = tb.feed("IMU", 3_000_000, "us", 20.0)
    assert [e.kind for e in ev] == ["fc_reboot"]


def test_connecting_to_an_fc_up_for_days_is_not_a_wrap_event():
    tb = FcTimebase()
    t_att, ev1 = tb.feed("ATTITUDE", 200_000_000, "ms", 5.0)  # 2.3 days after boot
    t_imu, ev2 = tb.feed("IMU", (200_000_000_000 + 3_000) % US32_WRAP, "us", 5.0)  # its uint32 us counter
    assert ev1 == ev2 == [] and t_imu == pytest.approx(200_000.003, abs=1e-6)


def test_late_pre_wrap_packet_is_dropped_not_jumped_forward():
    tb = FcTimebase()
    _feed_all(tb, [("A", MS_WRAP - 10, "ms", 0.0), ("A", 5, "ms", 0.01)])
    t, ev = tb.feed("A", MS_WRAP - 5, "ms", 0.02)  # reordered: belongs before the wrap
    assert t is None and ev == [] and tb.stale == 1


def test_reboot_detected_and_output_stays_monotonic():
    tb = FcTimebase(TimebaseParams(reboot_jump_s=1.0))
    out, ev = _feed_all(tb, [("IMU", 100_000_000, "us", 50.0), ("IMU", 100_005_000, "us", 50.005),
                             ("ATTITUDE", 100_010, "ms", 50.01)])
    assert out == pytest.approx([100.0, 100.005, 100.010])
    # FC rebooted: 3 s of local time later it says 0.5 s since boot
    t, ev = tb.feed("IMU", 500_000, "us", 53.005)
    assert [e.kind for e in ev] == ["fc_reboot"]
    assert t == pytest.approx(100.010 + (53.005 - 50.01))  # continued with elapsed local time
    t2, _ = tb.feed("IMU", 505_000, "us", 53.010)
    assert t2 - t == pytest.approx(0.005, abs=1e-9)
    t3, ev3 = tb.feed("ATTITUDE", 510, "ms", 53.011)  # other streams follow the new boot silently
    assert ev3 == [] and t3 == pytest.approx(t + 0.010)
    assert tb.reboots == 1


def test_quick_reboot_told_from_reordering_by_the_local_clock():
    """Up 3 s, reboot, 2 s of silence, first sample at 2 s since boot: only 1 s back, but 3 s
    behind what the local clock predicts and within the silence -> a restart candidate, confirmed
    by the next sample going on from it (that first sample is dropped as stale)."""
    tb = FcTimebase(TimebaseParams(reboot_jump_s=1.0))
    _feed_all(tb, [("IMU", 2_995_000, "us", 10.0), ("IMU", 3_000_000, "us", 10.005)])
    t, ev = tb.feed("IMU", 2_000_000, "us", 12.005)
    assert t is None and ev == [] and tb.stale == 1
    t, ev = tb.feed("IMU", 2_005_000, "us", 12.010)
    assert [e.kind for e in ev] == ["fc_reboot"] and t == pytest.approx(3.0 + 2.005)
    # whereas a late packet from 0.5 s ago arriving right away is just dropped
    tb.feed("IMU", 2_010_000, "us", 12.015)
    t, ev = tb.feed("IMU", 1_510_000, "us", 12.016)
    assert t is None and ev == [] and tb.reboots == 1


def test_reboot_during_a_long_outage_seen_from_the_local_clock():
    """Up 30 s, reboot, 60 s of outage: the first sample says 55 s since boot (forward!), but
    the local clock says it should be ~90 s."""
    tb = FcTimebase()
    tb.feed("IMU", 30_000_000, "us", 100.0)
    t, ev = tb.feed("IMU", 55_000_000, "us", 160.0)
    assert [e.kind for e in ev] == ["fc_reboot"] and "lags the local clock by 35.000 s" in ev[0].detail
    assert t == pytest.approx(90.0)
    # a plain outage (no reboot) is a gap, not a reboot
    tb2 = FcTimebase()
    tb2.feed("IMU", 30_000_000, "us", 100.0)
    t, ev = tb2.feed("IMU", 89_000_000, "us", 160.0, gap_s=0.5)
    assert [e.kind for e in ev] == ["time_gap"] and t == pytest.approx(89.0)


def test_small_backward_step_is_dropped_not_a_reboot():
    tb = FcTimebase(TimebaseParams(reboot_jump_s=1.0))
    out, ev = _feed_all(tb, [("IMU", 10_000_000, "us", 0), ("IMU", 10_005_000, "us", 0),
                             ("IMU", 10_005_000, "us", 0), ("IMU", 9_500_000, "us", 0),
                             ("IMU", 10_010_000, "us", 0)])
    assert out == [pytest.approx(10.0), pytest.approx(10.005), None, None, pytest.approx(10.010)]
    assert ev == [] and tb.stale == 2


def test_gap_reported_only_above_threshold():
    tb = FcTimebase()
    out, ev = _feed_all(tb, [("IMU", 1_000_000, "us", 0), ("IMU", 1_500_000, "us", 0),  # 0.5 s: not > 0.5
                             ("IMU", 2_000_001, "us", 0)], gap_s=0.5)  # 0.500001 s: a gap
    assert [e.kind for e in ev] == ["time_gap"] and "0.500 s" in ev[0].detail
    assert out[2] == pytest.approx(2.000001)


def test_params_validated():
    with pytest.raises(ValueError, match="reboot_jump_s"):
        TimebaseParams(reboot_jump_s=0.0)
    with pytest.raises(ValueError, match="unit"):
        FcTimebase().feed("A", 1, "s", 0.0)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["IMU", "PRESSURE", "ATTITUDE"]),
                          st.integers(min_value=-3000, max_value=3000),
                          st.booleans()), min_size=1, max_size=60),
       st.integers(min_value=0, max_value=MS_WRAP - 1))
def test_output_never_goes_backwards_per_stream(steps, start_ms):
    """Whatever the FC clock does (steps, wraps, restarts), each stream's output increases."""
    tb = FcTimebase()
    raw_ms = start_ms
    rx = 0.0
    last: dict[str, float] = {}
    for stream, step_ms, reboot in steps:
        raw_ms = 7 if reboot else (raw_ms + step_ms) % MS_WRAP
        rx += 0.01
        if stream == "IMU":
            t, _ = tb.feed(stream, raw_ms * 1000, "us", rx)
        else:
            t, _ = tb.feed(stream, raw_ms, "ms", rx)
        if t is not None:
            if stream in last:
                assert t > last[stream]
            last[stream] = t


# --- a lag alone is a stall or a backlog, never a reboot ------------------------------------------

IMU_DT_US = 5_000  # 200 Hz


def _imu_run(tb, t0_us, n, rx0_s, rx_step_s=IMU_DT_US * 1e-6, gap_s=0.05):
    """n consecutive 200 Hz RAW_IMU stamps from t0_us, received from rx0_s every rx_step_s."""
    return _feed_all(tb, [("IMU", t0_us + IMU_DT_US * i, "us", rx0_s + rx_step_s * i) for i in range(n)], gap_s)


def test_sender_stall_is_a_backlog_not_a_reboot():
    """GIVEN an FC (the simulator) whose clock paused for 5.35 s while the machine starved it
    WHEN its samples resume, consecutive at 200 Hz but 5.35 s behind the local clock
    THEN no reboot: one input_backlog naming the lag, every sample delivered 5 ms apart."""
    tb = FcTimebase()
    out1, ev1 = _imu_run(tb, 60_000_000, 400, 100.0)  # 2 s of flight at 60 s since boot
    out2, ev2 = _imu_run(tb, 60_000_000 + 400 * IMU_DT_US, 400, 100.0 + 400 * 0.005 + 5.35)
    out = out1 + out2
    assert ev1 == [] and [e.kind for e in ev2] == ["input_backlog"]
    assert "by 5.350 s" in ev2[0].detail and "not a reboot" in ev2[0].detail
    assert None not in out and np.allclose(np.diff(out), 0.005, atol=1e-9)  # integration goes on
    assert tb.reboots == 0 and tb.backlogs == 1 and tb.backlog_max_s == pytest.approx(5.35, abs=1e-6)


def test_read_loop_backlog_is_a_backlog_not_a_reboot():
    """GIVEN a daemon whose read loop stalled 5 s while the kernel queued the FC's samples
    WHEN it reads them all at once (one receive time for the whole batch)
    THEN every queued sample is delivered in order, 5 ms apart, one input_backlog, no reboot."""
    tb = FcTimebase()
    _imu_run(tb, 30_000_000, 200, 10.0)
    last_rx = 10.0 + 199 * 0.005
    out, ev = _imu_run(tb, 30_000_000 + 200 * IMU_DT_US, 1000, last_rx + 5.0, rx_step_s=0.0)
    assert [e.kind for e in ev] == ["input_backlog"] and "by 4.995 s" in ev[0].detail
    assert None not in out and np.allclose(np.diff(out), 0.005, atol=1e-9)
    assert tb.reboots == 0 and tb.stale == 0


def test_backlog_with_samples_lost_is_a_gap_not_a_reboot():
    """GIVEN 12 s of local silence after which the FC time went on by 5 s (a sender stalled 7 s,
    then the kernel dropped what the stalled reader could not hold; FC up 60 s) WHEN read THEN
    a time_gap and an input_backlog (7 s), no reboot: a clock 65 s since boot cannot have
    restarted within a 12 s silence."""
    tb = FcTimebase()
    _imu_run(tb, 60_000_000, 10, 0.0)
    t_after = 60_000_000 + 9 * IMU_DT_US + 5_000_000
    out, ev = _feed_all(tb, [("IMU", t_after, "us", 0.045 + 12.0)], gap_s=0.05)
    assert sorted(e.kind for e in ev) == ["input_backlog", "time_gap"] and out[0] == pytest.approx(65.045)
    assert "by 7.000 s" in next(e.detail for e in ev if e.kind == "input_backlog") and tb.reboots == 0


def test_stall_longer_than_the_uptime_is_still_no_reboot():
    """2 s after boot the sender stalls 6 s, then goes on 5 ms later: its time since boot (2 s)
    would fit in the silence, but a restarted clock does not continue where the old one stopped."""
    tb = FcTimebase()
    _imu_run(tb, 2_000_000, 10, 50.0)
    out, ev = _imu_run(tb, 2_000_000 + 10 * IMU_DT_US, 10, 50.045 + 6.0)
    assert [e.kind for e in ev] == ["input_backlog"] and tb.reboots == 0
    assert np.allclose(np.diff(out), 0.005, atol=1e-9)


def test_repeat_and_late_packet_in_a_backlog_are_dropped_not_a_reboot():
    """2 s after boot, a 4 s stall; a duplicated and a reordered packet arrive first (the late one
    could be a restarted clock's first sample: held), then the old clock goes on: no reboot."""
    tb = FcTimebase()
    _imu_run(tb, 2_000_000, 10, 50.0)
    last = 2_000_000 + 9 * IMU_DT_US
    out, ev = _feed_all(tb, [("IMU", last, "us", 54.045), ("IMU", last - 10_000, "us", 54.045),
                             ("IMU", last + IMU_DT_US, "us", 54.045), ("IMU", last + 2 * IMU_DT_US, "us", 54.045)])
    assert out[:2] == [None, None] and out[2:] == pytest.approx([2.05, 2.055])
    assert [e.kind for e in ev] == ["input_backlog"] and tb.stale == 2 and tb.reboots == 0


def test_reboot_inside_a_read_backlog_is_a_reboot():
    """The FC rebooted while our loop stalled: the batch holds the old boot, then the new one
    (its clock back near zero). One fc_reboot at the first new-boot sample, output monotonic."""
    tb = FcTimebase()
    _imu_run(tb, 80_000_000, 10, 0.0)
    old, ev_old = _imu_run(tb, 80_000_000 + 10 * IMU_DT_US, 20, 8.0, rx_step_s=0.0)
    new, ev_new = _imu_run(tb, 3_000_000, 20, 8.0, rx_step_s=0.0)
    assert [e.kind for e in ev_old] == ["input_backlog"]
    assert [e.kind for e in ev_new] == ["fc_reboot"] and "went back 77.145 s" in ev_new[0].detail
    out = old + new
    assert None not in out and np.all(np.diff(out) > 0) and tb.reboots == 1


def test_small_lag_is_not_reported():
    """A 0.9 s lag (below backlog_report_s = 1 s): delivered silently."""
    tb = FcTimebase()
    _imu_run(tb, 10_000_000, 10, 0.0)
    out, ev = _imu_run(tb, 10_000_000 + 10 * IMU_DT_US, 5, 0.045 + 0.905)
    assert ev == [] and None not in out and tb.backlogs == 0


def test_new_params_validated():
    with pytest.raises(ValueError, match="restart_margin_s"):
        TimebaseParams(restart_margin_s=-1.0)
    with pytest.raises(ValueError, match="backlog_report_s"):
        TimebaseParams(backlog_report_s=0.0)


# --- through the link: what the daemon sees ------------------------------------------------------

def test_link_reports_a_stalled_sender_as_a_backlog_not_a_reboot():
    """GIVEN a MavlinkLink on an in-memory transport and a fake clock, an FC streaming RAW_IMU at
    200 Hz (60 s since boot) WHEN the sender stalls 5.35 s and goes on where it stopped THEN the
    link yields every sample 5 ms apart in FC time, one input_backlog event with the lag, counts
    it (stats.input_backlogs), no fc_reboot, no reboot count, no rates re-requested for a reboot."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
    from mavlink_io.samples import ImuSample
    from mem_transport import MemTransport

    class Clock:
        t = 10.0

        def __call__(self):
            return self.t

    clock, tr = Clock(), MemTransport()
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", system_id=1), clock=clock, transport=tr)
    fc = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)

    def frame(msg) -> bytes:
        buf = bytes(msg.pack(fc))
        fc.seq = (fc.seq + 1) % 256
        return buf

    items: list = []
    tr.inbox.append(frame(mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3)))
    items += link.poll(0.0)
    for k in range(400):
        if k == 200:
            clock.t += 5.35  # the sender's clock pauses; ours does not
        tr.inbox.append(frame(mavlink2.MAVLink_raw_imu_message(60_000_000 + 5000 * k, 0, 0, -1000, 0, 0, 0,
                                                               200, 0, 400, 0, 0)))
        items += link.poll(0.0)
        clock.t += 0.005
    t = [i.time_fc_s for i in items if isinstance(i, ImuSample)]
    kinds = [i.kind for i in items if isinstance(i, LinkEvent)]
    assert len(t) == 400 and np.allclose(np.diff(t), 0.005, atol=1e-9)
    assert "fc_reboot" not in kinds and kinds.count("input_backlog") == 1
    backlog = next(i for i in items if isinstance(i, LinkEvent) and i.kind == "input_backlog")
    assert "by 5.350 s" in backlog.detail
    assert link.stats.input_backlogs == 1 and link.stats.fc_reboots == 0
    assert not any("FC rebooted" in i.detail for i in items if isinstance(i, LinkEvent) and i.kind == "rates_requested")
