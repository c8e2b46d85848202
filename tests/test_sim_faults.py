"""Link fault injection, without sockets."""
from __future__ import annotations

import numpy as np

from sim.faults import LinkFaults
from sim.scenario import DEFAULTS


def _faults(**kw):
    return LinkFaults(dict(DEFAULTS["faults"], **kw), np.random.default_rng(1))


def test_no_faults_passes_everything_unchanged():
    f = _faults()
    assert not f.active
    assert [f.outbound(bytes([i]), 0.0) for i in range(5)] == [[bytes([i])] for i in range(5)]


def test_outage_window_drops_both_ways_only_inside():
    f = _faults(outages=[[10.0, 12.0]])
    assert f.active and f.in_outage(10.0) and f.in_outage(11.9) and not f.in_outage(12.0)
    assert f.outbound(b"x", 11.0) == [] and f.outbound(b"x", 12.5) == [b"x"]
    assert f.stats.outage_dropped_tx == 1


def test_reorder_swaps_neighbours_and_loses_nothing():
    f = _faults(reorder_rate=0.3)
    sent = []
    for i in range(2000):
        sent += f.outbound(i.to_bytes(2, "big"), 1.0)
    got = [int.from_bytes(b, "big") for b in sent]
    assert f.stats.reordered > 400
    assert sorted(got) == list(range(len(got))) and len(got) >= 1999  # the last may still be held
    inversions = sum(a > b for a, b in zip(got[:-1], got[1:]))
    assert inversions == f.stats.reordered - (1 if len(got) == 1999 else 0)


def test_corruption_changes_bytes_and_keeps_length():
    f = _faults(corrupt_rate=1.0)
    buf = bytes(range(40))
    out = f.outbound(buf, 0.0)[0]
    assert len(out) == len(buf) and out != buf


def test_drop_and_duplicate_rates_are_statistically_right():
    f = _faults(drop_rate=0.25, duplicate_rate=0.1)
    n = 20000
    out = sum(len(f.outbound(b"p", 0.0)) for _ in range(n))
    expect = n * 0.75 * 1.1
    assert abs(out - expect) < 4 * np.sqrt(n * 0.25) + 3 * np.sqrt(n * 0.1)
