"""Method C's attitude filter with a gyro bias that does NOT move in flight (estimators/polar_attitude):
the other side of tests/test_polar_gyro_drift.py. The bias model must follow a ramp when the data show
one (that test) and stay tight when they do not (this one): 4070a47 widened the bias walk to 0.2 deg/s
over 600 s for ArduPlane SITL's ramp, and every steady-bias bench lost roll/pitch (the bias chased the
gusts). Now the walk is narrow again and a bias-rate state carries the ramp.

Measured on this flight (seed 3, the circuit of test_polar_gyro_drift with 16 legs, ~520 s after the
take-off, errors from 60 s after it), roll / pitch RMS: the narrow walk alone (0.05 deg/s, 1800 s: before
4070a47) 0.19 / 0.18 deg; 4070a47's wide walk 0.31 / 0.31; this model 0.25 / 0.27. So it is better than
the wide walk, not as tight as the narrow walk alone (which lags a ramp: 1.10 deg of roll in
test_polar_gyro_drift, where this model has 0.20). Analytical motion, seeded noise; truth only scores."""
import math

import numpy as np

from dataclasses import replace

from estimators.polar_attitude import (PolarAttitudeParams, polar_attitude_estimate, polar_attitude_init,
                                       polar_attitude_step)
from test_polar_gyro_drift import DT, _square_circuit

BIAS_RAD_S = np.radians([0.1, -0.08, 0.05])


def _fly_steady(params: PolarAttitudeParams, seed: int = 3, legs: int = 16):
    """The circuit with a constant bias measured at rest (the zero-rate updates' 0.005 deg/s), the
    re-levelling allowed until the take-off as the Pipeline does (which opens the bias rate and the
    bias step for flight); (roll errors, pitch errors, roll sigmas, pitch sigmas) in deg from 60 s
    after the take-off."""
    flying_params = replace(params, relevel_allowed=False)
    rng = np.random.default_rng(seed)
    st = polar_attitude_init(params, BIAS_RAD_S, math.radians(0.005))
    t_takeoff, out = None, []
    a_v = np.zeros(3)
    phi_gm = math.exp(-DT / 0.5)
    for t, phi, psi, w, f, flying in _square_circuit(legs=legs):
        if flying and t_takeoff is None:
            t_takeoff = t
        if flying:   # gusts: the vehicle acceleration the filter models (GM 0.2 m/s^2, 0.5 s)
            a_v = phi_gm * a_v + rng.normal(0.0, 0.2 * math.sqrt(1.0 - phi_gm ** 2), 3)
        gyro = w + BIAS_RAD_S + rng.normal(0.0, 0.002, 3)
        accel = f + (a_v if flying else 0.0) + rng.normal(0.0, 0.05, 3)
        st, _ = polar_attitude_step(st, t, gyro, accel, flying_params if flying else params)
        if flying and t - t_takeoff >= 60.0:
            est = polar_attitude_estimate(st)
            out.append((math.remainder(est.roll_rad - phi, 2.0 * math.pi), est.pitch_rad,
                        math.sqrt(est.cov_roll_pitch_rad2[0, 0]), math.sqrt(est.cov_roll_pitch_rad2[1, 1])))
    return np.degrees(np.array(out)).T


def test_given_a_steady_gyro_bias_when_flying_a_long_circuit_then_roll_and_pitch_stay_tight():
    er, ep, sr, sp = _fly_steady(PolarAttitudeParams())
    roll, pitch = float(np.sqrt(np.mean(er ** 2))), float(np.sqrt(np.mean(ep ** 2)))
    within = float(np.mean((np.abs(er) <= 3.0 * sr) & (np.abs(ep) <= 3.0 * sp)))
    print(f"roll RMS {roll:.3f} deg, pitch RMS {pitch:.3f} deg, both within 3 sigma {within:.3f}")
    # 4070a47's wide walk: 0.31 / 0.31 deg here (fails); this model 0.25 / 0.27
    assert roll <= 0.29 and pitch <= 0.29, (roll, pitch)
    assert within >= 0.95
