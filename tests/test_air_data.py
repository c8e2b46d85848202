"""Air data (METHODS.md B): ISA altitude, density, TAS, altitude rate and pitot flags."""
import math

import numpy as np
import pytest

from estimators.air_data import (AirDataParams, AirDataState, air_data_step,
                                 air_density_kg_m3, isa_temperature_k, pressure_altitude_m,
                                 true_airspeed_m_s)


def isa_pressure_pa(h_m):
    """Inverse ISA troposphere, written independently: p = p0 (1 - L h / T0)^(g / (R L))."""
    return 101325.0 * (1.0 - 0.0065 * h_m / 288.15) ** (9.80665 / (287.05287 * 0.0065))


@pytest.mark.parametrize("press_pa,alt_m", [
    (101325.0, 0.0),            # ISA table values (ICAO Doc 7488)
    (89874.57, 1000.0),
    (54019.9, 5000.0),
    (26436.3, 10000.0),
    (22632.06, 11000.0),
    (12044.6, 15000.0),         # isothermal layer
])
def test_pressure_altitude_against_isa_table(press_pa, alt_m):
    assert pressure_altitude_m(press_pa) == pytest.approx(alt_m, abs=0.3)


def test_density_and_tas_hand_values():
    # sea level ISA: rho = 101325 / (287.05287 * 288.15) = 1.225 kg/m^3
    assert air_density_kg_m3(101325.0, 288.15) == pytest.approx(1.2250, abs=1e-4)
    # q_c = 1/2 rho v^2 = 0.5 * 1.225 * 20^2 = 245 Pa  ->  20 m/s
    assert true_airspeed_m_s(245.0, 1.225) == pytest.approx(20.0, rel=1e-12)
    assert true_airspeed_m_s(-3.0, 1.225) == 0.0
    # 1000 m ISA: T = 281.65 K, rho = 89874.57 / (287.05287 * 281.65) = 1.11164
    assert isa_temperature_k(1000.0) == pytest.approx(281.65, abs=1e-9)
    assert air_density_kg_m3(89874.57, 281.65) == pytest.approx(1.11164, abs=1e-4)


def test_step_isa_vs_measured_temperature():
    st = AirDataState()
    p = isa_pressure_pa(1000.0)
    qc = 0.5 * 1.11164 * 25.0 ** 2
    st1, ad = air_data_step(st, p, qc, 320.0, 0.0, AirDataParams())
    assert ad.temperature_used_k == pytest.approx(281.65, abs=1e-6)
    assert ad.tas_m_s == pytest.approx(25.0, rel=1e-4)
    _, ad2 = air_data_step(st, p, qc, 320.0, 0.0, AirDataParams(use_measured_temperature=True))
    assert ad2.temperature_used_k == 320.0
    assert ad2.tas_m_s == pytest.approx(25.0 * math.sqrt(320.0 / 281.65), rel=1e-4)


def test_altitude_rate_converges_to_constant_climb():
    params = AirDataParams(alt_rate_tau_s=1.0)
    st = AirDataState()
    rates = []
    for k in range(600):  # 12 s at 50 Hz, climbing at 4 m/s from 200 m
        t = 0.02 * k
        st, ad = air_data_step(st, isa_pressure_pa(200.0 + 4.0 * t), 300.0, None, t, params)
        rates.append((t, ad.alt_rate_m_s, ad.rate_valid))
    assert not rates[10][2] and rates[-1][2]
    assert rates[-1][1] == pytest.approx(4.0, abs=1e-4)
    # first-order response: after 3 T the error is below e^-3 of the step (plus discretisation)
    t3 = [r for r in rates if r[0] >= 3.0][0]
    assert abs(t3[1] - 4.0) < 4.0 * 0.06


def test_gap_restarts_rate_filter_and_time_must_increase():
    st = AirDataState()
    st, _ = air_data_step(st, 100000.0, 300.0, None, 0.0)
    with pytest.raises(ValueError, match="increase"):
        air_data_step(st, 100000.0, 300.0, None, 0.0)
    st2, ad = air_data_step(st, 99000.0, 300.0, None, 5.0)  # 84 m jump after a 5 s gap
    assert ad.alt_rate_m_s == 0.0 and not ad.rate_valid
    with pytest.raises(ValueError, match="press_abs_pa"):
        air_data_step(st2, float("nan"), 300.0, None, 6.0)


def test_airspeed_low_blocked_and_noisy_flags():
    rng = np.random.default_rng(1)
    p = isa_pressure_pa(300.0)
    rho = air_density_kg_m3(p, isa_temperature_k(300.0))
    params = AirDataParams(min_airspeed_m_s=10.0, blocked_time_s=2.0, max_noise_std_m_s=1.5)

    def run(tas_series, t0=0.0):
        st, out = AirDataState(), []
        for k, v in enumerate(tas_series):
            st, ad = air_data_step(st, p, 0.5 * rho * v * v, None, t0 + 0.02 * k, params)
            out.append(ad)
        return out

    slow = run(np.full(50, 6.0) + rng.normal(0, 0.1, 50))
    assert all(a.airspeed_low for a in slow) and not any(a.pitot_blocked for a in slow)
    frozen = run(np.full(200, 22.0))  # 4 s of an identical reading at speed
    assert not frozen[90].pitot_blocked and frozen[110].pitot_blocked
    assert not frozen[110].usable and frozen[110].unusable_reason == "pitot blocked"
    live = run(22.0 + rng.normal(0, 0.3, 500))
    assert not any(a.pitot_blocked for a in live) and not live[-1].pitot_noisy
    assert live[-1].tas_noise_std_m_s == pytest.approx(0.3, rel=0.25)
    assert live[-1].usable
    noisy = run(22.0 + rng.normal(0, 3.0, 500))
    assert noisy[-1].pitot_noisy and noisy[-1].tas_noise_std_m_s == pytest.approx(3.0, rel=0.25)


def test_params_validation():
    with pytest.raises(ValueError, match="alt_rate_tau_s"):
        AirDataParams(alt_rate_tau_s=0.0)
    with pytest.raises(ValueError, match="press_abs_pa"):
        pressure_altitude_m(-1.0)
