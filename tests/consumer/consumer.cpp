// consumer.cpp - what a downstream project writes after installing madbp: plan one scene with the
// installed default model. MADBP_MODEL_DIR comes from the package (CMake target or madbp.pc).
// Built by tests/consumer/cmake (find_package) and tests/consumer/pkgconfig (a plain Makefile).
#include <cstdio>

#include "madbp.hpp"

int main() {
    madbp::World world = madbp::make_random_world("empty", 4, /*seed=*/0);
    madbp::DiffusionPlanner planner(madbp::load_model(MADBP_MODEL_DIR "/madbp-default.safetensors"));
    madbp::Plan plan = planner.plan(world);
    madbp::validate_plan(plan, world);  // throws unless every robot got finite waypoints
    std::printf("madbp %d.%d.%d: planned %zu robots, %zu waypoints each, first (%.3f, %.3f), model %s\n", MADBP_VERSION_MAJOR,
                MADBP_VERSION_MINOR, MADBP_VERSION_PATCH, plan.ids.size(), plan.waypoints[0].size(), plan.waypoints[0][0].x,
                plan.waypoints[0][0].y, MADBP_MODEL_DIR);
    return 0;
}
