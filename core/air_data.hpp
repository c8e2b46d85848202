// Air data from SCALED_PRESSURE (the compiled twin of estimators/air_data.py, which stays the
// reference and holds the derivation: ISA pressure altitude and density, TAS by Bernoulli, the
// filtered altitude rate h_dot[n] = (T h_dot[n-1] + (h[n] - h[n-1])) / (T + dt), pitot flags).
#pragma once

#include "ahrs_math.hpp"

namespace azimuthd {

namespace isa {
constexpr double P0_PA = 101325.0, T0_K = 288.15, LAPSE_K_M = 0.0065, R_DRY = 287.05287, G0 = 9.80665,
                 H11_M = 11000.0;
constexpr double T11_K = T0_K - LAPSE_K_M * H11_M;
inline double p11_pa() { return P0_PA * std::pow(T11_K / T0_K, G0 / (R_DRY * LAPSE_K_M)); }
constexpr double EXPONENT = R_DRY * LAPSE_K_M / G0;
}  // namespace isa

struct AirParams {
    double alt_rate_tau_s;
    bool use_measured_temperature;
    double min_airspeed_m_s, blocked_change_pa, blocked_time_s, noise_tau_s, max_noise_std_m_s, max_dt_s;
};

struct AirState {
    bool has_time = false;
    double time_s = 0.0, altitude_m = 0.0, alt_rate_m_s = 0.0, tas_m_s = 0.0, tas_diff_sq_mean = 0.0;
    bool has_diff_ref = false;
    double diff_ref_pa = 0.0, diff_change_time_s = 0.0, rate_start_time_s = 0.0;
};

struct AirOut {  // estimators.air_data.AirData
    double time_s, pressure_altitude_m, density_kg_m3, temperature_used_k, tas_m_s, alt_rate_m_s, tas_noise_std_m_s;
    bool airspeed_low, pitot_blocked, pitot_noisy, rate_valid;
    bool usable() const { return rate_valid && !(airspeed_low || pitot_blocked || pitot_noisy); }
    const char* unusable_reason() const {
        if (pitot_blocked) return "pitot blocked";
        if (pitot_noisy) return "pitot noisy";
        if (airspeed_low) return "airspeed below minimum";
        if (!rate_valid) return "altitude rate not settled";
        return "";
    }
};

inline double pressure_altitude_m(double p) {
    if (!(std::isfinite(p) && p > 0.0)) throw std::invalid_argument("press_abs_pa must be finite and > 0, got " + py_repr(p));
    static const double P11 = isa::p11_pa();
    if (p >= P11) return isa::T0_K / isa::LAPSE_K_M * (1.0 - std::pow(p / isa::P0_PA, isa::EXPONENT));
    return isa::H11_M + isa::R_DRY * isa::T11_K / isa::G0 * std::log(P11 / p);
}

// one sample; has_diff false: no pitot (press_diff_pa None)
inline AirOut air_data_step(AirState& s, double press_abs_pa, bool has_diff, double press_diff_pa, bool has_temp,
                            double temperature_k, double time_s, const AirParams& p) {
    if (!std::isfinite(time_s)) throw std::invalid_argument("time_s must be finite, got " + py_repr(time_s));
    if (s.has_time && time_s <= s.time_s)
        throw std::invalid_argument("time_s must increase: " + py_repr(time_s) + " after " + py_repr(s.time_s));
    const double h = pressure_altitude_m(press_abs_pa);
    const double temp = (p.use_measured_temperature && has_temp) ? temperature_k
                                                                 : isa::T0_K - isa::LAPSE_K_M * std::min(h, isa::H11_M);
    if (!(std::isfinite(temp) && temp > 0.0))
        throw std::invalid_argument("temperature_k must be finite and > 0, got " + py_repr(temp));
    const double rho = press_abs_pa / (isa::R_DRY * temp);
    if (has_diff && !std::isfinite(press_diff_pa))
        throw std::invalid_argument("press_diff_pa must be finite or None, got " + py_repr(press_diff_pa));
    const double tas = (!has_diff || press_diff_pa <= 0.0) ? 0.0 : std::sqrt(2.0 * press_diff_pa / rho);
    const bool restart = !s.has_time || (time_s - s.time_s) > p.max_dt_s;
    double alt_rate, diff_sq, change_t;
    bool has_ref;
    double diff_ref;
    if (restart) {
        alt_rate = 0.0;
        diff_sq = 0.0;
        has_ref = has_diff;
        diff_ref = press_diff_pa;
        change_t = time_s;
    } else {
        const double dt = time_s - s.time_s;
        const double T = p.alt_rate_tau_s;
        alt_rate = (T * s.alt_rate_m_s + (h - s.altitude_m)) / (T + dt);  // eq. 23 analogue
        const double a = std::exp(-dt / p.noise_tau_s);
        const double dv = tas - s.tas_m_s;
        diff_sq = a * s.tas_diff_sq_mean + (1.0 - a) * dv * dv;
        has_ref = s.has_diff_ref;
        diff_ref = s.diff_ref_pa;
        change_t = s.diff_change_time_s;
        if (!has_diff) {
            has_ref = false;
            change_t = time_s;
        } else if (!has_ref || std::fabs(press_diff_pa - diff_ref) > p.blocked_change_pa) {
            has_ref = true;
            diff_ref = press_diff_pa;
            change_t = time_s;
        }
    }
    const double noise_std = std::sqrt(0.5 * diff_sq);
    const bool airspeed_low = tas < p.min_airspeed_m_s;
    const bool blocked = has_diff && !airspeed_low && time_s - change_t >= p.blocked_time_s;
    const bool noisy = noise_std > p.max_noise_std_m_s;
    const double rate_start = restart ? time_s : s.rate_start_time_s;
    s.has_time = true;
    s.time_s = time_s;
    s.altitude_m = h;
    s.alt_rate_m_s = alt_rate;
    s.tas_m_s = tas;
    s.tas_diff_sq_mean = diff_sq;
    s.has_diff_ref = has_ref;
    s.diff_ref_pa = has_ref ? diff_ref : 0.0;
    s.diff_change_time_s = change_t;
    s.rate_start_time_s = rate_start;
    return AirOut{time_s, h, rho, temp, tas, alt_rate, noise_std, airspeed_low, blocked, noisy,
                  time_s - rate_start >= 3.0 * p.alt_rate_tau_s};
}

}  // namespace azimuthd
