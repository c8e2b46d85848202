// The heading arbitration: the compiled twin of service/heading_arbitration.py ``arbitrate``, which
// stays the reference and holds the rule (its module docstring: candidates, the reference propagated
// with the heading rate, the gate, covariance intersection of readings that share a group, the
// inverse-variance fusion about the reference, blended source changes, coasting and re-anchoring,
// the consistent majority). Here: ``_rank``, ``_fuse``, ``_evidence``, ``_majority``,
// ``_decorrelate``, ``_bleed`` and the step itself; the aiding records' numbers (innovation against
// the last gate's reference, its variance, test ratio); reasons and event messages come back as codes
// and numbers, worded by the Python face (service/arbitration_core.py) as the reference words them.
//
// A pure step: ``step(state, readings, time_s, params, rate) -> (state, output)`` on plain structs.
// Every scalar expression is the reference's, in its order (no FMA contraction: CMakeLists.txt);
// Python's ``x ** 2`` on floats is C pow(x, 2.0) (std::pow, as core/ahrs_math.hpp keeps it) and
// Python's float ``%`` is fmod with the result moved to the divisor's sign (py_mod): the reference's
// ``_wrap_pi`` has no clamp at 2pi, so core/ahrs_math.hpp's wrap_pi (which has) is not used.
// Readings are identified by their names (the Python face hands readings with repeated names to the
// reference), groups by bits of one call's distinct group names.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <string>
#include <utility>
#include <vector>

namespace azimuthd {
namespace arbitration {

constexpr double PI = 3.141592653589793;  // math.pi
constexpr double TWO_PI = 2.0 * PI;       // heading_arbitration.TWO_PI

// Python's float ``x % w`` (Objects/floatobject.c float_rem): fmod, moved to the divisor's sign
inline double py_mod(double x, double w) {
    double m = std::fmod(x, w);
    if (m != 0.0) {
        if ((w < 0.0) != (m < 0.0)) m += w;
    } else {
        m = std::copysign(0.0, w);
    }
    return m;
}
// heading_arbitration._wrap_pi, _wrap_2pi
inline double wrap_pi(double a) { return py_mod(a + PI, TWO_PI) - PI; }
inline double wrap_2pi(double a) {
    a = py_mod(a, TWO_PI);
    return a >= TWO_PI ? 0.0 : a;
}
inline double sq(double x) { return std::pow(x, 2.0); }  // Python's x ** 2

// heading_arbitration.ArbitrationParams
struct Params {
    double gate_chi2, max_age_s, max_sigma_rad, blend_rate_rad_s, rate_sigma_rad_s, rate_max_dt_s,
        max_turn_rate_rad_s, reinit_after_s;
    std::vector<std::string> priority;  // an entry that is no str: a text no name is ("\xff")
};

// heading_arbitration.ArbitrationState (has_*: the reference's Optional fields)
struct State {
    bool has_time = false;
    double time_s = 0.0;
    bool has_fused = false;
    double fused_rad = 0.0;
    double fused_var_rad2 = INFINITY;
    double offset_rad = 0.0;
    std::vector<std::string> sources;
    bool has_gated_since = false;
    double gated_since_s = 0.0;
    std::vector<std::pair<std::string, double>> last_fused_s;  // as the reference holds it (sorted)
};

// the state after a step that holds a fused (or coasted) heading
inline State held_state(double time_s, double fused_rad, double var_rad2, double offset_rad,
                        const std::vector<std::string>& sources) {
    State s;
    s.has_time = true;
    s.time_s = time_s;
    s.has_fused = true;
    s.fused_rad = fused_rad;
    s.fused_var_rad2 = var_rad2;
    s.offset_rad = offset_rad;
    s.sources = sources;
    return s;
}

// heading_arbitration.SourceReading, the fields the rule reads
struct Reading {
    std::string name;
    double heading_rad, sigma_rad, time_s;
    bool valid, consistent;
    std::uint64_t groups;  // one bit per distinct group name of the call
};

// why a reading is not fused (the Python face words it as the reference does)
enum Why : int {
    NONE = 0,            // fused, or a candidate with no reason
    NOT_VALID = 1,       // "not valid[: why_not]"                 (code: why_code or 'not_valid')
    INCONSISTENT = 2,    // "inconsistent[: why_not]"              (code: why_code or 'inconsistent')
    NON_FINITE = 3,      // "non-finite"
    SIGMA_RANGE = 4,     // "sigma %.1f deg out of range"
    STALE = 5,           // "stale (%.2f s)"
    GATED_OUT = 6,       // "gated out (NIS %.1f)"
    CORRELATED = 7,      // "correlated with a better source (group ...)"
};

struct Per {
    bool candidate = false, used = false;
    int why = NONE;
    double nis = NAN;
    bool gated = false;  // the gate wrote innov / innov_var
    double innov = NAN, innov_var = NAN;
};

enum EventKind : int { LOST = 0, MAJORITY = 1, RESET_STALE = 2, ACQUIRED = 3, SOURCE_CHANGE = 4, RESET = 5 };

struct Event {
    int kind;
    std::vector<std::string> to;  // from: the state's sources before the step (the caller has them)
    double jump_rad;
    double dt_s;  // RESET_STALE: the interval without output
};

enum OutKind : int { FUSED = 0, COAST = 1, NO_SOURCE = 2 };

struct Output {
    int kind = NO_SOURCE;
    double heading_rad = NAN;  // NO_SOURCE: None
    double sigma_rad = INFINITY;
    std::vector<std::string> names;  // FUSED: the fused sources
    double offset_rad = 0.0;
    std::vector<Event> events;
    std::vector<Per> per;                  // per reading, in the readings' order
    double ref_rad = NAN, ref_var_rad2 = NAN;  // the last gate's reference (the records' innovations)
};

// --- the reference's helpers ------------------------------------------------------------------------

inline int priority_of(const std::string& name, const Params& p) {
    for (std::size_t i = 0; i < p.priority.size(); ++i)
        if (p.priority[i] == name) return static_cast<int>(i);
    return static_cast<int>(p.priority.size());
}

// _rank(a) < _rank(b): (sigma, priority, name) as Python compares tuples
inline bool rank_less(const Reading& a, const Reading& b, const Params& p) {
    if (a.sigma_rad != b.sigma_rad) return a.sigma_rad < b.sigma_rad;
    const int pa = priority_of(a.name, p), pb = priority_of(b.name, p);
    if (pa != pb) return pa < pb;
    return a.name < b.name;
}

// min(idx, key=_rank): the first of the smallest
inline int best_of(const std::vector<Reading>& rs, const std::vector<int>& idx, const Params& p) {
    int best = idx[0];
    for (std::size_t k = 1; k < idx.size(); ++k)
        if (rank_less(rs[idx[k]], rs[best], p)) best = idx[k];
    return best;
}

// _fuse: (fused heading, its variance) about ``ref``; false: no reading (the reference divides by 0)
inline bool fuse(const std::vector<Reading>& rs, const std::vector<int>& idx, double ref, double& h, double& var) {
    double sw = 0.0, s = 0.0;
    for (int i : idx) {
        const double w = 1.0 / (rs[i].sigma_rad * rs[i].sigma_rad);
        sw += w;
        s += w * wrap_pi(rs[i].heading_rad - ref);
    }
    if (idx.empty()) return false;
    h = wrap_2pi(ref + s / sw);
    var = 1.0 / sw;
    return true;
}

// _evidence: connected components of 'shares a group'
inline int evidence(const std::vector<Reading>& rs, const std::vector<int>& idx) {
    const std::size_t n = idx.size();
    std::vector<char> seen(n, 0);
    std::vector<std::size_t> stack;
    int count = 0;
    for (std::size_t i = 0; i < n; ++i) {
        if (seen[i]) continue;
        ++count;
        seen[i] = 1;
        stack.assign(1, i);
        while (!stack.empty()) {
            const std::size_t j = stack.back();
            stack.pop_back();
            for (std::size_t k = 0; k < n; ++k)
                if (!seen[k] && (rs[idx[j]].groups & rs[idx[k]].groups)) {
                    seen[k] = 1;
                    stack.push_back(k);
                }
        }
    }
    return count;
}

// _majority: the largest pairwise-consistent subset of ``cands`` by (evidence, size), brute force
// over the subsets of the first 8
inline std::vector<int> majority(const std::vector<Reading>& rs, const std::vector<int>& cands, const Params& p) {
    const std::size_t n = cands.size();
    std::vector<char> ok(n * n, 1);
    for (std::size_t i = 0; i < n; ++i)
        for (std::size_t j = 0; j < n; ++j)
            if (i != j) {
                const Reading& a = rs[cands[i]];
                const Reading& b = rs[cands[j]];
                ok[i * n + j] = sq(wrap_pi(a.heading_rad - b.heading_rad)) / (sq(a.sigma_rad) + sq(b.sigma_rad)) <=
                                p.gate_chi2;
            }
    std::vector<int> best, sub;
    std::vector<std::size_t> at;
    int best_ev = 0;
    std::size_t best_len = 0;
    const std::size_t m = std::min<std::size_t>(n, 8);
    for (unsigned mask = 1; mask < (1u << m); ++mask) {
        at.clear();
        for (std::size_t i = 0; i < n; ++i)
            if (mask >> i & 1u) at.push_back(i);
        bool all = true;
        for (std::size_t a = 0; a < at.size() && all; ++a)
            for (std::size_t b = 0; b < at.size(); ++b)
                if (!ok[at[a] * n + at[b]]) {
                    all = false;
                    break;
                }
        if (!all) continue;
        sub.clear();
        for (std::size_t i : at) sub.push_back(cands[i]);
        const int ev = evidence(rs, sub);
        if (ev > best_ev || (ev == best_ev && sub.size() > best_len)) {
            best = sub;
            best_ev = ev;
            best_len = sub.size();
        }
    }
    return best;
}

inline bool by_name(const std::vector<Reading>& rs, int a, int b) { return rs[a].name < rs[b].name; }

// _decorrelate: in rank order, a reading kept only if it shares no group with one kept; by name
inline std::vector<int> decorrelate(const std::vector<Reading>& rs, std::vector<int> idx, const Params& p) {
    std::stable_sort(idx.begin(), idx.end(), [&](int a, int b) { return rank_less(rs[a], rs[b], p); });
    std::vector<int> kept;
    std::uint64_t taken = 0;
    for (int i : idx) {
        if (rs[i].groups & taken) continue;
        kept.push_back(i);
        taken |= rs[i].groups;
    }
    std::stable_sort(kept.begin(), kept.end(), [&](int a, int b) { return by_name(rs, a, b); });
    return kept;
}

// _bleed
inline double bleed(double offset, double dt, const Params& p) {
    const double step = p.blend_rate_rad_s * dt;
    if (std::abs(offset) <= step) return 0.0;
    return offset - std::copysign(step, offset);
}

inline bool contains(const std::vector<int>& v, int x) { return std::find(v.begin(), v.end(), x) != v.end(); }

// The reference's gate(ref_h, ref_v, anchor): the candidates against a reference
inline std::vector<int> gate(const std::vector<Reading>& rs, const std::vector<int>& cands, std::vector<Per>& per,
                             double ref_h, double ref_v, int anchor, const Params& p, Output& out) {
    out.ref_rad = ref_h;
    out.ref_var_rad2 = ref_v;
    std::vector<int> ok;
    for (int i : cands) {
        const Reading& r = rs[i];
        const double innov = i == anchor ? 0.0 : wrap_pi(r.heading_rad - ref_h);
        const double nis = sq(innov) / (sq(r.sigma_rad) + ref_v);
        Per& v = per[i];
        v.nis = nis;
        v.gated = true;
        v.innov = innov;
        v.innov_var = sq(r.sigma_rad) + ref_v;
        if (nis <= p.gate_chi2)
            ok.push_back(i);
        else
            v.why = GATED_OUT;
    }
    return ok;
}

inline std::vector<std::string> names_of(const std::vector<Reading>& rs, const std::vector<int>& idx) {
    std::vector<std::string> out;
    out.reserve(idx.size());
    for (int i : idx) out.push_back(rs[i].name);
    return out;
}

inline bool has_name(const std::vector<std::string>& v, const std::string& x) {
    return std::find(v.begin(), v.end(), x) != v.end();
}

// The records' innovations: a candidate's from its gate; a reading that is no candidate but has a
// finite heading and sigma against the same reference (NaN without one)
inline void record_innovations(const std::vector<Reading>& rs, Output& out) {
    for (std::size_t i = 0; i < rs.size(); ++i) {
        Per& v = out.per[i];
        if (!v.candidate && !v.gated && std::isfinite(out.ref_rad) && std::isfinite(rs[i].heading_rad) &&
            std::isfinite(rs[i].sigma_rad)) {
            v.innov = wrap_pi(rs[i].heading_rad - out.ref_rad);
            v.innov_var = sq(rs[i].sigma_rad) + out.ref_var_rad2;
        }
    }
}

// --- the step ---------------------------------------------------------------------------------------

// heading_arbitration.arbitrate (time_s checked finite by the caller). False: the reference divides
// by zero here (_fuse of no reading: a state with a fusion but no sources, only ever made by hand, or a
// sigma whose square underflows): nothing is given back, the caller runs the reference.
inline bool step(const State& st, const std::vector<Reading>& rs, double time_s, const Params& p, bool has_rate,
                 double rate, State& next, Output& out) {
    const double dt = st.has_time ? std::max(0.0, time_s - st.time_s) : 0.0;
    out = Output{};
    out.per.assign(rs.size(), Per{});
    std::vector<int> cands;
    for (std::size_t i = 0; i < rs.size(); ++i) {
        const Reading& r = rs[i];
        int why = NONE;
        if (!r.valid)
            why = NOT_VALID;
        else if (!r.consistent)
            why = INCONSISTENT;
        else if (!(std::isfinite(r.heading_rad) && std::isfinite(r.sigma_rad) && std::isfinite(r.time_s)))
            why = NON_FINITE;
        else if (!(0.0 < r.sigma_rad && r.sigma_rad <= p.max_sigma_rad))
            why = SIGMA_RANGE;
        else if (time_s - r.time_s > p.max_age_s)
            why = STALE;
        out.per[i].why = why;
        out.per[i].candidate = why == NONE;
        if (why == NONE) cands.push_back(static_cast<int>(i));
    }

    if (cands.empty()) {
        if (!st.sources.empty() || st.has_fused) out.events.push_back({LOST, {}, 0.0, 0.0});
        next = State{};
        next.has_time = true;
        next.time_s = time_s;
        next.last_fused_s = st.last_fused_s;
        out.kind = NO_SOURCE;
        return true;
    }

    // --- reference ---
    const bool stale = st.has_fused && dt > p.max_age_s;
    const bool anchored = !st.has_fused || stale;
    int best = -1;
    double ref, ref_var;
    if (anchored) {
        best = best_of(rs, cands, p);
        ref = rs[best].heading_rad;
        ref_var = sq(rs[best].sigma_rad);
    } else if (has_rate && std::isfinite(rate)) {
        ref = wrap_2pi(st.fused_rad + rate * dt);
        ref_var = st.fused_var_rad2 + sq(p.rate_sigma_rad_s * dt) +
                  sq(p.max_turn_rate_rad_s * std::max(0.0, dt - p.rate_max_dt_s));
    } else {
        ref = st.fused_rad;
        ref_var = st.fused_var_rad2 + sq(p.max_turn_rate_rad_s * dt);
    }

    std::vector<int> passing = gate(rs, cands, out.per, ref, ref_var, anchored ? best : -1, p, out);
    double gated_since = 0.0;  // the fused path always ends with gated_since_s None
    int kind = SOURCE_CHANGE;
    const std::vector<int> maj = majority(rs, cands, p);
    bool disjoint = true;
    for (int i : maj)
        if (contains(passing, i)) disjoint = false;
    if (!anchored && maj.size() >= 2 && disjoint && evidence(rs, maj) > evidence(rs, passing)) {
        // the published heading disagrees with a consistent majority it is no part of: re-anchor
        best = best_of(rs, maj, p);
        for (int i : cands) out.per[i].why = NONE;
        passing = gate(rs, cands, out.per, rs[best].heading_rad, sq(rs[best].sigma_rad), best, p, out);
        kind = RESET;
        std::vector<std::string> to = names_of(rs, maj);
        std::sort(to.begin(), to.end());
        out.events.push_back({MAJORITY, to, 0.0, 0.0});
    } else if (passing.empty()) {
        gated_since = st.has_gated_since ? st.gated_since_s : time_s;
        bool discredited = !st.sources.empty();
        for (const std::string& s : st.sources) {
            bool inconsistent = false;
            for (const Reading& r : rs)
                if (r.name == s && r.valid && !r.consistent) inconsistent = true;
            if (!inconsistent) discredited = false;
        }
        if (time_s - gated_since < p.reinit_after_s && !discredited) {
            // coast on the propagated reference
            next = held_state(time_s, ref, ref_var, bleed(st.offset_rad, dt, p), st.sources);
            next.has_gated_since = true;
            next.gated_since_s = gated_since;
            next.last_fused_s = st.last_fused_s;
            out.kind = COAST;
            out.heading_rad = wrap_2pi(ref + next.offset_rad);
            out.sigma_rad = std::sqrt(ref_var + sq(next.offset_rad));
            out.offset_rad = next.offset_rad;
            record_innovations(rs, out);
            return true;
        }
        // re-anchor on the best candidate
        best = best_of(rs, cands, p);
        for (int i : cands) out.per[i].why = NONE;
        passing = gate(rs, cands, out.per, rs[best].heading_rad, sq(rs[best].sigma_rad), best, p, out);
        kind = RESET;
    }

    const std::vector<int> used = decorrelate(rs, passing, p);
    double fused = 0.0, var = 0.0;
    // empty only when even the anchor failed its own gate (a sigma whose square underflows: NIS 0/0)
    if (!fuse(rs, used, ref, fused, var)) return false;
    const std::vector<std::string> names = names_of(rs, used);
    for (int i : passing) {
        if (contains(used, i))
            out.per[i].used = true;
        else
            out.per[i].why = CORRELATED;
    }

    double offset = bleed(st.offset_rad, dt, p);
    if (stale) {
        const double jump = wrap_pi(fused - st.fused_rad);
        offset = 0.0;
        out.events.push_back({RESET_STALE, names, jump, dt});
    } else if (anchored) {
        out.events.push_back({ACQUIRED, names, 0.0, 0.0});
    } else if (names != st.sources || kind == RESET) {
        // the old set evaluated now: its readings if every one of them is still finite and fresh,
        // else the reference (the old fusion propagated)
        std::vector<int> old;
        for (std::size_t i = 0; i < rs.size(); ++i) {
            const Reading& r = rs[i];
            if (has_name(st.sources, r.name) && std::isfinite(r.heading_rad) && std::isfinite(r.sigma_rad) &&
                r.sigma_rad > 0 && time_s - r.time_s <= p.max_age_s)
                old.push_back(static_cast<int>(i));
        }
        const bool whole = old.size() == st.sources.size();
        double old_now = ref;
        if (whole && kind != RESET) {
            double v_unused = 0.0;
            if (!fuse(rs, decorrelate(rs, old, p), ref, old_now, v_unused)) return false;
        }
        const double jump = wrap_pi(fused - old_now);
        offset = wrap_pi(offset - jump);
        out.events.push_back({kind, names, jump, 0.0});
    }
    std::map<std::string, double> last;
    for (const auto& kv : st.last_fused_s) last[kv.first] = kv.second;
    for (const std::string& n : names) last[n] = time_s;
    next = held_state(time_s, fused, var, offset, names);
    next.last_fused_s.assign(last.begin(), last.end());
    out.kind = FUSED;
    out.heading_rad = wrap_2pi(fused + offset);
    out.sigma_rad = std::sqrt(var + offset * offset);
    out.names = names;
    out.offset_rad = offset;
    record_innovations(rs, out);
    return true;
}

}  // namespace arbitration
}  // namespace azimuthd
