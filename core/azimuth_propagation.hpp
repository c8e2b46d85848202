// Method A's per-sample propagation (METHODS.md A step 4; estimators/azimuth.py azimuth_propagate,
// which stays the reference): the one strapdown (core/strapdown.hpp) of the bias-corrected rate
// and the attitude-error sensitivity to the gyro errors c_g = [bias change (3), scale and
// misalignment T (9)], by the trapezoid over the sample interval:
//     bias columns   G[:, 0:3]      -= dt/2 (C_{k-1} + C_k)
//     T columns      G[:, 3+3i+j]   += dt/2 (C_{k-1}[:, i] w_{k-1, j} + C_k[:, i] w_{k, j})
// with C = C_ISF<-SF from the strapdown quaternion. G and C change only when the sample is
// integrated. The reference's operand order, no FMA contraction (CMakeLists.txt): the same bits.
#pragma once

#include "strapdown.hpp"

namespace azimuthd {

// C_a_from_b from q_a_from_b, row-major (estimators/rotations.py dcm_from_quat)
inline void dcm_rows(const double q[4], double C[9]) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    C[0] = 1 - 2 * (y * y + z * z); C[1] = 2 * (x * y - w * z);     C[2] = 2 * (x * z + w * y);
    C[3] = 2 * (x * y + w * z);     C[4] = 1 - 2 * (x * x + z * z); C[5] = 2 * (y * z - w * x);
    C[6] = 2 * (x * z - w * y);     C[7] = 2 * (y * z + w * x);     C[8] = 1 - 2 * (x * x + y * y);
}

// One sample: s, G (3 x 12 row-major) and C (3 x 3 row-major) updated in place.
inline StrapdownCode azimuth_propagate(StrapdownState& s, double G[36], double C[9], const double w[3],
                                       double time_s, double max_dt_s, double& dt_s) {
    const double w0[3] = {s.gyro_prev_rad_s[0], s.gyro_prev_rad_s[1], s.gyro_prev_rad_s[2]};
    const StrapdownCode code = strapdown_step(s, w, time_s, max_dt_s, dt_s);
    if (code != StrapdownCode::integrated) return code;
    double C1[9];
    dcm_rows(s.q_ref_from_sensor, C1);
    const double h = 0.5 * dt_s;
    const double* w1 = s.gyro_prev_rad_s;
    for (int r = 0; r < 3; ++r) {
        for (int i = 0; i < 3; ++i) G[12 * r + i] = G[12 * r + i] - h * (C[3 * r + i] + C1[3 * r + i]);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                G[12 * r + 3 + 3 * i + j] = G[12 * r + 3 + 3 * i + j] + h * (C[3 * r + i] * w0[j] + C1[3 * r + i] * w1[j]);
    }
    for (int k = 0; k < 9; ++k) C[k] = C1[k];
    return code;
}

}  // namespace azimuthd
