// estimators._core: method C's rest detection held in the core (ZeroRate, core/zero_rate.hpp) and the
// filter step with its magnetometer chain as one call (filter_chain, core/filter_chain.hpp). The
// Python face is estimators/core.py (HeldZeroRate, rest_step, filter_chain_step); the references are
// estimators/zero_rate.py and service/pipeline.py Pipeline._filter_chain_python.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>

#include "filter_chain.hpp"
#include "bindings_arrays.hpp"

namespace py = pybind11;
using namespace azimuthd;
using ArrayC = py::array_t<double, py::array::c_style | py::array::forcecast>;

namespace {

using azimuthd::bind::arr;
using azimuthd::bind::np1;

using azimuthd::bind::opt;
py::object opt3(bool has, const V3& v) { return has ? py::object(np1(v)) : py::object(py::none()); }

zero_rate::Params zr_params(const py::object& o) {
    auto num = [&](const char* k) { return o.attr(k).cast<double>(); };
    return {num("gyro_deviation_rad_s"), num("accel_deviation_m_s2"), num("max_rate_rad_s"), num("lowpass_tau_s"),
            num("min_rest_s"), num("chunk_s"), num("mean_sigma_floor_rad_s"), num("gate_chi2")};
}

// ZeroRateState's fields as a dict of the reference's types (None where the reference has None)
py::dict zr_state(const zero_rate::State& s) {
    py::dict d;
    d["time_s"] = opt(s.has_time, s.time_s);
    d["gyro_lp_rad_s"] = opt3(s.has_time, s.gyro_lp);
    d["accel_lp_m_s2"] = opt3(s.has_time, s.accel_lp);
    d["rest_since_s"] = opt(s.has_rest, s.rest_since_s);
    d["reported"] = s.reported;
    d["n"] = s.n;
    d["sum_rad_s"] = opt3(s.has_rest, s.sum);
    d["run_n"] = s.run_n;
    d["run_sum_rad_s"] = opt3(s.has_rest, s.run_sum);
    d["run_sum_sq_rad2_s2"] = opt3(s.has_rest, s.run_sum_sq);
    d["chunk_start_s"] = opt(s.has_rest, s.chunk_start_s);
    return d;
}

zero_rate::State zr_from(const py::object& st) {
    zero_rate::State s;
    py::object t = st.attr("time_s");
    s.has_time = !t.is_none();
    if (s.has_time) {
        s.time_s = t.cast<double>();
        s.gyro_lp = arr<3>(st.attr("gyro_lp_rad_s"), "gyro_lp_rad_s");
        s.accel_lp = arr<3>(st.attr("accel_lp_m_s2"), "accel_lp_m_s2");
    }
    py::object r = st.attr("rest_since_s");
    s.has_rest = !r.is_none();
    s.reported = st.attr("reported").cast<bool>();
    s.n = st.attr("n").cast<long>();
    s.run_n = st.attr("run_n").cast<long>();
    if (s.has_rest) {
        s.rest_since_s = r.cast<double>();
        s.sum = arr<3>(st.attr("sum_rad_s"), "sum_rad_s");
        s.run_sum = arr<3>(st.attr("run_sum_rad_s"), "run_sum_rad_s");
        s.run_sum_sq = arr<3>(st.attr("run_sum_sq_rad2_s2"), "run_sum_sq_rad2_s2");
        s.chunk_start_s = st.attr("chunk_start_s").cast<double>();
    }
    return s;
}

py::tuple rest_out(const zero_rate::RestRate& r) { return py::make_tuple(np1(r.mean), np1(r.var), r.n, r.rest_s); }

zero_rate::RestRate rest_in(const py::object& r) {
    zero_rate::RestRate x;
    x.mean = arr<3>(r.attr("mean_gyro_body_rad_s"), "mean_gyro_body_rad_s");
    x.var = arr<3>(r.attr("variance_rad2_s2"), "variance_rad2_s2");
    x.n = r.attr("n_samples").cast<long>();
    x.rest_s = r.attr("rest_s").cast<double>();
    return x;
}

// polar_heading's diagnostics as bindings_polar_heading.cpp hands them to estimators/core.py _ph_diag
py::object hdiag_out(const polar_heading::Diag& d) {
    if (d.code == polar_heading::PLAIN) return py::int_(d.source_available ? 1 : 0);
    return py::make_tuple(d.code, d.source_available, d.dt_s, d.H, d.z, d.nu, d.S, d.ratio, d.reset_jump, d.why);
}

}  // namespace

void bind_filter_chain(py::module_& m) {
    py::class_<zero_rate::Params>(m, "ZeroRateParams")
        .def(py::init([](const py::object& p) { return zr_params(p); }), py::arg("params"),
             "estimators.zero_rate.ZeroRateParams, converted once.");
    py::class_<zero_rate::State>(m, "ZeroRate")
        .def(py::init([](const py::object& st) { return zr_from(st); }), py::arg("state"),
             "From estimators.zero_rate.ZeroRateState.")
        .def("get_state", &zr_state, "ZeroRateState's fields as a dict.")
        .def("step",
             [](zero_rate::State& s, const zero_rate::Params& p, double t, double wx, double wy, double wz, double fx,
                double fy, double fz) -> py::object {
                 zero_rate::RestRate r;
                 if (!zero_rate::rest_step(s, t, {wx, wy, wz}, {fx, fy, fz}, p, r)) return py::none();
                 return rest_out(r);
             },
             "rest_step: None or RestRate's fields (mean (3), variance (3), n_samples, rest_s).")
        .def_property_readonly("time_s", [](const zero_rate::State& s) { return opt(s.has_time, s.time_s); });

    m.def("attitude_zero_rate_update",
          [](polar::State& st, const py::object& rate, const zero_rate::Params& p) {
              double ratio;
              const int r = zero_rate::attitude_update(st, rest_in(rate), p, ratio);
              return py::make_tuple(r, ratio);
          },
          "estimators.zero_rate.attitude_zero_rate_update on the held PolarAttitude: (0 fused / 1 not levelled / "
          "2 gated out, test ratio).");
    m.def("heading_zero_rate_update",
          [](polar_heading::State& st, const py::object& rate, const zero_rate::Params& p) {
              double ratio;
              const int r = zero_rate::heading_update(st, rest_in(rate), p, ratio);
              return py::make_tuple(r, ratio);
          },
          "estimators.zero_rate.heading_zero_rate_update on the held PolarHeading: (0 fused / 1 not in the "
          "platform formulation / 2 gated out, test ratio).");

    m.def("filter_chain",
          [](polar::State& att, const polar::Params& att_p, zero_rate::State& zr, const zero_rate::Params& zr_p,
             MagDisturbance& md, const MagDisturbanceParams& md_p, MagUsability& mu, const MagUsabilityParams& mu_p,
             polar_heading::State& hdg, const polar_heading::Params& hdg_p, Deviation* dev, double t,
             const py::handle& gyro_b, const py::handle& accel_b, const py::handle& mag_b, const py::handle& C,
             const py::handle& fc, double fc_sigma_tilt_rad, double fc_tilt_max_age_s, double declination,
             double declination_sigma, const py::handle& field_model, bool dev_apply, double dev_min_coverage,
             int dev_min_samples_per_bin, bool dev_hard_iron_changed, const py::handle& dev_in_use) {
              filter_chain::States S{&att, &att_p, &zr, &zr_p, &md, &md_p, &mu, &mu_p, &hdg, &hdg_p, dev};
              filter_chain::Inputs in{};
              in.t = t;
              in.gyro_b = arr<3>(gyro_b, "gyro_b");
              in.accel_b = arr<3>(accel_b, "accel_b");
              in.has_mag = !mag_b.is_none();
              if (in.has_mag) in.mag_b = arr<3>(mag_b, "mag_b");
              in.C_body_from_sensor = arr<9>(C, "C_body_from_sensor");
              in.fc_trusted = !fc.is_none();   // (time_s, roll, pitch) of the FC's trusted ATTITUDE
              if (in.fc_trusted) {
                  py::tuple f = py::reinterpret_borrow<py::tuple>(fc);
                  in.fc_time_s = f[0].cast<double>();
                  in.fc_roll = f[1].cast<double>();
                  in.fc_pitch = f[2].cast<double>();
              }
              in.fc_sigma_tilt_rad = fc_sigma_tilt_rad;
              in.fc_tilt_max_age_s = fc_tilt_max_age_s;
              in.declination = declination;
              in.declination_sigma = declination_sigma;
              in.has_field_model = !field_model.is_none();
              if (in.has_field_model) in.field_model = arr<3>(field_model, "field_model_ned_gauss");
              in.dev_apply = dev_apply;
              in.dev_min_coverage = dev_min_coverage;
              in.dev_min_samples_per_bin = dev_min_samples_per_bin;
              filter_chain::Flags fl{dev_hard_iron_changed,
                                     dev_in_use.is_none() ? -1 : (dev_in_use.cast<bool>() ? 1 : 0)};
              filter_chain::Output out;
              filter_chain::step(S, in, fl, out);
              const polar_heading::Diag& h = out.hdiag;
              if (out.has_tilt && h.code == polar_heading::BAD_RESIDUAL)   // the reference's ValueError
                  throw py::value_error("mag_residual_sigma_gauss must be finite and >= 0 or None, got " +
                                        py_repr(h.H));
              if (out.has_tilt && h.code == polar_heading::BAD_FIELD_MODEL)
                  throw py::value_error("field_model_ned_gauss must be 3 finite numbers (NED, gauss), not all 0, or "
                                        "None, got " + py::repr(field_model).cast<std::string>());
              py::object est = py::none();
              if (out.has_att) {
                  double roll, pitch;
                  Mat<2, 2> cov;
                  polar::estimate(att, roll, pitch, cov);
                  py::array_t<double> c({2, 2});
                  for (int i = 0; i < 4; ++i) c.mutable_data()[i] = cov[i];
                  est = py::make_tuple(roll, pitch, c, np1(V3{att.x_hat[0], att.x_hat[1], att.x_hat[2]}),
                                       np1(att.q_P_from_body));
              }
              py::list events;
              for (const auto& e : out.events) events.append(py::make_tuple(e.first, e.second));
              return py::make_tuple(est, opt3(out.has_mag_s, out.mag_s), out.mag_raw,
                                    out.has_tilt ? hdiag_out(h) : py::object(py::none()), events,
                                    out.has_mag_status ? py::object(py::str(out.mag_status)) : py::object(py::none()),
                                    fl.dev_hard_iron_changed,
                                    fl.dev_in_use < 0 ? py::object(py::none())
                                                      : py::object(py::bool_(fl.dev_in_use == 1)));
          },
          "service/pipeline.py Pipeline._filter_chain_python in one call on the held states: (attitude estimate "
          "tuple or None, mag for B (sensor axes) or None, mag_b_raw present, heading diag (None: no tilt), events "
          "[(kind, text)], mag_status or None (unchanged), deviation hard iron changed, deviation in use).");
}
