// estimators._core.azimuth_fit (method A's re-solve: core/azimuth_fit.hpp) and estimators._core.Deviation
// (method D's RLS: core/mag_deviation.hpp). The Python faces are estimators/core.py fit_psi and
// HeldDeviation (estimators/azimuth_fit.py's and estimators/mag_deviation.py's signatures).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "azimuth_fit.hpp"
#include "mag_deviation.hpp"

namespace py = pybind11;
using namespace azimuthd;
using ArrayF = py::array_t<double, py::array::c_style | py::array::forcecast>;
using ArrayI = py::array_t<std::int64_t, py::array::c_style | py::array::forcecast>;

namespace {

void need_shape(const ArrayF& a, std::initializer_list<py::ssize_t> shape, const char* name) {
    bool ok = a.ndim() == static_cast<py::ssize_t>(shape.size());
    py::ssize_t i = 0;
    for (auto s : shape) ok = ok && a.shape(i++) == s;
    if (!ok) throw std::invalid_argument(std::string(name) + ": wrong shape");
}

ArrayF mat_out(const fit::Mat& m) {
    ArrayF out({py::ssize_t(m.r), py::ssize_t(m.c)});
    std::copy(m.a.begin(), m.a.end(), out.mutable_data());
    return out;
}

ArrayF vec_out(const std::vector<double>& v) {
    ArrayF out(py::ssize_t(v.size()));
    std::copy(v.begin(), v.end(), out.mutable_data());
    return out;
}

ArrayF vec3(const double* v) {
    ArrayF out(3);
    std::copy(v, v + 3, out.mutable_data());
    return out;
}

const double* v3(const ArrayF& a, const char* name) {
    need_shape(a, {3}, name);
    return a.data();
}

std::vector<std::int64_t> counts_in(const ArrayI& a) {
    if (a.ndim() != 1 || a.shape(0) < 1) throw std::invalid_argument("coverage counts must be a non-empty vector");
    return std::vector<std::int64_t>(a.data(), a.data() + a.shape(0));
}

ArrayI counts_out(const std::vector<std::int64_t>& v) {
    ArrayI out(py::ssize_t(v.size()));
    std::copy(v.begin(), v.end(), out.mutable_data());
    return out;
}

}  // namespace

void bind_fit(py::module_& m) {
    m.def("azimuth_fit",
          [](const ArrayF& C_sf_from_isf, const ArrayF& h, const ArrayF& var_white, const ArrayF& weight,
             py::object G_gyro, const ArrayF& C_isf_af, const ArrayF& e_ned, int model, int grid_points,
             int max_iterations, double tol_rad, py::object P_prior, bool estimate_errors) {
              if (model < 0 || model > 2) throw std::invalid_argument("model must be 0 (none), 1 (seed7) or 2 (full12)");
              if (grid_points < 1) throw std::invalid_argument("grid_points must be >= 1");
              if (h.ndim() != 2 || h.shape(1) != 3) throw std::invalid_argument("h_sf_gauss must have shape (N, 3)");
              const py::ssize_t N = h.shape(0);
              need_shape(C_sf_from_isf, {N, 3, 3}, "C_sf_from_isf");
              need_shape(var_white, {N}, "var_white_gauss2");
              need_shape(weight, {N}, "weight");
              need_shape(C_isf_af, {3, 3}, "C_isf_af");
              need_shape(e_ned, {3}, "e_ned");
              ArrayF G;
              fit::Samples d;
              d.N = static_cast<int>(N);
              if (!G_gyro.is_none()) {
                  G = ArrayF::ensure(G_gyro);
                  if (!G || G.ndim() != 3 || G.shape(0) != N || G.shape(1) != 3)
                      throw std::invalid_argument("G_gyro must have shape (N, 3, K)");
                  d.K = static_cast<int>(G.shape(2));
                  d.G = G.data();
              }
              d.C_sf_from_isf = C_sf_from_isf.data();
              d.h = h.data();
              d.var_white = var_white.data();
              d.w = weight.data();
              ArrayF P;
              const double* Pp = nullptr;
              int pr = 0, pc = 0;
              if (!P_prior.is_none()) {
                  P = ArrayF::ensure(P_prior);
                  if (!P || P.ndim() != 2) throw std::invalid_argument("P_prior must be a square matrix");
                  Pp = P.data();
                  pr = static_cast<int>(P.shape(0));
                  pc = static_cast<int>(P.shape(1));
              }
              fit::Result r;
              try {
                  py::gil_scoped_release nogil;
                  r = fit::fit_psi(d, C_isf_af.data(), e_ned.data(), model, grid_points, max_iterations, tol_rad, Pp,
                                   pr, pc, estimate_errors);
              } catch (const fit::LinAlgError& exc) {
                  throw py::value_error(std::string("linear algebra: ") + exc.what());
              }
              py::dict out;
              out["ok"] = r.ok;
              out["code"] = r.code;
              out["n_bad"] = r.n_bad;
              out["iterations"] = r.iterations;
              out["theta"] = vec_out(r.theta);
              out["cov_white"] = mat_out(r.cov_white);
              out["S"] = mat_out(r.S);
              out["s2"] = r.s2;
              out["residual_rms"] = r.residual_rms;
              out["cond"] = r.cond;
              out["c_hat"] = vec_out(r.c_hat);
              out["P_psi_c"] = r.ok ? py::object(mat_out(r.P_psi_c)) : py::object(py::none());
              out["psi_sigma_gate"] = r.psi_sigma_gate;
              return out;
          },
          py::arg("C_sf_from_isf"), py::arg("h_sf_gauss"), py::arg("var_white_gauss2"), py::arg("weight"),
          py::arg("G_gyro"), py::arg("C_isf_af"), py::arg("e_ned"), py::arg("model"), py::arg("grid_points"),
          py::arg("max_iterations"), py::arg("tol_rad"), py::arg("P_prior"), py::arg("estimate_errors"),
          "Method A's re-solve over the stored samples (estimators/azimuth_fit.py fit_psi's numbers as a dict).");

    m.def("orientation_diversity",
          [](const ArrayF& C_sf_from_af, double psi_rad, const ArrayF& e_ned) {
              if (C_sf_from_af.ndim() != 3 || C_sf_from_af.shape(1) != 3 || C_sf_from_af.shape(2) != 3)
                  throw std::invalid_argument("C_sf_from_af must have shape (N, 3, 3)");
              need_shape(e_ned, {3}, "e_ned");
              const int N = static_cast<int>(C_sf_from_af.shape(0));
              py::gil_scoped_release nogil;
              return fit::orientation_diversity(C_sf_from_af.data(), N, psi_rad, e_ned.data());
          },
          py::arg("C_sf_from_af"), py::arg("psi_rad"), py::arg("e_ned"),
          "Largest angle between the predicted field directions in SF (azimuth_fit.orientation_diversity_rad).");

    py::class_<Deviation>(m, "Deviation", "Method D's RLS state (core/mag_deviation.hpp).")
        .def(py::init([](const ArrayF& coeffs, const ArrayF& P, std::int64_t n, const ArrayF& resid_sq_sum,
                         std::int64_t n_resid, const ArrayI& hc, const ArrayI& rc, const ArrayI& pc) {
                 if (coeffs.ndim() != 2 || coeffs.shape(1) != 3 || (coeffs.shape(0) != 7 && coeffs.shape(0) != 11))
                     throw std::invalid_argument("coeffs must have shape (7, 3) or (11, 3)");
                 const py::ssize_t k = coeffs.shape(0);
                 need_shape(P, {k, k}, "P");
                 const double* rs = v3(resid_sq_sum, "resid_sq_sum");
                 Deviation d;
                 d.n_per = static_cast<int>(k);
                 d.coeffs.assign(coeffs.data(), coeffs.data() + 3 * k);
                 d.P.assign(P.data(), P.data() + k * k);
                 d.n = n;
                 d.n_resid = n_resid;
                 for (int i = 0; i < 3; ++i) d.resid_sq_sum[i] = rs[i];
                 d.heading_counts = counts_in(hc);
                 d.roll_counts = counts_in(rc);
                 d.pitch_counts = counts_in(pc);
                 return d;
             }),
             py::arg("coeffs"), py::arg("P"), py::arg("n"), py::arg("resid_sq_sum"), py::arg("n_resid"),
             py::arg("heading_counts"), py::arg("roll_counts"), py::arg("pitch_counts"))
        .def("copy", [](const Deviation& d) { return Deviation(d); })
        .def("step",
             [](Deviation& d, const ArrayF& m, const ArrayF& F, double psi, double phi, double theta, double lam,
                double roll_limit, double pitch_limit, int hb, int rb, int pb) {
                 DeviationParamsC p;
                 p.forgetting_factor = lam;
                 p.roll_limit_rad = roll_limit;
                 p.pitch_limit_rad = pitch_limit;
                 p.heading_bins = hb;
                 p.roll_bins = rb;
                 p.pitch_bins = pb;
                 if (static_cast<int>(d.heading_counts.size()) != hb || static_cast<int>(d.roll_counts.size()) != rb ||
                     static_cast<int>(d.pitch_counts.size()) != pb)
                     throw std::invalid_argument("the deviation state's coverage bins do not match the parameters");
                 double e[3] = {0.0, 0.0, 0.0};
                 const int code = static_cast<int>(d.step(v3(m, "mag_body_gauss"), v3(F, "field_ned_gauss"), psi, phi,
                                                          theta, p, e));
                 return py::make_tuple(code, vec3(e));
             },
             "One observation: (code 0 updated / 1 non-finite / 2 outside the limits, a-priori residual (3)).")
        .def("model",
             [](const Deviation& d, double psi, double phi, double theta) {
                 double o[3];
                 d.model(psi, phi, theta, o);
                 return vec3(o);
             })
        .def("corrected",
             [](const Deviation& d, const ArrayF& m, double psi, double phi, double theta) {
                 const double* mi = v3(m, "mag_body_gauss");
                 double o[3];
                 d.model(psi, phi, theta, o);
                 for (int i = 0; i < 3; ++i) o[i] = mi[i] - o[i];
                 return vec3(o);
             })
        .def("residual_sigma",
             [](const Deviation& d) {
                 double o[3];
                 d.residual_sigma(o);
                 return vec3(o);
             })
        .def("coverage",
             [](const Deviation& d, int k) {
                 const double hf = Deviation::fraction(d.heading_counts, k), rf = Deviation::fraction(d.roll_counts, k),
                              pf = Deviation::fraction(d.pitch_counts, k);
                 return py::make_tuple(hf, rf, pf, std::min(hf, std::min(rf, pf)));
             })
        .def_property_readonly("coeffs", [](const Deviation& d) {
            ArrayF out({py::ssize_t(d.n_per), py::ssize_t(3)});
            std::copy(d.coeffs.begin(), d.coeffs.end(), out.mutable_data());
            return out;
        })
        .def_property_readonly("P", [](const Deviation& d) {
            ArrayF out({py::ssize_t(d.n_per), py::ssize_t(d.n_per)});
            std::copy(d.P.begin(), d.P.end(), out.mutable_data());
            return out;
        })
        .def_property_readonly("n", [](const Deviation& d) { return d.n; })
        .def_property_readonly("n_resid", [](const Deviation& d) { return d.n_resid; })
        .def_property_readonly("resid_sq_sum", [](const Deviation& d) { return vec3(d.resid_sq_sum); })
        .def_property_readonly("heading_counts", [](const Deviation& d) { return counts_out(d.heading_counts); })
        .def_property_readonly("roll_counts", [](const Deviation& d) { return counts_out(d.roll_counts); })
        .def_property_readonly("pitch_counts", [](const Deviation& d) { return counts_out(d.pitch_counts); });
}
