// methods.hpp - the method registry of the `madbp` tool: every method `eval`, `render` and the
// evaluation suite can run, by name. Each method reads its own options from Args and returns a
// per-episode PolicyFactory. Included by madbp.cpp and by the tests.
//
// Adding a method: one entry in methods() below, or a register_*_methods() in its own header.
#pragma once
#include <functional>
#include <memory>

#include "cli_common.hpp"
#include "madbp.hpp"

namespace madbp_cli {

// Options shared by every method, read by eval and render.
// Steps per plan of the straight line's rows: SPEC 8's m, as the paper measures them.
constexpr int kBaselineReplan = 8;
struct MethodSetup {
    std::string map;      // map name, or "scene"
    int agents = 0;       // team size of the cell
    bool filter = true;   // --no-filter turns the safety filter off
    int replan = 0;       // --replan M: steps executed per plan; 0: the method's own (the planner
                          // preset's follower.replan_every, kBaselineReplan for the line)
};
// --model FILE wherever a method or bench plans with MA-DBP; without it the shipped model,
// looked up (madbp::default_model_path) only then, so that --model FILE needs no shipped model.
inline std::string model_option(Args& a) { return a.has("--model") ? a.str("--model", "") : madbp::default_model_path(); }

// What a method gives eval: the per-episode policy and the training team size it reports.
struct MethodSpec {
    madbp::PolicyFactory factory;
    int n_train = -1;     // -1: not a learned method (printed as "-", JSON null)
};
struct Method {
    std::string name, help;
    std::function<MethodSpec(Args&, const MethodSetup&)> make;  // reads its own options
};

}  // namespace madbp_cli

#include "methods_madiff.hpp"
#include "methods_nn.hpp"

namespace madbp_cli {

inline std::vector<Method> methods() {
    std::vector<Method> m;
    m.push_back({"clfqp",
                 "CLF-QP (SPEC 3.1): per agent, ignores others and obstacles;\n"
                 "                    --clf C_EV,C_VV,EPS (default 1,0.2,3), --clf-no-drag (VMAS's LfV)",
                 [](Args& a, const MethodSetup&) {
                     madbp::ClfQpParams p;
                     std::vector<std::string> c = split(a.str("--clf", "1,0.2,3"), "--clf");
                     if (c.size() != 3) throw std::invalid_argument("--clf: expected C_EV,C_VV,EPS, e.g. 1,0.2,3");
                     double* dst[3] = {&p.c_ev, &p.c_vv, &p.eps};
                     for (int k = 0; k < 3; ++k) {
                         size_t pos = 0;
                         try { *dst[k] = std::stod(c[k], &pos); } catch (...) { pos = 0; }
                         if (pos != c[k].size() || !(*dst[k] >= 0) || !std::isfinite(*dst[k]))
                             throw std::invalid_argument("--clf: '" + c[k] + "' is not a number >= 0");
                     }
                     p.drag_in_lfv = !a.flag("--clf-no-drag");
                     return MethodSpec{[p](const madbp::World&, uint64_t) { return std::make_unique<madbp::ClfQp>(p); }};
                 }});
    m.push_back({"line", "straight-line plan + tracker (+ safety filter) (SPEC 3.5); --lookahead L (default 0)",
                 [](Args& a, const MethodSetup& s) {
                     madbp::FollowerConfig fc;
                     fc.safety_filter = s.filter;
                     fc.replan_every = s.replan > 0 ? s.replan : kBaselineReplan;
                     fc.priority_weight = 1;  // the SPEC 3.5 baseline as measured throughout: equal weights,
                     fc.lookahead = a.real("--lookahead", 0, 0, madbp::kMaxLookahead);  // the waypoint planned for this step
                     fc.filter = madbp::SafetyFilterParams{};  // SPEC 3.2's filter rate, 2.5/s,
                     fc.replan_error = 0;                      // and a new line every m steps only
                     fc.unjam = 0;                             // no backing out of jams
                     return MethodSpec{[fc](const madbp::World&, uint64_t) {
                         return std::make_unique<madbp::PlanFollower>(madbp::LinePlanner{}, fc);
                     }};
                 }});
    m.push_back({"expert", "guided expert: wavefront field + conflict resolution + safety filter (SPEC 3.6)",
                 [](Args&, const MethodSetup& s) {
                     madbp::ExpertParams ep;
                     if (!s.filter) throw std::invalid_argument("--no-filter: the guided expert always uses its safety filter");
                     return MethodSpec{[ep](const madbp::World& w, uint64_t) {
                         return std::make_unique<madbp::GuidedExpert>(w.map(), ep, madbp::passage_traffic());
                     }};
                 }});
    register_nn_methods(m);
    register_mappo_methods(m);
    register_madiff_methods(m);
    return m;
}

inline const Method& find_method(const std::vector<Method>& all, const std::string& name) {
    std::string names;
    for (auto& m : all) {
        if (m.name == name) return m;
        names += (names.empty() ? "" : ", ") + m.name;
    }
    throw std::invalid_argument("--method: unknown method '" + madbp::printable(name) + "' (expected one of " + names + ")");
}

inline std::string method_list() {
    std::string s;
    for (auto& m : methods()) s += "    " + m.name + std::string(m.name.size() < 8 ? 8 - m.name.size() : 1, ' ') + m.help + "\n";
    return s;
}

}  // namespace madbp_cli
