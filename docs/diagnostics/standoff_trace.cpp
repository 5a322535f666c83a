// standoff_trace.cpp - one MA-DBP episode of an interaction scene, printed at every replan: each
// robot's position and where its new plan puts it 8 steps later (docs/experiments.md, "Keep
// right"). Shows whether a stalled pair's plans stand still or run through each other.
//   g++ -std=c++17 -O2 -I. -isystem /usr/include/eigen3 docs/diagnostics/standoff_trace.cpp -o build/standoff_trace
//   build/standoff_trace MAP SCENARIO|- N SEED [KEEP_RIGHT [TAKE_TURNS [LOOKAHEAD]]]   (e.g. build/standoff_trace empty corridor 4 1001 0)
// SCENARIO - is a random-spawn episode (as eval without --scenario); LOOKAHEAD sets the follower's.
// A robot told to wait for a one-lane passage (DiffusionPlanner::take_turns) is marked "waits at
// (x, y)", one told to go around a corridor "goes around".
#include <cstdio>
#include <cstdlib>

#include "madbp.hpp"
using namespace madbp;

int main(int argc, char** argv) {
    if (argc < 5) { std::fprintf(stderr, "usage: standoff_trace MAP SCENARIO|- N SEED [KEEP_RIGHT [TAKE_TURNS [LOOKAHEAD]]]\n"); return 2; }
    const std::string map = argv[1], scenario = argv[2];
    const int n = std::atoi(argv[3]);
    const uint64_t seed = std::strtoull(argv[4], nullptr, 10);
    set_num_threads(1);
    World w = scenario == "-" ? make_random_world(map, n, seed) : make_interaction_world(scenario, map, n, seed);
    DiffusionPlanner planner(load_model("models/madbp-default.safetensors"), seed);  // as eval: the episode's seed
    if (argc > 5) planner.sampler.keep_right = (float)std::atof(argv[5]);
    if (argc > 6) planner.take_turns = std::atoi(argv[6]) != 0;
    FollowerConfig fc;
    if (argc > 7) fc.lookahead = std::atof(argv[7]);
    PlanFollower follower([&](const World& ww) { return planner.plan(ww); }, fc);
    for (const Box& b : w.map().boxes) std::printf("wall (%.2f, %.2f) - (%.2f, %.2f)\n", b.lo.x, b.lo.y, b.hi.x, b.hi.y);
    int passage_cells = 0;
    RouteGuide guide;
    for (int p : planner.passages.passage(guide, w.map())) passage_cells += p >= 0;
    std::printf("passage cells: %d\n", passage_cells);
    for (const Agent& a : w.agents()) std::printf("robot %d: (%.2f, %.2f) -> (%.2f, %.2f)\n", a.id, a.pos.x, a.pos.y, a.goal.x, a.goal.y);
    int last_plans = 0;
    while (!w.done()) {
        const std::vector<Vec2> u = follower.act(w);
        if (follower.plans() != last_plans) {  // a new plan: positions now, and 8 steps on in the plan
            last_plans = follower.plans();
            const Plan& p = follower.plan();
            std::printf("t = %3d", w.t());
            for (size_t i = 0; i < p.ids.size(); ++i) {
                const Agent& a = w.agents()[w.index_of(p.ids[i])];
                const Vec2 e = p.waypoints[i][std::min<size_t>(7, p.waypoints[i].size() - 1)];
                std::printf("  %d: (%5.2f, %5.2f) -> (%5.2f, %5.2f)%s", a.id, a.pos.x, a.pos.y, e.x, e.y, w.at_goal(a) ? " at goal" : "");
                if (planner.last_waiting()[i] == PassageControl::kWait)
                    std::printf(" waits at (%.2f, %.2f)", planner.last_wait_points()[i].x, planner.last_wait_points()[i].y);
                if (planner.last_waiting()[i] == PassageControl::kGoAround) std::printf(" goes around");
            }
            std::printf("\n");
        }
        w.step(u);
    }
    std::printf("success %d, steps %d\n", (int)w.metrics().success, w.t());
}
