"""Method A supersedes the magnetometer sources only while it agrees with them (issue 18 item 3: a
published sigma below the error; service/heading_sources.AzimuthCheck).

Found on bench/synthetic_ahrs_accuracy.py's flight 0: after the GNSS loss method A solved (154 s)
and, B and C superseded, was published for the rest of the flight while its heading drifted with the
gyros to 13.6 deg at a 1.3-1.6 deg sigma (published 6.41 deg RMS, NEES 19, 57 % within 3 sigma); B,
not offered, was 0.7 deg off. Here the Pipeline's own source selection (Pipeline._readings, then the
arbitration as Pipeline._solution calls it) is given A's and B's outputs directly: no estimator runs,
so what A and B say is set by the test; no truth is involved (the arbitration never sees one)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from estimators.azimuth import AzimuthOutput
from estimators.synthetic_ahrs import SyntheticAhrsOutput
from service.config import validate
from service.heading_arbitration import SourceReading, arbitrate
from service.heading_sources import SOURCE_INCONSISTENT_AFTER_S, AzimuthCheck
from service.pipeline import Pipeline

D2R = math.radians


def _pipeline() -> Pipeline:
    return Pipeline(validate({"site": {"lat_deg": 48.14, "lon_deg": 11.58, "alt_m": 520.0, "decimal_year": 2026.42},
                              "launch": {"case": "aligned"}, "heading": {"use_fc_yaw": False},
                              "azimuth": {"solve_in_background": False}}))


def _a(t, hdg_deg, sig_deg):
    return AzimuthOutput(t, "solved", "", True, heading_rad=D2R(hdg_deg) % (2 * math.pi), heading_sigma_rad=D2R(sig_deg))


def _b(t, hdg_deg, sig_deg, air_fused):
    return SyntheticAhrsOutput(t, "b2", True, 0.0, 0.0, D2R(hdg_deg) % (2 * math.pi), D2R(0.5), D2R(0.5), D2R(sig_deg),
                               False, "FC EKF horizontal position lost (GNSS)", True, "", False, None, np.zeros(3),
                               mag_fused=int(t * 10), air_fused=air_fused + 1)


def _fly(a_deg, b_deg=lambda t: 100.0, a_sig=1.3, b_sig=1.5, duration_s=40.0, dt=0.1):
    """The Pipeline's selection every ``dt`` with A at a_deg(t) +- a_sig and B (flying on air data
    and its magnetometer, the FC lost) at b_deg(t) +- b_sig. Per step: (t, published heading deg,
    published sigma deg, source, A's aiding record)."""
    p = _pipeline()
    rows = []
    for k in range(int(duration_s / dt)):
        t = k * dt
        p.azimuth_out, p.ahrs_out = _a(t, a_deg(t), a_sig), _b(t, b_deg(t), b_sig, air_fused=k)
        readings, not_offered = p._readings(t)
        p.arb, out = arbitrate(p.arb, readings, t, p.arb_params, 0.0, not_offered)
        rows.append((t, math.degrees(out.heading_rad), math.degrees(out.sigma_rad), out.source, out.records["azimuth"]))
    return rows


def _err(h, ref):
    return (h - ref + 180.0) % 360.0 - 180.0


def test_a_drifting_away_from_b_loses_the_arbitration_to_b():
    """GIVEN A solved and agreeing with B at 100 deg, WHEN A's heading drifts at -0.3 deg/s (its gyro
    bias walked) at a steady 1.3 deg sigma while B holds 100 deg +- 1.5 deg, THEN A supersedes B
    while it agrees within 1 sigma of the difference (NIS <= 1, to ~6.6 s); past that its offered
    sigma grows with its demonstrated disagreement (x sqrt(mean NIS)), and once that is above B's
    for 2 s B is fused beside it; once A is more than 3 sigma of the difference away (|d| > 5.95 deg,
    at ~20 s) for 2 s, A is inconsistent (its record says so, with the comparison as its
    source-level test ratio) and B is published: from 25 s on the published heading is within 3
    published sigma of B's, the published source B. Before 5692267: A was published throughout,
    12 deg off at 40 s with its 1.3 deg sigma; before the demonstrated-disagreement scale: A alone
    until it was dropped at ~22 s."""
    rows = _fly(lambda t: 100.0 - 0.3 * t)
    early = [r for r in rows if r[0] < 6.5]
    assert all(r[3] == "azimuth" for r in early)                 # agreeing: A supersedes B
    assert all(r[4].fused and r[4].source_test_ratio <= 1.0 / 9.0 for r in early)
    assert all(r[4].observation_sigma_rad == pytest.approx(D2R(1.3), rel=1e-12) for r in early)
    middle = [r for r in rows if 11.0 <= r[0] < 21.5]
    assert all(r[3] == "azimuth+synthetic_ahrs" for r in middle)   # A's scaled sigma above B's
    assert all(r[4].observation_sigma_rad > D2R(1.5) for r in middle)
    late = [r for r in rows if r[0] >= 25.0]
    assert all(r[3] == "synthetic_ahrs" for r in late)
    assert all(abs(_err(r[1], 100.0)) <= 3.0 * r[2] for r in late)
    a = late[-1][4]
    assert (a.candidate, a.fused, a.why_not) == (False, False, "inconsistent")
    assert "disagrees with synthetic_ahrs" in a.detail and a.source_test_ratio > 1.0
    # the switch came 2 s after the disagreement passed the gate, not earlier
    first_bad = next(r[0] for r in rows if r[4].source_test_ratio > 1.0)
    first_b = next(r[0] for r in rows if r[3] == "synthetic_ahrs")
    assert first_b == pytest.approx(first_bad + SOURCE_INCONSISTENT_AFTER_S, abs=0.15)


def test_a_that_agrees_with_b_keeps_superseding_it():
    """GIVEN A and B within 1 sigma of their difference (A wanders +-1.9 deg about B; the sigma of
    the difference is 1.98 deg), THEN A is published throughout, at its own sigma, and B stays
    superseded."""
    rows = _fly(lambda t: 100.0 + 1.9 * math.sin(0.3 * t), duration_s=60.0)
    assert all(r[3] == "azimuth" for r in rows)
    assert all(r[2] == pytest.approx(1.3, rel=1e-9) for r in rows)


def test_a_wandering_beyond_one_sigma_of_the_difference_is_fused_while_it_does():
    """GIVEN A wandering +-2.5 deg about B (within the gate: 3 sigma of the difference is 5.95 deg;
    NIS up to 1.6), THEN A supersedes B while its 2 s mean NIS keeps its scaled sigma at or below
    B's 1.5 deg, and is fused with B while it does not; the choice changes no more often than the
    2 s hold allows, and every published heading is within 2 published sigma of B's. Before the
    scale: A alone throughout, at its own 1.3 deg, while 2.5 deg off."""
    rows = _fly(lambda t: 100.0 + 2.5 * math.sin(0.3 * t), duration_s=60.0)
    srcs = {r[3] for r in rows}
    assert srcs == {"azimuth", "azimuth+synthetic_ahrs"}
    changes = [r[0] for i, r in enumerate(rows) if i and r[3] != rows[i - 1][3]]
    assert all(b - a >= SOURCE_INCONSISTENT_AFTER_S for a, b in zip(changes, changes[1:]))
    assert all(abs(_err(r[1], 100.0)) <= 2.0 * r[2] for r in rows)


def test_a_comes_back_once_it_agrees_again_for_as_long():
    """GIVEN A dropped for a 10 deg disagreement, WHEN it agrees with B again (a new solution), THEN it
    is a candidate again after SOURCE_INCONSISTENT_AFTER_S of agreement, not at the first agreeing
    step: fused beside B at first (its sigma scaled by the disagreement still in its 2 s window made
    it less certain than B), superseding B once it has been the more certain for 2 s more."""
    rows = _fly(lambda t: 90.0 if t < 20.0 else 100.5, duration_s=40.0)
    assert rows[-1][3] == "azimuth"
    back = next(r[0] for r in rows if r[0] > 20.0 and r[4].fused)
    assert back == pytest.approx(20.0 + SOURCE_INCONSISTENT_AFTER_S, abs=0.15)
    alone = next(r[0] for r in rows if r[0] > 20.0 and r[3] == "azimuth")
    assert alone == pytest.approx(back + SOURCE_INCONSISTENT_AFTER_S, abs=0.15)
    assert any(r[3] == "synthetic_ahrs" for r in rows if 5.0 < r[0] < 20.0)


def test_a_stays_out_while_the_check_source_only_grew_less_certain():
    """GIVEN A dropped 7 deg off B while B was sharp (1.5 deg: NIS 12.4), WHEN B's sigma grows to
    3 deg (NIS 4.6: within the gate, not within 1 sigma), A's heading still 7 deg off, THEN A stays
    out (before: it came back 2 s later with the same error, and went again when B sharpened)."""
    rows = _fly(lambda t: 93.0, b_sig=1.5, duration_s=10.0)
    assert rows[-1][3] == "synthetic_ahrs"
    p = _pipeline()
    for k in range(300):
        t = 0.1 * k
        p.azimuth_out, p.ahrs_out = _a(t, 93.0, 1.3), _b(t, 100.0, 1.5 if t < 10.0 else 3.0, air_fused=k + 1)
        readings, not_offered = p._readings(t)
        p.arb, out = arbitrate(p.arb, readings, t, p.arb_params, 0.0, not_offered)
        if t >= 12.0:
            assert out.source == "synthetic_ahrs", t
            assert "disagreed with synthetic_ahrs (now -7.0 deg, NIS 4.6" in out.records["azimuth"].detail


def test_a_less_certain_than_b_does_not_supersede_it():
    """GIVEN A consistent with B (1 deg apart) but less certain (its sigma grown to 4 deg after its fit
    window; B 2 deg), THEN B is offered beside A and both are fused: the published sigma is below
    both and the published heading between them, nearer B (before: A alone at 4 deg)."""
    rows = _fly(lambda t: 101.0, a_sig=4.0, b_sig=2.0, duration_s=5.0)
    t, h, s, src, a = rows[-1]
    assert src == "azimuth+synthetic_ahrs" and a.fused
    assert s < 2.0 and 100.0 < h < 100.5


def R(name, hdg_deg, sig_deg, **kw):
    return SourceReading(name, D2R(hdg_deg), D2R(sig_deg), True, 0.0, **kw)


def test_a_check_source_contradicted_by_another_is_no_evidence():
    """GIVEN B (the most certain check) 20 deg from A, but C disagrees with B and agrees with A, THEN
    A stays consistent (who is wrong is not known); with C agreeing with B instead, A is dropped."""
    chk = AzimuthCheck()
    for k in range(40):
        ok, why, _ = chk.check(D2R(120.0), D2R(1.3), (R("synthetic_ahrs", 100.0, 1.5), R("heading_filter", 119.0, 2.0)),
                               0.1 * k, 9.0)
        assert ok and why == ""
    for k in range(40):
        ok, why, own = chk.check(D2R(120.0), D2R(1.3), (R("synthetic_ahrs", 100.0, 1.5), R("heading_filter", 101.0, 2.0)),
                                 4.0 + 0.1 * k, 9.0)
    assert not ok and "disagrees with synthetic_ahrs: +20.0 deg" in why
    assert own["source_innovation_rad"] == pytest.approx(D2R(20.0))
    assert own["source_innovation_variance_rad2"] == pytest.approx(D2R(1.3) ** 2 + D2R(1.5) ** 2)


def test_no_check_source_leaves_a_standing():
    """GIVEN A dropped, WHEN no check source is a candidate any more (B lost its reference, C not
    consistent), THEN A stands again at once: nothing contradicts it, and it is the only heading."""
    chk = AzimuthCheck()
    for k in range(30):
        ok, _, _ = chk.check(D2R(120.0), D2R(1.3), (R("synthetic_ahrs", 100.0, 1.5),), 0.1 * k, 9.0)
    assert not ok
    ok, why, own = chk.check(D2R(120.0), D2R(1.3), (R("synthetic_ahrs", 100.0, 1.5, consistent=False),), 3.1, 9.0)
    assert ok and why == "" and own == {}


def test_sigmas_that_cross_every_cycle_do_not_flip_the_selection():
    """GIVEN A consistent with B and its sigma 1.31 / 1.33 deg on alternate 20 ms cycles about B's
    1.32 (make run, 2026-12-02: A's and B's sigmas equal to 0.01 deg at 183 s), THEN whether A
    supersedes B is decided at the first comparison (A more certain: A alone) and kept: A's record
    says fused on every cycle and the published source never changes. Before: the verdict was taken
    per cycle, B withdrawn on every other one (250 changes of the fused set in 5 s)."""
    p = _pipeline()
    srcs = []
    for k in range(250):
        t = 0.02 * k
        p.azimuth_out, p.ahrs_out = _a(t, 100.5, 1.31 if k % 2 == 0 else 1.33), _b(t, 100.0, 1.32, air_fused=k)
        readings, not_offered = p._readings(t)
        p.arb, out = arbitrate(p.arb, readings, t, p.arb_params, 0.0, not_offered)
        srcs.append(out.source)
    assert set(srcs) == {"azimuth"}


def test_a_that_stays_less_certain_is_fused_after_the_hold():
    """GIVEN A superseding B (A 1.2 deg, B 1.5), WHEN A's sigma grows to 1.8 deg and stays there
    (its fit window over), THEN B is offered beside A once that has held for
    SOURCE_INCONSISTENT_AFTER_S, and A and B are fused from then on."""
    p = _pipeline()
    srcs = []
    for k in range(300):
        t = 0.02 * k
        p.azimuth_out, p.ahrs_out = _a(t, 100.5, 1.2 if t < 2.0 else 1.8), _b(t, 100.0, 1.5, air_fused=k)
        readings, not_offered = p._readings(t)
        p.arb, out = arbitrate(p.arb, readings, t, p.arb_params, 0.0, not_offered)
        srcs.append((t, out.source))
    first_fused = next(t for t, s in srcs if s == "azimuth+synthetic_ahrs")
    assert all(s == "azimuth" for t, s in srcs if t < first_fused)
    assert first_fused == pytest.approx(2.0 + SOURCE_INCONSISTENT_AFTER_S, abs=0.03)
    assert all(s == "azimuth+synthetic_ahrs" for t, s in srcs if t >= first_fused)


def test_a_drifting_inside_the_gate_is_weighted_by_its_demonstrated_disagreement():
    """GIVEN B right at 100 deg with a conservative 3 deg sigma, and A drifting at -0.03 deg/s with
    a sigma sqrt(1.3^2 + (0.01 t)^2) that grows slower than its error (synthetic_ahrs_accuracy's
    flights: A's in-run bias walks ~3x its 0.01 deg/s prior), WHEN for 300 s A's NIS against B stays
    inside the gate (3.8 at the end: A stays consistent), THEN A's sigma as offered is its own times
    sqrt(mean NIS over 2 s) once that mean exceeds 1 (its own below), B is offered and fused with A
    from ~174 s on, and every published heading is within 2.1 published sigma of 100 deg. Before: A
    superseded B until its own sigma passed B's (272 s), 8.2 deg off at 3.0 deg (2.7 sigma)."""
    p = _pipeline()
    worst, rows = 0.0, []
    for k in range(3000):
        t = 0.1 * k
        own = math.hypot(1.3, 0.01 * t)
        p.azimuth_out, p.ahrs_out = _a(t, 100.0 - 0.03 * t, own), _b(t, 100.0, 3.0, air_fused=k)
        readings, not_offered = p._readings(t)
        p.arb, out = arbitrate(p.arb, readings, t, p.arb_params, 0.0, not_offered)
        worst = max(worst, abs(_err(math.degrees(out.heading_rad), 100.0)) / math.degrees(out.sigma_rad))
        a = out.records["azimuth"]
        rows.append((t, out.source, math.degrees(a.observation_sigma_rad), own, a.source_test_ratio * 9.0))
    assert worst <= 2.1
    for t, src, offered, own, nis in rows:
        if nis < 0.9:                       # agreeing within the sum of the sigmas: A's own sigma
            assert offered == pytest.approx(own, rel=1e-12), t
        if t >= 100.0 and nis > 1.2:        # the mean over 2 s of a slowly growing NIS ~ the NIS now
            assert offered == pytest.approx(own * math.sqrt(nis), rel=0.02), t
        if t < 170.0:
            assert src == "azimuth", t
        if t >= 176.0:
            assert src == "azimuth+synthetic_ahrs", t


def test_the_scale_is_the_mean_nis_over_the_window():
    """AzimuthCheck.sigma_scale: sqrt(max(1, mean NIS against the check source over the last
    SOURCE_INCONSISTENT_AFTER_S)); one disagreeing cycle among agreeing ones moves it by its share."""
    chk = AzimuthCheck()
    b = lambda t: R("synthetic_ahrs", 100.0, 1.5)
    for k in range(20):                                   # 1.9 s agreeing: NIS 0
        chk.check(D2R(100.0), D2R(1.5), (b(0.1 * k),), 0.1 * k, 9.0)
    assert chk.sigma_scale == 1.0
    chk.check(D2R(100.0 + 1.5 * math.sqrt(2.0) * math.sqrt(63.0)), D2R(1.5), (b(2.0),), 2.0, 9.0)  # NIS 63
    assert chk.sigma_scale == pytest.approx(math.sqrt(63.0 / 21.0))       # 21 checks in the window
    chk.check(D2R(100.0), D2R(1.5), (b(4.05),), 4.05, 9.0)                  # the window has moved on
    assert chk.sigma_scale == 1.0
