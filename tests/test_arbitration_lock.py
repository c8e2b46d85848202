"""Heading arbitration cannot lock onto a wrong source (issue 18): a source without its reference or
inconsistent with its own measurements is no candidate, and a published heading that disagrees
with a consistent majority is re-acquired from it.
"""
import math

from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading, arbitrate

D = math.radians
MAG = "magnetometer"


def B(h_deg, s_deg, t, valid=True, consistent=True, why=""):
    return SourceReading("synthetic_ahrs", D(h_deg) % (2 * math.pi), D(s_deg), valid, t, MAG, consistent, why)


def C(h_deg, s_deg, t):
    return SourceReading("heading_filter", D(h_deg) % (2 * math.pi), D(s_deg), True, t, MAG)


def A(h_deg, s_deg, t):
    return SourceReading("azimuth", D(h_deg) % (2 * math.pi), D(s_deg), True, t)


def err_deg(out, truth_deg):
    return abs(math.degrees(math.remainder(out.heading_rad - D(truth_deg), 2 * math.pi)))


def test_given_b_lost_its_reference_and_c_right_then_output_follows_c():
    # issue 18's final rest: C 97.4 +- 5.5 deg (right), B 3.3 +- 14 deg with no FC and no air data
    st, out = arbitrate(ArbitrationState(), [B(3.3, 14.0, 0.0, valid=False, why="lost its reference (no FC, no air data)"),
                                             C(97.4, 5.5, 0.0)], 0.0)
    assert out.source == "heading_filter" and err_deg(out, 97.4) < 1e-9
    assert out.records["synthetic_ahrs"].detail == "not valid: lost its reference (no FC, no air data)"
    assert not out.records["synthetic_ahrs"].candidate


def test_given_output_on_b_when_b_turns_inconsistent_then_c_takes_over_with_a_reported_jump():
    p = ArbitrationParams()
    st, out = arbitrate(ArbitrationState(), [B(100.0, 1.0, 0.0), C(104.0, 5.0, 0.0)], 0.0, p)
    assert out.source == "synthetic_ahrs"
    st, out = arbitrate(st, [B(100.0, 1.0, 0.1, consistent=False, why="its magnetometer updates gated out (40 of 45 in 5 s)"),
                             C(104.0, 5.0, 0.1)], 0.1, p, heading_rate_rad_s=0.0)
    assert out.source == "heading_filter"
    assert out.records["synthetic_ahrs"].detail.startswith("inconsistent: its magnetometer updates gated out")
    assert [e.kind for e in out.events] == ["source_change"] and abs(math.degrees(out.events[0].jump_rad) - 4.0) < 1e-6


def test_given_output_locked_on_a_drifting_b_when_a_consistent_majority_disagrees_then_reacquired():
    """B (sigma 1 deg, best of the magnetometer group) drifts at 1 deg/s; the output follows it (the
    gate against the propagated output never trips on a slow drift) and C (right, 100 deg) is gated
    out. When an independent source (method A) agrees with C, {A, C} is a consistent majority of
    two independent sources against B alone: the output re-anchors on it, reports it, and the
    published sigma covers the distance to the truth while the jump is blended."""
    p = ArbitrationParams()
    st, t = ArbitrationState(), 0.0
    for k in range(601):
        t = 0.1 * k
        st, out = arbitrate(st, [B(100.0 + t, 1.0, t), C(100.0, 5.0, t)], t, p, heading_rate_rad_s=0.0)
    assert out.source == "synthetic_ahrs" and err_deg(out, 100.0) > 55.0         # locked onto the drift
    assert out.records["heading_filter"].detail.startswith("gated out")
    assert out.records["heading_filter"].why_not == "gated_out" and out.records["heading_filter"].test_ratio > 1.0
    kinds = []
    for k in range(1, 401):
        t = 60.0 + 0.1 * k
        st, out = arbitrate(st, [B(100.0 + t, 1.0, t), C(100.0, 5.0, t), A(100.5, 2.0, t)], t, p,
                            heading_rate_rad_s=0.0)
        kinds += [e.kind for e in out.events]
        assert err_deg(out, 100.0) <= 2.0 * out.sigma_rad * 180.0 / math.pi + 1.0   # honest while blending
        assert "synthetic_ahrs" not in out.source.split("+")
    assert kinds[:2] == ["majority", "reset"]
    assert out.source == "azimuth+heading_filter" and err_deg(out, 100.0) < 1.0  # blended in (2 deg/s)


def test_two_disagreeing_members_of_one_group_are_no_majority():
    """B and C share the magnetometer: their agreement is one piece of evidence, not two, so they
    cannot out-vote an independent source the output follows."""
    p = ArbitrationParams()
    st, out = arbitrate(ArbitrationState(), [A(50.0, 1.0, 0.0)], 0.0, p)
    st, out = arbitrate(st, [A(50.0, 1.0, 0.1), B(80.0, 1.0, 0.1), C(80.5, 1.5, 0.1)], 0.1, p, heading_rate_rad_s=0.0)
    assert out.source == "azimuth" and not [e for e in out.events if e.kind == "majority"]
