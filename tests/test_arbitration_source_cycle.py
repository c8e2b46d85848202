"""A change of the fused set is blended from what the OLD set says now (service/heading_arbitration.py
docstring step 6), also when a member of the old set is no longer offered at all.

Found on `make run` (bench/live_demo.py, 2026-12-02, HEAD 22c5bf5): method A's and B's sigmas were
equal to 0.01 deg, so A superseded B on one output cycle and not on the next; the fused set went
azimuth+synthetic_ahrs -> azimuth+fc (B withdrawn as 'superseded', the FC kept) -> back, 11 times in
1 s. The old set was evaluated from the members still offered (A alone, without B), so each round
trip left A - fused(A+B) in the blending offset: the published heading ran to +14 deg off truth
(sigma 13 deg) and bled off at 2 deg/s; the demo's heading RMS was 1.67 deg, 0.87 without this.
No truth here: the readings are set by the test."""
import math

from service.aiding import NotOffered
from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading, arbitrate

D = math.radians
MAG, FC_REF = "magnetometer", "fc_reference"


def _err_deg(h_rad, ref_deg):
    return (math.degrees(h_rad) - ref_deg + 180.0) % 360.0 - 180.0


def test_a_set_alternating_every_step_does_not_ratchet_the_offset():
    """GIVEN A at 102 +- 1.3 deg, B (magnetometer, aligned to the FC) at 99 +- 1.3 and the FC at
    100 +- 1.5 (B and the FC share groups: only one of them is fused), WHEN B is withdrawn on every
    other 20 ms cycle for 2 s (50 round trips A+B -> A+fc -> A+B), THEN the published heading stays
    within the readings (99..102 deg) and its offset never exceeds the largest jump between the two
    fusions (F(A,fc) - F(A,B) = 0.65 deg). Before: the offset grew by A - F(A,B) = 1.5 deg per
    round trip (to ~75 deg, less the 2 deg/s bleed)."""
    p = ArbitrationParams()
    a = lambda t: SourceReading("azimuth", D(102.0), D(1.3), True, t)
    b = lambda t: SourceReading("synthetic_ahrs", D(99.0), D(1.3), True, t, (MAG, FC_REF))
    fc = lambda t: SourceReading("fc", D(100.0), D(1.5), True, t, (MAG, FC_REF))
    st, out = arbitrate(ArbitrationState(), [a(0.0), b(0.0), fc(0.0)], 0.0, p)
    assert out.source == "azimuth+synthetic_ahrs"
    w_a, w_fc = 1.0 / 1.3 ** 2, 1.0 / 1.5 ** 2
    jump = (102.0 * w_a + 100.0 * w_fc) / (w_a + w_fc) - 100.5      # F(A,fc) - F(A,B) = 0.65 deg
    sources = set()
    for k in range(1, 101):
        t = 0.02 * k
        rs = [a(t), fc(t)] if k % 2 else [a(t), b(t), fc(t)]
        no = (NotOffered("synthetic_ahrs", "superseded", "test"),) if k % 2 else ()
        st, out = arbitrate(st, rs, t, p, 0.0, no)
        sources.add(out.source)
        assert -0.01 <= _err_deg(out.heading_rad, 99.0) <= 3.01, (t, math.degrees(out.heading_rad))
        assert abs(math.degrees(out.offset_rad)) <= jump + 1e-6, (t, math.degrees(out.offset_rad))
    assert sources == {"azimuth+synthetic_ahrs", "azimuth+fc"}


def test_a_member_withdrawn_is_blended_not_jumped():
    """GIVEN A (100 +- 1) and C (106 +- 2) fused at 101.2 deg, WHEN A is no longer offered at all
    (no reading: its solution withdrawn), THEN C alone (106) is reached by blending from the old
    fusion (a 'source_change' event with a +4.8 deg jump, the offset absorbing it), not at once.
    Before: the old set was evaluated from C alone, a jump of 0: 106 published at once."""
    p = ArbitrationParams()
    st, out = arbitrate(ArbitrationState(), [SourceReading("azimuth", D(100.0), D(1.0), True, 0.0),
                                             SourceReading("heading_filter", D(106.0), D(2.0), True, 0.0, MAG)], 0.0, p)
    assert abs(_err_deg(out.heading_rad, 101.2)) < 1e-9
    st, out = arbitrate(st, [SourceReading("heading_filter", D(106.0), D(2.0), True, 0.02, MAG)], 0.02, p, 0.0,
                        (NotOffered("azimuth", "no_estimate", "test"),))
    assert out.source == "heading_filter"
    ev = out.events[0]
    assert ev.kind == "source_change" and abs(math.degrees(ev.jump_rad) - 4.8) < 1e-6
    assert abs(_err_deg(out.heading_rad, 101.2)) < 1e-6
    assert abs(math.degrees(out.sigma_rad) - math.hypot(2.0, 4.8)) < 1e-6
