// methods_nn.hpp - the learned methods and the training subcommands of the `madbp` tool:
// `eval --method madbp`, `collect`, `train`. Included by madbp.cpp.
#pragma once
#include <chrono>
#include <map>
#include <memory>
#include <mutex>

#include "madbp_train.hpp"
#include "methods_mappo.hpp"

namespace madbp_cli {


// What the tool plans with: the model file, the planner's settings (madbp::PlannerConfig) and
// whether robots plan for themselves. Shared by eval, render, demo, bench --plan and dagger.
struct PlannerChoice {
    std::string model_path;
    madbp::PlannerConfig settings;
    bool decentralised = false;  // each robot plans for itself (madbp::DecentralisedTeam)
};
// The planner flags' help, for every subcommand that reads them.
inline const char* kPlannerFlagsHelp =
    "--model FILE (default: the shipped model, see madbp --help), --preset tuned|paper (default tuned),\n"
    "                    --neighbours K|auto, --sensing-radius R|auto, --set GROUP.NAME=VALUE (any planner\n"
    "                    setting, repeatable; `madbp eval --list-settings` lists each with its default,\n"
    "                    range and meaning), --decentralised (each robot plans for itself, plan_robot)";
// --model, --preset, --neighbours, --sensing-radius, --set (repeatable), --decentralised. `setup`
// (eval's --replan and --no-filter) goes in before --set, so an explicit setting wins.
inline PlannerChoice read_planner_choice(Args& a, const MethodSetup* setup = nullptr) {
    PlannerChoice o;
    o.model_path = model_option(a);
    const std::string preset = a.str("--preset", "tuned");
    try {
        o.settings = madbp::PlannerConfig::preset(preset);
    } catch (const std::invalid_argument&) {
        throw std::invalid_argument("--preset: expected tuned or paper, got '" + madbp::printable(preset) + "'");
    }
    if (setup) {
        if (setup->replan > 0) o.settings.follower.replan_every = setup->replan;
        o.settings.follower.safety_filter = setup->filter;
    }
    apply_planner_settings(a, o.settings);
    o.decentralised = a.flag("--decentralised");
    return o;
}

// The planner policy of one episode: one planner for the team (plan), or one per robot
// (--decentralised, plan_robot). Planners keep workspaces: every episode gets its own.
inline madbp::PolicyFactory planner_factory(std::shared_ptr<const madbp::MadbpModel> model, const PlannerChoice& o) {
    // (sampler.sample_steps needs no check against the model here: it is capped at the model's own S.)
    return [model, o](const madbp::World&, uint64_t seed) -> std::unique_ptr<madbp::Policy> {
        if (o.decentralised)
            return std::make_unique<madbp::PlanFollower>(
                [team = std::make_shared<madbp::DecentralisedTeam>(model, o.settings, seed)](const madbp::World& w) { return team->plan(w); },
                o.settings.follower);
        auto planner = std::make_shared<madbp::DiffusionPlanner>(model->clone(), seed, o.settings);
        return std::make_unique<madbp::PlanFollower>([planner](const madbp::World& w) { return planner->plan(w); }, o.settings.follower);
    };
}

// Loads the model once for every episode of a cell.
inline MethodSpec madbp_method(const PlannerChoice& o) {
    // One thread per plan (SPEC 9 measures one core); eval --threads runs episodes in parallel.
    madbp::set_num_threads(1);
    auto shared = std::make_shared<const madbp::MadbpModel>(madbp::load_model(o.model_path));
    MethodSpec spec;
    spec.n_train = shared->config.n_train_max > 0 ? shared->config.n_train_max : -1;
    spec.factory = planner_factory(shared, o);
    return spec;
}

// `madbp eval --list-settings`: every planner setting with both presets' values, its range and meaning.
inline std::string planner_settings_text() {
    const madbp::PlannerConfig tuned = madbp::PlannerConfig::tuned(), paper = madbp::PlannerConfig::paper();
    std::string out = "Planner settings (--set GROUP.NAME=VALUE; --preset tuned|paper):\n";
    char line[512];
    std::snprintf(line, sizeof line, "%-30s %-7s %-7s %-22s %s\n", "setting", "tuned", "paper", "range", "meaning");
    out += line;
    for (const madbp::PlannerSetting& s : madbp::planner_settings()) {
        std::snprintf(line, sizeof line, "%-30s %-7s %-7s %-22s %s\n", s.name, s.value_text(tuned).c_str(), s.value_text(paper).c_str(),
                      s.range_text().c_str(), s.meaning);
        out += line;
        if (s.automatic) out += std::string(70, ' ') + "auto: " + s.automatic + "\n";
    }
    return out;
}

inline void register_nn_methods(std::vector<Method>& m) {
    m.push_back({"madbp",
                 std::string("MA-DBP diffusion planner + tracker (+ safety filter) (SPEC 5-8);\n                    ") + kPlannerFlagsHelp,
                 [](Args& a, const MethodSetup& s) { return madbp_method(read_planner_choice(a, &s)); }});
}

// ---------------------------------------------------------------------------------------------
// --scenarios: "NAME:FRACTION,..." (all:F = F split evenly among every scenario); "" = none.
inline std::vector<std::pair<std::string, double>> parse_scenario_mix(const std::string& list) {
    std::vector<std::pair<std::string, double>> mix;
    if (list.empty()) return mix;
    for (const std::string& item : split(list, "--scenarios")) {
        const size_t colon = item.find(':');
        const std::string name = item.substr(0, colon), frac = colon == std::string::npos ? "" : item.substr(colon + 1);
        size_t pos = 0;
        double f = -1;
        try { f = std::stod(frac, &pos); } catch (...) { pos = 0; }
        if (frac.empty() || pos != frac.size() || !(f >= 0 && f <= 1))
            throw std::invalid_argument("--scenarios: expected NAME:FRACTION with a fraction in [0, 1], got '" + item + "'");
        const auto& names = madbp::interaction_scenarios();
        if (name == "all") {
            for (const std::string& n : names) mix.push_back({n, f / names.size()});
        } else if (std::find(names.begin(), names.end(), name) != names.end()) {
            mix.push_back({name, f});
        } else {
            throw std::invalid_argument("--scenarios: unknown scenario '" + name + "' (expected all, swap, cross, gap, corridor, parked or circle)");
        }
    }
    double total = 0;
    for (auto& m : mix) total += m.second;
    if (total > 1 + 1e-9) throw std::invalid_argument("--scenarios: fractions sum to " + std::to_string(total) + ", more than 1");
    return mix;
}

// --maps LIST (default empty,obstacles,barrier); an unknown name fails here, before any work.
inline std::vector<std::string> read_maps(Args& a) {
    std::vector<std::string> maps;
    for (const std::string& m : split(a.str("--maps", "empty,obstacles,barrier"), "--maps")) {
        madbp::Rng probe(0);
        madbp::make_map(m, probe);
        maps.push_back(m);
    }
    return maps;
}

inline int cmd_collect(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp collect - record demonstrations for training (SPEC 7)\n"
            "  --demonstrator D  expert (default) or mappo with --model FILE ({n} in FILE = team size)\n"
            "  --maps LIST       maps (default empty,obstacles,barrier)\n"
            "  --n-train-max N   teams of 1..N agents (default 4)\n"
            "  --n-train-min N   teams of N..n-train-max agents only (default 1; seeds as without it)\n"
            "  --episodes E      episodes per (map, n) cell (default 500)\n"
            "  --keep-failures   also keep episodes the demonstrator failed\n"
            "  --scenarios LIST  interaction scenes mixed into every cell of n <= 4, as NAME:FRACTION items\n"
            "                    (swap, cross, gap, corridor, parked, circle; all:F splits F evenly among\n"
            "                    them), e.g. all:0.5 or swap:0.2,corridor:0.1; default none (random spawns)\n"
            "  --threads T       parallel episodes (default 2)\n"
            "  --seed S          base seed (default 0)\n"
            "  --out FILE        dataset file (default demos.bin)\n"
            "  --json            print a JSON summary\n");
        return 0;
    }
    madbp::CollectConfig c;
    std::string dem = a.str("--demonstrator", "expert");
    c.maps = read_maps(a);
    c.n_train_max = (int)a.integer("--n-train-max", 4, 1, 64);
    c.n_train_min = (int)a.integer("--n-train-min", 1, 1, 64);
    c.scenarios = parse_scenario_mix(a.str("--scenarios", ""));
    c.episodes = (int)a.integer("--episodes", 500, 1, 10000000);
    c.successful_only = !a.flag("--keep-failures");
    c.threads = (int)a.integer("--threads", 2, 1, 256);
    c.seed = (uint64_t)a.integer("--seed", 0, 0);
    std::string out = a.str("--out", "demos.bin");
    std::string model = a.str("--model", "");
    bool json = a.flag("--json");
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", out}});
    if (dem != "expert" && dem != "mappo") throw std::invalid_argument("--demonstrator: unknown demonstrator '" + dem + "' (expected expert or mappo)");
    if (dem == "mappo" && model.empty())
        throw std::invalid_argument("--model: --demonstrator mappo needs a policy file, e.g. 'models/mappo/empty-{n}.safetensors' ({n} = team size)");
    auto t0 = std::chrono::steady_clock::now();
    c.progress = progress_line("collect");
    madbp::DemoSet set = madbp::collect_demonstrations(c, dem == "mappo" ? madbp::mappo_demonstrator(model) : madbp::expert_demonstrator(),
                                                       dem == "mappo" ? "mappo:" + model : dem);
    double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    madbp::save_demos(out, set);
    long steps = 0;
    for (auto& d : set.episodes) steps += d.steps;
    const long asked = (long)c.maps.size() * (c.n_train_max - c.n_train_min + 1) * c.episodes;
    if (json)
        std::printf("%s\n", Json().add("out", out).add("demonstrator", dem).add("episodes", (long)set.episodes.size())
                                .add("asked", asked).add("steps", steps).add("seconds", secs).line().c_str());
    else
        std::printf("collect: kept %zu of %ld episodes (%ld steps) from '%s' in %.1f s -> %s\n", set.episodes.size(), asked, steps,
                    dem.c_str(), secs, out.c_str());
    return 0;
}

inline int cmd_train(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp train - train the MA-DBP denoiser on demonstrations (SPEC 7)\n"
            "  --data FILE        dataset from `madbp collect` (default demos.bin)\n"
            "  --out FILE         model file (default model.safetensors); training state goes to\n"
            "                     FILE.train, loss curves to FILE.csv and FILE.svg\n"
            "  --resume           continue from FILE.train\n"
            "  --steps N          optimizer steps (default 20000)\n"
            "  --batch B          windows per step (default 64)\n"
            "  --lr X             Adam learning rate (default 3e-4)\n"
            "  --n-train-max N    curriculum end (default 4)\n"
            "  --curriculum-end F fraction of training at which n_curr reaches N (default 0.5)\n"
            "  --weights a,b,c,d  loss weights noise,boundary,temporal,collision (default .85,.025,.025,.1)\n"
            "  --horizon H --dim D --heads K --channels C1,C2 --kernel K --n-max N --grid G\n"
            "  --processor AAP|LE --window MW|CT --prediction x0|eps --local-grid G (0: off)\n"
            "  --window-scale W --waypoint-stride K   model configuration (SPEC 5; defaults in docs/design.md;\n"
            "                     window scale default min(2.4, 0.6 (H-1) stride / 15))\n"
            "  --frame world|local  scene coordinates: from the world's centre (paper) or from each scene's\n"
            "                     centre with a grid cropped around it, for any world size (default local)\n"
            "  --subgoal D        a goal farther than D world units, or out of view, is shown D away in the\n"
            "                     direction of the route around the map; 0 = off (default 1.5)\n"
            "  --checkpoint-every N (default 1000)   --seed S (default 0)\n"
            "  --threads T        data-parallel replicas (default 2); results depend on T, not on the machine\n"
            "  --json             print the final losses as JSON\n");
        return 0;
    }
    std::string data = a.str("--data", "demos.bin");
    madbp::TrainConfig tc;
    tc.out = a.str("--out", "model.safetensors");
    tc.resume = a.flag("--resume");
    tc.steps = a.integer("--steps", 20000, 1, 100000000);
    tc.batch = (int)a.integer("--batch", 64, 1, 100000);
    tc.lr = (float)a.real("--lr", 3e-4, 1e-7, 1);
    tc.n_train_max = (int)a.integer("--n-train-max", 4, 1, 1024);
    tc.curriculum_end = (float)a.real("--curriculum-end", 0.5, 0, 1);
    tc.checkpoint_every = a.integer("--checkpoint-every", 1000, 1);
    tc.seed = (uint64_t)a.integer("--seed", 0, 0);
    if (a.has("--weights")) {
        const std::vector<double> w = a.reals("--weights", "", 0, 1e6);
        if (w.size() != 4 || w[0] + w[1] + w[2] + w[3] <= 0)
            throw std::invalid_argument("--weights: expected four numbers >= 0, not all 0, like .85,.025,.025,.1, got '" +
                                        madbp::printable(a.str("--weights", "")) + "'");
        for (int i = 0; i < 4; ++i) tc.loss_weights[i] = (float)w[i];
    }
    madbp::ModelConfig mc;
    mc.horizon = (int)a.integer("--horizon", mc.horizon, 2, 4096);
    mc.dim = (int)a.integer("--dim", mc.dim, 4, 4096);
    mc.heads = (int)a.integer("--heads", mc.heads, 1, 64);
    mc.kernel = (int)a.integer("--kernel", mc.kernel, 1, 31);
    mc.n_max = (int)a.integer("--n-max", mc.n_max, 1, 1024);
    mc.grid = (int)a.integer("--grid", mc.grid, 8, 1024);
    std::string ch = a.str("--channels", "");
    if (!ch.empty()) {
        mc.channels.clear();
        for (long c : a.integers("--channels", ch, 1, 1024)) mc.channels.push_back((int)c);
    }
    mc.local_grid = (int)a.integer("--local-grid", mc.local_grid, 0, 256);
    mc.waypoint_stride = (int)a.integer("--waypoint-stride", mc.waypoint_stride, 1, 16);
    // Default: 0.6 world units per 15 steps of window (the top speed's reach), capped at 2.4 (a
    // complete trajectory crosses the world at most once), so H = 8, 32 and CT windows of ~100
    // steps get displacements of order 1, as H = 16 does with 0.6.
    const double span = (double)(mc.horizon - 1) * mc.waypoint_stride;
    mc.window_scale = (float)a.real("--window-scale", std::min(2.4, 0.6 * span / 15.0), 1e-3, 100);
    std::string pred = a.str("--prediction", "x0");
    if (pred != "x0" && pred != "eps") throw std::invalid_argument("--prediction: expected x0 or eps, got '" + pred + "'");
    mc.prediction = pred == "x0" ? madbp::Prediction::X0 : madbp::Prediction::Eps;
    std::string proc = a.str("--processor", "AAP"), win = a.str("--window", "MW");
    if (proc != "AAP" && proc != "LE") throw std::invalid_argument("--processor: expected AAP or LE, got '" + proc + "'");
    if (win != "MW" && win != "CT") throw std::invalid_argument("--window: expected MW or CT, got '" + win + "'");
    mc.processor = proc == "AAP" ? madbp::Processor::AAP : madbp::Processor::LE;
    mc.window = win == "MW" ? madbp::WindowMode::MW : madbp::WindowMode::CT;
    std::string frame = a.str("--frame", "local");
    if (frame != "world" && frame != "local") throw std::invalid_argument("--frame: expected world or local, got '" + frame + "'");
    mc.frame = frame == "local" ? madbp::SceneFrame::Local : madbp::SceneFrame::World;
    mc.subgoal_distance = (float)a.real("--subgoal", 1.5, 0, 100);
    mc.n_train_max = std::min(tc.n_train_max, mc.n_max);
    int threads = (int)a.integer("--threads", 2, 1, 256);
    bool json = a.flag("--json");
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", tc.out}}, {".train", ".csv", ".svg"});
    mc.validate();
    tc.threads = threads;
    madbp::set_num_threads(threads);
    madbp::DemoSet demos = load_training_data(data, mc.n_max);
    madbp::MadbpModel model(mc, tc.seed);
    if (!json) std::printf("train: %zu episodes from '%s', model with %ld parameters\n", demos.episodes.size(), demos.demonstrator.c_str(), model.parameter_count());
    tc.progress = progress_line("train");
    madbp::TrainReport r = madbp::train(demos, model, tc);
    write_curve_svg(tc.out + ".svg", r.curve, {"train_total", "val_total"}, "MA-DBP training loss", true);
    if (json)
        std::printf("%s\n", Json().add("out", tc.out).add("steps", r.steps).add("seconds", r.seconds).add("train_loss", r.last_train.total)
                                .add("val_loss", r.last_val.total).add("val_noise", r.last_val.noise).line().c_str());
    else
        std::printf("train: %ld steps in %.1f s; last train loss %.4f, validation loss %.4f (noise %.4f) -> %s\n", r.steps, r.seconds,
                    r.last_train.total, r.last_val.total, r.last_val.noise, tc.out.c_str());
    return 0;
}

inline int cmd_dagger(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp dagger - on-policy data aggregation (issue 12): roll the model out, label the states it\n"
            "               visits with what the guided expert does from them, fine-tune on the labels\n"
            "               of every round so far plus as many expert windows; repeat\n"
            "  --model FILE       the model to start from (default: the shipped model, see madbp --help)\n"
            "  --data FILE        the expert demonstrations it was trained on (default demos.bin)\n"
            "  --out FILE         final model (default dagger.safetensors); round R writes FILE.round-R.labels.bin\n"
            "                     and FILE.round-R.safetensors (+ .train, .csv); the log is FILE.dagger.csv\n"
            "  --resume           continue an interrupted run from its files\n"
            "  --rounds R         rounds (default 3); the log's round R+1 is the final model's evaluation\n"
            "  --episodes E       rollouts per (map, team size) cell and round (default 40)\n"
            "  --maps LIST        (default empty,obstacles,barrier)   --n-train-max N (teams 1..N, default 4)\n"
            "  --scenarios LIST   interaction scenes in the rollouts, as for collect (default all:0.3)\n"
            "  --label-every K    label every K-th visited state (default 2)\n"
            "  --base-ratio X     expert windows per label window in each fine-tune (default 1)\n"
            "  --steps N          fine-tune steps per round (default 3000)   --batch B (default 64)\n"
            "  --lr X             fine-tune learning rate (default 1e-4)\n"
            "  --seed S           seed of the rollouts (round R: S + R x 10^7) and the fine-tunes (default 50000000)\n"
            "  --threads T        parallel rollouts and training replicas (default 2)\n"
            "  planner options of the rollouts as for `eval --method madbp` (--preset, --set GROUP.NAME=VALUE, ...)\n");
        return 0;
    }
    const PlannerChoice o = read_planner_choice(a);
    std::string data = a.str("--data", "demos.bin");
    madbp::DaggerConfig c;
    c.train.out = a.str("--out", "dagger.safetensors");
    c.train.resume = a.flag("--resume");
    c.rounds = (int)a.integer("--rounds", 3, 1, 1000);
    c.rollouts.episodes = (int)a.integer("--episodes", 40, 1, 1000000);
    c.rollouts.maps = read_maps(a);
    c.rollouts.n_train_max = (int)a.integer("--n-train-max", 4, 1, 64);
    c.rollouts.scenarios = parse_scenario_mix(a.str("--scenarios", "all:0.3"));
    c.label_every = (int)a.integer("--label-every", 2, 1, 1000);
    c.base_ratio = a.real("--base-ratio", 1, 0, 1e6);
    c.train.steps = a.integer("--steps", 3000, 1, 100000000);
    c.train.batch = (int)a.integer("--batch", 64, 1, 100000);
    c.train.lr = (float)a.real("--lr", 1e-4, 1e-7, 1);
    c.train.n_train_max = c.rollouts.n_train_max;
    c.train.curriculum_end = 0;  // a fine-tune: every team size from the first step
    c.train.ema_start = 0;
    const uint64_t seed = (uint64_t)a.integer("--seed", (long)madbp::kDaggerDefaultSeed, 0);
    c.rollouts.seed = seed;
    c.train.seed = seed;
    const int threads = (int)a.integer("--threads", 2, 1, 256);
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", c.train.out}}, {".train", ".csv", ".dagger.csv"});
    c.rollouts.threads = threads;
    c.train.threads = threads;
    madbp::set_num_threads(1);
    madbp::MadbpModel model = madbp::load_model(o.model_path);
    if (c.train.n_train_max > model.config.n_max) throw std::invalid_argument("--n-train-max: exceeds the model's n_max");
    madbp::DemoSet base = load_training_data(data, model.config.n_max);
    c.rollouts.progress = progress_line("dagger rollouts");
    c.train.progress = progress_line("dagger fine-tune");
    c.on_round = [&](const madbp::DaggerRound& r) {
        const bool last = r.round == c.rounds + 1;
        if (last)
            std::printf("dagger: after round %d: success %.3f +- %.3f over %d rollouts, %.2f collisions/episode (%.0f s)\n", c.rounds, r.success,
                        r.success_se, r.episodes, r.collisions, r.seconds);
        else
            std::printf("dagger: round %d: the model going in: success %.3f +- %.3f over %d rollouts, %.2f collisions/episode; %ld labels; "
                        "fine-tuned on %ld episodes (%.0f s)\n", r.round, r.success, r.success_se, r.episodes, r.collisions, r.labels,
                        r.train_episodes, r.seconds);
        std::fflush(stdout);
    };
    madbp::dagger(base, model, c, [&](const madbp::MadbpModel& m) {
        return planner_factory(std::make_shared<const madbp::MadbpModel>(m.clone()), o);
    });
    std::printf("dagger: %d rounds -> %s (log %s.dagger.csv)\n", c.rounds, c.train.out.c_str(), c.train.out.c_str());
    return 0;
}

}  // namespace madbp_cli
