"""Method B takes back a snapshot after a silent divergence of its reference: the snapshot's attitude,
biases AND covariance (estimators/synthetic_ahrs._trust, core/synthetic_ahrs.hpp ahrs_trust).

GIVEN the GNSS-denied runway flight with the FC's yaw excluded and the GNSS loss at 180 s NOT
signalled, the agreement test finds the FC's attitude drifting (201 s) and B takes back a snapshot
taken 30 s earlier. Before, only the snapshot's attitude block was put beside the current
cross-covariances: no covariance (an eigenvalue -1.2e-5), a negative pitch variance and a math
domain error in the reference at 201.24 s. THEN every published sigma is a positive number and the
covariance stays positive definite, in the reference and the core."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from synthetic_ahrs_accuracy import events_of  # noqa: E402

from estimators import core  # noqa: E402
from estimators import synthetic_ahrs as ref  # noqa: E402
from estimators.geomag import earth_field_ned_gauss  # noqa: E402
from estimators.synthetic_ahrs import ImuEvent, SyntheticAhrsParams  # noqa: E402
from sim.offline import simulate  # noqa: E402

STEPS = [ref.synthetic_ahrs_step] + ([core.synthetic_ahrs_step] if core.B_AVAILABLE else [])


@pytest.fixture(scope="module")
def run():
    return simulate("runway_gnss_denied", seed=0, imu_grade="consumer", imu_rate_hz=100.0, duration_s=215.0)


@pytest.mark.parametrize("step", STEPS, ids=lambda s: s.__module__)
def test_given_a_silent_divergence_when_b_takes_its_snapshot_back_then_its_covariance_stays_one(run, step):
    s = run.site
    params = SyntheticAhrsParams(variant="b2", C_body_from_sensor=s["C_body_from_sensor"], use_fc_yaw=False,
                                 field_nav_gauss=tuple(earth_field_ned_gauss(s["lat_deg"], s["lon_deg"], s["alt_m"],
                                                                             s["decimal_year"])))
    st = ref.synthetic_ahrs_init(params)
    lost = None
    for ev in events_of(run, signalled=False):
        st, out = step(st, ev, params, output=isinstance(ev, ImuEvent))
        if out is not None and out.valid:
            assert all(math.isfinite(x) and x > 0.0 for x in (out.roll_sigma_rad, out.pitch_sigma_rad,
                                                              out.heading_sigma_rad)), ev.time_s
            if lost is None and not out.reference_trusted and ev.time_s > 100.0:
                lost = (ev.time_s, out.reference_reason)
    assert lost is not None and "disagrees" in lost[1], lost      # the silent path was taken
    P = (st.to_state() if hasattr(st, "to_state") else st).kf2.P
    assert np.linalg.eigvalsh(P).min() > 0.0
