// consumer.cpp - what a downstream project writes after installing madbp: plan one scene with the
// installed default model. default_model_path() finds it through MADBP_MODEL_DIR, which the
// package defines (CMake target or madbp.pc).
// Built by tests/consumer/cmake (find_package) and tests/consumer/pkgconfig (a plain Makefile).
#include <cstdio>

#include "madbp.hpp"

int main() {
    madbp::World world = madbp::make_random_world("empty", 4, /*seed=*/0);
    const std::string model = madbp::default_model_path();
    madbp::DiffusionPlanner planner(madbp::load_model(model));
    madbp::Plan plan = planner.plan(world);
    madbp::validate_plan(plan, world);  // throws unless every robot got finite waypoints
    std::printf("madbp %d.%d.%d: planned %zu robots, %zu waypoints each, first (%.3f, %.3f), model %s\n", MADBP_VERSION_MAJOR,
                MADBP_VERSION_MINOR, MADBP_VERSION_PATCH, plan.ids.size(), plan.waypoints[0].size(), plan.waypoints[0][0].x,
                plan.waypoints[0][0].y, model.c_str());
    return 0;
}
