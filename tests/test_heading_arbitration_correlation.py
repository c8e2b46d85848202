"""Heading arbitration with correlated sources and after an input gap (service/heading_arbitration.py
docstring steps 2 and 4).

The bound: readings whose errors share a common part of unknown size cannot be fused as
independent. Covariance intersection of scalars picks the smaller variance (var_CI(w) =
1 / (w/v1 + (1-w)/v2) is monotonic in w), so the fused sigma of readings that share a group is
never below the smallest of their sigmas. Independent readings still fuse to less.
"""
import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading, arbitrate

D = math.radians
MAG, FC_REF = "magnetometer", "fc_reference"


def R(name, h_deg, s_deg, t, group=""):
    return SourceReading(name, D(h_deg) % (2 * math.pi), D(s_deg), True, t, group)


def test_fc_and_b_sharing_the_fc_reference_are_not_fused_as_independent():
    # B is aligned to the FC (group fc_reference) and uses the magnetometer; the FC only shares the
    # reference here. Independent fusion would give 1/sqrt(1/1.5^2 + 1/1.2^2) = 0.94 deg.
    rs = [R("fc", 100.0, 1.5, 0.0, (FC_REF,)), R("synthetic_ahrs", 100.5, 1.2, 0.0, (MAG, FC_REF))]
    _, out = arbitrate(ArbitrationState(), rs, 0.0)
    assert out.source == "synthetic_ahrs" and abs(out.sigma_rad - D(1.2)) < 1e-12
    assert abs(math.degrees(out.heading_rad) - 100.5) < 1e-9
    assert not out.records["fc"].fused and out.records["fc"].why_not == "correlated"


def test_several_groups_select_greedily_and_independent_sources_still_fuse():
    # C shares the magnetometer with B, B shares the FC reference with the FC, A shares nothing:
    # B (best of the chain) is kept, C and the FC are dropped, A fuses with B as independent.
    rs = [R("azimuth", 50.0, 2.0, 0.0), R("synthetic_ahrs", 51.0, 1.0, 0.0, (MAG, FC_REF)),
          R("heading_filter", 52.0, 1.5, 0.0, MAG), R("fc", 50.5, 1.5, 0.0, (FC_REF,))]
    _, out = arbitrate(ArbitrationState(), rs, 0.0)
    assert out.source == "azimuth+synthetic_ahrs"
    assert abs(out.sigma_rad - 1.0 / math.sqrt(1 / D(2.0) ** 2 + 1 / D(1.0) ** 2)) < 1e-12


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0.1, 20.0), st.floats(-3.0, 3.0),
                          st.sets(st.sampled_from(["a", "b", "c"]), min_size=1)), min_size=2, max_size=5))
def test_fused_sigma_never_below_the_smallest_sigma_of_mutually_correlated_readings(specs):
    # all readings share group "z" (besides others): fully mutually correlated -> CI bound
    rs = [R(f"s{i}", 200.0 + dh, s, 0.0, tuple(sorted(g | {"z"}))) for i, (s, dh, g) in enumerate(specs)]
    _, out = arbitrate(ArbitrationState(), rs, 0.0)
    assert out.sigma_rad >= min(r.sigma_rad for r in rs) - 1e-15
    assert "+" not in out.source


def test_monte_carlo_common_error_gives_honest_nees_only_with_groups():
    """Two readings with one common error e ~ N(0, 1 deg) (a shared reference) plus small own
    noise: with the group the NEES is ~1; fused as independent it would be ~2."""
    rng = np.random.default_rng(7)
    nees_grouped, nees_indep = [], []
    for k in range(2000):
        e = rng.normal(0.0, 1.0)
        h1, h2 = 30.0 + e + rng.normal(0, 0.1), 30.0 + e + rng.normal(0, 0.1)
        s = math.hypot(1.0, 0.1)
        for group, acc in ((FC_REF, nees_grouped), ("", nees_indep)):
            _, out = arbitrate(ArbitrationState(), [R("fc", h1, s, 0.0, group), R("synthetic_ahrs", h2, s, 0.0, group)],
                               0.0)
            err = math.remainder(out.heading_rad - D(30.0), 2 * math.pi)
            acc.append((err / out.sigma_rad) ** 2)
    assert 0.9 < np.mean(nees_grouped) < 1.1
    assert np.mean(nees_indep) > 1.8        # what the old pairing (FC without a group) published


def test_after_an_input_gap_the_heading_is_reacquired_not_blended():
    """10 s without a call (a link outage) while the vehicle turned 60 deg: the held heading is
    no reference any more. The new heading is taken at once with a 'reset' event naming the jump;
    blending it at 2 deg/s would publish a heading 60 deg off for 30 s."""
    p = ArbitrationParams()
    st_, out = arbitrate(ArbitrationState(), [R("fc", 10.0, 1.5, 0.0), R("heading_filter", 10.5, 2.0, 0.0)], 0.0, p)
    st_, out = arbitrate(st_, [R("fc", 10.0, 1.5, 0.1)], 0.1, p, heading_rate_rad_s=0.0)   # C drops out
    st_, out = arbitrate(st_, [R("heading_filter", 70.0, 2.0, 10.1)], 10.1, p, heading_rate_rad_s=0.0)
    assert out.valid and abs(math.degrees(out.heading_rad) - 70.0) < 1e-9 and out.offset_rad == 0.0
    assert abs(out.sigma_rad - D(2.0)) < 1e-12
    ev = out.events[0]
    assert ev.kind == "reset" and abs(math.degrees(ev.jump_rad) - 60.0) < 0.5 and "without output" in ev.message
    # an ordinary cadence keeps blending source changes (step 6 unchanged)
    st_, out = arbitrate(st_, [R("heading_filter", 70.0, 2.0, 10.12), R("fc", 74.0, 1.5, 10.12)], 10.12, p,
                         heading_rate_rad_s=0.0)
    assert out.events and out.events[0].kind == "source_change" and out.offset_rad != 0.0
