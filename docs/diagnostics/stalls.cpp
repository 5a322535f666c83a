// stalls.cpp - where MA-DBP's robots stand still (docs/experiments.md, "Tracking lookahead").
// A robot away from its goal "stalls" at a step when slower than 0.1 units/s; each stall is put
// down to the plan (its waypoint 8 steps on is within 0.1 of the robot), else to the safety
// filter (it changed the tracker's action by more than 0.3), else to neither.
//   g++ -std=c++17 -O2 -fopenmp -I. -isystem /usr/include/eigen3 docs/diagnostics/stalls.cpp -o build/stalls
//   build/stalls MAP N EPISODES [SCENARIO [LOOKAHEAD]]   (seeds 1000..; e.g. build/stalls empty 4 40 corridor 0)
#include <cstdio>
#include <cstdlib>

#include "madbp.hpp"
using namespace madbp;

int main(int argc, char** argv) {
    if (argc < 4) { std::fprintf(stderr, "usage: stalls MAP N EPISODES [SCENARIO [LOOKAHEAD]]\n"); return 2; }
    const std::string map = argv[1], scenario = argc > 4 ? argv[4] : "";
    const int n = std::atoi(argv[2]), episodes = std::atoi(argv[3]);
    FollowerConfig nominal;  // the follower without its filter: the tracker's actions
    nominal.safety_filter = false;
    if (argc > 5) nominal.lookahead = std::atof(argv[5]);
    set_num_threads(1);
    const MadbpModel base = load_model("models/madbp-default.safetensors");
    long travelling = 0, stalled = 0, by_plan = 0, by_filter = 0, near = 0;
    int successes = 0;
    for (int e = 0; e < episodes; ++e) {
        const uint64_t seed = 1000 + e;
        World w = scenario.empty() ? make_random_world(map, n, seed) : make_interaction_world(scenario, map, n, seed);
        DiffusionPlanner planner(base.clone(), seed);
        PlanFollower f([&](const World& ww) { return planner.plan(ww); }, nominal);
        PlanFollower weights([](const World& ww) { return LinePlanner{}(ww); });  // only its filter_weights
        while (!w.done()) {
            const std::vector<Vec2> u0 = f.act(w);
            const std::vector<Vec2> u = safety_filter(w, u0, follower_filter(), weights.filter_weights(w));
            for (int i = 0; i < w.size(); ++i) {
                const Agent& a = w.agents()[i];
                if (w.at_goal(a)) continue;
                travelling++;
                if (norm(a.vel) >= 0.1) continue;
                stalled++;
                const Plan& p = f.plan();
                const auto& wp = p.waypoints[std::find(p.ids.begin(), p.ids.end(), a.id) - p.ids.begin()];
                if (norm(wp[std::min((int)wp.size() - 1, 7)] - a.pos) < 0.1) by_plan++;
                else if (norm(u[i] - u0[i]) > 0.3) by_filter++;
                double closest = 1e9;
                for (int j = 0; j < w.size(); ++j) if (j != i) closest = std::min(closest, norm(w.agents()[j].pos - a.pos));
                near += closest < 0.45;
            }
            w.step(u);
        }
        successes += w.metrics().success;
    }
    std::printf("%s %s n=%d: success %d/%d; robot-steps away from the goal %ld, stalled %ld (%.1f%%): plan stands %ld, "
                "filter holds %ld, neither %ld; within 0.45 of another robot %ld\n", map.c_str(), scenario.c_str(), n, successes,
                episodes, travelling, stalled, 100.0 * stalled / std::max(1L, travelling), by_plan, by_filter, stalled - by_plan - by_filter, near);
}
