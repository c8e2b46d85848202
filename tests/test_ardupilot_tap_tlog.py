"""The ArduPlane SITL bench's relay writes what ArduPilot sent the daemon as a .tlog that
``azimuthd replay`` reads: the replay then sees the live flight's input (issue 18: the compass flight's
reference-health drop was reproduced and bisected on such a replay)."""
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench import ardupilot_sitl as aps  # noqa: E402


def _frames():
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega as m
    fc = m.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [fc.heartbeat_encode(m.MAV_TYPE_FIXED_WING, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 3).pack(fc)]
    for k in range(20):
        t_ms = 1000 + 20 * k
        frames.append(fc.raw_imu_encode(t_ms * 1000, 0, 0, -1000, 10 * k, -5, 3, 200, 10, 400).pack(fc))
        frames.append(fc.attitude_encode(t_ms, 0.01, -0.02, 0.5, 0.0, 0.0, 0.0).pack(fc))
    return frames


def test_the_tap_writes_the_fc_to_daemon_bytes_as_a_tlog_the_replay_reads(tmp_path):
    from mavlink_io.tlog import TlogReader
    from mavlink_io.samples import FcAttitude, ImuSample
    from service.logreaders import open_log
    # GIVEN a relay that recorded ArduPilot's frames cut across chunk boundaries, some stray bytes
    #       (SITL's TCP stream starts with a few) and the daemon's own frames the other way
    frames = _frames()
    stream = b"\x00\x01garbage" + b"".join(frames)
    tap = aps.TcpTap(0)
    try:
        t0 = time.monotonic()
        cuts = list(range(0, len(stream), 37)) + [len(stream)]
        for i, (a, b) in enumerate(zip(cuts[:-1], cuts[1:])):
            tap.chunks.append((t0 + 0.01 * i, "fc", stream[a:b]))
            if i % 5 == 0:
                tap.chunks.append((t0 + 0.01 * i + 0.001, "daemon", frames[1]))
        # WHEN it writes the FC -> daemon direction as a .tlog
        path = tmp_path / "fc_to_daemon.tlog"
        n = tap.write_tlog(path)
    finally:
        tap.listen.close()
    # THEN every ArduPilot frame is there once, byte for byte, in order, stamped with the receive
    #      time of the chunk that completed it (Unix seconds, non-decreasing), and nothing else
    got = list(TlogReader(path.read_bytes()))
    assert n == len(frames) == len(got)
    assert [f for _, f in got] == frames
    ts = [t for t, _ in got]
    assert all(b >= a for a, b in zip(ts, ts[1:]))
    assert abs(ts[0] - time.time()) < 60.0
    # ... and azimuthd replay's reader decodes it as the daemon's link would: 20 IMU samples with
    #     their FC time and values, 20 FC attitudes
    items = list(open_log(path).items())
    imu = [i for i in items if isinstance(i, ImuSample)]
    att = [i for i in items if isinstance(i, FcAttitude)]
    assert len(imu) == 20 and len(att) == 20
    assert [round(s.time_fc_s, 3) for s in imu] == [round(1.0 + 0.02 * k, 3) for k in range(20)]
    assert imu[3].gyro_rad_s[0] == 0.03 and att[0].yaw_rad == 0.5
