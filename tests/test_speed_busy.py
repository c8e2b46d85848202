"""bench/speed.py --busy (issue 19 item 5): the loss accounting of the competing-load run adds up.

GIVEN what each observer counted (the simulator's sends, the tap, the kernel's socket tables, the
daemon's own counters) WHEN samples are lost at known places THEN busy_accounting names each loss
where it happened, the total is their sum, and the observers' cross-checks agree (or say which
one does not). A real run with the tap dropping every n-th IMU datagram on purpose reports exactly
those, and the daemon's sequence counter saw them. Nothing here depends on the machine's speed.
"""
from __future__ import annotations

import socket
import time

import pytest

from bench.sitl import udp_socket_state
from bench.speed import busy_accounting, busy_run, busy_verdict


def _observers(tap_kernel=10, on_purpose=5, daemon_kernel=7, before_hb=3, rejected=2, link_dropped=3):
    """Counts as each observer would report them for a run that lost IMU samples at every stage."""
    sim_sent = {"RAW_IMU": 1000, "HEARTBEAT": 10, "ATTITUDE": 100}
    received_imu = 1000 - tap_kernel                      # the tap's socket dropped tap_kernel IMU datagrams
    forwarded_imu = received_imu - on_purpose
    tap = {"received_by_type": {"RAW_IMU": received_imu, "HEARTBEAT": 10, "ATTITUDE": 100},
           "dropped_on_purpose": {"RAW_IMU": on_purpose} if on_purpose else {},
           "forwarded_by_type": {"RAW_IMU": forwarded_imu, "HEARTBEAT": 10, "ATTITUDE": 100},
           "forwarded_before_heartbeat": {"RAW_IMU": before_hb} if before_hb else {},
           "forwarded_datagrams": forwarded_imu + 110}
    accepted = forwarded_imu - before_hb - daemon_kernel  # the daemon's socket dropped daemon_kernel
    daemon = {"imu_messages": accepted, "imu_samples": accepted - rejected - link_dropped, "imu_rejected": rejected,
              "kernel_rx_drops": daemon_kernel, "link_messages_received": forwarded_imu + 110 - daemon_kernel,
              "link_foreign": before_hb, "link_seq_lost": tap_kernel + on_purpose + daemon_kernel}
    return sim_sent, tap, tap_kernel, daemon, daemon_kernel


def _verdict_input(acc: dict, rate_hz: float = 50.0, speed: float = 1.0) -> dict:
    return {**acc, "attitude_rate_hz": rate_hz, "attitude_rate_configured_hz": 50.0, "window_s": 600.0,
            "rate_hz": 400.0, "competitors": 2, "load_avg_1min_mean": 2.5, "load_avg_1min_max": 3.0,
            "simulator": {"achieved_speed": speed}}


def test_each_loss_is_named_where_it_happened_and_the_observers_agree():
    acc = busy_accounting(*_observers())
    assert acc["samples_lost_parts"] == {"tap_socket_kernel": 10, "tap_dropped_on_purpose": 5,
                                         "daemon_socket_kernel": 7, "daemon_read_not_processed": 5}
    assert acc["daemon_read_not_processed_parts"] == {"pipeline_rejected": 2, "link_dropped": 3,
                                                      "internal_faults_any_input": 0}
    assert acc["samples_lost"] == 27 and acc["samples_lost_harness"] == 15 and acc["daemon_samples_lost"] == 12
    # 1000 sent, 3 ignored before the FC's first HEARTBEAT (not lost: the FC is not known yet)
    assert acc["samples_sent"] == 997 and acc["ignored_before_fc_heartbeat"] == 3
    assert acc["samples_sent"] - acc["samples_processed"] == acc["samples_lost"]
    assert acc["observers_agree"], acc["checks"]
    # a lossy run is never a PASS; a harness loss makes it prove nothing
    assert busy_verdict(_verdict_input(acc)) [0].startswith("INVALID")


def test_a_clean_run_passes_and_a_daemon_loss_fails():
    clean = busy_accounting(*_observers(tap_kernel=0, on_purpose=0, daemon_kernel=0, rejected=0, link_dropped=0))
    assert clean["samples_lost"] == 0 and clean["observers_agree"]
    text, ok = busy_verdict(_verdict_input(clean))
    assert ok and text.startswith("PASS")
    assert not busy_verdict(_verdict_input(clean, rate_hz=49.0))[1]        # 2 % short of the configured rate
    assert busy_verdict(_verdict_input(clean, speed=0.95))[0].startswith("INVALID")  # simulator behind
    lossy = busy_accounting(*_observers(tap_kernel=0, on_purpose=0, daemon_kernel=4, rejected=0, link_dropped=0))
    text, ok = busy_verdict({**_verdict_input(lossy), "daemon_loss_events": {"input_overflow": 1}})
    assert not ok and text.startswith("FAIL") and "daemon lost 4 samples (socket 4" in text
    assert "logged no input_overflow" not in text
    # a loss the daemon did not report is a failure of its own
    assert "logged no input_overflow" in busy_verdict(_verdict_input(lossy))[0]


def test_datagrams_left_queued_at_the_daemons_stop_are_lost_at_its_socket_and_fail_the_run():
    sim_sent, tap, tap_kernel, daemon, daemon_kernel = _observers(tap_kernel=0, on_purpose=0, daemon_kernel=0,
                                                                  rejected=0, link_dropped=0)
    left = 6   # IMU datagrams the daemon had not read when it was stopped (it was behind)
    daemon = dict(daemon, imu_messages=daemon["imu_messages"] - left, imu_samples=daemon["imu_samples"] - left,
                  link_messages_received=daemon["link_messages_received"] - left)
    acc = busy_accounting(sim_sent, tap, tap_kernel, daemon, daemon_kernel, daemon_socket_left_bytes=6 * 60)
    assert acc["samples_lost_parts"]["daemon_socket_kernel"] == left and acc["daemon_samples_lost"] == left
    assert acc["observers_agree"], acc["checks"]   # forwarded > read + drops: the rest was still queued
    text, ok = busy_verdict(_verdict_input(acc))
    assert not ok and text.startswith("FAIL") and "it was behind" in text


def test_observers_that_disagree_are_named():
    sim_sent, tap, tap_kernel, daemon, daemon_kernel = _observers()
    daemon = dict(daemon, kernel_rx_drops=0, link_seq_lost=daemon["link_seq_lost"] - 1)
    acc = busy_accounting(sim_sent, tap, tap_kernel, daemon, daemon_kernel)
    assert not acc["observers_agree"]
    bad = sorted(k for k, c in acc["checks"].items() if not c["agree"])
    assert bad == ["daemon_kernel_counter_vs_bench", "daemon_sequence_gaps_vs_datagrams_lost"]
    assert acc["checks"]["daemon_kernel_counter_vs_bench"] == {"a": 0, "b": 7, "agree": False}
    assert "observers disagree" in busy_verdict(_verdict_input(acc))[0]


def test_the_8_bit_sequence_is_a_lower_bound_when_a_full_socket_dropped_runs():
    # a full socket drops runs of datagrams; a run of 128 or more is beyond the 8-bit MAVLink
    # sequence (mavlink_io.framing.SeqTracker): its count is short, the kernel's counter exact
    sim_sent, tap, tap_kernel, daemon, daemon_kernel = _observers(tap_kernel=0, on_purpose=0, daemon_kernel=300)
    short = busy_accounting(sim_sent, tap, tap_kernel, dict(daemon, link_seq_lost=44), daemon_kernel)
    c = short["checks"]["daemon_sequence_gaps_vs_datagrams_lost"]
    assert (c["a"], c["b"], c["agree"]) == (44, 300, True) and "lower bound" in c["note"]
    assert short["observers_agree"] and short["samples_lost_parts"]["daemon_socket_kernel"] == 300
    # more gaps than datagrams lost is no undercount: the observers disagree
    over = busy_accounting(sim_sent, tap, tap_kernel, dict(daemon, link_seq_lost=301), daemon_kernel)
    assert not over["observers_agree"]
    # short, but the daemon's kernel counter does not agree with the bench's: no excuse either
    unsure = busy_accounting(sim_sent, tap, tap_kernel, dict(daemon, link_seq_lost=44, kernel_rx_drops=0),
                             daemon_kernel)
    assert not unsure["checks"]["daemon_sequence_gaps_vs_datagrams_lost"]["agree"]


def test_the_kernel_drop_observer_counts_what_a_full_socket_dropped():
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)   # holds a few datagrams only
        rx.bind(("127.0.0.1", 0))
        port = rx.getsockname()[1]
        assert udp_socket_state(port)["drops"] == 0
        sent = 200
        for _ in range(sent):
            tx.sendto(bytes(40), ("127.0.0.1", port))
        rx.setblocking(False)
        read, hang_guard = 0, time.monotonic() + 30.0
        while True:
            try:
                rx.recv(100)
                read += 1
                continue
            except BlockingIOError:
                pass
            st = udp_socket_state(port)
            if read + st["drops"] == sent or time.monotonic() > hang_guard:
                break
            time.sleep(0.01)
        assert st["drops"] > 0 and read + st["drops"] == sent and st["rx_queue_bytes"] == 0
    finally:
        rx.close()
        tx.close()
    assert udp_socket_state(port) is None   # closed: no longer listed


@pytest.mark.timeout(600)
def test_datagrams_dropped_on_purpose_are_reported_exactly_and_seen_by_the_daemon():
    # GIVEN the simulator and the daemon as processes, the tap dropping every 40th IMU datagram
    every = 40
    b = busy_run(5.0, competitors=0, drop_imu_every=every, start_timeout_s=300.0)
    received_imu = sum(v for k, v in b["tap"]["received_by_type"].items() if k in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU"))
    k = received_imu // every
    # THEN exactly those are lost, named as the tap's, and the daemon's own sequence counter saw them
    assert k > 0 and b["samples_lost_parts"]["tap_dropped_on_purpose"] == k
    assert b["samples_lost"] == sum(b["samples_lost_parts"].values())
    assert b["samples_lost_harness"] == k + b["samples_lost_parts"]["tap_socket_kernel"]
    assert b["observers_agree"], b["checks"]
    assert b["checks"]["daemon_sequence_gaps_vs_datagrams_lost"]["a"] >= k
    assert b["samples_sent"] - b["samples_processed"] == b["samples_lost"]
    assert b["verdict"].startswith("INVALID") and not b["pass"]
