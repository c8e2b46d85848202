// Small fixed-size matrices and the rotation helpers of method B (the compiled twins of
// estimators/rotations.py and estimators/euler_kinematics.py, which stay the reference and hold
// the conventions: Hamilton scalar-first q_nav_from_body, ZYX Euler, C_nav_from_body = Rz Ry Rx).
// Matrices are row-major std::arrays; products sum k = 0..K-1 in order (numpy's BLAS may order
// or fuse differently: the core agrees with the reference to rounding, 1e-9 relative is asserted).
// Python's ``x ** y`` on floats is C pow(): kept as std::pow where the reference writes it.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <string>
#include <unordered_set>

namespace azimuthd {

template <int R, int C>
using Mat = std::array<double, R * C>;
using V3 = std::array<double, 3>;
using Q4 = std::array<double, 4>;
using M3 = Mat<3, 3>;

constexpr double PI_ = 3.141592653589793;  // math.pi
constexpr double TWO_PI_ = 2.0 * PI_;

template <int R, int K, int C>
inline Mat<R, C> mm(const Mat<R, K>& A, const Mat<K, C>& B) {
    Mat<R, C> out{};
    for (int i = 0; i < R; ++i)
        for (int j = 0; j < C; ++j) {
            double s = A[i * K] * B[j];
            for (int k = 1; k < K; ++k) s = s + A[i * K + k] * B[k * C + j];
            out[i * C + j] = s;
        }
    return out;
}

template <int R, int C>
inline Mat<C, R> tr(const Mat<R, C>& A) {
    Mat<C, R> out{};
    for (int i = 0; i < R; ++i)
        for (int j = 0; j < C; ++j) out[j * R + i] = A[i * C + j];
    return out;
}

template <int R, int K>
inline std::array<double, R> mv(const Mat<R, K>& A, const std::array<double, K>& x) {
    std::array<double, R> out{};
    for (int i = 0; i < R; ++i) {
        double s = A[i * K] * x[0];
        for (int k = 1; k < K; ++k) s = s + A[i * K + k] * x[k];
        out[i] = s;
    }
    return out;
}

template <int N>
inline Mat<N, N> eye() {
    Mat<N, N> I{};
    for (int i = 0; i < N; ++i) I[i * N + i] = 1.0;
    return I;
}

// 0.5 (P + P^T)
template <int N>
inline void symmetrise(Mat<N, N>& P) {
    const Mat<N, N> T = P;
    for (int i = 0; i < N; ++i)
        for (int j = 0; j < N; ++j) P[i * N + j] = 0.5 * (T[i * N + j] + T[j * N + i]);
}

// A^-1 by Gauss-Jordan with partial pivoting (np.linalg.inv: LU, partial pivoting). Singular:
// ValueError (numpy's LinAlgError is a ValueError).
template <int N>
inline Mat<N, N> inv(const Mat<N, N>& A) {
    Mat<N, N> a = A, b = eye<N>();
    for (int c = 0; c < N; ++c) {
        int p = c;
        for (int r = c + 1; r < N; ++r)
            if (std::fabs(a[r * N + c]) > std::fabs(a[p * N + c])) p = r;
        if (a[p * N + c] == 0.0) throw std::invalid_argument("Singular matrix");
        if (p != c)
            for (int j = 0; j < N; ++j) { std::swap(a[p * N + j], a[c * N + j]); std::swap(b[p * N + j], b[c * N + j]); }
        const double d = a[c * N + c];
        for (int j = 0; j < N; ++j) { a[c * N + j] = a[c * N + j] / d; b[c * N + j] = b[c * N + j] / d; }
        for (int r = 0; r < N; ++r) {
            if (r == c) continue;
            const double f = a[r * N + c];
            if (f == 0.0) continue;
            for (int j = 0; j < N; ++j) { a[r * N + j] = a[r * N + j] - f * a[c * N + j]; b[r * N + j] = b[r * N + j] - f * b[c * N + j]; }
        }
    }
    return b;
}

template <int N>
inline std::array<double, N> solve(const Mat<N, N>& A, const std::array<double, N>& y) {
    return mv<N, N>(inv<N>(A), y);
}

inline double norm3(const V3& v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }
inline double dot4(const Q4& q) { return q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]; }
inline bool finite3(const V3& v) { return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]); }

// Python's repr of a float (shortest round-trip digits), for messages that must read the same.
inline std::string py_repr(double x) {
    if (std::isnan(x)) return "nan";
    if (std::isinf(x)) return x > 0 ? "inf" : "-inf";
    char buf[40];
    for (int p = 1; p <= 17; ++p) {
        std::snprintf(buf, sizeof buf, "%.*g", p, x);
        if (std::strtod(buf, nullptr) == x) break;
    }
    std::string s(buf);
    if (s.find_first_of(".en") == std::string::npos) s += ".0";
    return s;
}

// A stable C string for a reason worded once (the few distinct reasons live for the process):
// states copy a pointer, not a string.
inline const char* intern(const std::string& text) {
    static std::unordered_set<std::string> pool;
    return pool.insert(text).first->c_str();
}

// --- rotations.py -------------------------------------------------------------------------------

inline double wrap_2pi(double a) {
    a = std::fmod(a, TWO_PI_);
    if (a < 0.0) a += TWO_PI_;
    return a >= TWO_PI_ ? 0.0 : a;  // fmod of a value just below 0 can round to exactly 2pi
}
inline double wrap_pi(double a) { return wrap_2pi(a + PI_) - PI_; }
inline double clip1(double x) { return std::max(-1.0, std::min(1.0, x)); }

inline M3 skew(const V3& v) { return {0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0}; }

inline Q4 quat_mul(const Q4& p, const Q4& q) {
    const double pw = p[0], px = p[1], py = p[2], pz = p[3], qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    return {pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw};
}
inline Q4 quat_conj(const Q4& q) { return {q[0], -q[1], -q[2], -q[3]}; }

inline Q4 quat_normalize(const Q4& q) {
    double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (!(n > 0.0) || !std::isfinite(n)) throw std::invalid_argument("cannot normalise quaternion");
    if (q[0] < 0.0) n = -n;
    return {q[0] / n, q[1] / n, q[2] / n, q[3] / n};
}
// q / sqrt(q @ q) (no sign convention: what the filters do after a product)
inline Q4 quat_unit(const Q4& q) {
    const double n = std::sqrt(dot4(q));
    return {q[0] / n, q[1] / n, q[2] / n, q[3] / n};
}

inline Q4 quat_from_rotvec(const V3& v) {
    const double vx = v[0], vy = v[1], vz = v[2];
    const double angle = std::sqrt(vx * vx + vy * vy + vz * vz);
    const double half = 0.5 * angle;
    const double k = angle < 1e-6 ? 0.5 - angle * angle / 48.0 : std::sin(half) / angle;
    return {std::cos(half), k * vx, k * vy, k * vz};
}

inline M3 dcm_from_quat(const Q4& q) {
    const double w = q[0], x = q[1], y = q[2], z = q[3];
    return {1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)};
}

inline V3 euler_from_dcm(const M3& C) {
    const double pitch = -std::asin(clip1(C[6]));
    const double roll = std::atan2(C[7], C[8]);
    const double yaw = wrap_2pi(std::atan2(C[3], C[0]));
    return {roll, pitch, yaw};
}

inline M3 rot_x(double a) { const double c = std::cos(a), s = std::sin(a); return {1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c}; }
inline M3 rot_y(double a) { const double c = std::cos(a), s = std::sin(a); return {c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c}; }
inline M3 rot_z(double a) { const double c = std::cos(a), s = std::sin(a); return {c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0}; }

inline M3 dcm_from_euler(double roll, double pitch, double yaw) {
    return mm<3, 3, 3>(mm<3, 3, 3>(rot_z(yaw), rot_y(pitch)), rot_x(roll));
}

inline Q4 quat_from_euler(double roll, double pitch, double yaw) {
    const double cr = std::cos(0.5 * roll), sr = std::sin(0.5 * roll);
    const double cp = std::cos(0.5 * pitch), sp = std::sin(0.5 * pitch);
    const double cy = std::cos(0.5 * yaw), sy = std::sin(0.5 * yaw);
    return quat_normalize({cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                           cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy});
}

// --- euler_kinematics.py --------------------------------------------------------------------

// np_scalar: the reference passes a numpy float64 there, whose repr the message quotes
inline void check_pitch(double pitch, bool np_scalar) {
    if (std::fabs(std::fabs(pitch) - 0.5 * PI_) < 1e-6)
        throw std::invalid_argument("Euler kinematics singular at pitch " +
                                    (np_scalar ? "np.float64(" + py_repr(pitch) + ")" : py_repr(pitch)) +
                                    " rad (|pitch| = 90 deg)");
}

// T(phi, theta): euler_dot = T omega_body (and delta_euler = T gamma_body)
inline M3 euler_rate_matrix(double roll, double pitch, bool np_scalar = false) {
    check_pitch(pitch, np_scalar);
    const double sp = std::sin(roll), cp = std::cos(roll), tt = std::tan(pitch), ct = std::cos(pitch);
    return {1.0, sp * tt, cp * tt, 0.0, cp, -sp, 0.0, sp / ct, cp / ct};
}

// T for reporting an Euler covariance at any pitch (euler_kinematics.euler_rate_matrix_reported):
// within the singular margin the pitch is taken at twice the margin from 90 deg
inline M3 euler_rate_matrix_reported(double roll, double pitch) {
    const double bound = 0.5 * PI_ - 2.0 * 1e-6;
    return euler_rate_matrix(roll, std::copysign(std::min(std::fabs(pitch), bound), pitch));
}

// W = T^-1: omega_body = W euler_dot
inline M3 body_rate_matrix(double roll, double pitch) {
    const double sp = std::sin(roll), cp = std::cos(roll), st = std::sin(pitch), ct = std::cos(pitch);
    return {1.0, 0.0, -st, 0.0, cp, ct * sp, 0.0, -sp, ct * cp};
}

inline V3 euler_rates(double roll, double pitch, const V3& w, bool np_scalar = false) {
    const double p = w[0], q = w[1], r = w[2];
    check_pitch(pitch, np_scalar);
    const double sp = std::sin(roll), cp = std::cos(roll);
    const double a = q * sp + r * cp;
    return {p + std::tan(pitch) * a, q * cp - r * sp, a / std::cos(pitch)};
}

}  // namespace azimuthd
