"""A Zenoh subscriber that stalls does not block the daemon's publishing (issue 10).

GIVEN the daemon's ZenohBus listening on TCP and a subscriber in another process whose callback
blocks forever on the first sample it gets (a stuck dashboard), WHEN the bus publishes 3000 large
``health`` payloads back to back (far more than the TCP buffers hold) THEN no publish call
waits: all 3000 return (congestion control DROP; with BLOCK the first publish that meets the
full TCP buffer would wait for the stuck subscriber forever). How long each call took depends on
the machine's load: printed as a figure (measured idle: max well under the daemon's 5 ms loop
period), not a pass mark. The wall-clock deadline only detects the hang.
"""
import socket
import subprocess
import sys
import textwrap
import threading
import time

from conftest import HANG_S

from service.zenoh_bus import ZenohBus, health_payload

SUBSCRIBER = textwrap.dedent("""
    import json, sys, time, zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
    s = zenoh.open(conf)
    def stuck(sample):
        print("got one, stalling", flush=True)
        time.sleep(3600)
    sub = s.declare_subscriber("azimuthd/**", stuck)
    print("ready", flush=True)
    time.sleep(3600)
""")


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_stalled_subscriber_does_not_block_publish():
    endpoint = f"tcp/127.0.0.1:{_free_tcp_port()}"
    bus = ZenohBus("stalltest", mode="peer", listen=[endpoint])
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, endpoint], stdout=subprocess.PIPE, text=True)
    try:
        assert sub.stdout.readline().strip() == "ready"
        big = {f"counter_{i}": i for i in range(400)}  # ~10 kB of JSON per message
        t_end = time.monotonic() + 10.0
        got = False
        while time.monotonic() < t_end and not got:  # until the subscriber has one and is stuck
            bus.publish("health", health_payload(True, "boot", 0.0, {}, big))
            time.sleep(0.05)
            got = sub.poll() is None and _readable(sub)
        assert got, "the subscriber never received a sample"
        durations = []

        def publish_all():
            for k in range(3000):
                t0 = time.perf_counter()
                bus.publish("health", health_payload(True, "in-flight", float(k), {"RAW_IMU": 1000.0}, big))
                durations.append(time.perf_counter() - t0)

        th = threading.Thread(target=publish_all, daemon=True)
        th.start()
        th.join(HANG_S)
        assert not th.is_alive() and len(durations) == 3000, \
            f"publish blocked on the stalled subscriber after {len(durations)} of 3000"
        durations.sort()
        print(f"publish with a stalled subscriber: median {1e3 * durations[1500]:.3f} ms, "
              f"p99 {1e3 * durations[2970]:.3f} ms, max {1e3 * durations[-1]:.3f} ms")
    finally:
        sub.kill()
        sub.wait(5)
        bus.close()


def _readable(p) -> bool:
    import select
    r, _w, _x = select.select([p.stdout], [], [], 0.0)
    return bool(r) and "stalling" in p.stdout.readline()
