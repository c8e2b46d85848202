"""Replay's summary and progress: each event reason once with its count; a progress bar with the
ETA on a terminal (or when asked), nothing otherwise."""
import io

from service.replay import _Progress, event_reasons


def test_event_reasons_grouped_numbers_aside():
    events = [(1.0, "not_still", "accelerometer not still (std 4.9 m/s^2)"),
              (3.0, "not_still", "accelerometer not still (std 5.2 m/s^2)"),
              (5.0, "not_still", "gyro not still: moving (std 12.0 deg/s > 10)"),
              (6.0, "levelled", "roll 1.00 deg, pitch 2.00 deg"),
              (9.0, "not_still", "accelerometer not still (std 4.9 m/s^2)"),
              (None, "link.fc_reboot", "time went back")]
    g = event_reasons(events)
    assert [(x["kind"], x["count"], x["variants"], x["first_time_s"]) for x in g] == [
        ("not_still", 3, 2, 1.0), ("not_still", 1, 1, 5.0), ("levelled", 1, 1, 6.0), ("link.fc_reboot", 1, 1, None)]
    assert g[0]["reason"] == "accelerometer not still (std 4.9 m/s^2)"  # the first one's text


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_progress_bar_on_a_terminal_only_unless_asked():
    tty, pipe = _Tty(), io.StringIO()
    for stream, enabled in ((tty, None), (pipe, None), (pipe, True)):
        p = _Progress(enabled, stream)
        p.next_s = 0.0  # due now: the test does not wait for the first second
        p.update(0.5, 12.0, 1000)
        p.done()
    text = tty.getvalue()
    assert text.startswith("\rreplay [############            ]  50.0%  ETA ") and text.endswith("\n")
    # not a terminal: nothing by default, one line per update when asked
    lines = pipe.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("replay [") and "ETA " in lines[0] and "log t=12.0 s" in lines[0]


def test_magnetometer_timeline_judges_the_whole_log_not_its_first_rejection():
    """GIVEN a log whose magnetometer was rejected for 18 s, then usable for 70 s (px4-quad-no-gnss's
    shape) THEN the log's magnetometer is usable, with the rejection's time and reason kept; GIVEN one
    usable 8 s at the end of 200 s rejected THEN it is rejected, though usable at the end."""
    from service.replay import magnetometer_timeline
    rej = "rejected (dip 79.4 deg vs the model's 63.5 deg): the heading coasts on the gyros"
    quad = [(100.0, "phase", "pre-launch"), (105.0, "magnetometer", rej), (123.0, "magnetometer", "usable")]
    m = magnetometer_timeline(quad, 193.0)
    assert m["usable"] and m["usable_at_end"] and m["rejections"] == 1
    assert m["rejected_s"] == 18.0 and m["usable_s"] == 70.0 and m["reason"] == rej
    assert m["first_rejected_s"] == 105.0 and m["since_s"] == 123.0
    late = [(0.0, "magnetometer", rej), (200.0, "magnetometer", "usable")]
    m = magnetometer_timeline(late, 208.0)
    assert not m["usable"] and m["usable_at_end"] and abs(m["usable_share"] - 8 / 208) < 1e-12
    assert magnetometer_timeline([(1.0, "phase", "pre-launch")], 10.0) is None  # no verdict: none claimed
