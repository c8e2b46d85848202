// The filter step's solution numbers (service/pipeline.py Pipeline._solution, the reference, which
// holds the reasoning): C's roll/pitch and their sigmas, the heading rate the arbitration blends
// with, and method C's heading as a source reading, read from the held attitude and heading filters
// in one call. Every expression is the reference's, in its order (bit for bit the same:
// tests/test_core_solution.py).
#pragma once

#include <algorithm>
#include <cmath>

#include "polar_attitude.hpp"
#include "polar_heading.hpp"

namespace azimuthd {
namespace solution {

struct AttitudeNumbers {
    double roll = 0.0, pitch = 0.0, roll_sigma = 0.0, pitch_sigma = 0.0;
    double yaw_P = 0.0;         // yaw of the attitude filter's platform attitude q_P_from_body
    bool has_rate = false;
    double heading_rate = 0.0;  // rad/s
};

// pa initialised. prev: (time, yaw_P) of the last solution (has_prev false: none); rates_body: the
// body rates, bias removed (rad/s).
inline AttitudeNumbers attitude_numbers(const polar::State& pa, double t, bool has_prev, double prev_t,
                                        double prev_yaw, const V3& rates_body) {
    AttitudeNumbers a{};
    Mat<2, 2> cov{};
    polar::estimate(pa, a.roll, a.pitch, cov);
    a.roll_sigma = std::sqrt(std::max(cov[0], 0.0));   // math.sqrt(max(cov[0, 0], 0.0)): a NaN stays NaN
    a.pitch_sigma = std::sqrt(std::max(cov[3], 0.0));
    a.yaw_P = euler_from_dcm(dcm_from_quat(pa.q_P_from_body))[2];
    if (has_prev && t > prev_t) {
        // the yaw's change over the step from the full attitude (exact through pitch +-90 deg)
        a.has_rate = true;
        a.heading_rate = wrap_pi(a.yaw_P - prev_yaw) / (t - prev_t);
    } else if (std::abs(std::cos(a.pitch)) > 1e-3) {
        // psi_dot = (q sin(phi) + r cos(phi)) / cos(theta)
        a.has_rate = true;
        a.heading_rate = (rates_body[1] * std::sin(a.roll) + rates_body[2] * std::cos(a.roll)) / std::cos(a.pitch);
    }
    return a;
}

}  // namespace solution
}  // namespace azimuthd
