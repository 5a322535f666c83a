// plan_scene.cpp - plan a scene file with the guided expert, print the result, draw it.
//   build/plan_scene [examples/swap4.scene] [out.svg]
#include <cstdio>

#include "madbp_sim.hpp"

int main(int argc, char** argv) {
    const char* path = argc > 1 ? argv[1] : "examples/swap4.scene";
    const char* out = argc > 2 ? argv[2] : "plan_scene.svg";
    try {
        madbp::World world = madbp::make_world(madbp::load_scene(path));  // map + robots
        madbp::GuidedExpert expert(world.map());                          // the planner
        madbp::EpisodeLog log;
        log.map = world.map();
        log.record(world);
        while (!world.done()) {
            world.step(expert.act(world));  // one force per robot, then physics
            log.record(world);
        }
        const madbp::Metrics& m = world.metrics();
        std::printf("%s: %d robots, %s after %d steps, %ld collisions, %.2f ms per plan\n", path, world.size(),
                    m.success ? "all at their goals" : "not all at their goals", m.steps, m.collisions(), expert.decision_ms());
        madbp::SvgOptions opt;
        opt.title = path;
        madbp::write_text_file(out, madbp::render_svg(log, opt));
        std::printf("wrote %s\n", out);
        return m.success ? 0 : 1;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "plan_scene: %s\n", e.what());
        return 2;
    }
}
