// One gyro propagation: coning-correct quaternion strapdown (the compiled twin of
// estimators/strapdown.py, which stays the reference; tests/test_core_strapdown.py proves them equal).
//
// Per sample k with rate w_k at FC time t_k, the rate taken linear over [t_{k-1}, t_k] (Bortz's
// equation integrated to second order):
//     phi_k = (w_{k-1} + w_k) / 2 dt + dt^2 / 12 (w_{k-1} x w_k)      (coning term)
//     q_k   = q_{k-1} * q(phi_k), renormalised                         (Hamilton, scalar first)
// Every expression keeps the reference's operand order, and the build turns off FMA contraction
// (CMakeLists.txt), so the results are the same IEEE operations, not merely close.
#pragma once

#include <cmath>
#include <cstdint>

namespace azimuthd {

// Why a sample was or was not integrated (estimators/strapdown.py StrapdownDiag.reason).
enum class StrapdownCode : std::int8_t {
    integrated = 0,
    first_sample = 1,    // no previous sample: stored, nothing integrated
    non_finite = 2,      // the sample is dropped, the state kept
    time_not_increasing = 3,
    gap = 4,             // dt > max_dt_s: increments restart at this sample, attitude kept
};

struct StrapdownState {
    double q_ref_from_sensor[4];  // Hamilton [w, x, y, z]
    bool has_prev;                // a previous accepted sample exists (time and rate below)
    double time_prev_s;
    double gyro_prev_rad_s[3];
};

// One bias-corrected rate sample (rad/s, sensor axes) at time_s. dt_s: the interval judged.
inline StrapdownCode strapdown_step(StrapdownState& s, const double w[3], double time_s, double max_dt_s,
                                    double& dt_s) {
    dt_s = 0.0;
    const double wx = w[0], wy = w[1], wz = w[2];
    if (!(std::isfinite(wx) && std::isfinite(wy) && std::isfinite(wz) && std::isfinite(time_s)))
        return StrapdownCode::non_finite;
    if (!s.has_prev) {
        s.has_prev = true;
        s.time_prev_s = time_s;
        s.gyro_prev_rad_s[0] = wx; s.gyro_prev_rad_s[1] = wy; s.gyro_prev_rad_s[2] = wz;
        return StrapdownCode::first_sample;
    }
    const double dt = time_s - s.time_prev_s;
    dt_s = dt;
    if (dt <= 0.0) return StrapdownCode::time_not_increasing;
    const double ax = s.gyro_prev_rad_s[0], ay = s.gyro_prev_rad_s[1], az = s.gyro_prev_rad_s[2];
    s.time_prev_s = time_s;
    s.gyro_prev_rad_s[0] = wx; s.gyro_prev_rad_s[1] = wy; s.gyro_prev_rad_s[2] = wz;
    if (dt > max_dt_s) return StrapdownCode::gap;
    const double h = 0.5 * dt;
    const double c = dt * dt / 12.0;
    // phi = (w0 + w)/2 dt + dt^2/12 (w0 x w)
    const double px = (ax + wx) * h + c * (ay * wz - az * wy);
    const double py = (ay + wy) * h + c * (az * wx - ax * wz);
    const double pz = (az + wz) * h + c * (ax * wy - ay * wx);
    // q(phi) = [cos(|phi|/2), sin(|phi|/2) phi/|phi|], the series near zero
    const double angle = std::sqrt(px * px + py * py + pz * pz);
    const double k = angle < 1e-6 ? 0.5 - angle * angle / 48.0 : std::sin(0.5 * angle) / angle;
    const double rw = std::cos(0.5 * angle), rx = k * px, ry = k * py, rz = k * pz;
    double* q = s.q_ref_from_sensor;
    const double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    // q_k = q_{k-1} * q(phi) (Hamilton product), renormalised
    const double nw = qw * rw - qx * rx - qy * ry - qz * rz;
    const double nx = qw * rx + qx * rw + qy * rz - qz * ry;
    const double ny = qw * ry - qx * rz + qy * rw + qz * rx;
    const double nz = qw * rz + qx * ry - qy * rx + qz * rw;
    const double n = std::sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
    q[0] = nw / n; q[1] = nx / n; q[2] = ny / n; q[3] = nz / n;
    return StrapdownCode::integrated;
}

}  // namespace azimuthd
