"""One aiding record per heading source (service/aiding.py), filled by the arbitration
(service/heading_arbitration.py) from what each source computes (service/heading_sources.py):
fused, or a stable code of why not, the innovation against the arbitration's reference and its
test ratio, the source's own innovation and gate ratio, the time of the last fusion.

The flights are the simulator's (sim.offline: its own Earth field and sensor errors) through the
daemon's Pipeline; the estimators see only the samples. Truth only scores (and is not read here)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from service import schema
from service.aiding import CSV_FIELDS, SOURCES, WHY_NOT, AidingRecord, NotOffered, csv_columns, csv_row, payload
from service.config import validate
from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading, arbitrate
from service.pipeline import Pipeline, site_field
from service.zenoh_bus import sources_payload
from sim.offline import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from sitl import feed_pipeline, pipeline_inputs  # noqa: E402

IMU_HZ = 50.0
D2R = math.radians


def _records_per_solution(p: Pipeline, items) -> list[tuple[float, dict]]:
    return [(sol.time_fc_s, dict(p.aiding), sol.heading_source) for sol in feed_pipeline(p, items)]


# --- the arbitration fills the records ----------------------------------------------------------

def R(name, hdg_deg, sig_deg, t, **kw):
    return SourceReading(name, D2R(hdg_deg), D2R(sig_deg), True, t, **kw)


def test_each_reading_gets_fused_or_a_code_and_its_innovation_against_the_reference():
    """GIVEN A fused at 100 deg WHEN the FC reads 120 deg +- 2, C is inconsistent, D's azimuth is
    stale and B is not offered THEN every source has a record: A fused, innovation 0.4 deg against
    the propagated reference; the FC gated out with test ratio = innovation^2 / S / gate > 1; C and
    the stale one not candidates; B's record says superseded with no innovation."""
    p = ArbitrationParams()
    st, _ = arbitrate(ArbitrationState(), [R("azimuth", 100.0, 0.5, 0.0)], 0.0, p)
    st, out = arbitrate(st, [R("azimuth", 100.4, 0.5, 0.1), R("fc", 120.0, 2.0, 0.1),
                             R("heading_filter", 101.0, 3.0, 0.1, consistent=False, why_not="gated out for 2.1 s"),
                             R("synthetic_ahrs", 99.0, 3.0, -0.6)],
                        0.1, p, 0.0, (NotOffered("deviation", "no_estimate", "no coefficients"),))
    rec = out.records
    assert set(rec) == {"azimuth", "fc", "heading_filter", "synthetic_ahrs", "deviation"}
    a = rec["azimuth"]
    assert (a.fused, a.why_not, a.detail, a.time_last_fused_s) == (True, "", "", 0.1)
    S = D2R(0.5) ** 2 + st.fused_var_rad2 + (p.rate_sigma_rad_s * 0.1) ** 2  # the reference propagated 0.1 s
    assert a.innovation_rad == pytest.approx(D2R(0.4), rel=1e-12)
    assert a.innovation_variance_rad2 == pytest.approx(S, rel=1e-12)
    assert a.test_ratio == pytest.approx(D2R(0.4) ** 2 / S / p.gate_chi2, rel=1e-12)
    fc = rec["fc"]
    assert (fc.fused, fc.candidate, fc.why_not) == (False, True, "gated_out")
    assert fc.innovation_rad == pytest.approx(D2R(20.0), rel=1e-12) and fc.test_ratio > 1.0
    assert fc.test_ratio == pytest.approx(fc.innovation_rad ** 2 / fc.innovation_variance_rad2 / p.gate_chi2, rel=1e-12)
    assert math.isnan(fc.time_last_fused_s)
    c = rec["heading_filter"]
    assert (c.candidate, c.fused, c.why_not) == (False, False, "inconsistent")
    assert c.innovation_rad == pytest.approx(D2R(1.0), rel=1e-9)  # compared all the same, as PX4 reports
    assert rec["synthetic_ahrs"].why_not == "stale"
    d = rec["deviation"]
    assert (d.why_not, d.detail) == ("no_estimate", "no coefficients") and math.isnan(d.innovation_rad)


def test_time_last_fused_survives_a_step_without_candidates_and_a_save_restore():
    """GIVEN C fused at 1.0 s WHEN no source is a candidate at 1.1 s THEN C's record keeps 1.0 s as
    its last fusion and the state's to_dict/from_dict keeps it too."""
    st, _ = arbitrate(ArbitrationState(), [R("heading_filter", 10.0, 2.0, 1.0)], 1.0)
    st, out = arbitrate(st, [R("heading_filter", 10.0, 2.0, 1.1, consistent=False)], 1.1)
    assert out.heading_rad is None
    c = out.records["heading_filter"]
    assert (c.fused, c.why_not, c.time_last_fused_s) == (False, "inconsistent", 1.0)
    assert math.isnan(c.innovation_rad)  # no candidate: no reference to compare with
    assert ArbitrationState.from_dict(st.to_dict()) == st and dict(st.last_fused_s) == {"heading_filter": 1.0}


def test_the_schema_lists_the_same_codes_and_sources_as_the_code():
    d = schema.load_schema()["$defs"]
    assert set(d["aiding_record"]["properties"]["why_not"]["enum"]) == set(WHY_NOT)
    assert set(d["heading"]["properties"]["sources"]["propertyNames"]["enum"]) == set(SOURCES)


def test_a_record_rejects_an_unknown_code_and_a_fused_flag_that_contradicts_it():
    with pytest.raises(ValueError, match="why_not must be one of"):
        AidingRecord("fc", 0.0, "felt_wrong")
    with pytest.raises(ValueError, match="contradicts"):
        AidingRecord("fc", 0.0, "gated_out", fused=True)


# --- a disturbed magnetometer: C's own gate rejects, its record says so -------------------------

@pytest.fixture(scope="module")
def magnet_turned():
    """A hand-held IMU (no FC, no air data) at rest from 21 s; from 22 s a magnet nearby turns the
    horizontal field by 40 deg (a constant field in NED: norm and dip unchanged, so the norm/dip
    disturbance tests cannot see it; only C's heading innovation can)."""
    cfg = validate({"site": {"lat_deg": 48.14, "lon_deg": 11.58, "alt_m": 520.0, "decimal_year": 2026.42},
                    "launch": {"case": "aligned", "vehicle": "hand"}, "heading": {"use_fc_yaw": False},
                    "azimuth": {"solve_in_background": False}, "mavlink": {"imu_rate_hz": IMU_HZ}})
    F, a = site_field(cfg).e_ned_gauss, D2R(40.0)
    turn = [F[0] * math.cos(a) - F[1] * math.sin(a) - F[0], F[0] * math.sin(a) + F[1] * math.cos(a) - F[1], 0.0]
    run = simulate("any_motion_magnet_nearby", seed=3, imu_rate_hz=IMU_HZ, duration_s=28.0,
                   overrides={"mag": {"disturbances": [{"start_s": 22.0, "field_ned_gauss": turn}]}})
    items = [ImuSample(t, t, run.gyro_rad_s[k].copy(), run.accel_m_s2[k].copy(), run.mag_gauss[k].copy(), "RAW_IMU", 0)
             for k, t in enumerate(run.time_s.tolist())]
    return _records_per_solution(Pipeline(cfg), items)


def test_given_a_disturbed_magnetometer_when_c_rejects_it_then_its_record_says_not_fused_and_why(magnet_turned):
    rows = magnet_turned
    before = [r["heading_filter"] for t, r, _ in rows if 18.0 <= t < 22.0]
    rejecting = [r["heading_filter"] for t, r, _ in rows if 22.2 <= t < 24.0]
    after = [(t, r["heading_filter"], src) for t, r, src in rows if 24.2 <= t]
    # before: C fused at every step, its own magnetometer innovations inside its gate
    assert before and all(c.fused and c.why_not == "" and c.time_last_fused_s == c.time_s for c in before)
    assert all(c.source_test_ratio <= 1.0 for c in before if math.isfinite(c.source_test_ratio))
    # WHEN the field turns, C's own gate rejects every measurement (ratio > 1: its gate) ...
    ratios = [c.source_test_ratio for c in rejecting if math.isfinite(c.source_test_ratio)]
    assert len(ratios) >= 0.8 * len(rejecting) and min(ratios) > 1.0
    # ... THEN after 2 s of it (SOURCE_INCONSISTENT_AFTER_S) C's record says: not a candidate, not
    # fused, inconsistent, with the reason, its test ratio > 1, and when it was last fused
    assert after and all(not c.candidate and not c.fused and c.why_not == "inconsistent" for _, c, _ in after)
    assert all(c.detail.startswith("inconsistent: its magnetometer innovations gated out for") for _, c, _ in after)
    assert all(c.source_test_ratio > 1.0 for _, c, _ in after if math.isfinite(c.source_test_ratio))
    last = {c.time_last_fused_s for _, c, _ in after}
    assert len(last) == 1 and 23.9 <= last.pop() < 24.2
    assert all(src != "heading_filter" for _, _, src in after)
    # the records as published: valid against the schema, codes from the one list
    heading = {"schema": "azimuthd/1", "vehicle": "uav1", "time_fc_s": 25.0, "time_rx_s": 25.0,
               "heading_valid": False, "heading_true_deg": None, "heading_sigma_deg": None,
               "heading_source": "none", "sources": sources_payload(rows[-1][1])}
    assert schema.validate("heading", heading) == []
    assert all(r.why_not in WHY_NOT for _, recs, _ in rows for r in recs.values())


# --- the FC reference lost: B and the FC are not candidates, and say why -------------------------

@pytest.fixture(scope="module")
def fc_lost():
    """A multicopter with its FC's attitude (no air data) until 20 s, then none."""
    run = simulate("multicopter_takeoff", seed=2, imu_rate_hz=IMU_HZ, duration_s=24.0)
    s = run.site
    cfg = validate({"site": {k: s[k] for k in ("lat_deg", "lon_deg", "alt_m", "decimal_year")},
                    "launch": {"case": "inclined", "vehicle": "multicopter"},
                    "azimuth": {"solve_in_background": False}, "mavlink": {"imu_rate_hz": IMU_HZ}})
    items = [it for it in pipeline_inputs(run) if type(it) is ImuSample
             or (type(it) is FcAttitude and it.time_fc_s < 20.0)]
    assert not any(type(it) is PressureSample for it in items)
    return _records_per_solution(Pipeline(cfg), items)


def test_given_the_fc_reference_lost_then_b_and_the_fc_are_not_candidates_and_say_why(fc_lost):
    rows = fc_lost
    before = [r for t, r, _ in rows if 15.0 <= t < 20.0]
    after = [(t, r) for t, r, _ in rows if 21.0 <= t]
    assert before and after
    # before: B and the FC are candidates (one of them fused: they share the magnetometer group)
    assert all(r["synthetic_ahrs"].candidate and r["fc"].candidate for r in before)
    assert all(r["synthetic_ahrs"].fused or r["fc"].fused for r in before)
    # THEN B: not a candidate, not fused, its reference lost, in words
    for t, r in after:
        b = r["synthetic_ahrs"]
        assert (b.candidate, b.fused, b.why_not) == (False, False, "no_reference"), (t, b)
        assert b.detail == "not valid: lost its reference (no trusted FC attitude, no air data)"
        assert b.time_last_fused_s < 20.6
        fc = r["fc"]
        assert (fc.candidate, fc.fused, fc.why_not) == (False, False, "no_reference"), (t, fc)
        assert fc.detail.startswith("FC attitude not trusted (")
        assert math.isnan(fc.observation_rad)  # not offered: nothing to compare
    # ... and the heading goes on from C, whose record says fused
    assert all(r["heading_filter"].fused for _, r in after)


def test_csv_cells_are_degrees_codes_and_flags():
    rec = {"fc": AidingRecord("fc", 3.0, "gated_out", "gated out (NIS 31.0)", True, False, 1.5, D2R(370.0), D2R(2.0),
                              D2R(-20.0), D2R(2.5) ** 2, 7.1)}
    cells = dict(zip(csv_columns(), csv_row(rec)))
    assert cells["aid_fc_observation_deg"] == "10" and cells["aid_fc_innovation_deg"] == "-20"
    assert float(cells["aid_fc_innovation_sigma_deg"]) == pytest.approx(2.5, rel=1e-12)
    assert (cells["aid_fc_fused"], cells["aid_fc_why_not"], cells["aid_fc_time_last_fused_s"]) == ("0", "gated_out", "1.5")
    assert cells["aid_fc_source_test_ratio"] == "" and cells["aid_azimuth_fused"] == ""
    assert (cells["aid_fc_observation_sigma_deg"], cells["aid_fc_test_ratio"]) == ("2", "7.1")
    # the CSV cells and the Zenoh payload say the same
    p = payload(rec["fc"])
    assert p["source_innovation_deg"] is None
    for f in CSV_FIELDS:
        want = ("1" if p[f] else "0") if f == "fused" else p[f] if f == "why_not" else \
            "" if p[f] is None else format(p[f], ".12g")
        assert cells[f"aid_fc_{f}"] == want, f
