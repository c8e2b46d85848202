"""Decoders: each message encoded by pymavlink, packed to bytes, parsed back, decoded; units
checked against values computed by hand."""
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io import decode as dec

G0 = 9.80665


def wire(msg):
    """Pack with a MAVLink 2 sender and parse back: the decoders see what the link would see."""
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    buf = msg.pack(tx)
    rx = mavlink2.MAVLink(None)
    out = rx.parse_buffer(buf)
    assert out is not None and len(out) == 1 and out[0].get_type() == msg.get_type()
    return out[0]


def test_raw_imu_units():
    m = wire(mavlink2.MAVLink_raw_imu_message(123_456_789, 500, -250, -1002, 1234, -5, 0, 210, -45, 390, 2, 4500))
    s = dec.decode_raw_imu(m, 123.456789, 7.0)
    # 500 mG = 0.5 g = 4.903325 m/s^2 ; -1002 mG = -(9.80665 + 0.0196133) = -9.8262633 m/s^2
    np.testing.assert_allclose(s.accel_m_s2, [4.903325, -2.4516625, -9.8262633], rtol=0, atol=1e-9)
    np.testing.assert_allclose(s.gyro_rad_s, [1.234, -0.005, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.mag_gauss, [0.210, -0.045, 0.390], rtol=0, atol=1e-12)
    assert (s.source, s.imu_id, s.time_fc_s, s.time_rx_s) == ("RAW_IMU", 2, 123.456789, 7.0)


def test_raw_imu_without_compass_gives_mag_none():
    m = wire(mavlink2.MAVLink_raw_imu_message(1, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0, 0))
    assert dec.decode_raw_imu(m, 0.0, 0.0).mag_gauss is None


def test_scaled_imu_units():
    m = wire(mavlink2.MAVLink_scaled_imu_message(5000, -1000, 0, 0, 0, 0, 100, 300, 0, -400, 0))
    s = dec.decode_scaled_imu(m, 5.0, 0.0)
    np.testing.assert_allclose(s.accel_m_s2, [-G0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(s.gyro_rad_s, [0, 0, 0.1], atol=1e-12)
    np.testing.assert_allclose(s.mag_gauss, [0.3, 0.0, -0.4], atol=1e-12)
    assert s.source == "SCALED_IMU"


def test_highres_imu_units_and_pressure():
    m = wire(mavlink2.MAVLink_highres_imu_message(
        2_000_000, 0.1, -0.2, -9.81, 0.01, 0.02, -0.03, 0.21, 0.02, 0.43, 1001.5, 2.25, 100.0, 15.0, 0x1FFF, 0))
    imu, p = dec.decode_highres_imu(m, 2.0, 0.5)
    np.testing.assert_allclose(imu.accel_m_s2, [0.1, -0.2, -9.81], atol=1e-6)  # float32 on the wire
    np.testing.assert_allclose(imu.gyro_rad_s, [0.01, 0.02, -0.03], atol=1e-8)
    np.testing.assert_allclose(imu.mag_gauss, [0.21, 0.02, 0.43], atol=1e-7)
    assert p.press_abs_pa == pytest.approx(100150.0, abs=1e-2)  # 1001.5 hPa
    assert p.press_diff_pa == pytest.approx(225.0, abs=1e-4)  # 2.25 hPa
    assert p.temperature_k == pytest.approx(288.15, abs=1e-5)  # 15 degC
    assert p.source == "HIGHRES_IMU" and p.time_fc_s == 2.0


def test_highres_imu_fields_updated_bits():
    # accel + gyro only (bits 0..5): no mag, no pressure sample
    m = wire(mavlink2.MAVLink_highres_imu_message(
        1, 0, 0, -9.8, 0, 0, 0, 9.0, 9.0, 9.0, 1000.0, 0, 0, 20.0, 0x3F, 0))
    imu, p = dec.decode_highres_imu(m, 0.0, 0.0)
    assert imu.mag_gauss is None and p is None
    # missing gyro bits: not a usable IMU sample
    m = wire(mavlink2.MAVLink_highres_imu_message(1, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0x7, 0))
    with pytest.raises(dec.NonFiniteField):
        dec.decode_highres_imu(m, 0.0, 0.0)


def test_highres_optional_nan_becomes_none_and_is_counted():
    nan = float("nan")
    m = wire(mavlink2.MAVLink_highres_imu_message(1, 0, 0, -9.8, 0, 0, 0, nan, 0, 0, 1000.0, nan, 0, 20.0, 0xFFFF, 0))
    opt = dec.OptionalFieldCounter()
    imu, p = dec.decode_highres_imu(m, 0.0, 0.0, opt)
    assert imu.mag_gauss is None and p.press_diff_pa is None and p.press_abs_pa == pytest.approx(1e5)
    assert opt.count == 2


def test_scaled_pressure_units():
    m = wire(mavlink2.MAVLink_scaled_pressure_message(12_345, 1013.25, -0.75, -1234, 0))
    p = dec.decode_scaled_pressure(m, 12.345, 1.0)
    assert p.press_abs_pa == pytest.approx(101325.0, abs=1e-2)
    assert p.press_diff_pa == pytest.approx(-75.0, abs=1e-4)
    assert p.temperature_k == pytest.approx(273.15 - 12.34, abs=1e-9)  # -1234 cdegC


def test_attitude():
    m = wire(mavlink2.MAVLink_attitude_message(777, -0.5, 0.25, -3.0, 0.1, -0.1, 0.2))
    a = dec.decode_attitude(m, 0.777, 0.0)
    assert (a.roll_rad, a.pitch_rad, a.yaw_rad) == pytest.approx((-0.5, 0.25, -3.0), abs=1e-7)
    np.testing.assert_allclose(a.rates_rad_s, [0.1, -0.1, 0.2], atol=1e-7)
    m = wire(mavlink2.MAVLink_attitude_message(777, 0, 0, float("inf"), 0, 0, 0))
    with pytest.raises(dec.NonFiniteField, match="ATTITUDE.yaw"):
        dec.decode_attitude(m, 0.0, 0.0)


def test_heartbeat():
    m = wire(mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                                mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | 1, 0x40000, 4, 3))
    h = dec.decode_heartbeat(m, 3.0)
    assert h.autopilot == "px4" and h.armed and h.custom_mode == 0x40000 and h.vehicle_type == 2
    assert (h.system_id, h.component_id) == (1, 1)
    assert dec.autopilot_name(mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA) == "ardupilot"
    assert dec.autopilot_name(mavlink2.MAV_AUTOPILOT_GENERIC) == "other"


def test_ekf_status_and_estimator_status():
    m = wire(mavlink2.MAVLink_ekf_status_report_message(
        mavlink2.EKF_ATTITUDE | mavlink2.EKF_UNINITIALIZED, 0.1, 0.2, 0.3, 0.8, 0.0, 0.0))
    e = dec.decode_ekf_status_report(m, 1.0)
    assert not e.attitude_ok and not e.horiz_pos_ok  # uninitialised EKF: attitude not trusted
    assert e.compass_variance == pytest.approx(0.8, abs=1e-7) and e.time_fc_s is None
    m = wire(mavlink2.MAVLink_estimator_status_message(
        9_000_000, mavlink2.ESTIMATOR_ATTITUDE | mavlink2.ESTIMATOR_POS_HORIZ_ABS, 0.1, 0.2, 0.3, 0.45, 0, 0, 0, 0))
    e = dec.decode_estimator_status(m, 9.0, 1.0)
    assert e.attitude_ok and e.horiz_pos_ok and e.source == "ESTIMATOR_STATUS"
    assert e.compass_variance == pytest.approx(0.45, abs=1e-7) and e.time_fc_s == 9.0


def test_sys_status_health_none_when_absent():
    gyro, acc, mag, ahrs = 1, 2, 4, 0x200000  # baro (8) absent
    m = wire(mavlink2.MAVLink_sys_status_message(gyro | acc | mag | ahrs, gyro | acc | ahrs, gyro | ahrs,
                                                 999, 0xFFFF, -1, -1, 150, 0, 0, 0, 0, 0, 0, 0, 0))
    s = dec.decode_sys_status(m, 0.0)
    assert s.gyro_healthy is True and s.accel_healthy is False and s.ahrs_healthy is True
    assert s.mag_healthy is None  # present but disabled
    assert s.baro_healthy is None  # absent
    assert s.battery_voltage_v is None and s.load_fraction == pytest.approx(0.999)
    assert s.drop_rate_comm_fraction == pytest.approx(0.015)


def test_command_ack():
    m = wire(mavlink2.MAVLink_command_ack_message(511, 3, 0, 0, 1, 191))
    a = dec.decode_command_ack(m, 2.0)
    assert (a.command, a.result, a.target_system, a.target_component) == (511, 3, 1, 191)


def test_g0_matches_ardupilot():
    assert dec.MG_TO_M_S2 * 1000.0 == pytest.approx(G0, abs=0) and math.isclose(dec.G0_M_S2, 9.80665)
