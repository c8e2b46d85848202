"""Method C's attitude filter in flight with a gyro bias that moves after the rest (estimators/
polar_attitude): ArduPlane SITL's gyro drifts 0.05 deg/s per minute on every axis (its
SIM_DRIFT_SPEED), reads 0 at rest, and the zero-rate updates pin the filter's bias there to
~0.005 deg/s; a MEMS gyro's bias likewise follows its temperature once the motors run. And the
levelling at start on a window that was not still (SITL's first samples after boot).
Analytical motion, seeded noise; the truth only scores."""
import math

import numpy as np

from estimators.polar_attitude import (PolarAttitudeParams, polar_attitude_estimate, polar_attitude_init,
                                       polar_attitude_step)
from estimators.rotations import dcm_from_quat, quat_from_euler

G = 9.80665
DT = 0.02
SPEED_M_S = 22.0
BANK_RAD = math.radians(40.0)
DRIFT_RAD_S_PER_S = math.radians(0.05) / 60.0     # SITL's 0.05 deg/s per minute


def _square_circuit(rest_s: float = 30.0, legs: int = 6):
    """Rest, then ``legs`` x (20 s straight and level, a coordinated 90 deg turn: roll in at
    20 deg/s to 40 deg, turn, roll out). Yields (t, roll, yaw, body rates, specific force in body)."""
    t, phi, psi = 0.0, 0.0, 0.0
    roll_rate = math.radians(20.0)
    n_rest = int(round(rest_s / DT))
    for _ in range(n_rest):
        t += DT
        yield t, 0.0, 0.0, np.zeros(3), np.array([0.0, 0.0, -G]), False
    for _ in range(legs):
        plan = [("straight", 20.0)]
        for kind, dur in plan:
            for _ in range(int(round(dur / DT))):
                t += DT
                yield t, phi, psi, np.zeros(3), np.array([0.0, 0.0, -G]), True
        psi_target = psi + math.pi / 2.0
        stage = "in"
        while True:
            if stage == "in":
                p = roll_rate if phi < BANK_RAD else 0.0
                if phi >= BANK_RAD:
                    stage = "hold"
            if stage == "hold":
                p = 0.0
                # roll out so the heading ends near the target (the roll-out turns ~psi_dot_max / 2 x 2 s)
                if psi_target - psi <= 0.5 * G * math.tan(BANK_RAD) / SPEED_M_S * (BANK_RAD / roll_rate):
                    stage = "out"
            if stage == "out":
                p = -roll_rate
                if phi <= 0.0:
                    phi = 0.0
                    break
            phi_mid = phi + 0.5 * p * DT
            psi_dot = G * math.tan(phi_mid) / SPEED_M_S
            w = np.array([p, psi_dot * math.sin(phi_mid), psi_dot * math.cos(phi_mid)])
            # coordinated level turn: specific force along body z, g / cos(phi)
            f = np.array([0.0, 0.0, -G / math.cos(phi_mid)])
            phi += p * DT
            psi += psi_dot * DT
            t += DT
            yield t, phi, psi, w, f, True


def _fly(params: PolarAttitudeParams, seed: int = 3):
    """The circuit with the bias ramping from the take-off; (roll errors deg, roll sigmas deg) from
    60 s after the take-off, and the final state."""
    rng = np.random.default_rng(seed)
    st = polar_attitude_init(params, np.zeros(3), math.radians(0.005))   # as after the zero-rate updates
    t_takeoff, errs, sig = None, [], []
    a_v = np.zeros(3)
    phi_gm = math.exp(-DT / 0.5)
    for t, phi, psi, w, f, flying in _square_circuit():
        if flying and t_takeoff is None:
            t_takeoff = t
        bias = np.full(3, DRIFT_RAD_S_PER_S * (t - t_takeoff)) if flying else np.zeros(3)
        if flying:   # gusts: the vehicle acceleration the filter models (GM 0.2 m/s^2, 0.5 s)
            a_v = phi_gm * a_v + rng.normal(0.0, 0.2 * math.sqrt(1.0 - phi_gm ** 2), 3)
        gyro = w + bias + rng.normal(0.0, 0.002, 3)
        accel = f + (a_v if flying else 0.0) + rng.normal(0.0, 0.05, 3)
        st, _ = polar_attitude_step(st, t, gyro, accel, params)
        if flying and t - t_takeoff >= 60.0:
            est = polar_attitude_estimate(st)
            errs.append(math.degrees(math.remainder(est.roll_rad - phi, 2.0 * math.pi)))
            sig.append(math.degrees(math.sqrt(est.cov_roll_pitch_rad2[0, 0])))
    return np.array(errs), np.array(sig), st


def test_given_a_gyro_bias_drifting_after_the_rest_when_flying_a_circuit_then_roll_stays_within_a_degree():
    errs, sig, st = _fly(PolarAttitudeParams())
    rms = float(np.sqrt(np.mean(errs ** 2)))
    print(f"roll RMS {rms:.2f} deg, max {np.max(np.abs(errs)):.2f}, within 3 sigma {np.mean(np.abs(errs) <= 3 * sig):.3f}, "
          f"bias learnt {np.degrees(st.x_hat[0:3])} deg/s")
    assert rms <= 1.0, rms
    assert np.mean(np.abs(errs) <= 3.0 * sig) >= 0.95


def test_given_a_levelling_window_that_was_not_still_then_the_pitch_is_levelled_not_the_accel_bias():
    # ArduPlane SITL at boot (compass flight, 2026-12-02): for the first 0.45 s the specific force
    # along x swings from +1.4 to -2.1 m/s^2 and back (the airframe settling), the gyros read 0;
    # then the vehicle is still and level. 30 s at rest
    rng = np.random.default_rng(5)
    params = PolarAttitudeParams()
    st = polar_attitude_init(params)
    t = 0.0
    for k in range(int(30.0 / DT)):
        fx = -2.1 * math.sin(math.pi * t / 0.45) if t < 0.45 else 0.0
        f = np.array([fx, 0.0, -G]) + rng.normal(0.0, 0.02, 3)
        t += DT
        st, _ = polar_attitude_step(st, t, rng.normal(0.0, 0.001, 3), f, params)
    est = polar_attitude_estimate(st)
    print(f"pitch {math.degrees(est.pitch_rad):.3f} deg, accel bias x {st.x_hat[12]:.3f} m/s^2")
    assert abs(math.degrees(est.pitch_rad)) <= 0.2
    assert abs(st.x_hat[12]) <= 0.03
