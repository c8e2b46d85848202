"""Air data from SCALED_PRESSURE (METHODS.md B, "Air data"; seed AU756340B2 eq. 22-23).

Per pressure sample (static ``press_abs_pa``, pitot ``press_diff_pa``, ``temperature_k``):

    pressure altitude (ISA troposphere, h < 11 km)
        h = T0 / L * (1 - (p / p0)^(R L / g0))
    lower stratosphere (11-20 km, isothermal T11 = 216.65 K, p11 = 22632.06 Pa)
        h = 11000 + R T11 / g0 * ln(p11 / p)
    air density   rho = p / (R T)           (T: measured, or ISA T0 - L h, see below)
    true airspeed v   = sqrt(2 q_c / rho)    (incompressible Bernoulli; q_c = press_diff; below
                                              Mach 0.3 the compressibility error is < 2.3 %)
    altitude rate: the seed high-passes altitude (eq. 23). We use the first-order filtered
        derivative H(s) = s / (T s + 1), discretised backward-Euler with the sample interval
        dt taken from the timestamps:
            h_dot[n] = (T h_dot[n-1] + (h[n] - h[n-1])) / (T + dt)
        (a constant climb rate c is reproduced exactly in steady state: h_dot = c.)

Temperature: SCALED_PRESSURE.temperature is the pressure sensor's die temperature, which on a
real board runs well above outside air. The seed therefore uses the ISA temperature profile
("a so-called standard temperature distribution"); that is the default here
(``use_measured_temperature=False``). Set it True when the temperature is outside-air.

Pitot health flags:
- ``airspeed_low``: v below ``min_airspeed_m_s`` (or q_c <= 0): air-data references unusable.
- ``pitot_blocked``: the differential pressure has not moved by more than
  ``blocked_change_pa`` for ``blocked_time_s`` while the vehicle is at speed (a live pitot in
  flight always shows turbulence and sensor noise; a frozen reading means a blocked or failed
  sensor).
- ``pitot_noisy``: the sample-to-sample TAS noise, estimated as sqrt(E[(dv)^2] / 2) with an
  exponential average of time constant ``noise_tau_s``, exceeds ``max_noise_std_m_s``.

Pure: ``air_data_step(state, press_abs_pa, press_diff_pa, temperature_k, time_s, params)
-> (state, AirData)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

# ISA constants (ICAO Doc 7488 / ISO 2533)
P0_PA = 101325.0
T0_K = 288.15
LAPSE_K_M = 0.0065
R_DRY_J_KG_K = 287.05287
G0_M_S2 = 9.80665
H11_M = 11000.0
T11_K = T0_K - LAPSE_K_M * H11_M  # 216.65 K
P11_PA = P0_PA * (T11_K / T0_K) ** (G0_M_S2 / (R_DRY_J_KG_K * LAPSE_K_M))  # 22632.06 Pa
ISA_EXPONENT = R_DRY_J_KG_K * LAPSE_K_M / G0_M_S2  # 0.190263


def pressure_altitude_m(press_abs_pa: float) -> float:
    """ISA pressure altitude (m) for a static pressure (Pa); valid 0 < p, formula to 20 km."""
    if not (math.isfinite(press_abs_pa) and press_abs_pa > 0.0):
        raise ValueError(f"press_abs_pa must be finite and > 0, got {press_abs_pa!r}")
    if press_abs_pa >= P11_PA:
        return T0_K / LAPSE_K_M * (1.0 - (press_abs_pa / P0_PA) ** ISA_EXPONENT)
    return H11_M + R_DRY_J_KG_K * T11_K / G0_M_S2 * math.log(P11_PA / press_abs_pa)


def isa_temperature_k(altitude_m: float) -> float:
    """ISA temperature (K) at a geopotential altitude (m), troposphere + isothermal layer."""
    return T0_K - LAPSE_K_M * min(altitude_m, H11_M)


def air_density_kg_m3(press_abs_pa: float, temperature_k: float) -> float:
    """rho = p / (R_d T), dry air."""
    if not (math.isfinite(temperature_k) and temperature_k > 0.0):
        raise ValueError(f"temperature_k must be finite and > 0, got {temperature_k!r}")
    return press_abs_pa / (R_DRY_J_KG_K * temperature_k)


def true_airspeed_m_s(press_diff_pa: float, density_kg_m3: float) -> float:
    """v = sqrt(2 q_c / rho); 0 for q_c <= 0."""
    if press_diff_pa <= 0.0:
        return 0.0
    return math.sqrt(2.0 * press_diff_pa / density_kg_m3)


@dataclass(frozen=True)
class AirDataParams:
    alt_rate_tau_s: float = 1.0
    """T of the filtered derivative s/(T s + 1) (s). Larger: less noise, more lag."""
    use_measured_temperature: bool = False
    """Use SCALED_PRESSURE.temperature for the density (True) or the ISA profile (False)."""
    min_airspeed_m_s: float = 10.0
    """Below this TAS the air-data attitude references are not usable."""
    blocked_change_pa: float = 0.05
    """A pitot reading that moves less than this (Pa) ..."""
    blocked_time_s: float = 2.0
    """... for this long, at speed, is flagged blocked."""
    noise_tau_s: float = 2.0
    """Time constant of the TAS-noise estimate (s)."""
    max_noise_std_m_s: float = 1.5
    """TAS sample-to-sample noise above this (m/s, 1-sigma) flags a noisy pitot."""
    max_dt_s: float = 0.5
    """A longer gap between samples restarts the altitude-rate filter."""

    def __post_init__(self):
        for name in ("alt_rate_tau_s", "min_airspeed_m_s", "blocked_change_pa", "blocked_time_s",
                     "noise_tau_s", "max_noise_std_m_s", "max_dt_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")


@dataclass(frozen=True)
class AirDataState:
    time_s: float | None = None
    altitude_m: float = 0.0
    alt_rate_m_s: float = 0.0
    tas_m_s: float = 0.0
    tas_diff_sq_mean: float = 0.0
    """Exponential mean of (v[n] - v[n-1])^2, (m/s)^2."""
    diff_ref_pa: float | None = None
    """Differential pressure at the last significant change (blocked-pitot test)."""
    diff_change_time_s: float = 0.0
    rate_start_time_s: float = 0.0
    """Time the altitude-rate filter (re)started; its output is valid 3 T later."""


@dataclass(frozen=True)
class AirData:
    time_s: float
    pressure_altitude_m: float
    density_kg_m3: float
    temperature_used_k: float
    tas_m_s: float
    alt_rate_m_s: float
    tas_noise_std_m_s: float
    airspeed_low: bool
    pitot_blocked: bool
    pitot_noisy: bool
    rate_valid: bool
    """False until 3 T after the first sample or a gap (altitude-rate filter settling)."""

    @property
    def usable(self) -> bool:
        """Airspeed and altitude rate good enough for the attitude references."""
        return self.rate_valid and not (self.airspeed_low or self.pitot_blocked or self.pitot_noisy)

    @property
    def unusable_reason(self) -> str:
        for flag, why in ((self.pitot_blocked, "pitot blocked"), (self.pitot_noisy, "pitot noisy"),
                          (self.airspeed_low, "airspeed below minimum"),
                          (not self.rate_valid, "altitude rate not settled")):
            if flag:
                return why
        return ""


def air_data_step(state: AirDataState, press_abs_pa: float, press_diff_pa: float | None,
                  temperature_k: float | None, time_s: float,
                  params: AirDataParams = AirDataParams()) -> tuple[AirDataState, AirData]:
    """One SCALED_PRESSURE sample -> air data. ``press_diff_pa`` None: no airspeed sensor."""
    if not math.isfinite(time_s):
        raise ValueError(f"time_s must be finite, got {time_s!r}")
    if state.time_s is not None and time_s <= state.time_s:
        raise ValueError(f"time_s must increase: {time_s!r} after {state.time_s!r}")
    h = pressure_altitude_m(press_abs_pa)
    if params.use_measured_temperature and temperature_k is not None:
        temp = float(temperature_k)
    else:
        temp = isa_temperature_k(h)
    rho = air_density_kg_m3(press_abs_pa, temp)
    if press_diff_pa is not None and not math.isfinite(press_diff_pa):
        raise ValueError(f"press_diff_pa must be finite or None, got {press_diff_pa!r}")
    tas = 0.0 if press_diff_pa is None else true_airspeed_m_s(press_diff_pa, rho)

    restart = state.time_s is None or (time_s - state.time_s) > params.max_dt_s
    if restart:
        alt_rate = 0.0
        diff_sq = 0.0
        diff_ref = press_diff_pa
        change_t = time_s
    else:
        dt = time_s - state.time_s
        T = params.alt_rate_tau_s
        alt_rate = (T * state.alt_rate_m_s + (h - state.altitude_m)) / (T + dt)  # eq. 23 analogue
        a = math.exp(-dt / params.noise_tau_s)
        dv = tas - state.tas_m_s
        diff_sq = a * state.tas_diff_sq_mean + (1.0 - a) * dv * dv
        diff_ref, change_t = state.diff_ref_pa, state.diff_change_time_s
        if press_diff_pa is None:
            diff_ref, change_t = None, time_s
        elif diff_ref is None or abs(press_diff_pa - diff_ref) > params.blocked_change_pa:
            diff_ref, change_t = press_diff_pa, time_s
    noise_std = math.sqrt(0.5 * diff_sq)
    airspeed_low = tas < params.min_airspeed_m_s
    blocked = (press_diff_pa is not None and not airspeed_low
               and time_s - change_t >= params.blocked_time_s)
    noisy = noise_std > params.max_noise_std_m_s
    new = AirDataState(time_s=time_s, altitude_m=h, alt_rate_m_s=alt_rate, tas_m_s=tas,
                       tas_diff_sq_mean=diff_sq, diff_ref_pa=diff_ref, diff_change_time_s=change_t,
                       rate_start_time_s=time_s if restart else state.rate_start_time_s)
    out = AirData(time_s=time_s, pressure_altitude_m=h, density_kg_m3=rho, temperature_used_k=temp,
                  tas_m_s=tas, alt_rate_m_s=alt_rate, tas_noise_std_m_s=noise_std,
                  airspeed_low=airspeed_low, pitot_blocked=blocked, pitot_noisy=noisy,
                  rate_valid=time_s - new.rate_start_time_s >= 3.0 * params.alt_rate_tau_s)
    return new, out


def air_data_init() -> AirDataState:
    return AirDataState()


__all__ = ["AirData", "AirDataParams", "AirDataState", "air_data_step", "air_data_init",
           "pressure_altitude_m", "air_density_kg_m3", "true_airspeed_m_s", "isa_temperature_k"]
