// plan_diffusion.cpp - plan a scene with the shipped MA-DBP diffusion model, print the result,
// draw it. The loop a simulator or robot runs: plan a window, follow it, replan every 4 steps.
//   build/plan_diffusion [examples/swap4.scene] [MODEL (default: madbp::default_model_path())] [out.svg]
#include <cstdio>

#include "madbp.hpp"

int main(int argc, char** argv) {
    const char* scene = argc > 1 ? argv[1] : "examples/swap4.scene";
    const char* out = argc > 3 ? argv[3] : "plan_diffusion.svg";
    try {
        madbp::set_num_threads(1);                                        // plans on one core
        madbp::World world = madbp::make_world(madbp::load_scene(scene));  // map + robots
        const std::string model = argc > 2 ? argv[2] : madbp::default_model_path();  // $MADBP_MODEL, the install, ./models
        madbp::DiffusionPlanner planner(madbp::load_model(model), /*seed=*/0);
        // The tracker and safety filter follow each window; a new one every 4 steps.
        madbp::PlanFollower follower([&](const madbp::World& w) { return planner.plan(w); });
        madbp::EpisodeLog log;
        log.map = world.map();
        log.record(world);
        while (!world.done()) {
            world.step(follower.act(world));  // one force per robot, then physics
            log.record(world);
        }
        const madbp::Metrics& m = world.metrics();
        std::printf("%s: %d robots, %s after %d steps, %ld collisions, %.2f ms per plan\n", scene, world.size(),
                    m.success ? "all at their goals" : "not all at their goals", m.steps, m.collisions(), follower.decision_ms());
        madbp::SvgOptions opt;
        opt.title = std::string(scene) + " (MA-DBP)";
        madbp::write_text_file(out, madbp::render_svg(log, opt));
        std::printf("wrote %s\n", out);
        return m.success ? 0 : 1;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "plan_diffusion: %s\n", e.what());
        return 2;
    }
}
