// bench_alloc.cpp - heap allocations per diffusion plan once sizes are steady (SPEC 9: none).
// A program of its own because it replaces malloc and operator new (tests/alloc_counter.hpp);
// the shipped tool keeps the system allocator.
//   build/bench_alloc [--model FILE] [--agents 1,2,4,8,16,32,64] [--plans N] [--set GROUP.NAME=VALUE ...] [--json]
// --model's default is the shipped model (default_model_path), as for eval and bench --plan.
// Worlds as bench --plan's: empty, at constant density (madbp::default_half_size); plans
// alternate between a world and the same world 8 steps on, cold and warm-started.
#include <cstdio>

#include "cli_common.hpp"
#include "madbp.hpp"

#include "alloc_counter.hpp"  // after the system headers it redeclares

using namespace madbp_cli;

int main(int argc, char** argv) {
    try {
        Args a(argc, argv, 1);
        std::string model_path = a.str("--model", "");
        if (model_path.empty()) model_path = madbp::default_model_path();  // throws, naming the places tried, only when needed
        std::vector<long> teams = a.integers("--agents", "1,2,4,8,16,32,64", 1, kMaxTeam);
        int plans = (int)a.integer("--plans", 10, 1, 1000000);
        madbp::PlannerConfig settings;  // tuned; --set changes any setting
        apply_planner_settings(a, settings);
        bool json = a.flag("--json");
        a.finish();
        if (!MADBP_TEST_COUNT_ALLOCS) throw std::runtime_error("built with a sanitizer that owns malloc: nothing can be counted");
        madbp::set_num_threads(1);
        if (!json) std::printf("alloc bench: %s\n%4s %12s\n", model_path.c_str(), "n", "allocs/plan");
        for (long n : teams) {
            madbp::DiffusionPlanner planner(madbp::load_model(model_path), 0, settings);
            madbp::World world = madbp::make_random_world("empty", (int)n, 0, madbp::default_half_size((int)n));
            const madbp::World later = held_still(world, 8);  // its plans are warm-started
            madbp::Plan plan;
            auto cold_then_warm = [&] { planner.plan_into(world, plan); planner.plan_into(later, plan); };
            for (int i = 0; i < 3; ++i) cold_then_warm();  // warm-up: workspaces take their sizes
            const double per_plan = (double)count_allocs([&] { for (int i = 0; i < plans; ++i) cold_then_warm(); }) / (2.0 * plans);
            if (json) std::printf("%s\n", Json().add("bench", "alloc").add("agents", n).add("allocs_per_plan", per_plan).line().c_str());
            else std::printf("%4ld %12.1f\n", n, per_plan);
        }
        return 0;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_alloc: %s\n", e.what());
        return 2;
    }
}
