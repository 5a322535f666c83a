// madbp.cpp - the `madbp` command-line tool (SPEC 10).
//
//   madbp <subcommand> [options]     every subcommand takes --help, --seed, --json
//
// Adding things:
//   - a method for `eval` / `render`: one entry in methods() in methods.hpp (name, help, and a
//     function that reads its own options and returns a per-episode PolicyFactory). Planners
//     plug in through madbp::PlanFollower.
//   - a subcommand: one entry in subcommands() in main().
// Bad input prints one line on stderr and exits with code 2; a failure of the environment (a
// write the disk refused, lost standard output) exits with code 1.
#include <omp.h>

#include <cstring>
#include <iostream>

#include "cli_common.hpp"
#include "madbp_sim.hpp"

#include "methods.hpp"
#include "suite.hpp"  // eval --suite paper: every table and figure (docs/evaluation.md)
#include "bench_nn.hpp"
#include "bench_plan.hpp"

using namespace madbp_cli;

namespace {

// An error line longer than this is cut (a 100 KB flag value is not echoed whole).
constexpr size_t kMaxMessageBytes = 1000;

// render records every frame of the episode: its step limit bounds the log and the SVG.
constexpr int kMaxRenderSteps = 10000;

std::string fixed(double v, int prec) {
    if (!(v == v)) return "-";
    char b[32];
    std::snprintf(b, sizeof b, "%.*f", prec, v);
    return b;
}


// --scenario NAME (an interaction scene generator), checked; not with --scene.
std::string read_scenario(Args& a, const std::string& scene_path) {
    std::string name = a.str("--scenario", "");
    if (name.empty()) return name;
    if (!scene_path.empty()) throw std::invalid_argument("--scenario: not with --scene (a scene file fixes the problem)");
    const auto& names = madbp::interaction_scenarios();
    if (std::find(names.begin(), names.end(), name) == names.end())
        throw std::invalid_argument("--scenario: unknown scenario '" + name + "' (expected swap, cross, gap, corridor, parked or circle)");
    return name;
}

// ---------------------------------------------------------------------------------------------
int cmd_eval(Args& a) {
    if (a.has("--suite")) return cmd_suite(a);
    if (a.flag("--list-settings")) {
        a.finish();
        std::fputs(planner_settings_text().c_str(), stdout);
        return 0;
    }
    if (a.flag("--help")) {
        std::printf(
            "madbp eval - success, collisions and steps of a method over seeded episodes (SPEC 10)\n"
            "  --method M        method (default expert):\n%s"
            "  --map NAMES       empty, obstacles, barrier; comma list (default empty)\n"
            "  --agents LIST     team sizes, e.g. 2,4,6 (default 2,4,6; each in [1, 1024])\n"
            "  --episodes N      episodes per cell (default 100)\n"
            "  --seed S          episode i uses seed S+i (default 0)\n"
            "  --scene FILE      a fixed problem (SPEC 2) instead of random maps; seeds vary only\n"
            "                    the method's own randomness (not with --map, --agents, --half-size)\n"
            "  --scenario NAME   interaction scenes instead of random spawns on each --map, n <= 4: swap,\n"
            "                    cross, gap, corridor, parked, circle (madbp_sim.hpp Section 4b)\n"
            "  --no-filter       turn the safety filter off (line and planners)\n"
            "  --replan M        steps executed per plan (default: madbp 4, madbp --preset paper 8,\n"
            "                    the others 8)\n"
            "  --threads T       episodes in parallel (default 1; results do not depend on it)\n"
            "  --half-size H     half-size of random worlds (default: constant density, 1.2 up to 8 robots,\n"
            "                    about 0.425 sqrt(n) beyond: 3.4 at 64, 13.6 at 1024; with --scenario 1.2; at most 100)\n"
            "  --max-steps N     episode step limit (default 100 x half-size / 1.2; with --scene at least twice\n"
            "                    the longest robot's shortest route at cruise: madbp::scene_step_limit)\n"
            "  --json            one JSON object per cell instead of the table, with failed_seeds (the\n"
            "                    seeds of the episodes that failed: render or trace those)\n"
            "  --suite paper     every table and figure of the paper plus ours (--suite paper --help)\n"
            "  --list-settings   every planner setting (--set) with its defaults, range and meaning\n"
            "Columns: method, map, n_train, n, episodes, success, success_se, collisions (per\n"
            "episode), steps (mean of successful episodes), plan_ms (mean ms per decision: one plan for\n"
            "planners, one action for MAPPO and MADiff).\n",
            method_list().c_str());
        return 0;
    }
    std::string method_name = a.str("--method", "expert");
    std::vector<std::string> maps = split(a.str("--map", "empty"), "--map");
    std::vector<long> counts = a.integers("--agents", "2,4,6", 1, kMaxTeam);
    int episodes = (int)a.integer("--episodes", 100, 1, 1000000);
    uint64_t seed = (uint64_t)a.integer("--seed", 0, 0);
    std::string scene_path = a.str("--scene", "");
    std::string scenario = read_scenario(a, scene_path);
    bool json = a.flag("--json");
    MethodSetup setup;
    setup.filter = !a.flag("--no-filter");
    setup.replan = (int)a.integer("--replan", 0, 1, 1000);
    int threads = (int)a.integer("--threads", 1, 1, 256);
    const HalfSize half_size = read_half_size(a);
    const int max_steps = (int)a.integer("--max-steps", 0, 1, 1000000);  // 0: default_max_steps
    auto all = methods();
    const Method& method = find_method(all, method_name);
    madbp::Scene scene;
    refuse_scene_overrides(a, scene_path);
    if (!scene_path.empty()) {
        scene = madbp::load_scene(scene_path);
        maps = {"scene"};
        counts = {(long)scene.starts.size()};
    }
    // Each cell's world: the scene's, --half-size, or the constant density of its team size.
    auto cell_half_size = [&](long n) { return scene_path.empty() ? half_size.of(n, scenario) : scene.map.half_size; };
    for (auto& m : maps) {  // validate names, and that each team fits its world, before any long run
        madbp::Rng probe(0);
        if (m == "scene") continue;
        madbp::make_map(m, probe);
        if (scenario.empty())
            for (long n : counts) check_random_world(m, n, seed, cell_half_size(n));
    }
    std::vector<MethodSpec> specs;
    for (auto& m : maps)
        for (long n : counts) {
            setup.map = m;
            setup.agents = (int)n;
            specs.push_back(method.make(a, setup));
        }
    a.finish();
    if (!json)
        std::printf("%-8s %-10s %7s %3s %8s %8s %10s %10s %6s %8s\n", "method", "map", "n_train", "n", "episodes", "success",
                    "success_se", "collisions", "steps", "plan_ms");
    size_t cell = 0;
    for (auto& m : maps)
        for (long n : counts) {
            const MethodSpec& spec = specs[cell++];
            madbp::EvalConfig c;
            c.map = m;
            c.agents = (int)n;
            c.episodes = episodes;
            c.seed = seed;
            c.threads = threads;
            c.progress = progress_line("eval " + m + " n=" + std::to_string(n));
            c.half_size = cell_half_size(n);
            c.world.max_steps = max_steps > 0 ? max_steps : scene_path.empty() ? madbp::default_max_steps(c.half_size) : madbp::scene_step_limit(scene);
            c.scene = scene_path.empty() ? nullptr : &scene;
            c.scenario = scenario;
            madbp::EvalResult r = madbp::evaluate(c, spec.factory);
            if (json) {
                Json j;
                j.add("method", method_name).add("map", m);
                if (!scenario.empty()) j.add("scenario", scenario);
                if (spec.n_train >= 0) j.add("n_train", spec.n_train); else j.raw("n_train", "null");
                j.add("n", n).add("episodes", episodes).add("success", r.success).add("success_se", r.success_se)
                    .add("collisions", r.collisions).add("agent_collisions", r.agent_collisions)
                    .add("obstacle_collisions", r.obstacle_collisions).add("steps", r.steps).add("plan_ms", r.decision_ms)
                    .add("seed", (long)seed);
                std::string failed;
                for (uint64_t f : r.failed_seeds) failed += (failed.empty() ? "" : ", ") + std::to_string(f);
                j.raw("failed_seeds", "[" + failed + "]");
                std::printf("%s\n", j.line().c_str());
            } else {
                std::printf("%-8s %-10s %7s %3ld %8d %8s %10s %10s %6s %8s\n", method_name.c_str(),
                            (scenario.empty() ? m : m + "/" + scenario).c_str(),
                            spec.n_train >= 0 ? std::to_string(spec.n_train).c_str() : "-", n, episodes, fixed(r.success, 2).c_str(),
                            fixed(r.success_se, 3).c_str(), fixed(r.collisions, 2).c_str(), fixed(r.steps, 1).c_str(),
                            fixed(r.decision_ms, 3).c_str());
            }
            check_written(stdout);  // stop at the first lost cell, not after the whole run
        }
    return 0;
}

// Runs one recorded episode and writes its SVG; shared by render and demo.
int render_episode(const Method& method, Args& a, MethodSetup setup, const madbp::Scene* scene, uint64_t seed,
                   const std::string& out, bool animate, bool json, double half_size = 1.2, int max_steps = 100,
                   const std::string& scenario = "") {
    MethodSpec spec = method.make(a, setup);
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", out}});
    madbp::WorldConfig wc;
    wc.max_steps = max_steps;
    madbp::World world = scene               ? madbp::make_world(*scene, wc)
                         : !scenario.empty() ? madbp::make_interaction_world(scenario, setup.map, setup.agents, seed, half_size, wc)
                                             : madbp::make_random_world(setup.map, setup.agents, seed, half_size, wc);
    auto policy = spec.factory(world, seed);
    // One episode of 1024 robots can take minutes: its steps on a progress line.
    madbp::ProgressFn progress = progress_line("render " + setup.map + " n=" + std::to_string(setup.agents) + " steps");
    std::function<void(madbp::World&)> on_step;
    if (progress) on_step = [&](madbp::World& w) { progress(w.metrics().steps, w.config().max_steps, ""); };
    madbp::EpisodeResult r = madbp::run_episode(world, *policy, true, on_step);
    progress = nullptr;  // ends the line before the result is printed
    madbp::SvgOptions opt;
    opt.animate = animate;
    opt.title = method.name + "  " + setup.map + (scenario.empty() ? "" : "/" + scenario) + "  n=" + std::to_string(setup.agents) + "  seed " + std::to_string(seed) +
                (r.success ? "  success in " + std::to_string(r.steps) + " steps" : "  failed") +
                "  collisions " + std::to_string(r.collisions());
    madbp::write_text_file(out, madbp::render_svg(r.log, opt));
    if (json)
        std::printf("%s\n", Json().add("method", method.name).add("map", setup.map).add("n", setup.agents).add("seed", (long)seed)
                                .add("success", r.success).add("steps", r.steps).add("collisions", r.collisions())
                                .add("out", out).line().c_str());
    else
        std::printf("%s: %s, %d steps, %ld collisions -> wrote %s\n", method.name.c_str(), r.success ? "success" : "failed",
                    r.steps, r.collisions(), out.c_str());
    return 0;
}

int cmd_render(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp render - run one episode and draw it as SVG (map, goals, trajectories, collisions)\n"
            "  --method M     method (default expert):\n%s"
            "  --map NAME     empty, obstacles, barrier (default barrier)\n"
            "  --agents N     team size (default 4; at most 1024)\n"
            "  --seed S       episode seed (default 0)\n"
            "  --scene FILE   a fixed problem instead of a random one (not with --map, --agents, --half-size)\n"
            "  --scenario NAME  an interaction scene on --map instead of random spawns (n <= 4; as for eval)\n"
            "  --out FILE     output (default episode.svg)\n"
            "  --animate      an animated SVG that plays the episode\n"
            "  --no-filter, --replan M, --half-size H   as for eval (default half-size: constant density)\n"
            "  --max-steps N  episode step limit (default as for eval, at most 10000: every frame is drawn)\n"
            "  --json         print the result as JSON\n",
            method_list().c_str());
        return 0;
    }
    auto all = methods();
    const Method& method = find_method(all, a.str("--method", "expert"));
    MethodSetup setup;
    setup.map = a.str("--map", "barrier");
    setup.agents = (int)a.integer("--agents", 4, 1, kMaxTeam);
    setup.filter = !a.flag("--no-filter");
    setup.replan = (int)a.integer("--replan", 0, 1, 1000);
    uint64_t seed = (uint64_t)a.integer("--seed", 0, 0);
    std::string scene_path = a.str("--scene", ""), out = a.str("--out", "episode.svg");
    std::string scenario = read_scenario(a, scene_path);
    bool animate = a.flag("--animate"), json = a.flag("--json");
    double half_size = read_half_size(a).of(setup.agents, scenario);
    int max_steps = (int)a.integer("--max-steps", 0, 1, kMaxRenderSteps);  // 0: default_max_steps
    madbp::Scene scene;
    refuse_scene_overrides(a, scene_path);
    if (!scene_path.empty()) {
        scene = madbp::load_scene(scene_path);
        setup.map = "scene";
        setup.agents = (int)scene.starts.size();
        half_size = scene.map.half_size;
    } else if (scenario.empty()) {
        check_random_world(setup.map, setup.agents, seed, half_size);
    }
    if (max_steps == 0)
        max_steps = std::min(scene_path.empty() ? madbp::default_max_steps(half_size) : madbp::scene_step_limit(scene), kMaxRenderSteps);
    return render_episode(method, a, setup, scene_path.empty() ? nullptr : &scene, seed, out, animate, json, half_size, max_steps, scenario);
}

int cmd_demo(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp demo - the shipped MA-DBP model plans for 4 robots on a barrier map; writes SVG\n"
            "  --seed S       episode seed (default 0)\n"
            "  --model FILE   model (default: the shipped model, see madbp --help)\n"
            "  --method M     another method instead, e.g. expert or line\n"
            "  --out FILE     output (default demo.svg); an animated copy goes to FILE with -anim\n"
            "  --json         print the result as JSON\n");
        return 0;
    }
    uint64_t seed = (uint64_t)a.integer("--seed", 0, 0);
    std::string out = a.str("--out", "demo.svg");
    std::string method = a.str("--method", "madbp");
    bool json = a.flag("--json");
    auto all = methods();
    MethodSetup setup;
    setup.map = "barrier";
    setup.agents = 4;
    std::string anim = out.size() > 4 && out.substr(out.size() - 4) == ".svg" ? out.substr(0, out.size() - 4) + "-anim.svg" : out + "-anim.svg";
    int rc = render_episode(find_method(all, method), a, setup, nullptr, seed, out, false, json);
    render_episode(find_method(all, method), a, setup, nullptr, seed, anim, true, json);
    if (!json) std::printf("open %s (picture) or %s (animation) in a browser\n", out.c_str(), anim.c_str());
    return rc;
}

int cmd_bench(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp bench - world steps per second for a batch of worlds stepping together\n"
            "  --worlds N     worlds in the batch (default 1000)\n"
            "  --agents N     agents per world (default 4; at most 1024)\n"
            "  --half-size H  of the obstacles worlds (default: constant density, 1.2 up to 8 agents)\n"
            "  --steps N      steps timed (default 200)\n"
            "  --threads LIST thread counts, e.g. 1,2 (default 1,2)\n"
            "  --seed S       seed of the worlds and actions (default 0)\n"
            "  --nn           benchmark the neural-network kernels instead\n"
            "  --plan         benchmark the diffusion planner instead: ms per plan and GFLOP/s against\n"
            "                 Eigen's GEMM (allocations: build/bench_alloc); with --agents LIST (default\n"
            "                 1,2,4,8,16,32,64; each in [1, 1024]), --plans N, --half-size H (default:\n"
            "                 constant density, as for eval), and the planner flags of eval --method madbp\n"
            "                 (--model, --preset, --neighbours, --set; default the shipped model, tuned);\n"
            "                 ms/plan is a first plan, warm_ms one replan interval later; --threads T (default\n"
            "                 2): the first plans again on T threads, side by side; --no-expert: skip\n"
            "                 the guided expert's column (seconds per plan beyond 128 robots);\n"
            "                 --map empty|obstacles|barrier: the worlds' map (default empty);\n"
            "                 --episode-steps K: also the mean and the longest plan in an episode's\n"
            "                 first K steps, as eval plans them (goal fields, early replans,\n"
            "                 routes remade; default 0: not run)\n"
            "  --json         one JSON object per thread count\n");
        return 0;
    }
    if (a.flag("--plan")) return bench_plan(a);
    if (a.flag("--nn")) return bench_nn(a);
    int worlds = (int)a.integer("--worlds", 1000, 1, 1000000);
    int agents = (int)a.integer("--agents", 4, 1, kMaxTeam);
    const double half_size = read_half_size(a).of(agents);
    int steps = (int)a.integer("--steps", 200, 1, 1000000);
    std::vector<long> threads = a.integers("--threads", "1,2", 1, 256);
    uint64_t seed = (uint64_t)a.integer("--seed", 0, 0);
    bool json = a.flag("--json");
    a.finish();
    check_random_world("obstacles", agents, seed, half_size);
    for (long th : threads) {
        madbp::WorldBatch batch;
        madbp::WorldConfig cfg;
        cfg.max_steps = 1 << 30;
        for (int w = 0; w < worlds; ++w) batch.worlds.push_back(madbp::make_random_world("obstacles", agents, seed + w, half_size, cfg));
        madbp::Rng rng(seed);
        std::vector<std::vector<madbp::Vec2>> actions(worlds, std::vector<madbp::Vec2>(agents));
        for (auto& wa : actions)
            for (auto& u : wa) u = {rng.uniform(-1, 1), rng.uniform(-1, 1)};
        omp_set_num_threads((int)th);
        batch.step(actions);  // warm-up
        auto t0 = std::chrono::steady_clock::now();
        for (int s = 0; s < steps; ++s) batch.step(actions);
        double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        double rate = (double)steps * worlds / secs;
        if (json)
            std::printf("%s\n", Json().add("bench", "world").add("worlds", worlds).add("agents", agents).add("threads", th)
                                    .add("world_steps_per_s", rate).add("agent_steps_per_s", rate * agents).line().c_str());
        else
            std::printf("world bench: %d worlds x %d agents (obstacles map), %ld thread(s): %.3g world-steps/s (%.3g agent-steps/s)\n",
                        worlds, agents, th, rate, rate * agents);
    }
    return 0;
}

int cmd_convert(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp convert - a MovingAI MAPF benchmark map and scenario as a scene file (docs/formats.md)\n"
            "  --movingai MAP    the .map file (type octile; . G S passable, @ O T W blocked)\n"
            "  --scen FILE       its .scen file (version 1); robot i takes scenario row offset + i\n"
            "  --random-scen     instead of --scen: draw the rows from --seed, for a map without .scen\n"
            "                    files: start and goal in one connected component (8 directions, no\n"
            "                    corner cutting), no two starts alike, no two goals alike\n"
            "  --seed S          the rows of --random-scen (default 0; each seed its own rows)\n"
            "  --write-scen FILE with --random-scen: also save the drawn rows as a version-1 .scen file\n"
            "  --agents N        robots (1 to 1024)\n"
            "  --cell C          world units per map cell (default 0.3: a one-cell aisle fits a robot of\n"
            "                    diameter 0.2; at least 0.2); the world's half-size is max(W, H) x C / 2\n"
            "  --offset K        with --scen: first scenario row used, from 0 (default 0)\n"
            "  --out FILE        the scene file to write\n"
            "  --json            print the result as JSON\n");
        return 0;
    }
    const ConvertOptions o = read_convert_options(a);
    std::vector<FileArg> outputs = {{"--out", o.out}};
    if (!o.write_scen.empty()) outputs.push_back({"--write-scen", o.write_scen});
    const auto locks = claim_outputs(a, outputs);
    madbp::Scene scene;
    if (o.random_scen) {
        const madbp::MovingAiMap map = madbp::load_movingai_map(o.map_path);
        const std::vector<madbp::MovingAiScenarioRow> rows = madbp::random_movingai_scenario(map, o.agents, o.seed);
        const std::string source = o.write_scen.empty() ? "random, seed " + std::to_string(o.seed) : o.write_scen;
        scene = madbp::movingai_scene(map, rows, source, o.agents, o.cell);  // checked before anything is written
        if (!o.write_scen.empty()) madbp::write_file_atomic(o.write_scen, madbp::movingai_scenario_text(rows));
    } else {
        scene = madbp::load_movingai_scene(o.map_path, o.scen_path, o.agents, o.cell, o.offset);
    }
    madbp::write_file_atomic(o.out, madbp::scene_text(scene));
    const int steps = madbp::scene_step_limit(scene);
    if (o.json)
        std::printf("%s\n", Json().add("out", o.out).add("half_size", scene.map.half_size).add("boxes", (long)scene.map.boxes.size())
                                .add("agents", o.agents).add("max_steps", steps).line().c_str());
    else
        std::printf("wrote %s: world half-size %s, %zu boxes, %d robots; default step limit %d\n", o.out.c_str(),
                    madbp::number_text(scene.map.half_size).c_str(), scene.map.boxes.size(), o.agents, steps);
    return 0;
}

struct Subcommand {
    const char* name;
    const char* help;
    int (*run)(Args&);
};

const std::vector<Subcommand>& subcommands() {
    static const std::vector<Subcommand> s = {
        {"demo", "a planning episode on the barrier map, written as SVG", cmd_demo},
        {"eval", "success / collisions / steps of a method over seeded episodes", cmd_eval},
        {"render", "one episode drawn as (animated) SVG", cmd_render},
        {"convert", "a MovingAI benchmark map and scenario as a scene file", cmd_convert},
        {"bench", "world stepping speed (--nn kernels, --plan planner)", cmd_bench},
        {"collect", "record demonstrations for training", cmd_collect},
        {"train", "train the MA-DBP model", cmd_train},
        {"dagger", "improve a model on its own rollouts, labelled by the expert (DAgger)", cmd_dagger},
        {"mappo", "train a MAPPO policy for one map and team size (SPEC 3.3)", cmd_mappo},
        {"madiff", "train a MADiff baseline for one map and team size (SPEC 3.4)", cmd_madiff},
    };
    return s;
}

void usage(FILE* f) {
    std::fprintf(f, "madbp %d.%d.%d - multi-robot planning with diffusion (see README.md)\n\nusage: madbp <subcommand> [options]\n\n",
                 MADBP_VERSION_MAJOR, MADBP_VERSION_MINOR, MADBP_VERSION_PATCH);
    for (auto& s : subcommands()) std::fprintf(f, "  %-8s %s\n", s.name, s.help);
    std::fprintf(f, "\nEvery subcommand takes --help, --seed and --json.\n"
                    "--model's default, the shipped model madbp-default.safetensors: $MADBP_MODEL (the file) if set, else\n"
                    "the first found in <this program's directory>/../share/madbp/models, the models directory it was\n"
                    "built for (MADBP_MODEL_DIR), ./models (madbp.hpp's default_model_path).\n");
}

// The one line of an error. Every message passes through madbp::printable: a value a message
// quotes (a flag's, a file's) reaches the terminal without its escape bytes and cut short.
void report_error(const std::string& subcommand, const std::exception& e) {
    std::fprintf(stderr, "madbp %s: %s\n", madbp::printable(subcommand).c_str(), madbp::printable(e.what(), kMaxMessageBytes).c_str());
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") || !std::strcmp(argv[1], "help")) {
        usage(argc < 2 ? stderr : stdout);
        return argc < 2 ? 2 : 0;
    }
    std::string name = argv[1];
    try {
        for (auto& s : subcommands()) {
            if (name != s.name) continue;
            Args args(argc, argv, 2);
            const int rc = s.run(args);
            check_written(stdout);
            return rc;
        }
        throw std::invalid_argument("unknown subcommand '" + madbp::printable(name) + "' (try madbp --help)");
    } catch (const madbp::EnvironmentError& e) {  // disk full, lost stdout: one line, exit code 1
        report_error(name, e);
        return 1;
    } catch (const std::bad_alloc&) {  // the machine's memory, not the input (inputs are bounded)
        std::fprintf(stderr, "madbp %s: out of memory\n", madbp::printable(name).c_str());
        return 1;
    } catch (const std::exception& e) {  // bad flags, files, maps: one line, exit code 2
        report_error(name, e);
        return 2;
    }
}
