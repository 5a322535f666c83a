// methods_madiff.hpp - MADiff in the `madbp` tool: `eval/render --method madiff` and the
// `madbp madiff` training subcommand (SPEC 3.4, 10). Included by methods.hpp after the Method
// types.
#pragma once
#include <chrono>
#include <memory>
#include <sys/stat.h>

#include "madbp_train.hpp"

namespace madbp_cli {

// Where `madbp madiff` writes, and `eval --method madiff` looks, by default.
inline std::string default_madiff_path(const std::string& map, int agents) {
    return "models/madiff/" + map + "-" + std::to_string(agents) + ".safetensors";
}

// The policy for one eval cell: --model FILE, or the shipped model of the cell's map and n.
// MADiff is built per team size, so a model of another n is refused before any episode.
inline MethodSpec madiff_method(Args& a, const MethodSetup& s) {
    madbp::set_num_threads(1);  // one thread per decision; eval --threads runs episodes in parallel
    const std::string path = a.str("--model", "");
    const int steps = (int)a.integer("--sample-steps", 0, 1, 100000);  // 0 (not given): the model's own; --sample-steps 0 is an error
    const double w = a.real("--guidance", -1, 0, 100);
    const double target = a.real("--return", -1e9, -10, 10);
    if (path.empty() && s.map == "scene") throw std::invalid_argument("--model: needed with --scene (MADiff models are per map and n)");
    const std::string file = path.empty() ? default_madiff_path(s.map, s.agents) : path;
    auto shared = std::make_shared<madbp::MadiffModel>(madbp::load_madiff(file));
    const madbp::MadiffConfig& c = shared->config;
    if (c.agents != s.agents)
        throw std::invalid_argument("--model: " + file + " was trained for " + std::to_string(c.agents) + " agents, the cell has " +
                                    std::to_string(s.agents) + " (MADiff is built for a fixed team size)");
    if (steps > c.diffusion_steps)
        throw std::invalid_argument("--sample-steps: " + std::to_string(steps) + " exceeds the model's " + std::to_string(c.diffusion_steps) +
                                    " diffusion steps");
    MethodSpec spec;
    spec.n_train = c.agents;
    spec.factory = [shared, steps, w, target](const madbp::World&, uint64_t seed) -> std::unique_ptr<madbp::Policy> {
        auto p = std::make_unique<madbp::MadiffPolicy>(shared->clone(), seed);
        if (steps > 0) p->sample_steps = steps;
        if (w >= 0) p->guidance = (float)w;
        if (target > -1e8) p->return_target = (float)target;
        return p;
    };
    return spec;
}

inline void register_madiff_methods(std::vector<Method>& m) {
    m.push_back({"madiff",
                 "MADiff baseline (SPEC 3.4): diffused observations + inverse dynamics, replans every\n"
                 "                    step, raw actions (no safety filter); --model FILE (default\n"
                 "                    models/madiff/<map>-<n>.safetensors), --sample-steps S (default the\n"
                 "                    model's, 10), --guidance W (default 1.2), --return R (normalised\n"
                 "                    return to condition on; default the model's, the data's 90th percentile)",
                 madiff_method});
}

// ---------------------------------------------------------------------------------------------
inline int cmd_madiff(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp madiff - train a MADiff baseline for one map and team size (SPEC 3.4)\n"
            "  --map NAME          empty, obstacles, barrier (default empty)\n"
            "  --agents N          team size the model is built for (default 2); the dataset's\n"
            "                      episodes on --map with exactly N agents are used\n"
            "  --data FILE         demonstrations from `madbp collect` (default demos.bin)\n"
            "  --out FILE          model file (default models/madiff/<map>-<n>.safetensors);\n"
            "                      resumable state in FILE.train, loss curve in FILE.csv\n"
            "  --resume            continue from FILE.train\n"
            "  --steps S           optimizer steps (default 3000)\n"
            "  --time-budget S     stop after S seconds of training (default: none)\n"
            "  --batch B           windows per step, each with N agents (default 32)\n"
            "  --horizon H         frames per window (default 8; multiple of 4)\n"
            "  --sample-steps S    DDIM steps the policy uses by default (default 10)\n"
            "  --route-goal D      observe the point D ahead on the route around the map (as\n"
            "                      MA-DBP's model and MAPPO --route-goal), not the goal (default 0)\n"
            "  --lr X              Adam learning rate (default 3e-4)\n"
            "  --threads T         threads (default 1); the result does not depend on it\n"
            "  --seed S            (default 0)\n"
            "  --json              print the summary as JSON\n");
        return 0;
    }
    madbp::MadiffConfig mc;
    madbp::MadiffTrainConfig tc;
    mc.map = a.str("--map", "empty");
    mc.agents = (int)a.integer("--agents", 2, 1, 64);
    const std::string data = a.str("--data", "demos.bin");
    tc.out = a.str("--out", default_madiff_path(mc.map, mc.agents));
    tc.resume = a.flag("--resume");
    tc.steps = a.integer("--steps", tc.steps, 1, 100000000);
    const double budget = a.real("--time-budget", 0, 1e-3, 1e9);  // 0 (not given): none; --time-budget 0 is an error
    tc.batch = (int)a.integer("--batch", tc.batch, 1, 100000);
    mc.horizon = (int)a.integer("--horizon", mc.horizon, 2, 256);
    mc.sample_steps = (int)a.integer("--sample-steps", mc.sample_steps, 1, 100000);
    mc.route_goal = a.real("--route-goal", mc.route_goal, 0, 10);
    tc.lr = (float)a.real("--lr", tc.lr, 1e-8, 0.999);
    tc.threads = (int)a.integer("--threads", 1, 1, 256);
    tc.seed = (uint64_t)a.integer("--seed", 0, 0);
    const bool json = a.flag("--json");
    a.finish();
    mc.validate();
    tc.validate();
    if (budget > 0) {
        const auto t0 = std::chrono::steady_clock::now();
        tc.keep_going = [t0, budget](long) { return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < budget; };
    }
    const madbp::DemoSet demos = load_training_data(data, madbp::kMaxDatasetAgents);
    const size_t slash = tc.out.find_last_of('/');
    if (slash != std::string::npos && slash > 0) ::mkdir(tc.out.substr(0, slash).c_str(), 0755);  // e.g. models/madiff; exists: fine
    const auto locks = claim_outputs(a, {{"--out", tc.out}}, {".train", ".csv"});
    madbp::MadiffModel model(mc);
    tc.progress = progress_line("madiff " + mc.map + " n=" + std::to_string(mc.agents));
    const madbp::MadiffReport r = madbp::train_madiff(demos, mc, tc, &model);
    madbp::MadiffLoss last;
    if (!r.curve.rows.empty()) {
        const auto& row = r.curve.rows.back();
        last.total = row[r.curve.column("loss")];
        last.diffusion = row[r.curve.column("diffusion")];
        last.inverse = row[r.curve.column("inverse")];
    }
    if (json)
        std::printf("%s\n", Json().add("out", tc.out).add("map", mc.map).add("agents", mc.agents).add("steps", r.steps)
                                .add("seconds", r.seconds).add("episodes", r.episodes).add("windows", r.windows)
                                .add("parameters", model.parameter_count()).add("loss", last.total).add("diffusion_loss", last.diffusion)
                                .add("inverse_loss", last.inverse).add("return_target", (double)model.config.return_target).line().c_str());
    else
        std::printf("madiff %s n=%d: %ld steps in %.1f s on %d episodes (%ld windows), %ld parameters; loss %.4f (diffusion %.4f,"
                    " inverse %.4f) -> %s\n",
                    mc.map.c_str(), mc.agents, r.steps, r.seconds, r.episodes, r.windows, model.parameter_count(), last.total,
                    last.diffusion, last.inverse, tc.out.c_str());
    return 0;
}

}  // namespace madbp_cli
