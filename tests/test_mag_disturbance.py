"""Magnetic disturbances in motion (issue 18 item 4, estimators/mag_disturbance): a magnet attached
is a new hard iron that is learnt again; a magnet nearby is a field that departs from the recent
undisturbed one and is rejected with a named reason. Synthetic body turns (seeded), pure steps."""
import math

import numpy as np
import pytest

from estimators.mag_disturbance import (MagDisturbanceParams, MagDisturbanceState, mag_disturbance_params_for_field,
                                        mag_disturbance_step)
from estimators.rotations import dcm_from_quat, quat_from_euler, quat_from_rotvec, quat_mul, quat_normalize

DT = 0.02
FIELD_NED_GAUSS = np.array([0.21, 0.01, 0.44])


def rate_rad_s(t):
    """A slow hand-held tumble whose axis wanders (a fixed body axis would leave the hard iron
    along it unobservable): 15-25 deg/s."""
    return np.radians([20.0 * math.sin(0.5 * t), 15.0 * math.cos(0.3 * t), 20.0 * math.sin(0.2 * t + 1.0)])


def _run(seconds, hard_iron_at, nav_extra_at=lambda t: np.zeros(3), seed=0, state=None, t0=0.0, q0=None):
    """Feed ``seconds`` of a turning body; ``hard_iron_at(t)`` (body) and ``nav_extra_at(t)`` (NED)
    are the disturbances. Returns the final (state, q, t) and the per-sample verdicts."""
    rng = np.random.default_rng(seed)
    p = mag_disturbance_params_for_field(FIELD_NED_GAUSS)
    st = state if state is not None else MagDisturbanceState()
    q = q0 if q0 is not None else quat_from_euler(0.1, -0.2, 1.0)
    t, out = t0, []
    for _ in range(int(round(seconds / DT))):
        q = quat_normalize(quat_mul(q, quat_from_rotvec(rate_rad_s(t) * DT)))
        t += DT
        C = dcm_from_quat(q)
        m = C.T @ (FIELD_NED_GAUSS + nav_extra_at(t)) + hard_iron_at(t) + rng.normal(0.0, 0.003, 3)
        # the attitude filter's attitude: exact tilt, an arbitrary platform azimuth (30 deg)
        q_P = quat_mul(quat_from_euler(0.0, 0.0, 0.5), q)
        st, v = mag_disturbance_step(st, t, m, q_P, p)
        out.append((t, v))
    return st, q, t, out


def test_given_an_uncompensated_hard_iron_when_the_body_turns_then_it_is_learnt_and_the_field_usable():
    b0 = np.array([0.015, -0.010, 0.012])
    st, _, _, out = _run(20.0, lambda t: b0)
    v = out[-1][1]
    assert v.usable and v.reason == ""
    assert np.all(np.abs(v.hard_iron_gauss - b0) <= 3.0 * v.hard_iron_sigma_gauss)
    assert v.hard_iron_sigma_gauss < 0.008          # measured 0.0063 G after 12 s
    assert np.allclose(v.mag_corrected_gauss, out[-1][1].mag_corrected_gauss)
    assert st.n_relearns == 0


def test_given_a_magnet_attached_when_the_body_turns_then_its_hard_iron_is_relearnt_within_6_s():
    b0 = np.array([0.015, -0.010, 0.012])
    magnet = np.array([0.18, -0.20, 0.12])                 # ~0.3 G, as any_motion_magnet_attached
    st, q, t, _ = _run(15.0, lambda t: b0)
    st, q, t, out = _run(20.0, lambda t: b0 + magnet, state=st, t0=t, q0=q)
    # THEN it is found changed (once), rejected meanwhile with a named reason ...
    assert st.n_relearns == 1
    first_rejected = next(i for i, (_, v) in enumerate(out) if not v.usable)
    assert out[first_rejected][0] - 15.0 < 0.5
    reasons = {v.reason.split(":")[0] for _, v in out if not v.usable}
    assert reasons <= {"magnetic disturbance", "re-learning its hard iron (a magnet attached?)"}, reasons
    assert "re-learning its hard iron (a magnet attached?)" in reasons
    # ... and learnt again, not rejected forever: usable for good from at most 6 s after (measured
    # 4.5 s turning at 15-25 deg/s: three inconsistent 30 deg pairs, then two to learn it), the new
    # hard iron within 3 sigma
    last_bad = max(tt for tt, v in out if not v.usable)
    assert last_bad - 15.0 < 6.0, last_bad - 15.0
    v = out[-1][1]
    assert v.usable
    assert np.all(np.abs(v.hard_iron_gauss - (b0 + magnet)) <= 3.0 * v.hard_iron_sigma_gauss + 1e-9)
    assert v.hard_iron_sigma_gauss < 0.01           # measured 0.007 G 20 s after


def test_given_a_magnet_nearby_when_the_field_norm_departs_then_rejected_and_the_hard_iron_kept():
    b0 = np.array([0.015, -0.010, 0.012])
    nearby = np.array([0.22, -0.18, 0.10])                 # fixed in NED: as any_motion_magnet_nearby
    st, q, t, _ = _run(15.0, lambda t: b0)
    b_before = st.hard_iron_gauss.copy()
    st, q, t, out = _run(20.0, lambda t: b0, lambda t: nearby if t < 25.0 else np.zeros(3), state=st, t0=t, q0=q)
    during = [(tt, v) for tt, v in out if 15.3 < tt < 25.0]
    assert all(not v.usable and v.reason.startswith("magnetic disturbance: field") for _, v in during)
    assert "vs the recent undisturbed" in during[-1][1].reason
    assert all(v.mag_corrected_gauss is None for _, v in during)
    # the magnet is not mistaken for a new hard iron: the pairs stayed consistent
    assert st.n_relearns == 0 and np.allclose(st.hard_iron_gauss, b_before, atol=0.003)
    # usable again within 1 s of its removal
    back = next(tt for tt, v in out if tt > 25.0 and v.usable)
    assert back - 25.0 < 1.0
    assert all(v.usable for tt, v in out if tt > back)


def test_a_field_off_the_model_is_never_the_reference_however_long_it_lasts():
    # a magnet lying beside the vehicle from the start: norm 0.71 G against the model's 0.49 G
    st, _, _, out = _run(40.0, lambda t: np.zeros(3), lambda t: np.array([0.22, -0.18, 0.10]))
    assert not any(v.usable for _, v in out)
    assert out[-1][1].reason.startswith("magnetic disturbance") and "not the model's" in out[-1][1].reason


def test_bad_input_is_a_clear_error():
    p = mag_disturbance_params_for_field(FIELD_NED_GAUSS)
    with pytest.raises(ValueError, match="must be finite"):
        mag_disturbance_step(MagDisturbanceState(), 0.0, [math.nan, 0, 0], [1, 0, 0, 0], p)
    with pytest.raises(ValueError, match="must not decrease"):
        st, _ = mag_disturbance_step(MagDisturbanceState(), 1.0, [0.2, 0, 0.4], [1, 0, 0, 0], p)
        mag_disturbance_step(st, 0.5, [0.2, 0, 0.4], [1, 0, 0, 0], p)
    with pytest.raises(ValueError, match="norm_tolerance"):
        MagDisturbanceParams(model_norm_gauss=0.5, model_dip_rad=1.0, norm_tolerance=0.0)
