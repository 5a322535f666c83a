// methods_mappo.hpp - MAPPO in the `madbp` tool: `eval/render --method mappo` and the
// `madbp mappo` training subcommand (SPEC 3.3, 10). Included after madbp.cpp's Method types.
#pragma once
#include <chrono>
#include <cmath>
#include <memory>
#include <sys/stat.h>

#include "madbp_train.hpp"

namespace madbp_cli {

// Where `madbp mappo` writes, and `eval --method mappo` looks, by default.
inline std::string default_mappo_path(const std::string& map, int agents) {
    return "models/mappo/" + map + "-" + std::to_string(agents) + ".safetensors";
}

// The policy for one eval cell: --model FILE, or the shipped policy of the cell's map and n.
// MAPPO is trained per team size, so a policy of another n is refused before any episode.
inline MethodSpec mappo_method(Args& a, const MethodSetup& s) {
    const std::string path = a.str("--model", "");
    if (path.empty() && s.map == "scene") throw std::invalid_argument("--model: needed with --scene (MAPPO policies are per map and n)");
    const std::string file = path.empty() ? default_mappo_path(s.map, s.agents) : path;
    auto shared = std::make_shared<madbp::MappoNet>(madbp::load_mappo(file));
    if (shared->config.agents != s.agents)
        throw std::invalid_argument("--model: " + file + " was trained for " + std::to_string(shared->config.agents) +
                                    " agents, the cell has " + std::to_string(s.agents) + " (MAPPO is trained per team size)");
    MethodSpec spec;
    spec.n_train = shared->config.agents;
    spec.factory = [shared](const madbp::World&, uint64_t) { return std::unique_ptr<madbp::Policy>(new madbp::MappoPolicy(shared->clone())); };
    return spec;
}

inline void register_mappo_methods(std::vector<Method>& m) {
    m.push_back({"mappo",
                 "MAPPO policy (SPEC 3.3), mean action, no safety filter (raw, as in the paper);\n"
                 "                    --model FILE (default models/mappo/<map>-<n>.safetensors)",
                 mappo_method});
}

// Per-step decision time (paper Fig. 3b), all methods measured in one run on one thread:
// microseconds per act() while the policy drives empty-map worlds (a new random world every 100
// steps). MAPPO: the actor on every agent (untrained weights of width `hidden`: the time depends
// only on the architecture). CLF-QP: its closed-form QP per agent. MA-DBP: the whole executor
// (a window plan every `replan` steps, tracking and the safety filter on every step), so its plan
// time is amortised over the replan interval; skipped (NaN) when `madbp_model` is empty.
struct DecisionTime {
    long n = 0;
    double mappo_us = NAN, clfqp_us = NAN, madbp_us = NAN;  // per step, whole team
    double madbp_plan_ms = NAN;                            // per window plan
};
inline double time_policy_us(madbp::Policy& policy, int n, int steps, uint64_t seed) {
    madbp::WorldConfig wc;
    wc.max_steps = 1 << 30;
    madbp::World w = madbp::make_random_world("empty", n, seed, 1.2, wc);
    for (int s = 0; s < 10; ++s) w.step(policy.act(w));  // warm-up
    const auto t0 = std::chrono::steady_clock::now();
    for (int s = 0; s < steps; ++s) {
        const auto u = policy.act(w);
        if (s % 100 == 99) w = madbp::make_random_world("empty", n, seed + s, 1.2, wc);
        else w.step(u);
    }
    return std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now() - t0).count() / steps;
}
inline std::vector<DecisionTime> measure_decision_times(const std::vector<long>& counts, int steps, const std::string& madbp_model,
                                                        int replan, uint64_t seed, int mappo_hidden = 64) {
    madbp::set_num_threads(1);
    std::shared_ptr<madbp::MadbpModel> model;
    if (!madbp_model.empty()) model = std::make_shared<madbp::MadbpModel>(madbp::load_model(madbp_model));
    std::vector<DecisionTime> out;
    for (long n : counts) {
        DecisionTime d;
        d.n = n;
        madbp::MappoNetConfig nc;
        nc.agents = (int)n;
        nc.hidden = mappo_hidden;
        madbp::MappoPolicy mappo{madbp::MappoNet(nc, seed)};
        d.mappo_us = time_policy_us(mappo, (int)n, steps, seed);
        madbp::ClfQp clfqp;
        d.clfqp_us = time_policy_us(clfqp, (int)n, steps, seed);
        if (model) {
            madbp::FollowerConfig fc;
            fc.replan_every = replan;
            auto planner = std::make_shared<madbp::DiffusionPlanner>(model->clone(), seed);
            madbp::PlanFollower follower([planner](const madbp::World& w) { return planner->plan(w); }, fc);
            d.madbp_us = time_policy_us(follower, (int)n, steps, seed);
            d.madbp_plan_ms = follower.decision_ms();
        }
        out.push_back(d);
    }
    return out;
}

inline int bench_decision(const std::vector<long>& counts, int hidden, int steps, uint64_t seed, const std::string& madbp_model,
                          int replan, bool json) {
    if (!json) std::printf("%4s %12s %12s %12s %14s\n", "n", "mappo_us", "clfqp_us", "madbp_us", "madbp_plan_ms");
    for (const DecisionTime& d : measure_decision_times(counts, steps, madbp_model, replan, seed, hidden)) {
        if (json)
            std::printf("%s\n", Json().add("bench", "decision").add("n", d.n).add("mappo_us", d.mappo_us).add("clfqp_us", d.clfqp_us)
                                    .add("madbp_us", d.madbp_us).add("madbp_plan_ms", d.madbp_plan_ms).add("replan", replan).line().c_str());
        else
            std::printf("%4ld %12.2f %12.2f %12.2f %14.3f\n", d.n, d.mappo_us, d.clfqp_us, d.madbp_us, d.madbp_plan_ms);
        std::fflush(stdout);
    }
    return 0;
}

// ---------------------------------------------------------------------------------------------
inline int cmd_mappo(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp mappo - train a MAPPO policy for one map and team size (SPEC 3.3)\n"
            "  --map NAME          empty, obstacles, barrier (default empty)\n"
            "  --agents N          team size the policy is built for (default 2)\n"
            "  --out FILE          policy file (default models/mappo/<map>-<n>.safetensors);\n"
            "                      resumable state in FILE.train, curve in FILE.csv and FILE.svg\n"
            "  --resume            continue from FILE.train\n"
            "  --iterations I      rollout + update rounds (default 300); each plays 100 steps on\n"
            "                      every world\n"
            "  --time-budget S     stop after S seconds of training (default: none)\n"
            "  --worlds W          worlds stepping together (default 32)\n"
            "  --hidden H          width of the 2 hidden Tanh layers of actor and critic (default 64)\n"
            "  --lidar-rays R --lidar-range X  the observation's lidar (default 12 rays of 0.35)\n"
            "  --route-goal D      observe the point D ahead on the route around the map (as\n"
            "                      MA-DBP's model), not the goal (default 0: the goal)\n"
            "  --epochs E --minibatches M   PPO passes per rollout and minibatches per pass (4, 4)\n"
            "  --lr X --gamma G --lambda L --clip C --ent-coef E --vf-coef V --max-grad-norm N\n"
            "                      (defaults 3e-4, 0.99, 0.9, 0.2, 1e-3, 0.5, 1.0)\n"
            "  --reward-shaping X --reward-success X --reward-collision X --reward-time X\n"
            "  --reward-at-goal X  reward terms per agent and step (MappoRewards; defaults 1, 5,\n"
            "                      -0.1, -0.01, 0)\n"
            "  --reward-route      shape on the distance along the shortest way around the map,\n"
            "                      not the straight one (for maps with walls, e.g. the barrier)\n"
            "  --checkpoint-every K  iterations between checkpoints (default 10)\n"
            "  --threads T         threads (default 2); the result does not depend on it\n"
            "  --seed S            (default 0)\n"
            "  --json              print the summary as JSON\n"
            "  --bench-decision LIST  instead of training: us per step of MAPPO (the actor, width\n"
            "                      --hidden), CLF-QP and MA-DBP (plan amortised over --replan M\n"
            "                      steps, default 4; --model FILE, default the shipped model,\n"
            "                      'none' to skip) for each team size, e.g. 1,2,4,8,16 (Fig. 3b)\n"
            "  --bench-steps K     steps timed per size (default 5000)\n");
        return 0;
    }
    madbp::MappoConfig c;
    c.map = a.str("--map", "empty");
    c.agents = (int)a.integer("--agents", 2, 1, 64);
    c.out = a.str("--out", default_mappo_path(c.map, c.agents));
    c.resume = a.flag("--resume");
    c.iterations = a.integer("--iterations", c.iterations, 1, 100000000);
    const double budget = a.real("--time-budget", 0, 1e-3, 1e9);  // 0 (not given): none; --time-budget 0 is an error
    c.worlds = (int)a.integer("--worlds", c.worlds, 1, 100000);
    c.hidden = (int)a.integer("--hidden", c.hidden, 1, 4096);
    c.obs.rays = (int)a.integer("--lidar-rays", c.obs.rays, 1, madbp::kMaxLidarRays);
    c.obs.range = a.real("--lidar-range", c.obs.range, 1e-3, 10);
    c.obs.route_goal = a.real("--route-goal", c.obs.route_goal, 0, 10);
    c.epochs = (int)a.integer("--epochs", c.epochs, 1, 1000);
    c.minibatches = (int)a.integer("--minibatches", c.minibatches, 1, 100000);
    c.lr = (float)a.real("--lr", c.lr, 1e-8, 1);
    c.gamma = (float)a.real("--gamma", c.gamma, 0, 1);
    c.lambda = (float)a.real("--lambda", c.lambda, 0, 1);
    c.ppo.ratio_clip = (float)a.real("--clip", c.ppo.ratio_clip, 1e-4, 10);
    c.ppo.ent_coef = (float)a.real("--ent-coef", c.ppo.ent_coef, 0, 10);
    c.ppo.vf_coef = (float)a.real("--vf-coef", c.ppo.vf_coef, 0, 100);
    c.max_grad_norm = (float)a.real("--max-grad-norm", c.max_grad_norm, 1e-6, 1e6);
    c.rewards.shaping = (float)a.real("--reward-shaping", c.rewards.shaping, 0, 1000);
    c.rewards.success_bonus = (float)a.real("--reward-success", c.rewards.success_bonus, 0, 1000);
    c.rewards.collision = (float)a.real("--reward-collision", c.rewards.collision, -1000, 0);
    c.rewards.time = (float)a.real("--reward-time", c.rewards.time, -1000, 0);
    c.rewards.at_goal = (float)a.real("--reward-at-goal", c.rewards.at_goal, 0, 1000);
    c.rewards.route = a.flag("--reward-route");
    c.checkpoint_every = a.integer("--checkpoint-every", c.checkpoint_every, 1);
    c.threads = (int)a.integer("--threads", 2, 1, 256);
    c.seed = (uint64_t)a.integer("--seed", 0, 0);
    const bool json = a.flag("--json");
    const std::string bench = a.str("--bench-decision", "");
    const int bench_steps = (int)a.integer("--bench-steps", 5000, 1, 100000000);
    if (!bench.empty()) {
        const std::vector<long> counts = a.integers("--bench-decision", bench, 1, 64);
        std::string model = model_option(a);
        const int replan = (int)a.integer("--replan", madbp::FollowerConfig{}.replan_every, 1, 1000);
        a.finish();
        return bench_decision(counts, c.hidden, bench_steps, c.seed, model == "none" ? "" : model, replan, json);
    }
    a.finish();
    c.validate();
    if (budget > 0) {
        // The budget counts this process's training time; train_mappo checkpoints where it stops.
        const auto t0 = std::chrono::steady_clock::now();
        c.keep_going = [t0, budget](long) { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < budget; };
    }
    const size_t slash = c.out.find_last_of('/');
    if (slash != std::string::npos && slash > 0) ::mkdir(c.out.substr(0, slash).c_str(), 0755);  // e.g. models/mappo; exists: fine
    const auto locks = claim_outputs(a, {{"--out", c.out}}, {".train", ".csv", ".svg"});
    c.progress = progress_line("mappo " + c.map + " n=" + std::to_string(c.agents));
    madbp::MappoReport r = madbp::train_mappo(c);
    if (!c.out.empty())
        write_curve_svg(c.out + ".svg", r.curve, {"success", "episode_return"}, "MAPPO " + c.map + " n=" + std::to_string(c.agents), false);
    struct { double success = 0, episode_return = 0; } last;
    if (!r.curve.rows.empty())
        last = {r.curve.rows.back()[r.curve.column("success")], r.curve.rows.back()[r.curve.column("episode_return")]};
    if (json)
        std::printf("%s\n", Json().add("out", c.out).add("map", c.map).add("agents", c.agents).add("iterations", r.iterations)
                                .add("env_steps", r.env_steps).add("seconds", r.seconds).add("train_success", last.success)
                                .add("train_return", last.episode_return).line().c_str());
    else
        std::printf("mappo %s n=%d: %ld iterations (%ld world steps) in %.1f s; last rollout success %.2f, return %.3f -> %s\n",
                    c.map.c_str(), c.agents, r.iterations, r.env_steps, r.seconds, last.success, last.episode_return, c.out.c_str());
    return 0;
}

}  // namespace madbp_cli
