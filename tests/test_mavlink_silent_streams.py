"""StreamRates.check_silent runs on every wake-up of the daemon's loop (every datagram); it skips its walk
over the streams until the earliest time one can be silent. GIVEN random flights of four streams
(flowing, stopping, coming back, refused and granted again, a full new round now and then, the link
going down and up) WHEN the link's check_silent and the former one (every stream walked on every
call, kept here as the reference) see the same calls THEN they re-request the same streams at the
same times and keep the same counts; and in a steady flight the skip is taken on almost every call."""
from __future__ import annotations

import types

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import stream_rates
from mavlink_io.link_config import FcPeer, LinkConfig
from mavlink_io.stats import LinkStats
from mavlink_io.stream_rates import StreamRates

STREAMS = {"RAW_IMU": 400.0, "SCALED_PRESSURE": 50.0, "ATTITUDE": 50.0, "SYS_STATUS": 2.0}


def _former_check_silent(self, now: float, items: list, connected: bool) -> None:
    """check_silent before the skip (session 9), verbatim."""
    if (self.cfg.stream_recheck_s <= 0 or not connected or self.requester.active
            or not self.wanted):
        return
    silent = []
    for name, msg_id, rate in self.wanted:
        if self.stats.rate_results.get(name) in ("denied", "unsupported", "failed"):
            continue
        if now - self._last_request_s.get(name, now) < max(self.cfg.stream_recheck_s, self.cfg.link_timeout_s):
            continue
        seen_s = self._seen_s.get(name)
        if seen_s is not None and now - seen_s <= self.cfg.link_timeout_s:
            self._silent_requests.pop(name, None)
            continue
        if self._silent_requests.get(name, 0) >= stream_rates._MAX_SILENT_REQUESTS:
            continue
        self._silent_requests[name] = self._silent_requests.get(name, 0) + 1
        silent.append((name, msg_id, rate))
    if silent:
        self.request(now, f"stream(s) silent: {', '.join(n for n, _i, _r in silent)}", items, only=silent)


class _Requester:
    """A requester whose rounds end at once (the FC's answers are not what is tested here)."""
    active = False
    granted_hz: dict = {}
    asked_hz: dict = {}

    def start(self, batch, now):
        return []

    def poll(self, now):
        return []

    def next_due_s(self):
        return None


def _rates(seen: dict, events: list) -> StreamRates:
    cfg = LinkConfig(url="udpin:127.0.0.1:14550", stream_rates_hz=STREAMS, stream_recheck_s=5.0, link_timeout_s=2.0)
    r = StreamRates(cfg, LinkStats(), FcPeer(1, 1, "ardupilot"), seen, mavlink2.MAVLink(None), lambda m: True,
                    lambda kind, detail, now, items: events.append((now, kind, detail)))
    r.requester = _Requester()
    return r


@pytest.mark.parametrize("seed", range(4))
def test_check_silent_requests_what_the_former_walk_did(seed):
    rng = np.random.default_rng(seed)
    seen_new, seen_old, ev_new, ev_old = {}, {}, [], []
    new, old = _rates(seen_new, ev_new), _rates(seen_old, ev_old)
    old.check_silent = types.MethodType(_former_check_silent, old)
    t = 0.0
    for r in (new, old):
        r.request(t, "autopilot detected", [])
    flowing = {n: True for n in STREAMS}
    connected = True
    counts_reset = 0
    for _ in range(20000):
        t += float(rng.choice([0.0025, 0.02, 0.3, 1.7]))
        for n in STREAMS:
            if rng.random() < 0.004:
                flowing[n] = not flowing[n]
            if flowing[n] and rng.random() < 0.9:
                seen_new[n] = seen_old[n] = t
        if rng.random() < 0.002:
            name = str(rng.choice(list(STREAMS)))
            res = str(rng.choice(["denied", "accepted", "failed"]))
            new.stats.rate_results[name] = old.stats.rate_results[name] = res
        if rng.random() < 0.0005:
            for r in (new, old):
                r.request(t, "FC rebooted", [])
        if rng.random() < 0.001:
            connected = not connected
        before = dict(old._silent_requests)
        new.check_silent(t, [], connected)
        old.check_silent(t, [], connected)
        counts_reset += any(k not in old._silent_requests for k in before)
        assert new._silent_requests == old._silent_requests, t
        assert ev_new == ev_old, t
    silent_rounds = sum(1 for _t, kind, d in ev_old if "silent" in d)
    assert silent_rounds > 20 and counts_reset > 5           # streams went silent, were asked again, came back
    assert any(c >= stream_rates._MAX_SILENT_REQUESTS for c in old._silent_requests.values()) or silent_rounds > 50


def test_with_every_stream_flowing_the_walk_is_skipped():
    """The daemon in flight: every stream comes, the loop wakes at 400 Hz for 20 s: the walk runs about
    once per link timeout, and nothing is re-requested (as the former walk)."""
    seen_new, seen_old, ev_new, ev_old = {}, {}, [], []
    new, old = _rates(seen_new, ev_new), _rates(seen_old, ev_old)
    old.check_silent = types.MethodType(_former_check_silent, old)
    for r in (new, old):
        r.request(0.0, "autopilot detected", [])
    walks = 0
    for k in range(1, 8001):
        t = 0.0025 * k
        for n in STREAMS:
            seen_new[n] = seen_old[n] = t
        bound = new._silent_not_before_s
        new.check_silent(t, [], True)
        old.check_silent(t, [], True)
        walks += not (new._silent_bound_at_s <= t < bound)
    assert ev_new == ev_old and len(ev_old) == 1   # the first round only
    assert walks <= 12, walks
