// end_probe.cpp - the windows MA-DBP plans for one robot near its goal (docs/experiments.md,
// "Windows that arrive"): robot 0 of `build/madbp eval --method madbp --map empty --scenario gap
// --agents 4 --seed 1005`, where it hovered 0.3 from its goal to the step limit. Its position and
// goal, alone or with the three others parked on their goals, on the gap scene's map or with
// the walls removed; every second waypoint of three plans, without and with the end bend
// (SamplerConfig::end_bend).
//   g++ -std=c++17 -O2 -I. -isystem /usr/include/eigen3 docs/diagnostics/end_probe.cpp -o build/end_probe
//   build/end_probe
#include <cstdio>

#include "madbp.hpp"
using namespace madbp;

int main() {
    set_num_threads(1);
    const World scene = make_interaction_world("gap", "empty", 4, 1005);
    const Vec2 pos{0.590, 0.218}, goal{0.317, 0.086};  // robot 0 at step 72 of that episode
    const Vec2 others[3] = {{0.389, -0.336}, {-0.303, -0.242}, {-0.237, 0.205}};
    const Vec2 other_goals[3] = {{0.324, -0.394}, {-0.227, -0.269}, {-0.235, 0.211}};
    for (float bend : {0.0f, kDefaultEndBend})
        for (bool walls : {true, false})
            for (bool team : {false, true}) {
                WorldMap map = scene.map();
                if (!walls) map.boxes.clear();
                World w(map);
                w.add_agent(pos, goal);
                if (team)
                    for (int i = 0; i < 3; ++i) w.add_agent(others[i], other_goals[i]);
                DiffusionPlanner planner(load_model("models/madbp-default.safetensors"), 1005);
                planner.sampler.end_bend = bend;
                for (int rep = 0; rep < 3; ++rep) {
                    const Plan p = planner.plan(w);
                    std::printf("end bend %.0f, %-8s %-5s plan %d:", bend, walls ? "gap map," : "no walls,", team ? "team" : "alone", rep);
                    for (size_t t = 0; t < p.waypoints[0].size(); t += 2) std::printf(" (%.2f, %.2f)", p.waypoints[0][t].x, p.waypoints[0][t].y);
                    std::printf("\n");
                }
            }
    std::printf("goal (%.2f, %.2f)\n", goal.x, goal.y);
}
