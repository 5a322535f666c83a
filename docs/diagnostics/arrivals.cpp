// arrivals.cpp - where MA-DBP's robots lose time against the expert's (docs/experiments.md,
// "The follower's filter rate"). For the robots that do not start on their goals ("travellers"):
// straight-line distance, path length, the step they settle on their goals, and their slow steps
// (speed < 0.3 away from the goal) split into the first 5 steps, within 0.3 of the goal, and
// within 0.45 of another robot. Tuning seeds 1000.. of an interaction scenario.
//   g++ -std=c++17 -O2 -fopenmp -I. -isystem /usr/include/eigen3 docs/diagnostics/arrivals.cpp -o build/arrivals
//   build/arrivals MAP SCENARIO N EPISODES [FILTER_RATE]   (e.g. build/arrivals barrier parked 4 30 2.5)
#include <cstdio>
#include <cstdlib>

#include "madbp.hpp"
using namespace madbp;

struct Tally {
    double episodes = 0, successes = 0, steps = 0, last_parked = 0;
    double travellers = 0, straight = 0, path = 0, settle = 0, slow = 0, slow_start = 0, slow_goal = 0, slow_robot = 0;
};

static Tally run(const std::string& map, const std::string& scenario, int n, int episodes, bool madbp, double rate) {
    const MadbpModel base = load_model("models/madbp-default.safetensors");
    Tally t;
    for (int e = 0; e < episodes; ++e) {
        const uint64_t seed = 1000 + e;
        World w = make_interaction_world(scenario, map, n, seed);
        std::unique_ptr<Policy> policy;
        if (madbp) {
            auto planner = std::make_shared<DiffusionPlanner>(base.clone(), seed);
            FollowerConfig fc;
            fc.filter.rate = rate;
            policy = std::make_unique<PlanFollower>([planner](const World& ww) { return planner->plan(ww); }, fc);
        } else {
            policy = std::make_unique<GuidedExpert>(w.map());
        }
        std::vector<bool> parked;
        std::vector<Vec2> start;
        for (const Agent& a : w.agents()) { parked.push_back(norm(a.goal - a.pos) < 0.15); start.push_back(a.pos); }
        std::vector<int> settle(n, 0);
        std::vector<double> path(n, 0);
        while (!w.done()) {
            std::vector<Vec2> before;
            for (const Agent& a : w.agents()) before.push_back(a.pos);
            w.step(policy->act(w));
            for (int i = 0; i < n; ++i) {
                const Agent& a = w.agents()[i];
                path[i] += norm(a.pos - before[i]);
                if (w.at_goal(a)) continue;
                settle[i] = w.t();
                if (parked[i] || norm(a.vel) >= 0.3) continue;
                t.slow++;
                if (w.t() <= 5) { t.slow_start++; continue; }
                if (norm(a.goal - a.pos) < 0.3) { t.slow_goal++; continue; }
                for (const Agent& b : w.agents())
                    if (b.id != a.id && norm(b.pos - a.pos) < 0.45) { t.slow_robot++; break; }
            }
        }
        t.episodes++;
        if (w.metrics().success) { t.successes++; t.steps += w.metrics().success_step; }
        int last = 0;
        for (int i = 1; i < n; ++i) if (settle[i] > settle[last]) last = i;
        t.last_parked += parked[last];
        for (int i = 0; i < n; ++i) {
            if (parked[i]) continue;
            t.travellers++;
            t.straight += norm(w.agents()[i].goal - start[i]);
            t.path += path[i];
            t.settle += settle[i];
        }
    }
    return t;
}

int main(int argc, char** argv) {
    if (argc < 5) { std::fprintf(stderr, "usage: arrivals MAP SCENARIO N EPISODES [FILTER_RATE]\n"); return 2; }
    const double rate = argc > 5 ? std::atof(argv[5]) : FollowerConfig{}.filter.rate;
    set_num_threads(1);
    for (bool madbp : {false, true}) {
        const Tally t = run(argv[1], argv[2], std::atoi(argv[3]), std::atoi(argv[4]), madbp, rate);
        const double k = 1 / std::max(1.0, t.travellers);
        std::printf("%-6s success %.2f, steps %.1f, last to settle parked %.2f | per traveller: straight %.2f, path %.2f, "
                    "settles at %.1f, slow steps %.1f (first 5 steps %.1f, near the goal %.1f, near a robot %.1f)\n",
                    madbp ? "madbp" : "expert", t.successes / t.episodes, t.steps / std::max(1.0, t.successes), t.last_parked / t.episodes,
                    t.straight * k, t.path * k, t.settle * k, t.slow * k, t.slow_start * k, t.slow_goal * k, t.slow_robot * k);
    }
}
