"""The SET_MESSAGE_INTERVAL round as a pure state machine: one request at a time, retries with
confirmation, results, early give-up, REQUEST_DATA_STREAM groups."""
from mavlink_io.rates import Finished, RateRequester, SendInterval, data_stream_requests

W = [("RAW_IMU", 27, 200.0), ("SCALED_PRESSURE", 29, 50.0), ("ATTITUDE", 30, 50.0)]


def test_sequential_requests_with_acks():
    r = RateRequester(ack_timeout_s=0.5, max_tries=3)
    acts = r.start(W, 10.0)
    assert acts == [SendInterval("RAW_IMU", 27, 5000.0, 0)]
    assert r.on_ack(400, 0, 10.1) == []  # an ACK for another command is not ours
    assert r.on_ack(511, 5, 10.1) == []  # in progress: keep waiting
    assert r.on_ack(511, 0, 10.2) == [SendInterval("SCALED_PRESSURE", 29, 20000.0, 0)]
    assert r.poll(10.69) == []
    assert r.poll(10.70) == [SendInterval("SCALED_PRESSURE", 29, 20000.0, 1)]  # resend, confirmation 1
    assert r.on_ack(511, 3, 10.8) == [SendInterval("ATTITUDE", 30, 20000.0, 0)]
    acts = r.on_ack(511, 2, 10.9)
    assert acts == [Finished({"RAW_IMU": "accepted", "SCALED_PRESSURE": "unsupported", "ATTITUDE": "denied"})]
    assert not r.active and r.next_due_s() is None


def test_no_ack_gives_up_early():
    r = RateRequester(ack_timeout_s=0.5, max_tries=2, give_up_after=2)
    r.start(W, 0.0)
    assert r.poll(0.5) == [SendInterval("RAW_IMU", 27, 5000.0, 1)]
    assert r.poll(1.0) == [SendInterval("SCALED_PRESSURE", 29, 20000.0, 0)]
    r.poll(1.5)
    assert r.poll(2.0) == [Finished({"RAW_IMU": "no_ack", "SCALED_PRESSURE": "no_ack", "ATTITUDE": "not_tried"})]


def test_no_give_up_once_something_was_accepted():
    r = RateRequester(ack_timeout_s=0.5, max_tries=1, give_up_after=1)
    r.start(W, 0.0)
    r.on_ack(511, 0, 0.1)
    assert r.poll(0.6) == [SendInterval("ATTITUDE", 30, 20000.0, 0)]  # SCALED_PRESSURE no_ack, go on


def test_data_stream_groups_take_the_max_rate():
    assert data_stream_requests(W + [("SYS_STATUS", 1, 2.0), ("EKF_STATUS_REPORT", 193, 0.2),
                                     ("VFR_HUD", 74, 4.0)]) == {1: 200, 10: 50, 2: 2, 12: 1}
