"""Heading arbitration (service/heading_arbitration.py): gated inverse-variance fusion, no silent jumps."""
import math

import pytest

from service.heading_arbitration import (ArbitrationParams, ArbitrationState, SourceReading, arbitrate)

D = math.radians


def R(name, h_deg, s_deg, t, valid=True, group=""):
    return SourceReading(name, D(h_deg) % (2 * math.pi), D(s_deg), valid, t, group)


def test_single_source_passes_through():
    st, out = arbitrate(ArbitrationState(), [R("azimuth", 123.0, 1.0, 0.0)], 0.0)
    assert out.valid and out.source == "azimuth"
    assert abs(out.heading_rad - D(123.0)) < 1e-12 and abs(out.sigma_rad - D(1.0)) < 1e-12
    assert out.events[0].kind == "acquired"


def test_inverse_variance_fusion_across_north():
    rs = [R("azimuth", 359.0, 1.0, 0.0), R("heading_filter", 2.0, 2.0, 0.0)]
    st, out = arbitrate(ArbitrationState(), rs, 0.0)
    # weights 1 and 1/4: -1 + (3 * 0.25) / 1.25 = -0.4 deg
    assert abs(math.degrees(out.heading_rad) - 359.6) < 1e-9
    assert abs(out.sigma_rad - D(1.0) * math.sqrt(1 / 1.25)) < 1e-12
    assert out.source == "azimuth+heading_filter"


def test_correlated_group_uses_only_the_best_member():
    rs = [R("synthetic_ahrs", 10.0, 2.0, 0.0, group="mag"), R("heading_filter", 11.0, 1.5, 0.0, group="mag")]
    st, out = arbitrate(ArbitrationState(), rs, 0.0)
    assert out.source == "heading_filter" and abs(out.sigma_rad - D(1.5)) < 1e-12
    assert out.records["synthetic_ahrs"].why_not == "correlated" and "correlated" in out.records["synthetic_ahrs"].detail


def test_outlier_is_gated_out():
    st, _ = arbitrate(ArbitrationState(), [R("azimuth", 50.0, 1.0, 0.0), R("fc", 50.5, 2.0, 0.0)], 0.0)
    st, out = arbitrate(st, [R("azimuth", 50.2, 1.0, 0.1), R("fc", 80.0, 2.0, 0.1)], 0.1, heading_rate_rad_s=0.0)
    assert out.source == "azimuth" and not out.records["fc"].fused
    assert out.records["fc"].why_not == "gated_out" and out.records["fc"].test_ratio > 1.0
    assert out.events[0].kind == "source_change" and out.events[0].to_sources == ("azimuth",)


def test_source_change_never_jumps_silently_and_blends():
    p = ArbitrationParams(blend_rate_rad_s=D(2.0))
    st, out = arbitrate(ArbitrationState(), [R("azimuth", 100.0, 0.5, 0.0), R("heading_filter", 104.0, 3.0, 0.0)], 0.0, p)
    first = out.heading_rad
    # azimuth goes away: the heading filter alone says 104 (fused was ~100.1)
    st, out = arbitrate(st, [R("azimuth", 100.0, 0.5, 0.1, valid=False), R("heading_filter", 104.0, 3.0, 0.1)],
                        0.1, p, heading_rate_rad_s=0.0)
    ev = out.events[0]
    assert ev.kind == "source_change" and ev.from_sources == ("azimuth", "heading_filter")
    assert abs(math.degrees(ev.jump_rad) - (104.0 - math.degrees(first))) < 1e-9
    assert abs(math.degrees(out.heading_rad - first)) <= 2.0 * 0.1 + 1e-9       # bled at <= 2 deg/s
    assert out.sigma_rad > D(3.0)                                               # offset counted in sigma
    t = 0.1
    for _ in range(30):                                                         # 3 s later: blended in
        t += 0.1
        st, out = arbitrate(st, [R("heading_filter", 104.0, 3.0, t)], t, p, heading_rate_rad_s=0.0)
        assert out.events == ()
    assert abs(math.degrees(out.heading_rad) - 104.0) < 1e-9 and out.offset_rad == 0.0


def test_all_gated_coasts_then_resets_with_an_event():
    p = ArbitrationParams(reinit_after_s=1.0)
    st, _ = arbitrate(ArbitrationState(), [R("azimuth", 10.0, 0.5, 0.0)], 0.0, p)
    t, kinds = 0.0, []
    for _ in range(15):
        t += 0.1
        st, out = arbitrate(st, [R("azimuth", 40.0, 0.5, t)], t, p, heading_rate_rad_s=0.0)
        kinds.append(out.source)
        if out.events:
            ev = out.events[0]
    assert kinds[:9] == ["coast"] * 9 and kinds[-1] == "azimuth"
    assert ev.kind == "reset" and abs(math.degrees(ev.jump_rad) - 30.0) < 1e-6


def test_lost_then_invalid_and_validation():
    st, _ = arbitrate(ArbitrationState(), [R("fc", 10.0, 1.0, 0.0)], 0.0)
    st, out = arbitrate(st, [R("fc", 10.0, 1.0, 0.0)], 2.0)                   # stale
    assert not out.valid and out.heading_rad is None and out.events[0].kind == "lost"
    assert out.records["fc"].why_not == "stale" and "stale" in out.records["fc"].detail
    assert ArbitrationState.from_dict(st.to_dict()) == st
    with pytest.raises(ValueError, match="gate_chi2"):
        ArbitrationParams(gate_chi2=0.0)


def test_reference_follows_the_heading_rate():
    st, _ = arbitrate(ArbitrationState(), [R("azimuth", 0.0, 0.5, 0.0)], 0.0)
    t = 0.0
    for k in range(1, 50):               # a 20 deg/s turn seen by the source and by the gyros
        t += 0.1
        st, out = arbitrate(st, [R("azimuth", 2.0 * k, 0.5, t)], t, heading_rate_rad_s=D(20.0))
        assert out.source == "azimuth"
    assert abs(math.degrees(out.heading_rad) - 98.0) < 1e-9
