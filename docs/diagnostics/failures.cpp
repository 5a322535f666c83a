// failures.cpp - how MA-DBP's failed episodes end (docs/experiments.md, "Keep right"): for each
// episode that times out, every robot not at its goal, how far it is from its goal and from the
// nearest other robot. The shipped model and planner defaults, seeds 1000.. as `madbp eval`.
//   g++ -std=c++17 -O2 -I. -isystem /usr/include/eigen3 docs/diagnostics/failures.cpp -o build/failures
//   build/failures MAP SCENARIO|- N EPISODES [LOOKAHEAD]   (e.g. build/failures empty corridor 4 40)
#include <cstdio>
#include <cstdlib>

#include "madbp.hpp"
using namespace madbp;

int main(int argc, char** argv) {
    if (argc < 5) { std::fprintf(stderr, "usage: failures MAP SCENARIO|- N EPISODES [LOOKAHEAD]\n"); return 2; }
    const std::string map = argv[1], scenario = argv[2];
    const int n = std::atoi(argv[3]), episodes = std::atoi(argv[4]);
    set_num_threads(1);
    const MadbpModel base = load_model("models/madbp-default.safetensors");
    int failures = 0;
    for (int e = 0; e < episodes; ++e) {
        const uint64_t seed = 1000 + e;
        World w = scenario == "-" ? make_random_world(map, n, seed) : make_interaction_world(scenario, map, n, seed);
        DiffusionPlanner planner(base.clone(), seed);
        FollowerConfig fc;
        if (argc > 5) fc.lookahead = std::atof(argv[5]);
        PlanFollower follower([&](const World& ww) { return planner.plan(ww); }, fc);
        if (run_episode(w, follower).success) continue;
        failures++;
        std::printf("seed %llu:", (unsigned long long)seed);
        for (const Box& b : w.map().boxes) std::printf(" wall (%.2f, %.2f)-(%.2f, %.2f)", b.lo.x, b.lo.y, b.hi.x, b.hi.y);
        std::printf("\n");
        for (const Agent& a : w.agents()) {
            if (w.at_goal(a)) continue;
            double nearest = 1e9;
            for (const Agent& b : w.agents()) if (b.id != a.id) nearest = std::min(nearest, norm(b.pos - a.pos));
            std::printf("  robot %d: %.2f from its goal, %.2f from the nearest robot\n", a.id, norm(a.goal - a.pos), nearest);
        }
    }
    std::printf("%s %s n = %d: %d of %d episodes failed\n", map.c_str(), scenario.c_str(), n, failures, episodes);
}
