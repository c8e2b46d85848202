"""Method C's heading filter weighs its magnetometer by how far the body has turned
(estimators/polar_heading ``mag_error_turn_rad``): the body-fixed part of the measurement error
(tilt error through the dip, the floor) is another draw once the body has turned ~1 rad, the
declination error (fixed in the navigation frame) never is. Analytical inputs: a level body
turning about its vertical, a clean field, the platform formulation."""
import math

import numpy as np
import pytest

from estimators.polar_heading import PolarHeadingParams, polar_heading_init, polar_heading_step, HeadingInputs
from estimators.rotations import dcm_from_quat, quat_from_euler

DT = 0.02
FIELD_NED_GAUSS = np.array([0.20, 0.0, 0.43])          # dip 65 deg, no declination


def _heading_var_after(rate_rad_s: float, seconds: float, decl_sigma_rad: float,
                       params: PolarHeadingParams = PolarHeadingParams()) -> float:
    """The filter's own heading variance (rad^2) after ``seconds`` of a yaw turn at ``rate``."""
    st = polar_heading_init(params=params)
    cov_att = np.diag([math.radians(0.3) ** 2] * 3)
    for k in range(int(round(seconds / DT))):
        t = (k + 1) * DT
        q = quat_from_euler(0.0, 0.0, rate_rad_s * t)
        mag_b = dcm_from_quat(q).T @ FIELD_NED_GAUSS
        st, _ = polar_heading_step(st, HeadingInputs(
            t, np.array([0.0, 0.0, rate_rad_s]), math.nan, math.nan, np.zeros((2, 2)), mag_b, 0.0,
            decl_sigma_rad, 0.0, q, cov_att), params)
    return float(st.P[0, 0])


def test_given_a_turning_body_then_its_magnetometer_counts_more_than_a_still_ones():
    # GIVEN no declination error WHEN the body turns at 30 deg/s (1 rad every 1.9 s) for 20 s
    still = _heading_var_after(0.0, 20.0, 0.0)
    turning = _heading_var_after(math.radians(30.0), 20.0, 0.0)
    # THEN its heading variance ends 9x below the still body's (2.14 -> 0.71 deg; 30 s / 1.9 s = 16x
    # per measurement, less the prior and the process noise)
    assert turning < still / 8.0, (math.degrees(math.sqrt(still)), math.degrees(math.sqrt(turning)))


def test_given_a_declination_error_then_turning_does_not_average_it_away():
    # GIVEN a declination sigma that dominates the measurement error (2 deg, fixed in N)
    sd = math.radians(2.0)
    still = _heading_var_after(0.0, 20.0, sd)
    turning = _heading_var_after(math.radians(30.0), 20.0, sd)
    # THEN turning gains little: that part stays counted once per 30 s (3.21 -> 2.99 deg)
    assert turning > still / 2.0, (math.degrees(math.sqrt(still)), math.degrees(math.sqrt(turning)))


def test_the_turn_weighting_switched_off_gives_the_still_weighting():
    p = PolarHeadingParams(mag_error_turn_rad=0.0)
    assert _heading_var_after(math.radians(30.0), 10.0, 0.0, p) == pytest.approx(
        _heading_var_after(0.0, 10.0, 0.0, p), rel=0.05)
