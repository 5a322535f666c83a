// tracking_lag.cpp - how far MA-DBP's robots trail their plans (docs/experiments.md, "Tracking
// lookahead"). For every robot not at its goal whose plan is moving, the lag is the plan step
// of the waypoint planned for now minus the plan step of the robot's closest point on the plan's
// polyline; printed as the mean and by steps since the plan was made (k1..k8).
//   g++ -std=c++17 -O2 -fopenmp -I. -isystem /usr/include/eigen3 docs/diagnostics/tracking_lag.cpp -o build/tracking_lag
//   build/tracking_lag MAP N EPISODES [LOOKAHEAD]     (seeds 1000..; e.g. build/tracking_lag barrier 4 30 1.5)
#include <cstdio>
#include <cstdlib>

#include "madbp.hpp"
using namespace madbp;

int main(int argc, char** argv) {
    if (argc < 4) { std::fprintf(stderr, "usage: tracking_lag MAP N EPISODES [LOOKAHEAD]\n"); return 2; }
    const std::string map = argv[1];
    const int n = std::atoi(argv[2]), episodes = std::atoi(argv[3]);
    FollowerConfig fc;
    if (argc > 4) fc.lookahead = std::atof(argv[4]);
    set_num_threads(1);
    const MadbpModel base = load_model("models/madbp-default.safetensors");
    double sum = 0, by_k[16] = {};
    long count = 0, n_k[16] = {};
    for (int e = 0; e < episodes; ++e) {
        World w = make_random_world(map, n, 1000 + e);
        DiffusionPlanner planner(base.clone(), 1000 + e);
        PlanFollower f([&](const World& ww) { return planner.plan(ww); }, fc);
        Plan plan;
        int t0 = 0, plans = 0;
        while (!w.done()) {
            const std::vector<Vec2> u = f.act(w);
            if (f.plans() != plans) plans = f.plans(), plan = f.plan(), t0 = w.t();
            w.step(u);
            const int k = w.t() - t0;  // the plan's point for now: polyline index k (0 = where the plan began)
            for (size_t i = 0; i < plan.ids.size(); ++i) {
                const Agent& a = w.agent(plan.ids[i]);
                if (w.at_goal(a)) continue;
                std::vector<Vec2> P = {2.0 * plan.waypoints[i][0] - plan.waypoints[i][1]};  // about where the plan began
                P.insert(P.end(), plan.waypoints[i].begin(), plan.waypoints[i].end());
                if (k + 1 >= (int)P.size() || norm(P[k + 1] - P[k]) < 0.02) continue;  // only while the plan moves
                double best = 1e9, at = 0;
                for (size_t j = 0; j + 1 < P.size(); ++j) {
                    const Vec2 d = P[j + 1] - P[j];
                    const double len2 = dot(d, d), s = len2 > 0 ? std::clamp(dot(a.pos - P[j], d) / len2, 0.0, 1.0) : 0;
                    const double dist = norm(P[j] + d * s - a.pos);
                    if (dist < best) best = dist, at = j + s;
                }
                sum += k - at, count++;
                by_k[std::min(k, 15)] += k - at, n_k[std::min(k, 15)]++;
            }
        }
    }
    std::printf("%s n=%d lookahead %.2f: mean lag %.2f steps;", map.c_str(), n, fc.lookahead, count ? sum / count : 0.0);
    for (int k = 1; k <= 8; ++k) std::printf(" k%d:%.2f", k, n_k[k] ? by_k[k] / n_k[k] : 0.0);
    std::printf("\n");
}
