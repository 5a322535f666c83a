// bench_plan.hpp - `madbp bench --plan`: wall time per window plan against team size, beside the
// guided expert's plan time on the same worlds, one robot's own plan (plan_robot), and the
// sampler's arithmetic rate as a share of the same run's Eigen matrix-product rate (SPEC 9 and
// issue 13 speed targets). Heap allocations per plan are counted by build/bench_alloc (tool/bench_alloc.cpp),
// which replaces malloc: the shipped tool does not.
#pragma once
#include <chrono>
#include <optional>

#include "madbp.hpp"

namespace madbp_cli {

// Multiply-adds x 2 of one plan: the context encoder once, then S denoiser passes. Counts the
// products (Linear, Conv1d/2d as GEMMs, attention scores and sums), which are nearly all the work.
inline double plan_flops(const madbp::ModelConfig& c, int n, int S) {
    const double A = n, H = c.horizon, D = c.dim, k = c.kernel;
    double denoise = 2 * 4 * D * H * A;  // in_proj
    if (c.processor == madbp::Processor::AAP) {
        denoise += 4 * 2 * D * D * H * A + 2 * 2 * H * H * D * A;          // time attention
        denoise += 4 * 2 * D * D * H * A + 2 * 2 * n * n * D * H;          // agent attention
        denoise += 2 * 2 * D * 2 * D * H * A;                              // MLP
    }
    denoise += 2 * D * 2 * D + 2 * 2 * D * D;  // step embedding (one scene)
    const int L = c.levels();
    double cin = D;
    for (int l = 0; l < L; ++l) {  // down blocks: two convs and a FiLM projection each
        const double T = H / (1 << l), co = c.channels[l];
        denoise += 2 * (cin * co + co * co) * k * T * A + 2 * D * 2 * co * A;
        cin = co;
    }
    const double TL = H / (1 << L);
    denoise += 2 * 2 * cin * cin * k * TL * A + 2 * D * 2 * cin * A;  // middle block
    for (int l = L - 1; l >= 0; --l) {  // up blocks: concatenated skip
        const double T = H / (1 << l), co = c.channels[l];
        denoise += 2 * ((cin + co) * co + co * co) * k * T * A + 2 * D * 2 * co * A;
        cin = co;
    }
    denoise += 2 * cin * 2 * H * A;  // decoder
    const double G = c.grid, P = c.image_tokens(), Gl = c.local_grid;
    double context = 2 * 9 * (1 * 16 * (G / 2) * (G / 2) + 16 * 32 * (G / 4) * (G / 4) + 32 * D * (G / 8) * (G / 8));
    if (Gl > 0) context += 2 * A * (9 * (8 * (Gl / 2) * (Gl / 2) + 8 * 16 * (Gl / 4) * (Gl / 4)) + 16 * D * (Gl / 4) * (Gl / 4));
    context += 2 * A * (4 * D + D * D) + 2 * D * D * (A + 2 * (P + A + 1) + A) + 2 * 2 * A * (P + A + 1) * D;  // fusion: q, k, v, o; scores, sums
    return context + S * denoise;
}

// GFLOP/s of a single-threaded Eigen product of the U-Net's typical shape, timed for ~0.3 s.
inline double eigen_gemm_rate(int m, int kdim, int n) {
    madbp::Mat a = madbp::Mat::Random(m, kdim), b = madbp::Mat::Random(kdim, n), c(m, n);
    long reps = 0;
    auto t0 = std::chrono::steady_clock::now();
    double secs = 0;
    while (secs < 0.3) {
        for (int i = 0; i < 50; ++i) c.noalias() = a * b;
        reps += 50;
        a(0, 0) += c(0, 0) * 1e-12f;  // keep the products live
        secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    }
    return 2.0 * m * kdim * n * reps / secs / 1e9;
}

inline int bench_plan(Args& a) {
    const PlannerChoice choice = read_planner_choice(a);  // the shipped model and the tuned planner unless told
    std::vector<long> teams = a.integers("--agents", "1,2,4,8,16,32,64", 1, kMaxTeam);
    const HalfSize half_sizes = read_half_size(a);
    int plans = (int)a.integer("--plans", 50, 1, 1000000);
    uint64_t seed = (uint64_t)a.integer("--seed", 0, 0);
    bool json = a.flag("--json");
    // The same first plans again on this many threads (set_num_threads), beside one thread's.
    const int threads = (int)a.integer("--threads", 2, 1, 256);
    const bool expert_row = !a.flag("--no-expert");  // the guided expert takes seconds per plan beyond 128 robots
    // The worlds' map: empty (the default), or obstacles, where robots route around the map
    // (RouteGuide's fields are made in the first plans, then cached).
    const std::string map = a.str("--map", "empty");
    // Plans inside an episode: the team runs this many steps as eval runs it (make_follower), and
    // those plans are timed. They cost what the first plans above do not: goal fields made as
    // robots come near new routes, plans every m/2 steps when a robot strays
    // (follower.replan_error), routes around crowds made again (0: not run).
    const int episode_steps = (int)a.integer("--episode-steps", 0, 0, 100000);
    a.finish();
    for (long n : teams) check_random_world(map, n, seed, half_sizes.of(n));  // before the long run
    if (choice.decentralised) throw std::invalid_argument("--decentralised: bench --plan times a team's plans (plan_robot: --agents 1)");
    madbp::set_num_threads(1);  // SPEC 9: one core
    const std::string& model_path = choice.model_path;
    const madbp::MadbpModel loaded = madbp::load_model(model_path);
    const madbp::ModelConfig& config = loaded.config;
    const madbp::SamplerConfig sc = choice.settings.sampler_config(config);
    const int S = sc.sample_steps;
    // The GEMM of the first down block's convolution for 8 agents: (C0, D*k) x (D*k, H*8).
    const double gemm = eigen_gemm_rate(config.channels[0], config.dim * config.kernel, config.horizon * 8);
    if (!json)
        std::printf("plan bench: %s, S = %d, guidance %g, keep-right %g, candidates %d (plans of <= %d robot windows %d), warm start %d, line start %d, one thread;\n"
                    "Eigen GEMM %dx%d * %dx%d: %.1f GFLOP/s\n"
                    "random %s worlds: %s; scenes x robots\n"
                    "per scene (x candidates) as the planner chose (automatic neighbourhoods); ms/plan: a first plan (line start: the\n"
                    "last W steps from straight lines; else all S); warm_ms: a plan follower.replan_every steps after the last, warm-started;\n"
                    "new_ms: a first plan of a new world on the same map (new goals: their goal fields are made);\n"
                    "expert: the guided expert's ms per plan; GFLOP/s: of a first plan;\n"
                    "ms/robot: ms/plan per robot; growth: ms/plan grows as n^growth from the row above (1 = linear in robots);\n"
                    "ms_%dt: a first plan on %d threads, x%dt: its speed-up, measured in the same run; new_%dt: new_ms on %d threads (other new worlds);\n"
                    "%s"
                    "%4s %6s %10s %10s %10s %10s %10s %8s %9s %6s %9s %6s %10s %10s %11s\n",
                    model_path.c_str(), S, sc.guidance, sc.keep_right, sc.candidates,
                    madbp::kSmallPlanWindows, choice.settings.sampler.small_plan_candidates, sc.warm_start, choice.settings.sampler.line_start ? 1 : 0, config.channels[0], config.dim * config.kernel, config.dim * config.kernel, config.horizon * 8, gemm,
                    map.c_str(), half_sizes.given > 0 ? ("half-size " + madbp::number_text(half_sizes.given)).c_str()
                                         : "half-size at constant density (1.2 up to 8 robots, 3.4 at 64, 13.6 at 1024)",
                    threads, threads, threads, threads, threads,
                    episode_steps > 0 ? ("episode_ms, episode_max: the mean and the longest plan in the first " + std::to_string(episode_steps) +
                                         " steps of an episode from the same world, as eval plans them (--episode-steps)\n").c_str() : "",
                    "n",
                    "scenes", "ms/plan", "warm_ms", "new_ms", "expert_ms", "GFLOP/s", "of GEMM", "ms/robot", "growth",
                    ("ms_" + std::to_string(threads) + "t").c_str(), ("x" + std::to_string(threads) + "t").c_str(), ("new_" + std::to_string(threads) + "t").c_str(), "episode_ms", "episode_max");
    double robot_ms = 0, robot_warm_ms = 0;
    double last_ms = 0;  // the row above: the growth exponent
    long last_n = 0;
    int robot_K = 0;
    long robot_n = 0;  // the team plan_robot was timed in: the largest planned in neighbourhoods
    for (long n : teams) {
        // Held in an optional: it is let go before the episode's planner is made (two at 1024 robots
        // would double the peak resident memory).
        std::optional<madbp::DiffusionPlanner> first_planner(std::in_place, loaded.clone(), seed, choice.settings);
        madbp::DiffusionPlanner& planner = *first_planner;
        // DDIM steps of a first plan: with line start and warm start on, the last W, else all S.
        const int first_steps = choice.settings.sampler.line_start && sc.warm_starts() ? sc.warm_start : S;
        const double half_size = half_sizes.of(n);
        madbp::World world = madbp::make_random_world(map, (int)n, seed, half_size);
        madbp::Plan plan;
        // Plans done on a terminal's progress line: at 1024 robots a plan takes seconds. The
        // expert's run is a unit, then each episode step.
        madbp::ProgressFn progress = progress_line("bench --plan n=" + std::to_string(n) + " plans");
        long done = 0;
        auto tick = [&](const char* note) { if (progress) progress(++done, 3 + 4L * plans + 1 + episode_steps, note); };
        for (int i = 0; i < 3; ++i) planner.plan_into(world, plan), tick("warm-up");  // warm-up: workspaces take their sizes
        auto t0 = std::chrono::steady_clock::now();
        for (int i = 0; i < plans; ++i) planner.plan_into(world, plan), tick("first plans");
        const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        // The same first plans on `threads` threads, right after: a side-by-side ratio.
        madbp::set_num_threads(threads);
        for (int i = 0; i < 2; ++i) planner.plan_into(world, plan);  // the other threads' workspaces take their sizes
        auto p0 = std::chrono::steady_clock::now();
        for (int i = 0; i < plans; ++i) planner.plan_into(world, plan);
        const double threads_secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - p0).count();
        madbp::set_num_threads(1);
        const int scenes = planner.last_scene_batch().B, per_scene = planner.last_scene_batch().n;
        // Warm plans: each of `plans` plans the world one replan interval on (robots held still)
        // right after an untimed plan of the world itself, so it starts from that plan's windows.
        const int interval = choice.settings.follower.replan_every;
        const madbp::World later = held_still(world, interval);
        double warm_secs = 0;
        for (int i = 0; i < plans; ++i) {
            planner.plan_into(world, plan);
            auto w0 = std::chrono::steady_clock::now();
            planner.plan_into(later, plan);
            warm_secs += std::chrono::duration<double>(std::chrono::steady_clock::now() - w0).count();
            tick("warm plans");
        }
        // New worlds: what a plan costs when the team has just been given new goals (an episode's
        // first plan), the goal fields of the window cost's guidance included: `plans` worlds on
        // one thread, then as many others on `threads` threads, whose fields are made there too
        // (not the same worlds: on the empty map the planner would still hold their goals' fields).
        auto time_new_worlds = [&](int on_threads, uint64_t first_seed, const char* note, const char* next) {
            madbp::set_num_threads(on_threads);
            double total = 0;
            for (int i = 0; i < plans; ++i) {
                const madbp::World fresh = madbp::make_random_world(map, (int)n, first_seed + (uint64_t)i, half_size);
                auto f0 = std::chrono::steady_clock::now();
                planner.plan_into(fresh, plan);
                total += std::chrono::duration<double>(std::chrono::steady_clock::now() - f0).count();
                tick(i + 1 < plans ? note : next);
            }
            madbp::set_num_threads(1);
            return total;
        };
        const double new_secs = time_new_worlds(1, seed + 1, "new worlds", "new worlds on threads");
        const double new_threads_secs = time_new_worlds(threads, seed + 1 + (uint64_t)plans, "new worlds on threads", "the expert");
        const int drawn = planner.last_plan_candidates();  // candidates per scene (small plans draw more)
        const double ms = 1000 * secs / plans, growth = last_n > 0 && n > last_n ? std::log(ms / last_ms) / std::log((double)n / last_n) : NAN, warm_ms = 1000 * warm_secs / plans, new_ms = 1000 * new_secs / plans, rate = plan_flops(config, per_scene, first_steps) * scenes * drawn / (secs / plans) / 1e9;
        // The guided expert on the same world: mean ms per plan over `plans` / 5 plans (at least 3).
        madbp::GuidedExpert expert(world.map(), madbp::ExpertParams{}, madbp::passage_traffic());  // as eval's
        madbp::World ew = world;
        const int expert_plans = std::max(3, plans / 5);
        for (int i = 0; expert_row && i < expert_plans * madbp::ExpertParams{}.replan_every && !ew.done(); ++i) ew.step(expert.act(ew));
        const double expert_ms = expert_row ? expert.decision_ms() : NAN;
        tick("");
        if (scenes > 1) {  // one robot's own scene (plan_robot) among the others of the team (the largest team's is printed)
            std::vector<madbp::DiffusionPlanner::Neighbour> others;
            for (int j = 1; j < world.size(); ++j) others.push_back({world.agents()[j].pos, world.agents()[j].goal, world.agents()[j].id});
            std::vector<madbp::Vec2> window;
            const madbp::Agent& me = world.agents()[0];
            auto plan_robot_at = [&](long step) { planner.plan_robot(world.map(), me.id, me.pos, me.goal, others, window, step); };
            for (int i = 0; i < 3; ++i) plan_robot_at(-1);
            auto r0 = std::chrono::steady_clock::now();
            for (int i = 0; i < plans; ++i) plan_robot_at(-1);
            robot_ms = 1000 * std::chrono::duration<double>(std::chrono::steady_clock::now() - r0).count() / plans;
            // Warm: the robot's clock one replan interval on (robots held still), right after an untimed plan at step 0.
            double warm_secs = 0;
            for (int i = 0; i < plans; ++i) {
                plan_robot_at(0);
                auto w0 = std::chrono::steady_clock::now();
                plan_robot_at(interval);
                warm_secs += std::chrono::duration<double>(std::chrono::steady_clock::now() - w0).count();
            }
            robot_warm_ms = 1000 * warm_secs / plans;
            robot_K = per_scene;
            robot_n = n;
        }
        // The episode: a fresh planner, as eval's episodes start with, on the same world with eval's
        // step limit (or K steps if more); a team that finishes early runs fewer steps (episode_steps_run).
        double episode_ms = NAN, episode_max_ms = NAN;
        int episode_plans = 0, episode_steps_run = 0;
        if (episode_steps > 0) {
            first_planner.reset();
            madbp::DiffusionPlanner episode_planner(loaded.clone(), seed, choice.settings);
            madbp::PlanFollower follower = madbp::make_follower(episode_planner);
            madbp::WorldConfig limit;
            limit.max_steps = std::max(episode_steps, madbp::default_max_steps(half_size));
            madbp::World w = madbp::make_random_world(map, (int)n, seed, half_size, limit);
            for (int t = 0; t < episode_steps; ++t) {
                if (!w.done()) w.step(follower.act(w)), ++episode_steps_run;
                tick("episode steps");
            }
            episode_ms = follower.decision_ms(), episode_max_ms = follower.max_decision_ms(), episode_plans = follower.plans();
        }
        progress = nullptr;  // the line ends before the row
        if (json)
            std::printf("%s\n", Json().add("bench", "plan").add("map", map).add("agents", n).add("half_size", half_size).add("scenes", scenes).add("per_scene", per_scene).add("sample_steps", S)
                                    .add("guidance", sc.guidance).add("keep_right", sc.keep_right).add("candidates", drawn).add("warm_start", sc.warm_start).add("line_start", choice.settings.sampler.line_start ? 1 : 0).add("ms_per_plan", ms).add("warm_ms_per_plan", warm_ms).add("new_world_ms_per_plan", new_ms).add("expert_ms_per_plan", expert_ms).add("ms_per_robot", ms / n).add("growth", growth).add("threads", threads).add("threads_ms_per_plan", 1000 * threads_secs / plans).add("threads_speedup", secs / threads_secs).add("threads_new_world_ms_per_plan", 1000 * new_threads_secs / plans)
                                    .add("episode_steps", episode_steps).add("episode_steps_run", episode_steps_run).add("episode_plans", episode_plans).add("episode_ms_per_plan", episode_ms).add("episode_max_ms", episode_max_ms)
                                    .add("gflops", rate).add("gemm_gflops", gemm).add("share_of_gemm", rate / gemm).line().c_str());
        else {
            const std::string shape = std::to_string(scenes) + "x" + std::to_string(per_scene) + (drawn > 1 ? "x" + std::to_string(drawn) : "");
            std::printf("%4ld %6s %10.3f %10.3f %10.3f %10.3f %10.1f %7.0f%% %9.3f %6.2f %9.3f %6.2f %10.3f %10.3f %11.3f\n", n, shape.c_str(), ms, warm_ms, new_ms, expert_ms, rate, 100 * rate / gemm,
                        ms / n, growth, 1000 * threads_secs / plans, secs / threads_secs, 1000 * new_threads_secs / plans, episode_ms, episode_max_ms);
        }
        std::fflush(stdout);
        last_ms = ms, last_n = n;
    }
    if (robot_K > 0) {
        if (json)
            std::printf("%s\n", Json().add("bench", "plan_robot").add("agents", robot_n).add("per_scene", robot_K).add("ms_per_plan", robot_ms).add("warm_ms_per_plan", robot_warm_ms).line().c_str());
        else std::printf("one robot's own plan (plan_robot, a scene of K = %d among %ld robots): %.3f ms first, %.3f ms warm\n", robot_K, robot_n, robot_ms, robot_warm_ms);
    }
    return 0;
}

}  // namespace madbp_cli
