// Deploy large (issue 13): the Local scene frame, route subgoals, automatic neighbourhood
// planning and the decentralised per-robot plan (madbp.hpp "model inputs" and DiffusionPlanner;
// RouteGuide in madbp_sim.hpp Section 12; eval --decentralised in tool/methods_nn.hpp).
#include <doctest/doctest.h>

#include "madbp_train.hpp"
#include "tiny_model.hpp"

#include "alloc_counter_api.hpp"

using namespace madbp;

namespace {

ModelConfig local_config() {
    ModelConfig c = tiny_config();
    c.frame = SceneFrame::Local;
    c.subgoal_distance = 0.8f;
    c.n_train_max = 3;
    return c;
}

// A world of half-size 3.4 with a few obstacles and robots around `shift`, everything (but the
// walls, far away) moved by `shift`.
World shifted_world(Vec2 shift) {
    WorldMap map;
    map.half_size = 3.4;
    map.discs.push_back({Vec2{0.31, -0.17} + shift, 0.15});  // off the crops' cell lines
    map.boxes.push_back({Vec2{-0.63, 0.33} + shift, Vec2{-0.21, 0.41} + shift});
    World w(map);
    const Vec2 starts[5] = {{-0.53, -0.47}, {0.51, 0.49}, {0.03, 0.91}, {-0.89, 0.02}, {0.83, -0.71}};
    const Vec2 goals[5] = {{0.61, 0.58}, {-0.62, -0.57}, {0.01, -0.93}, {1.52, 0.23}, {-0.81, 0.79}};
    for (int i = 0; i < 5; ++i) w.add_agent(starts[i] + shift, goals[i] + shift);
    return w;
}

// The largest distance between two windows' waypoints at the same step.
double max_gap(const std::vector<Vec2>& a, const std::vector<Vec2>& b) {
    REQUIRE(a.size() == b.size());
    double w = 0;
    for (size_t t = 0; t < a.size(); ++t) w = std::max(w, norm(a[t] - b[t]));
    return w;
}

}  // namespace

TEST_CASE("large: a scene in the Local frame encodes the same when the whole world is translated") {
    ModelConfig c = local_config();
    c.subgoal_distance = 0;  // route subgoals sit on the route grid's cells, which do not move (below)
    // Exact in binary (positions stay exact after the shift) and a whole number of the guidance's
    // goal-field cells (0.04: the fields are fixed to the world, their 8-direction metric to the grid).
    const Vec2 shift{1.0, -1.0};
    World a = shifted_world({0, 0}), b = shifted_world(shift);
    DiffusionPlanner pa(MadbpModel(c, 3), 11), pb(MadbpModel(c, 3), 11);
    pa.settings.neighbourhood.cover = pb.settings.neighbourhood.cover = 0;  // a scene per robot
    const Plan plan_a = pa.plan(a), plan_b = pb.plan(b);
    const SceneBatch &sa = pa.last_scene_batch(), &sb = pb.last_scene_batch();
    REQUIRE(sa.B == 5);  // a larger world: a scene per robot
    REQUIRE(sa.n == 5);
    for (int s = 0; s < sa.B; ++s) {
        CHECK(sb.origin[s].x == doctest::Approx(sa.origin[s].x + shift.x));
        CHECK(sb.origin[s].y == doctest::Approx(sa.origin[s].y + shift.y));
    }
    CHECK(sa.grid == sb.grid);
    CHECK(sa.local == sb.local);
    CHECK(sa.agent_mask == sb.agent_mask);
    CHECK(sa.goal_final == sb.goal_final);
    CHECK((sa.pose - sb.pose).cwiseAbs().maxCoeff() < 1e-5f);
    // The same draw: every window is the same motion, moved by `shift`.
    for (int i = 0; i < 5; ++i)
        for (size_t t = 0; t < plan_a.waypoints[i].size(); ++t) {
            CHECK(plan_b.waypoints[i][t].x == doctest::Approx(plan_a.waypoints[i][t].x + shift.x).epsilon(1e-4));
            CHECK(plan_b.waypoints[i][t].y == doctest::Approx(plan_a.waypoints[i][t].y + shift.y).epsilon(1e-4));
        }
    // The World frame is not translation-invariant: positions are from the world's centre.
    ModelConfig w = c;
    w.frame = SceneFrame::World;
    DiffusionPlanner qa(MadbpModel(w, 3), 11), qb(MadbpModel(w, 3), 11);
    qa.plan(a);
    qb.plan(b);
    CHECK((qa.last_scene_batch().pose - qb.last_scene_batch().pose).cwiseAbs().maxCoeff() > 0.5f);
    // With route subgoals the goals move with the world up to the route grid's cell.
    ModelConfig r = local_config();
    DiffusionPlanner ra(MadbpModel(r, 3), 11), rb(MadbpModel(r, 3), 11);
    ra.plan(a);
    rb.plan(b);
    CHECK(ra.last_scene_batch().grid == rb.last_scene_batch().grid);
    CHECK((ra.last_scene_batch().pose - rb.last_scene_batch().pose).cwiseAbs().maxCoeff() < 1.5 * RouteGuide{}.cell / r.position_scale);
}

TEST_CASE("large: route subgoals lie on a collision-free way to the goal and within reach") {
    RouteGuide guide;
    int far = 0;
    for (uint64_t seed = 0; seed < 40; ++seed) {
        World w = make_random_world(seed % 2 ? "barrier" : "obstacles", 1, seed, seed % 4 < 2 ? 1.2 : 2.4);
        const WorldMap& map = w.map();
        Vec2 p = w.agents()[0].pos;
        const Vec2 goal = w.agents()[0].goal;
        const double D = 0.8;
        // Hop from subgoal to subgoal: each hop is a straight segment clear of the map by the
        // robot's radius and at most D (plus a cell) long, and the hops arrive at the goal.
        int hops = 0;
        for (; hops < 100; ++hops) {
            const RouteGoal r = guide.subgoal(map, p, goal, D);
            CHECK(norm(r.goal - p) <= D + 1.5 * guide.grid().cell);
            // (visibility is checked every half cell: between two checks the clearance may dip a little)
            for (int k = 0; k <= 50; ++k) CHECK(static_clearance(map, p + (r.goal - p) * (k / 50.0)) >= guide.view_clear - 0.01);
            if (r.final) {
                CHECK(r.goal == goal);
                break;
            }
            CHECK(norm(r.goal - p) > 0.05);  // progress
            p = r.goal;
        }
        CHECK(hops < 100);
        far += hops > 0;
    }
    CHECK(far > 20);  // most goals were beyond one subgoal
    // What the model is shown (route_goal): a goal behind a wall is shown D away toward the gap.
    WorldMap wall;
    wall.boxes.push_back({Vec2{-1.2, -0.05}, Vec2{0.2, 0.05}});
    wall.boxes.push_back({Vec2{0.7, -0.05}, Vec2{1.2, 0.05}});
    ModelConfig rc = local_config();
    rc.subgoal_distance = 1.5f;
    const Vec2 start{-0.6, -0.6};
    const RouteGoal hidden = route_goal(guide, rc, wall, start, {-0.6, 0.6});  // 1.2 away, behind the wall
    CHECK_FALSE(hidden.final);
    CHECK(norm(hidden.goal - start) == doctest::Approx(1.5));
    CHECK(hidden.goal.x - start.x > 0.5 * (hidden.goal.y - start.y));  // toward the gap at x in (0.2, 0.7)
    const RouteGoal seen = route_goal(guide, rc, wall, start, {0.3, -0.5});  // 0.9 away, in view
    CHECK(seen.final);
    CHECK(seen.goal == Vec2{0.3, -0.5});
    const RouteGoal far_seen = route_goal(guide, rc, WorldMap{}, {-1, -1}, {1, 1});  // in view but 2.8 away
    CHECK_FALSE(far_seen.final);
    CHECK(far_seen.goal.x == doctest::Approx(-1 + 1.5 / std::sqrt(2.0)).epsilon(0.05));
    // A goal within reach and in view is the goal itself; no subgoal model, no subgoals.
    CHECK(guide.subgoal(WorldMap{}, {0, 0}, {0.5, 0.2}, 0.8).final);
    ModelConfig c = tiny_config();
    const RouteGoal r = route_goal(guide, c, WorldMap{}, {-1, -1}, {1, 1});
    CHECK(r.final);
    CHECK(r.goal == Vec2{1, 1});
    CHECK_THROWS_WITH_AS(guide.subgoal(WorldMap{}, {0, 0}, {1, 0}, 0), doctest::Contains("distance"), std::invalid_argument);
}

TEST_CASE("large: automatic neighbourhood planning exactly when the world is larger than in training or the team than n_max") {
    ModelConfig c = local_config();  // n_train_max 3 (automatic K = 5), n_max 6, trained in half-size 1.2
    DiffusionPlanner p(MadbpModel(c, 1));
    CHECK(p.settings.neighbourhood.neighbours == -1);
    CHECK(p.neighbourhood(3, 1.2) == 3);  // as trained: one scene of the team
    CHECK(p.neighbourhood(1, 1.2) == 1);
    CHECK(p.neighbourhood(5, 1.2) == 5);  // a larger team in the training world: still one scene
    CHECK(p.neighbourhood(7, 1.2) == 5);  // more than n_max: scenes of K = ceil(1.5 n_train_max)
    CHECK(p.neighbourhood(2, 2.4) == 2);  // a larger world: a scene per robot, of the robots in range (at most K)
    CHECK(p.neighbourhood(5, 2.4) == 5);
    CHECK(p.neighbourhood(9, 2.4) == 5);
    {
        World w = make_random_world("empty", 2, 0, 2.4);
        p.plan(w);
        CHECK(p.last_scene_batch().B == 1);  // scenes that cover the team: one holds it all
        p.settings.neighbourhood.cover = 0;  // a scene per robot
        p.plan(w);
        CHECK(p.last_scene_batch().B == 2);
        p.settings.neighbourhood.cover = PlannerConfig{}.neighbourhood.cover;
    }
    {
        World w = make_random_world("empty", 5, 0);
        p.plan(w);
        CHECK(p.last_scene_batch().B == 1);
        CHECK(p.last_scene_batch().n == 5);
    }
    {
        World w = make_random_world("empty", 7, 0);
        p.plan(w);
        CHECK(p.last_scene_batch().B > 1);  // scenes that cover the team
        CHECK(p.last_scene_batch().B < 7);
        CHECK(p.last_scene_batch().n == 5);
        p.settings.neighbourhood.cover = 0;  // a scene per robot
        p.plan(w);
        CHECK(p.last_scene_batch().B == 7);
        p.settings.neighbourhood.cover = PlannerConfig{}.neighbourhood.cover;
    }
    p.settings.neighbourhood.neighbours = 0;  // asked for: the whole team, in any world
    CHECK(p.neighbourhood(5, 2.4) == 5);
    {
        World w = make_random_world("empty", 2, 0, 2.4);
        p.plan(w);
        CHECK(p.last_scene_batch().B == 1);
    }
    p.settings.neighbourhood.neighbours = 2;
    CHECK(p.neighbourhood(5, 1.2) == 2);
    p.settings.neighbourhood.neighbours = -2;
    CHECK_THROWS_WITH_AS(p.neighbourhood(5, 1.2), doctest::Contains("neighbours"), std::invalid_argument);
    // Unknown n_train_max (an older checkpoint): K = n_max.
    ModelConfig old = tiny_config();
    DiffusionPlanner q(MadbpModel(old, 1));
    CHECK(q.neighbourhood(6, 1.2) == 6);
    CHECK(q.neighbourhood(7, 1.2) == 6);
    CHECK(q.neighbourhood(4, 2.4) == 4);
}

TEST_CASE("large: the new model fields round-trip through checkpoints; a 0.1 checkpoint reads as the World frame") {
    const ModelConfig c = local_config();
    const std::string path = "test_large_model.safetensors";
    save_model(path, MadbpModel(c, 1));
    const ModelConfig back = load_model(path).config;
    CHECK(back.frame == SceneFrame::Local);
    CHECK(back.subgoal_distance == doctest::Approx(0.8));
    CHECK(back.n_train_max == 3);
    auto md = c.to_metadata();
    md.erase("frame");
    md.erase("subgoal_distance");
    md.erase("train.n_train_max");
    const ModelConfig old = ModelConfig::from_metadata(md, "old");
    CHECK(old.frame == SceneFrame::World);
    CHECK(old.subgoal_distance == 0);
    CHECK(old.n_train_max == 0);
    md["frame"] = "polar";
    CHECK_THROWS_WITH_AS(ModelConfig::from_metadata(md, "bad"), doctest::Contains("'frame'"), std::runtime_error);
    std::remove(path.c_str());
}

TEST_CASE("large: a checkpoint with the removed velocity or priority context loads only when it is off") {
    const std::string path = "test_large_removed.safetensors";
    const MadbpModel model(local_config(), 1);
    for (const char* key : {"velocity_context", "priority_context"}) {
        save_model(path, model, {{key, "0"}});  // 0 is the default: read as a file without the key
        const MadbpModel off = load_model(path);
        CHECK(off.config.to_metadata() == model.config.to_metadata());
        CHECK(off.params->value == model.params->value);
        save_model(path, model, {{key, "1"}});  // a model trained with it needs inputs the planner no longer gives
        const std::string removed = path + ": metadata field '" + key + "' = 1: the option was removed in release 0.3";
        CHECK_THROWS_WITH_AS(load_model(path), doctest::Contains(removed.c_str()), std::runtime_error);
        save_model(path, model, {{key, "yes"}});
        const std::string malformed = std::string("'") + key + "' must be 0 or 1";
        CHECK_THROWS_WITH_AS(load_model(path), doctest::Contains(malformed.c_str()), std::runtime_error);
    }
    std::remove(path.c_str());
}

TEST_CASE("large: a robot planning for itself gets the window the team plan gives it (same seed)") {
    World world = make_random_world("obstacles", 5, 4, 2.4);
    for (bool conflict_aware : {false, true}) {
        const ModelConfig c = local_config();
        DiffusionPlanner team(MadbpModel(c, 2), 9);
        team.settings.neighbourhood.cover = 0;  // a scene per robot, as plan_robot's
        if (conflict_aware) team.settings.guidance.weight = 0.004f, team.settings.sampler.candidates = 2;
        const Plan plan = team.plan(world);
        for (int i = 0; i < world.size(); ++i) {
            DiffusionPlanner robot(MadbpModel(c, 2), 9);
            robot.settings = team.settings;
            std::vector<DiffusionPlanner::Neighbour> others;
            for (int j = 0; j < world.size(); ++j)
                if (j != i) others.push_back({world.agents()[j].pos, world.agents()[j].goal, world.agents()[j].id});
            std::vector<Vec2> window;
            const Agent& me = world.agents()[i];
            robot.plan_robot(world.map(), me.id, me.pos, me.goal, others, window);
            CHECK(max_gap(window, plan.waypoints[i]) < 1e-4);  // one scene alone vs in a batch: the same numbers up to float summation order
        }
    }
    DiffusionPlanner robot(MadbpModel(local_config(), 2), 9);
    std::vector<Vec2> window;
    CHECK_THROWS_WITH_AS(robot.plan_robot(world.map(), 0, {0, 0}, {1, 1}, {{Vec2{NAN, 0}, Vec2{0, 0}}}, window),
                         doctest::Contains("neighbour 0"), std::invalid_argument);
}

TEST_CASE("large: neighbourhood planning in the Local frame allocates nothing once sizes are steady") {
    set_num_threads(1);  // Eigen's own threaded GEMM allocates per call
    for (double crowd_weight : {0.0, 0.04}) {  // and with routes around crowds (they act here: 7 robots, half-size 2.4)
        CAPTURE(crowd_weight);
        DiffusionPlanner planner(MadbpModel(local_config(), 2), 3);  // route subgoals and guidance on
        planner.settings.traffic.crowd_weight = crowd_weight;
        planner.settings.traffic.crowd_density = 0;  // 7 robots in half-size 2.4 are sparser than a crowd
        World w = make_random_world("obstacles", 7, 1, 2.4);
        Plan plan;
        for (int i = 0; i < 2; ++i) planner.plan_into(w, plan);
        REQUIRE(planner.last_scene_batch().B > 1);
        [[maybe_unused]] const long allocs = count_allocs([&] { for (int i = 0; i < 3; ++i) planner.plan_into(w, plan); });
#if MADBP_TEST_COUNT_ALLOCS
        CHECK(allocs == 0);
#endif
        CHECK(plan.ids.size() == 7);
    }
}

TEST_CASE("large: circle swaps of up to kMaxCircleAgents robots are valid scenes") {
    for (int n : {8, 12, 16})
        for (uint64_t seed = 0; seed < 5; ++seed) {
            const double half = n > 12 ? 2.4 : 1.2;
            World w = make_interaction_world("circle", "empty", n, seed, half);
            REQUIRE(w.size() == n);
            const Vec2 centre = (w.agents()[0].pos + w.agents()[0].goal) * 0.5;
            for (int i = 0; i < n; ++i) {
                const Agent& a = w.agents()[i];
                CHECK(norm((a.pos + a.goal) * 0.5 - centre) < 1e-9);  // antipodal: every swap through one centre
                CHECK(static_clearance(w.map(), a.pos) >= 0.16);
                for (int j = i + 1; j < n; ++j) CHECK(norm(a.pos - w.agents()[j].pos) >= 0.25);
            }
        }
    CHECK_THROWS_AS(make_interaction_world("circle", "empty", kMaxCircleAgents + 1, 0, 3.4), std::invalid_argument);
    CHECK_THROWS_AS(make_interaction_world("swap", "empty", kMaxScenarioAgents + 1, 0), std::invalid_argument);
}

TEST_CASE("large: plan_robot starts from its last windows when given its clock, as the team plan does") {
    const ModelConfig c = local_config();
    World world = make_random_world("obstacles", 3, 4, 2.4);
    auto others_of = [](const World& w, int i, bool reversed) {
        std::vector<DiffusionPlanner::Neighbour> others;
        for (int j = 0; j < w.size(); ++j)
            if (j != i) others.push_back({w.agents()[j].pos, w.agents()[j].goal, w.agents()[j].id});
        if (reversed) std::reverse(others.begin(), others.end());
        return others;
    };
    const World start = world;
    const int kWarm = 2, kElapsed = 3;  // of the tiny model's 5 DDIM steps; within its window of 7 waypoints
    DiffusionPlanner team(MadbpModel(c, 2), 9);
    team.settings.neighbourhood.cover = 0;  // a scene per robot, as plan_robot's
    team.settings.neighbourhood.sensing_radius = 0.2;  // every robot alone in its scene: its warm window is its own last one in both
    team.settings.sampler.warm_start = kWarm;
    team.settings.sampler.line_start = false;  // without last windows, from noise (line_start's own test is in test_interaction)
    team.plan(world);
    for (int k = 0; k < kElapsed; ++k) world.step(std::vector<Vec2>(world.size(), Vec2{0.3, -0.2}));
    const Plan warm_plan = team.plan(world);
    // Robot i's two plans, at step 0 and then at `second_step`, with its neighbours as told.
    auto robot_plans = [&](int i, double radius, long second_step, bool reversed, int unknown_id = 0) {
        DiffusionPlanner robot(MadbpModel(c, 2), 9);
        robot.settings.neighbourhood.sensing_radius = radius;
        robot.settings.sampler.warm_start = kWarm;
        robot.settings.sampler.line_start = false;
        std::vector<Vec2> window;
        const Agent &me0 = start.agents()[i], &me = world.agents()[i];
        robot.plan_robot(start.map(), me0.id, me0.pos, me0.goal, others_of(start, i, reversed), window, 0);
        auto others = others_of(world, i, reversed);
        if (unknown_id) others[0].id = -1;
        robot.plan_robot(world.map(), me.id, me.pos, me.goal, others, window, second_step);
        return window;
    };
    for (int i = 0; i < world.size(); ++i) {
        CHECK(max_gap(robot_plans(i, 0.2, kElapsed, false), warm_plan.waypoints[i]) < 1e-4);
        CHECK(max_gap(robot_plans(i, 0.2, -1, false), warm_plan.waypoints[i]) > 1e-3);  // cold differs: the warm start acts
        // With its neighbours in the scene, their windows are the ones this robot drew for them, found by id.
        const auto warm = robot_plans(i, 0, kElapsed, false), cold = robot_plans(i, 0, -1, false);
        CHECK(max_gap(robot_plans(i, 0, kElapsed, true), warm) < 1e-6);
        CHECK(max_gap(warm, cold) > 1e-5);  // the same computation otherwise: equal to 1e-6 below
        CHECK(max_gap(robot_plans(i, 0, 0, false), cold) < 1e-6);        // a clock that did not move on draws cold
        CHECK(max_gap(robot_plans(i, 0, kElapsed, false, 1), cold) < 1e-6);     // so does a neighbour without an id
    }
    DiffusionPlanner robot(MadbpModel(c, 2), 9);
    std::vector<Vec2> window;
    CHECK_THROWS_WITH_AS(robot.plan_robot(world.map(), 0, {0, 0}, {1, 1}, {}, window, -2), doctest::Contains("step"), std::invalid_argument);
}

TEST_CASE("large: DecentralisedTeam plans each robot with plan_robot: first as the team's neighbourhood plan, then warm") {
    const ModelConfig c = local_config();
    auto model = std::make_shared<const MadbpModel>(c, 2);
    PlannerConfig options;
    options.sampler.warm_start = 2;  // of the tiny model's 5 DDIM steps
    options.neighbourhood.cover = 0;  // the team plans a scene per robot, as plan_robot does
    World world = make_random_world("obstacles", 3, 4, 2.4);  // a larger world: the team plans a scene per robot
    const World start = world;
    DecentralisedTeam robots(model, options, 9);
    DiffusionPlanner team(model->clone(), 9, options);
    const Plan first = robots.plan(world), team_first = team.plan(world);
    REQUIRE(first.ids == team_first.ids);
    for (int i = 0; i < world.size(); ++i) CHECK(max_gap(first.waypoints[i], team_first.waypoints[i]) < 1e-4);
    // Three steps on, each robot starts from its last windows: the plan differs from a cold team's.
    for (int k = 0; k < 3; ++k) world.step(std::vector<Vec2>(world.size(), Vec2{0.3, -0.2}));
    const Plan second = robots.plan(world);
    PlannerConfig cold_options = options;
    cold_options.sampler.warm_start = 0;
    DecentralisedTeam cold(model, cold_options, 9);
    cold.plan(start);
    const Plan cold_second = cold.plan(world);
    double gap = 0;
    for (int i = 0; i < world.size(); ++i) gap = std::max(gap, max_gap(second.waypoints[i], cold_second.waypoints[i]));
    CHECK(gap > 1e-5);
}

TEST_CASE("large: DecentralisedTeam asks for the team's next plan when a robot's planner asks (one waits at a passage)") {
    // A wall across the world with a one-lane corridor through its middle; two robots head-on.
    WorldMap map;
    const double h = map.half_size;
    map.boxes = {{{-h, -0.05}, {-0.22, 0.05}}, {{0.22, -0.05}, {h, 0.05}}, {{-0.32, -0.4}, {-0.22, 0.4}}, {{0.22, -0.4}, {0.32, 0.4}}};
    World world(map);
    world.add_agent({0, -0.7}, {0, 0.9});
    world.add_agent({0, 0.9}, {0, -0.9});
    auto model = std::make_shared<const MadbpModel>(local_config(), 2);
    for (int after : {0, 3}) {
        PlannerConfig options;
        options.traffic.passage_replan = after;
        DecentralisedTeam robots(model, options, 9);
        CHECK(robots.plan(world).replan_after == after);
    }
}
