"""What the Pipeline gives method C's attitude filter from the config and from what the vehicle
measures: the accelerometer-bias prior ([imu] accel_bias_sigma_m_s2) and the speed that bounds the
centripetal acceleration of a turn (the measured airspeed, else [heading] manoeuvre_speed_m_s, else
the vehicle's). No simulator: analytical inputs."""
import math

import numpy as np
import pytest

from estimators.air_data import air_density_kg_m3, isa_temperature_k, pressure_altitude_m
from mavlink_io.samples import ImuSample, PressureSample
from service.config import validate
from service.pipeline import MULTICOPTER_MANOEUVRE_SPEED_M_S, Pipeline

G = 9.80665


def _pipeline(vehicle="hand", **heading) -> Pipeline:
    return Pipeline(validate({"site": {"lat_deg": 48.0, "lon_deg": 11.0, "alt_m": 500.0, "decimal_year": 2026.5},
                              "imu": {"accel_bias_sigma_m_s2": 0.07},
                              "launch": {"case": "aligned", "vehicle": vehicle},
                              "heading": {"use_fc_yaw": False, **heading},
                              "azimuth": {"solve_in_background": False}}))


def _rest(p: Pipeline, t0: float, n: int) -> None:
    for k in range(n):
        t = t0 + k * 0.02
        p.on_imu(ImuSample(t, t, np.zeros(3), np.array([0.0, 0.0, -G]), np.array([0.2, 0.0, 0.4]), "RAW_IMU"))


def test_given_the_config_then_the_attitude_filter_takes_its_accelerometer_bias_prior():
    assert _pipeline().polar_att_params.accel_bias_sigma_m_s2 == 0.07


@pytest.mark.parametrize("vehicle,heading,want", [
    ("hand", {}, 25.0),                                   # a fixed wing: the cruise speed
    ("runway", {"cruise_speed_m_s": 18.0}, 18.0),
    ("multicopter", {}, MULTICOPTER_MANOEUVRE_SPEED_M_S),
    ("multicopter", {"manoeuvre_speed_m_s": 1.5}, 1.5),   # configured: a hand-carried IMU
])
def test_given_no_air_data_then_the_manoeuvre_speed_is_the_configured_or_the_vehicles(vehicle, heading, want):
    p = _pipeline(vehicle, **heading)
    assert p.polar_att_params.manoeuvre_speed_m_s == want
    _rest(p, 0.0, 10)
    assert p.polar_att_params.manoeuvre_speed_m_s == want


def test_given_a_measured_airspeed_then_it_replaces_the_default_and_is_dropped_when_stale():
    # GIVEN a fixed wing (default: its cruise speed, 18 m/s here) whose FC reports a pitot at 21 m/s
    p = _pipeline("runway", cruise_speed_m_s=18.0)
    press, tas = 95000.0, 21.0
    temp_k = isa_temperature_k(pressure_altitude_m(press))       # what the air data assumes
    q_c = 0.5 * air_density_kg_m3(press, temp_k) * tas * tas
    for k in range(5):
        p.on_pressure(PressureSample(0.1 * k, 0.1 * k, press, q_c, temp_k))
    # WHEN the filters step THEN C's attitude filter takes the measured airspeed
    _rest(p, 0.42, 10)
    assert p.polar_att_params.manoeuvre_speed_m_s == pytest.approx(tas, abs=0.05)
    # ... and once the air data is older than a second, the vehicle's default again
    _rest(p, 2.0, 10)
    assert p.polar_att_params.manoeuvre_speed_m_s == 18.0
    assert math.isfinite(p.polar_att_params.manoeuvre_speed_m_s)


def test_given_a_multicopter_then_its_differential_pressure_is_no_airspeed():
    # GIVEN a multicopter whose FC sends SCALED_PRESSURE with a differential pressure near 0 (no pitot:
    # arducopter-flight.tlog read 0 m/s on 2547 of 2857 steps, and C took 0 m/s: roll 6.0 -> 46.6 deg RMS)
    p = _pipeline("multicopter")
    for k in range(5):
        p.on_pressure(PressureSample(0.1 * k, 0.1 * k, 95000.0, 0.0, None))
    # WHEN the filters step THEN C keeps the multicopter's bound
    _rest(p, 0.42, 10)
    assert p.polar_att_params.manoeuvre_speed_m_s == MULTICOPTER_MANOEUVRE_SPEED_M_S == 25.0


def test_given_a_pitot_reading_zero_on_the_ground_then_the_speed_is_zero_and_accepted():
    # a fixed wing armed on its launcher: the air data says 0 m/s, so no centripetal allowance
    p = _pipeline("launcher")
    for k in range(5):
        p.on_pressure(PressureSample(0.1 * k, 0.1 * k, 95000.0, 0.0, None))
    _rest(p, 0.42, 10)
    assert p.polar_att_params.manoeuvre_speed_m_s == 0.0
