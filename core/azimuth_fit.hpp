// Method A's re-solve of psi_s (METHODS.md A steps 5-8; estimators/azimuth_fit.py fit_psi, which stays
// the reference): variable projection + Gauss-Newton over the stored magnetometer samples, the
// white-noise sandwich covariance, the consider sensitivity and, with a prior, the joint MAP estimate
// of the gyro errors and the levelling tilt (_estimate_errors). The same steps in the same order as
// the reference; the reference's LAPACK calls (inv, pinv, lstsq, eigvalsh, cond) are done here by one
// cyclic Jacobi eigen-decomposition of the symmetric matrix, which gives the same results to rounding
// (the parity tests hold them to 1e-9 relative, covariances per element against sqrt(P_ii P_jj)).
// Samples come in as contiguous row-major arrays: C_SF<-ISF (N x 3 x 3), h (N x 3), var_white (N),
// weight (N), G (N x 3 x K).
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

namespace azimuthd {
namespace fit {

enum Model { NONE = 0, SEED7 = 1, FULL12 = 2 };
constexpr int N_TILT = 2;
constexpr double TWO_PI = 6.283185307179586;

inline int n_unknowns(int model) { return model == NONE ? 1 : model == SEED7 ? 7 : 13; }

// estimators/rotations.py wrap_2pi
inline double wrap_2pi(double a) {
    double r = std::fmod(a, TWO_PI);
    if (r < 0.0) r += TWO_PI;
    return r >= TWO_PI ? 0.0 : r;
}

// Row-major dense matrix.
struct Mat {
    int r = 0, c = 0;
    std::vector<double> a;
    Mat() = default;
    Mat(int rows, int cols, double v = 0.0) : r(rows), c(cols), a(static_cast<size_t>(rows) * cols, v) {}
    double& operator()(int i, int j) { return a[static_cast<size_t>(i) * c + j]; }
    double operator()(int i, int j) const { return a[static_cast<size_t>(i) * c + j]; }
};

// Symmetric eigen-decomposition A = Q diag(lam) Q^T by cyclic Jacobi rotations (A symmetric n x n).
// Non-finite input: returns false (the reference's LAPACK then fails too; see inv_spd).
inline bool eig_sym(const Mat& A, std::vector<double>& lam, Mat& Q) {
    const int n = A.r;
    Mat S = A;
    Q = Mat(n, n);
    for (int i = 0; i < n; ++i) Q(i, i) = 1.0;
    for (double v : S.a)
        if (!std::isfinite(v)) return false;
    // an element below eps of its diagonal's scale is left (the eigenvalues then have relative
    // accuracy ~eps, Demmel & Veselic); a sweep that rotates nothing ends the iteration
    constexpr double tol = 2.220446049250313e-16;
    for (int sweep = 0; sweep < 60; ++sweep) {
        bool rotated = false;
        for (int p = 0; p < n - 1; ++p) {
            for (int q = p + 1; q < n; ++q) {
                const double apq = S(p, q);
                if (std::fabs(apq) <= tol * std::sqrt(std::fabs(S(p, p) * S(q, q)))) continue;
                rotated = true;
                const double app = S(p, p), aqq = S(q, q);
                const double theta = (aqq - app) / (2.0 * apq);
                const double t = (theta >= 0.0 ? 1.0 : -1.0) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
                const double cs = 1.0 / std::sqrt(t * t + 1.0), sn = t * cs;
                for (int k = 0; k < n; ++k) {  // columns p, q
                    const double skp = S(k, p), skq = S(k, q);
                    S(k, p) = cs * skp - sn * skq;
                    S(k, q) = sn * skp + cs * skq;
                }
                for (int k = 0; k < n; ++k) {  // rows p, q
                    const double spk = S(p, k), sqk = S(q, k);
                    S(p, k) = cs * spk - sn * sqk;
                    S(q, k) = sn * spk + cs * sqk;
                }
                S(p, q) = S(q, p) = 0.0;
                for (int k = 0; k < n; ++k) {
                    const double qkp = Q(k, p), qkq = Q(k, q);
                    Q(k, p) = cs * qkp - sn * qkq;
                    Q(k, q) = sn * qkp + cs * qkq;
                }
            }
        }
        if (!rotated) break;
    }
    lam.assign(n, 0.0);
    for (int i = 0; i < n; ++i) lam[i] = S(i, i);
    return true;
}

// sum_k Q[:, k] f(lam_k) Q[:, k]^T over the kept eigenvalues
inline Mat from_eig(const std::vector<double>& lam, const Mat& Q, const std::vector<double>& inv_lam) {
    const int n = Q.r;
    Mat R(n, n);
    for (int k = 0; k < n; ++k) {
        if (inv_lam[k] == 0.0) continue;
        for (int i = 0; i < n; ++i) {
            const double qi = Q(i, k) * inv_lam[k];
            for (int j = 0; j < n; ++j) R(i, j) += qi * Q(j, k);
        }
    }
    (void)lam;
    return R;
}

// Pseudo-inverse of a symmetric matrix: eigenvalues with |lam| <= rcond max|lam| are dropped
// (numpy.linalg.pinv; with hermitian=False its singular values are the same |lam|).
inline bool pinv_sym(const Mat& A, double rcond, Mat& out) {
    std::vector<double> lam;
    Mat Q;
    if (!eig_sym(A, lam, Q)) return false;
    double smax = 0.0;
    for (double l : lam) smax = std::max(smax, std::fabs(l));
    std::vector<double> il(lam.size(), 0.0);
    for (size_t k = 0; k < lam.size(); ++k)
        if (std::fabs(lam[k]) > rcond * smax) il[k] = 1.0 / lam[k];
    out = from_eig(lam, Q, il);
    return true;
}

struct LinAlgError : std::runtime_error {
    using std::runtime_error::runtime_error;
};

// Inverse of a symmetric positive definite S by Cholesky (S = L L^T, inv = L^-T L^-1); false when a
// pivot is not positive or a number is not finite. cond1: ||S||_1 ||inv||_1 (>= the 2-norm condition).
inline bool chol_inverse(const Mat& S, Mat& inv, double& cond1) {
    const int n = S.r;
    Mat L(n, n), Li(n, n);
    for (int j = 0; j < n; ++j) {
        double sjj = S(j, j);
        for (int k = 0; k < j; ++k) sjj -= L(j, k) * L(j, k);
        if (!(sjj > 0.0) || !std::isfinite(sjj)) return false;
        L(j, j) = std::sqrt(sjj);
        for (int i = j + 1; i < n; ++i) {
            double sij = S(i, j);
            for (int k = 0; k < j; ++k) sij -= L(i, k) * L(j, k);
            L(i, j) = sij / L(j, j);
        }
    }
    for (int j = 0; j < n; ++j) {
        Li(j, j) = 1.0 / L(j, j);
        for (int i = j + 1; i < n; ++i) {
            double acc = 0.0;
            for (int k = j; k < i; ++k) acc += L(i, k) * Li(k, j);
            Li(i, j) = -acc / L(i, i);
        }
    }
    inv = Mat(n, n);
    for (int i = 0; i < n; ++i)
        for (int j = i; j < n; ++j) {
            double acc = 0.0;
            for (int k = j; k < n; ++k) acc += Li(k, i) * Li(k, j);
            inv(i, j) = inv(j, i) = acc;
        }
    double nS = 0.0, nI = 0.0;
    for (int j = 0; j < n; ++j) {
        double cs = 0.0, ci = 0.0;
        for (int i = 0; i < n; ++i) {
            cs += std::fabs(S(i, j));
            ci += std::fabs(inv(i, j));
        }
        nS = std::max(nS, cs);
        nI = std::max(nI, ci);
    }
    cond1 = nS * nI;
    return std::isfinite(cond1);
}

// estimators/azimuth_fit.py _inv_spd: Jacobi scaling, the inverse while cond < 1e13, else the
// pseudo-inverse with rcond 1e-13 (an unobservable direction). The inverse by Cholesky where its
// 1-norm condition (an upper bound of the 2-norm one the reference tests) is below 1e13; otherwise
// the eigen-decomposition decides as the reference does. A non-finite matrix: numpy's SVD does not
// converge; here the same LinAlgError.
inline Mat inv_spd(const Mat& H) {
    const int n = H.r;
    std::vector<double> d(n);
    for (int i = 0; i < n; ++i) {
        const double v = std::sqrt(std::fabs(H(i, i)));
        d[i] = v > 0.0 ? v : 1.0;
    }
    Mat Hs(n, n);
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) Hs(i, j) = H(i, j) / (d[i] * d[j]);
    for (int i = 0; i < n; ++i)
        for (int j = i + 1; j < n; ++j) Hs(i, j) = Hs(j, i) = 0.5 * (Hs(i, j) + Hs(j, i));
    {
        Mat R;
        double cond1 = INFINITY;
        if (chol_inverse(Hs, R, cond1) && cond1 < 1e13) {
            for (int i = 0; i < n; ++i)
                for (int j = 0; j < n; ++j) R(i, j) = R(i, j) / (d[i] * d[j]);
            return R;
        }
    }
    std::vector<double> lam;
    Mat Q;
    if (!eig_sym(Hs, lam, Q)) throw LinAlgError("SVD did not converge");
    double smax = 0.0, smin = std::numeric_limits<double>::infinity();
    for (double l : lam) {
        smax = std::max(smax, std::fabs(l));
        smin = std::min(smin, std::fabs(l));
    }
    const double cond = smin > 0.0 ? smax / smin : std::numeric_limits<double>::infinity();
    std::vector<double> il(n, 0.0);
    for (int k = 0; k < n; ++k) {
        if (cond < 1e13) il[k] = 1.0 / lam[k];
        else if (std::fabs(lam[k]) > 1e-13 * smax) il[k] = 1.0 / lam[k];
    }
    Mat R = from_eig(lam, Q, il);
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) R(i, j) = R(i, j) / (d[i] * d[j]);
    return R;
}

struct Samples {
    int N = 0, K = 0;
    const double* C_sf_from_isf = nullptr;  // N x 3 x 3
    const double* h = nullptr;              // N x 3
    const double* var_white = nullptr;      // N
    const double* w = nullptr;              // N
    const double* G = nullptr;              // N x 3 x K (K = 0: none)
};

struct Result {
    bool ok = false;
    int code = 0;  // 0 solved, 1 too few equations, 2 not converged, 3 non-finite samples
    int n_bad = 0;
    int iterations = 0;
    std::vector<double> theta, c_hat;
    Mat cov_white, S, P_psi_c;
    double s2 = NAN, residual_rms = NAN, cond = INFINITY, psi_sigma_gate = NAN;
};

inline void mat3_mul(const double* A, const double* B, double* C) {  // C = A B, 3x3 row-major
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}
inline void mat3_vec(const double* A, const double* v, double* y) {
    for (int i = 0; i < 3; ++i) y[i] = A[3 * i] * v[0] + A[3 * i + 1] * v[1] + A[3 * i + 2] * v[2];
}

// theta -> A (3x3 row-major), b
inline void unpack(int model, const std::vector<double>& th, double A[9], double b[3]) {
    for (int k = 0; k < 9; ++k) A[k] = (k % 4 == 0) ? 1.0 : 0.0;
    b[0] = b[1] = b[2] = 0.0;
    if (model == SEED7) {
        for (int k = 0; k < 9; ++k) A[k] = 0.0;
        A[0] = th[1]; A[4] = th[2]; A[8] = th[3];
        b[0] = th[4]; b[1] = th[5]; b[2] = th[6];
    } else if (model == FULL12) {
        for (int k = 0; k < 9; ++k) A[k] = th[1 + k];
        b[0] = th[10]; b[1] = th[11]; b[2] = th[12];
    }
}

// r = h - A m(psi) - b (3N), J = dr/dtheta (3N x p)
inline void residual_and_jacobian(int model, const std::vector<double>& th, const std::vector<double>& Cfa,
                                  const double* e, const double* h, int N, std::vector<double>& r, Mat* J,
                                  std::vector<double>* m_out = nullptr) {
    const int p = n_unknowns(model);
    double A[9], b[3];
    unpack(model, th, A, b);
    const double c = std::cos(th[0]), s = std::sin(th[0]);
    const double Re[3] = {c * e[0] + s * e[1], -s * e[0] + c * e[1], e[2]};  // R3(psi) e
    const double dRe[3] = {-s * e[0] + c * e[1], -c * e[0] - s * e[1], 0.0};  // dR3/dpsi e
    r.assign(3 * static_cast<size_t>(N), 0.0);
    if (J) *J = Mat(3 * N, p);
    if (m_out) m_out->assign(3 * static_cast<size_t>(N), 0.0);
    for (int n = 0; n < N; ++n) {
        double m[3], dm[3];
        mat3_vec(&Cfa[9 * n], Re, m);
        mat3_vec(&Cfa[9 * n], dRe, dm);
        for (int i = 0; i < 3; ++i) {
            const double Am = A[3 * i] * m[0] + A[3 * i + 1] * m[1] + A[3 * i + 2] * m[2];
            r[3 * n + i] = h[3 * n + i] - Am - b[i];
            if (J) {
                Mat& Jm = *J;
                const int row = 3 * n + i;
                Jm(row, 0) = -(dm[0] * A[3 * i] + dm[1] * A[3 * i + 1] + dm[2] * A[3 * i + 2]);
                if (model == SEED7) {
                    Jm(row, 1 + i) = -m[i];
                    Jm(row, 4 + i) = -1.0;
                } else if (model == FULL12) {
                    for (int k = 0; k < 3; ++k) Jm(row, 1 + 3 * i + k) = -m[k];
                    Jm(row, 10 + i) = -1.0;
                }
            }
            if (m_out) (*m_out)[3 * n + i] = m[i];
        }
    }
}

// X^T diag(wr) Y for row-weighted X (R x a), Y (R x b)
inline Mat xtwy(const Mat& X, const std::vector<double>& wr, const Mat& Y) {
    Mat out(X.c, Y.c);
    for (int k = 0; k < X.r; ++k) {
        const double wk = wr[k];
        for (int i = 0; i < X.c; ++i) {
            const double xi = X(k, i) * wk;
            if (xi == 0.0) continue;
            for (int j = 0; j < Y.c; ++j) out(i, j) += xi * Y(k, j);
        }
    }
    return out;
}
inline std::vector<double> xtwv(const Mat& X, const std::vector<double>& wr, const std::vector<double>& v) {
    std::vector<double> out(X.c, 0.0);
    for (int k = 0; k < X.r; ++k) {
        const double wv = wr[k] * v[k];
        for (int i = 0; i < X.c; ++i) out[i] += X(k, i) * wv;
    }
    return out;
}
inline Mat matmul(const Mat& A, const Mat& B) {
    Mat C(A.r, B.c);
    for (int i = 0; i < A.r; ++i)
        for (int k = 0; k < A.c; ++k) {
            const double aik = A(i, k);
            if (aik == 0.0) continue;
            for (int j = 0; j < B.c; ++j) C(i, j) += aik * B(k, j);
        }
    return C;
}
inline std::vector<double> matvec(const Mat& A, const std::vector<double>& v) {
    std::vector<double> y(A.r, 0.0);
    for (int i = 0; i < A.r; ++i)
        for (int k = 0; k < A.c; ++k) y[i] += A(i, k) * v[k];
    return y;
}
inline double wdot_sq(const std::vector<double>& wr, const std::vector<double>& r) {
    double s = 0.0;
    for (size_t k = 0; k < r.size(); ++k) s += wr[k] * (r[k] * r[k]);
    return s;
}

// D = dr/dc (3N x K+2) (azimuth_fit.consider_jacobian)
inline Mat consider_jacobian(int model, const std::vector<double>& th, const Samples& d, const double* C_isf_af,
                             const std::vector<double>& Cfa, const double* e) {
    double A[9], b[3];
    unpack(model, th, A, b);
    const double c = std::cos(th[0]), s = std::sin(th[0]);
    const double e_af[3] = {c * e[0] + s * e[1], -s * e[0] + c * e[1], e[2]};
    double e_isf[3];
    mat3_vec(C_isf_af, e_af, e_isf);
    const double sk_isf[9] = {0.0, -e_isf[2], e_isf[1], e_isf[2], 0.0, -e_isf[0], -e_isf[1], e_isf[0], 0.0};
    const double sk_af[9] = {0.0, -e_af[2], e_af[1], e_af[2], 0.0, -e_af[0], -e_af[1], e_af[0], 0.0};
    const int N = d.N, K = d.K;
    Mat D(3 * N, K + N_TILT);
    for (int n = 0; n < N; ++n) {
        double T1[9], T2[9];
        if (K) {
            mat3_mul(&d.C_sf_from_isf[9 * n], sk_isf, T1);
            mat3_mul(A, T1, T2);
            const double* Gn = d.G + static_cast<size_t>(3) * K * n;
            for (int i = 0; i < 3; ++i)
                for (int k = 0; k < K; ++k)
                    D(3 * n + i, k) = -(T2[3 * i] * Gn[k] + T2[3 * i + 1] * Gn[K + k] + T2[3 * i + 2] * Gn[2 * K + k]);
        }
        mat3_mul(&Cfa[9 * n], sk_af, T1);
        mat3_mul(A, T1, T2);
        for (int i = 0; i < 3; ++i)
            for (int k = 0; k < N_TILT; ++k) D(3 * n + i, K + k) = -T2[3 * i + k];
    }
    return D;
}

// lstsq of a symmetric normal system (rcond = eps max(rows, cols), numpy's None)
inline std::vector<double> lstsq_sym(const Mat& Nm, const Mat& rhs, int col) {
    Mat P;
    if (!pinv_sym(Nm, std::numeric_limits<double>::epsilon() * Nm.r, P)) throw LinAlgError("SVD did not converge in Linear Least Squares");
    std::vector<double> x(Nm.r, 0.0);
    for (int i = 0; i < Nm.r; ++i)
        for (int k = 0; k < Nm.r; ++k) x[i] += P(i, k) * rhs(k, col);
    return x;
}

// the weighted normal equations of the affine model h_n = A m_n + b (FULL12): X = [m_n^T 1] per row,
// XtWX (4x4) += w_n x x^T and XtWh (4x3) += w_n x h_n^T (azimuth_fit's lstsq of the same rows)
inline void affine_normal_equations(const double* m, const double* h, const double* w, int N, Mat& XtWX, Mat& XtWh) {
    for (int n = 0; n < N; ++n) {
        const double x[4] = {m[3 * n], m[3 * n + 1], m[3 * n + 2], 1.0};
        for (int i = 0; i < 4; ++i) {
            const double xw = x[i] * w[n];
            for (int j = 0; j < 4; ++j) XtWX(i, j) += xw * x[j];
            for (int j = 0; j < 3; ++j) XtWh(i, j) += xw * h[3 * n + j];
        }
    }
}

// profile cost c(psi) of one candidate (azimuth_fit._profile_costs); physical: the distortion keeps
// the field's handedness
inline double profile_cost(int model, double psi, const std::vector<double>& U, const std::vector<double>& V,
                           const std::vector<double>& Z, const double* h, const double* w, int N, bool& physical) {
    const double c = std::cos(psi), sn = std::sin(psi);
    std::vector<double> m(3 * static_cast<size_t>(N));
    for (size_t k = 0; k < m.size(); ++k) m[k] = c * U[k] + sn * V[k] + Z[k];
    double cost = 0.0;
    physical = true;
    if (model == NONE) {
        for (int n = 0; n < N; ++n)
            for (int i = 0; i < 3; ++i) {
                const double r = h[3 * n + i] - m[3 * n + i];
                cost += w[n] * (r * r);
            }
        return cost;
    }
    if (model == SEED7) {
        double S1 = 0.0;
        for (int n = 0; n < N; ++n) S1 += w[n];
        double sc[3], bb[3];
        for (int j = 0; j < 3; ++j) {
            double Sx = 0.0, Sxx = 0.0, Sh = 0.0, Sxh = 0.0;
            for (int n = 0; n < N; ++n) {
                const double x = m[3 * n + j], hj = h[3 * n + j];
                Sx += w[n] * x;
                Sxx += w[n] * (x * x);
                Sh += w[n] * hj;
                Sxh += w[n] * x * hj;
            }
            double det = Sxx * S1 - Sx * Sx;
            const bool ok = det > 1e-12 * std::max(Sxx * S1, 1e-300);
            if (!ok) det = 1.0;
            sc[j] = ok ? (S1 * Sxh - Sx * Sh) / det : 0.0;
            bb[j] = ok ? (Sxx * Sh - Sx * Sxh) / det : Sh / S1;
            physical = physical && sc[j] >= 0.0;
        }
        for (int n = 0; n < N; ++n)
            for (int i = 0; i < 3; ++i) {
                const double r = h[3 * n + i] - sc[i] * m[3 * n + i] - bb[i];
                cost += w[n] * (r * r);
            }
        return cost;
    }
    Mat XtWX(4, 4), XtWh(4, 3);
    affine_normal_equations(m.data(), h, w, N, XtWX, XtWh);
    Mat Pinv;
    if (!pinv_sym(XtWX, 1e-15, Pinv)) throw LinAlgError("SVD did not converge");
    const Mat beta = matmul(Pinv, XtWh);  // (4, 3): rows 0-2 = A^T, row 3 = b
    const double det = beta(0, 0) * (beta(1, 1) * beta(2, 2) - beta(1, 2) * beta(2, 1))
                     - beta(0, 1) * (beta(1, 0) * beta(2, 2) - beta(1, 2) * beta(2, 0))
                     + beta(0, 2) * (beta(1, 0) * beta(2, 1) - beta(1, 1) * beta(2, 0));
    physical = det > -1e-9;
    for (int n = 0; n < N; ++n)
        for (int j = 0; j < 3; ++j) {
            const double pred = m[3 * n] * beta(0, j) + m[3 * n + 1] * beta(1, j) + m[3 * n + 2] * beta(2, j) + beta(3, j);
            const double r = h[3 * n + j] - pred;
            cost += w[n] * (r * r);
        }
    return cost;
}

// The whole solve (azimuth_fit.fit_psi). P_prior: (K+2)^2 row-major or nullptr (zeros).
inline Result fit_psi(const Samples& d, const double* C_isf_af, const double* e, int model, int grid_points,
                      int max_iterations, double tol_rad, const double* P_prior, int P_prior_rows, int P_prior_cols,
                      bool estimate_errors) {
    const int N = d.N, K = d.K, p = n_unknowns(model), Kc = K + N_TILT;
    Result res;
    res.theta.assign(p, NAN);
    res.cov_white = Mat(p, p, NAN);
    res.S = Mat(p, Kc, 0.0);
    if (3 * N <= p) {
        res.code = 1;
        return res;
    }
    // non-finite samples: a named reason (the reference's check)
    int bad = 0;
    for (int n = 0; n < N; ++n) {
        bool fin = std::isfinite(d.var_white[n]) && std::isfinite(d.w[n]);
        for (int i = 0; i < 3; ++i) fin = fin && std::isfinite(d.h[3 * n + i]);
        for (int i = 0; i < 9; ++i) fin = fin && std::isfinite(d.C_sf_from_isf[9 * n + i]);
        for (int i = 0; i < 3 * K; ++i) fin = fin && std::isfinite(d.G[static_cast<size_t>(3) * K * n + i]);
        bad += fin ? 0 : 1;
    }
    if (bad) {
        res.code = 3;
        res.n_bad = bad;
        return res;
    }
    const double* h = d.h;
    const double* w = d.w;
    std::vector<double> Cfa(9 * static_cast<size_t>(N));
    for (int n = 0; n < N; ++n) mat3_mul(&d.C_sf_from_isf[9 * n], C_isf_af, &Cfa[9 * n]);
    std::vector<double> U(3 * static_cast<size_t>(N)), V(U.size()), Z(U.size());
    const double eu[3] = {e[0], e[1], 0.0}, ev[3] = {e[1], -e[0], 0.0}, ez[3] = {0.0, 0.0, e[2]};
    double sx = 0.0, sy = 0.0;
    for (int n = 0; n < N; ++n) {
        mat3_vec(&Cfa[9 * n], eu, &U[3 * n]);
        mat3_vec(&Cfa[9 * n], ev, &V[3 * n]);
        mat3_vec(&Cfa[9 * n], ez, &Z[3 * n]);
        const double* C = &Cfa[9 * n];
        const double hx = C[0] * h[3 * n] + C[3] * h[3 * n + 1] + C[6] * h[3 * n + 2];
        const double hy = C[1] * h[3 * n] + C[4] * h[3 * n + 1] + C[7] * h[3 * n + 2];
        sx += w[n] * hx;
        sy += w[n] * hy;
    }
    // candidates: the closed-form 2-D fit, then the grid
    std::vector<double> cands(1 + grid_points);
    cands[0] = wrap_2pi(std::atan2(e[1], e[0]) - std::atan2(sy, sx));
    const double step_g = TWO_PI / grid_points;
    for (int k = 0; k < grid_points; ++k) cands[1 + k] = k * step_g + 0.0;
    std::vector<double> costs(cands.size());
    std::vector<char> phys(cands.size());
    bool any_phys = false;
    for (size_t k = 0; k < cands.size(); ++k) {
        bool ph = true;
        costs[k] = profile_cost(model, cands[k], U, V, Z, h, w, N, ph);
        phys[k] = ph;
        any_phys = any_phys || ph;
    }
    if (model != NONE && any_phys)
        for (size_t k = 0; k < cands.size(); ++k)
            if (!phys[k]) costs[k] = INFINITY;
    size_t best = 0;  // numpy.argmin: the first NaN, else the first minimum
    for (size_t k = 0; k < costs.size(); ++k) {
        if (std::isnan(costs[k])) { best = k; break; }
        if (costs[k] < costs[best]) best = k;
    }
    const double psi0 = cands[best];
    // the linear unknowns at psi0 (azimuth_fit._solve_linear), packed
    std::vector<double> theta(p, 0.0);
    theta[0] = psi0;
    {
        const double c0 = std::cos(psi0), s0 = std::sin(psi0);
        std::vector<double> m0(3 * static_cast<size_t>(N));
        for (size_t k = 0; k < m0.size(); ++k) m0[k] = c0 * U[k] + s0 * V[k] + Z[k];
        if (model == SEED7) {
            double sw = 0.0;
            for (int n = 0; n < N; ++n) sw += w[n];
            for (int j = 0; j < 3; ++j) {
                Mat Nm(2, 2), rhs(2, 1);
                for (int n = 0; n < N; ++n) {
                    const double x = m0[3 * n + j];
                    Nm(0, 0) += w[n] * (x * x);
                    Nm(0, 1) += w[n] * x;
                    rhs(0, 0) += w[n] * (x * h[3 * n + j]);
                    rhs(1, 0) += w[n] * h[3 * n + j];
                }
                Nm(1, 0) = Nm(0, 1);
                Nm(1, 1) = sw;
                const std::vector<double> sol = lstsq_sym(Nm, rhs, 0);
                theta[1 + j] = sol[0];
                theta[4 + j] = sol[1];
            }
        } else if (model == FULL12) {
            Mat XtWX(4, 4), XtWh(4, 3);
            affine_normal_equations(m0.data(), h, w, N, XtWX, XtWh);
            for (int j = 0; j < 3; ++j) {  // beta[:, j] -> A row j, b_j
                const std::vector<double> sol = lstsq_sym(XtWX, XtWh, j);
                for (int k = 0; k < 3; ++k) theta[1 + 3 * j + k] = sol[k];
                theta[10 + j] = sol[3];
            }
        }
    }
    std::vector<double> sw(3 * static_cast<size_t>(N));
    for (int n = 0; n < N; ++n) sw[3 * n] = sw[3 * n + 1] = sw[3 * n + 2] = w[n];
    std::vector<double> r, r_new;
    Mat J, J_new;
    residual_and_jacobian(model, theta, Cfa, e, h, N, r, &J);
    double cost = wdot_sq(sw, r);
    int it = 0;
    for (it = 1; it <= max_iterations; ++it) {
        const Mat Hn = xtwy(J, sw, J);
        const std::vector<double> g = xtwv(J, sw, r);
        const std::vector<double> st0 = matvec(inv_spd(Hn), g);
        double lam = 1.0;
        std::vector<double> th_new(p);
        double c_new;
        while (true) {
            for (int k = 0; k < p; ++k) th_new[k] = theta[k] + lam * -st0[k];
            residual_and_jacobian(model, th_new, Cfa, e, h, N, r_new, &J_new);
            c_new = wdot_sq(sw, r_new);
            if (c_new <= cost * (1 + 1e-12) + 1e-300 || lam < 1e-4) break;
            lam *= 0.5;
        }
        theta = th_new;
        std::swap(r, r_new);
        std::swap(J, J_new);
        cost = c_new;
        if (std::fabs(lam * -st0[0]) < tol_rad) break;
    }
    if (it > max_iterations) it = max_iterations;
    theta[0] = wrap_2pi(theta[0]);
    for (double v : theta)
        if (!std::isfinite(v)) {
            res.code = 2;
            return res;
        }
    residual_and_jacobian(model, theta, Cfa, e, h, N, r, &J);
    const Mat H = xtwy(J, sw, J);
    const Mat H_inv = inv_spd(H);
    const int dof = 3 * N - p;
    const double s2_raw = wdot_sq(sw, r) / dof;
    std::vector<double> wR(sw.size());
    for (int n = 0; n < N; ++n)
        for (int i = 0; i < 3; ++i) wR[3 * n + i] = sw[3 * n + i] * d.var_white[n] * sw[3 * n + i];
    const Mat middle = xtwy(J, wR, J);
    Mat P_w = matmul(matmul(H_inv, middle), H_inv);
    const double infl = std::max(1.0, s2_raw);
    for (double& v : P_w.a) v = v * infl;
    const Mat D = consider_jacobian(model, theta, d, C_isf_af, Cfa, e);
    Mat S = matmul(H_inv, xtwy(J, sw, D));
    for (double& v : S.a) v = -v;
    // conditioning of the weighted, column-normalised Jacobian
    {
        std::vector<double> dn(p);
        for (int i = 0; i < p; ++i) {
            const double v = std::sqrt(H(i, i));
            dn[i] = v > 0.0 ? v : 1.0;
        }
        Mat Hs(p, p);
        for (int i = 0; i < p; ++i)
            for (int j = 0; j < p; ++j) Hs(i, j) = H(i, j) / (dn[i] * dn[j]);
        std::vector<double> lam;
        Mat Q;
        if (!eig_sym(Hs, lam, Q)) throw LinAlgError("Eigenvalues did not converge");
        const double lo = *std::min_element(lam.begin(), lam.end());
        const double hi = *std::max_element(lam.begin(), lam.end());
        res.cond = lo > hi * 1e-30 ? std::sqrt(hi / lo) : INFINITY;
    }
    Mat P_c(Kc, Kc, 0.0);
    if (P_prior) {
        if (P_prior_rows != Kc || P_prior_cols != Kc)
            throw std::invalid_argument("P_prior must be " + std::to_string(Kc) + "x" + std::to_string(Kc) + ", got (" +
                                        std::to_string(P_prior_rows) + ", " + std::to_string(P_prior_cols) + ")");
        for (int k = 0; k < Kc * Kc; ++k) P_c.a[k] = P_prior[k];
    }
    res.iterations = it;
    res.ok = true;
    res.cov_white = P_w;
    res.S = S;
    bool any_prior = false;
    for (int k = 0; k < Kc; ++k) any_prior = any_prior || P_c(k, k) > 0.0;
    if (estimate_errors && any_prior) {
        // joint MAP of [theta, c] with the prior c ~ N(0, P_c) (azimuth_fit._estimate_errors)
        std::vector<int> fr;
        for (int k = 0; k < Kc; ++k)
            if (P_c(k, k) > 0.0) fr.push_back(k);
        const int nf = static_cast<int>(fr.size());
        std::vector<double> info(nf);
        for (int k = 0; k < nf; ++k) info[k] = 1.0 / P_c(fr[k], fr[k]);
        std::vector<double> Ww(sw.size());
        for (int n = 0; n < N; ++n) Ww[3 * n] = Ww[3 * n + 1] = Ww[3 * n + 2] = 1.0 / d.var_white[n];
        std::vector<double> c(nf, 0.0);
        const int R = 3 * N;
        auto normal_eqs = [&](const std::vector<double>& th, const std::vector<double>& c_,
                              const std::vector<double>& prior_info, Mat& Ha, std::vector<double>& ga,
                              std::vector<double>& r_lin) {
            std::vector<double> r_;
            Mat J_;
            residual_and_jacobian(model, th, Cfa, e, h, N, r_, &J_);
            Mat Ja(R, p + nf);
            r_lin.assign(R, 0.0);
            for (int k = 0; k < R; ++k) {
                double acc = 0.0;
                for (int f = 0; f < nf; ++f) acc += -D(k, fr[f]) * c_[f];
                r_lin[k] = r_[k] + acc;
                for (int j = 0; j < p; ++j) Ja(k, j) = J_(k, j);
                for (int f = 0; f < nf; ++f) Ja(k, p + f) = -D(k, fr[f]);
            }
            Ha = xtwy(Ja, Ww, Ja);
            for (int f = 0; f < nf; ++f) Ha(p + f, p + f) += prior_info[f];
            ga = xtwv(Ja, Ww, r_lin);
            for (int f = 0; f < nf; ++f) ga[p + f] += prior_info[f] * c_[f];
        };
        Mat Ha;
        std::vector<double> ga, r_lin;
        for (int pass = 0; pass < 3; ++pass) {
            normal_eqs(theta, c, info, Ha, ga, r_lin);
            const std::vector<double> st = matvec(inv_spd(Ha), ga);
            for (int k = 0; k < p; ++k) theta[k] = theta[k] + -st[k];
            for (int f = 0; f < nf; ++f) c[f] = c[f] + -st[p + f];
        }
        normal_eqs(theta, c, info, Ha, ga, r_lin);
        const int dof2 = std::max(R - p, 1);
        double ss = 0.0;
        for (int k = 0; k < R; ++k) ss += Ww[k] * (r_lin[k] * r_lin[k]);
        const double s2 = ss / dof2;
        const double scale = std::max(1.0, s2);
        Mat Hinv = inv_spd(Ha);
        for (double& v : Hinv.a) v = v * scale;
        res.P_psi_c = Mat(1 + Kc, 1 + Kc, 0.0);
        std::vector<int> idx{0}, sel{0};
        for (int f = 0; f < nf; ++f) {
            idx.push_back(p + f);
            sel.push_back(1 + fr[f]);
        }
        for (size_t i = 0; i < idx.size(); ++i)
            for (size_t j = 0; j < idx.size(); ++j) res.P_psi_c(sel[i], sel[j]) = Hinv(idx[i], idx[j]);
        for (int k = 1; k < 1 + Kc; ++k) {
            res.P_psi_c(0, k) = -res.P_psi_c(0, k);
            res.P_psi_c(k, 0) = -res.P_psi_c(k, 0);
        }
        std::vector<double> info_nt = info;
        for (int f = 0; f < nf; ++f)
            if (fr[f] >= Kc - N_TILT) info_nt[f] = 1e16;
        Mat H_nt;
        std::vector<double> g_nt, r_nt;
        normal_eqs(theta, c, info_nt, H_nt, g_nt, r_nt);
        const double psi_var_nt = inv_spd(H_nt)(0, 0) * scale;
        res.c_hat.assign(Kc, 0.0);
        for (int f = 0; f < nf; ++f) res.c_hat[fr[f]] = c[f];
        theta[0] = wrap_2pi(theta[0]);
        res.theta = theta;
        res.s2 = s2;
        double rr = 0.0;
        for (double v : r_lin) rr += v * v;
        res.residual_rms = std::sqrt(rr / R);
        res.psi_sigma_gate = std::sqrt(std::max(psi_var_nt, 0.0));
        return res;
    }
    // consider only
    std::vector<double> s0(Kc);
    for (int k = 0; k < Kc; ++k) s0[k] = S(0, k);
    auto quad = [&](const std::vector<double>& a) {
        double q = 0.0;
        for (int i = 0; i < Kc; ++i) {
            double row = 0.0;
            for (int j = 0; j < Kc; ++j) row += a[j] * P_c(j, i);
            q += row * a[i];
        }
        return q;
    };
    res.P_psi_c = Mat(1 + Kc, 1 + Kc, 0.0);
    res.P_psi_c(0, 0) = P_w(0, 0) + quad(s0);
    for (int i = 0; i < Kc; ++i) {
        double v = 0.0;
        for (int j = 0; j < Kc; ++j) v += s0[j] * P_c(j, i);
        res.P_psi_c(0, 1 + i) = res.P_psi_c(1 + i, 0) = v;
        for (int j = 0; j < Kc; ++j) res.P_psi_c(1 + i, 1 + j) = P_c(i, j);
    }
    std::vector<double> s_nt = s0;
    for (int k = Kc - N_TILT; k < Kc; ++k) s_nt[k] = 0.0;
    res.theta = theta;
    res.s2 = s2_raw;
    double rr = 0.0;
    for (double v : r) rr += v * v;
    res.residual_rms = std::sqrt(rr / (3.0 * N));
    res.c_hat.assign(Kc, 0.0);
    res.psi_sigma_gate = std::sqrt(std::max(P_w(0, 0) + quad(s_nt), 0.0));
    return res;
}

// Largest angle between the predicted Earth-field directions in SF over the samples
// (azimuth_fit.orientation_diversity_rad): m_i = C_SF<-AF,i R3(psi) e, u_i = m_i / |m_i|, the smallest
// cosine over all pairs (the diagonal too, as the reference's N x N product), clipped as Python's
// max(-1, min(1, .)) clips (a NaN becomes -1, as there), then acos. O(N^2) multiply-adds, no N x N array.
inline double orientation_diversity(const double* C_sf_from_af, int N, double psi, const double* e) {
    const double c = std::cos(psi), s = std::sin(psi);
    const double Re[3] = {c * e[0] + s * e[1], -s * e[0] + c * e[1], e[2]};
    std::vector<double> u(3 * static_cast<size_t>(N));
    for (int n = 0; n < N; ++n) {
        double m[3];
        mat3_vec(&C_sf_from_af[9 * n], Re, m);
        const double norm = std::sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
        for (int i = 0; i < 3; ++i) u[3 * n + i] = m[i] / norm;
    }
    double dmin = INFINITY;
    bool nan_seen = false;
    for (int i = 0; i < N && !nan_seen; ++i) {
        const double* ui = &u[3 * i];
        for (int j = i; j < N; ++j) {
            const double* uj = &u[3 * j];
            const double d = ui[0] * uj[0] + ui[1] * uj[1] + ui[2] * uj[2];
            if (std::isnan(d)) { nan_seen = true; break; }
            if (d < dmin) dmin = d;
        }
    }
    if (N == 0) throw std::invalid_argument("orientation diversity of no samples");
    double v = nan_seen ? NAN : dmin;
    v = v > -1.0 ? v : -1.0;
    v = v < 1.0 ? v : 1.0;
    return std::acos(v);
}

}  // namespace fit
}  // namespace azimuthd
