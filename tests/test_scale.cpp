// Planning large teams (issue 47): scenes that cover the team, sampled in chunks on threads with
// the same results on any number of them, in a bounded workspace (madbp.hpp Section 9); routes
// around crowds (CrowdRoutes, Section 8).
#include <doctest/doctest.h>

#include "madbp.hpp"
#include "madbp_sim.hpp"
#include "tiny_model.hpp"

using namespace madbp;

namespace {
// Restores OpenMP's thread count for the tests that follow in the same binary.
struct ThreadCountGuard {
#ifdef _OPENMP
    int threads = omp_get_max_threads();
    ~ThreadCountGuard() { omp_set_num_threads(threads); }
#endif
};

// Two plans (a first one and a warm one 4 steps on) of a 24-robot world with `threads` threads.
// `subgoals`: the model heads for route subgoals (subgoal_distance 0.6), which robots within
// RouteGuide::near_reach of their goals walk on the threads, each with its own guide.
std::vector<Plan> plans_with(int threads, int chunk_scenes, int cover, bool subgoals = false) {
    set_num_threads(threads);
    ModelConfig c = tiny_config();
    if (subgoals) c.subgoal_distance = 0.6f;
    DiffusionPlanner planner(MadbpModel(c, 3), 17);  // K = n_max = 6; guidance and goal fields on
    planner.settings.workspace.chunk_scenes = chunk_scenes;
    planner.settings.neighbourhood.cover = cover;
    World w = make_random_world("obstacles", 24, 5, 2.4);
    std::vector<Plan> out{planner.plan(w)};
    for (int k = 0; k < 4; ++k) w.step(std::vector<Vec2>(w.size(), Vec2{0.2, 0.1}));
    out.push_back(planner.plan(w));
    return out;
}
}  // namespace

TEST_CASE("scale: a plan on 2 threads is the plan on one, bit for bit") {
    ThreadCountGuard restore;
    for (int chunk : {2, 1024})      // several chunks (one per thread at a time), and the whole batch as one
        for (int cover : {3, 0})     // scenes that cover the team, and a scene per robot
            for (bool subgoals : {false, true}) {  // heading for goals, or for route subgoals
                CAPTURE(chunk);
                CAPTURE(cover);
                CAPTURE(subgoals);
                const std::vector<Plan> one = plans_with(1, chunk, cover, subgoals), two = plans_with(2, chunk, cover, subgoals);
                for (size_t p = 0; p < one.size(); ++p) {
                    REQUIRE(one[p].ids == two[p].ids);
                    bool same = true;
                    for (size_t i = 0; i < one[p].waypoints.size(); ++i)
                        for (size_t t = 0; t < one[p].waypoints[i].size(); ++t)
                            same = same && one[p].waypoints[i][t].x == two[p].waypoints[i][t].x && one[p].waypoints[i][t].y == two[p].waypoints[i][t].y;
                    CHECK(same);
                }
            }
    // The chunk size is arithmetic, not only scheduling: the windows stay close across sizes.
    const std::vector<Plan> small = plans_with(1, 2, 3), whole = plans_with(1, 1024, 3);
    double gap = 0;
    for (size_t i = 0; i < small[0].waypoints.size(); ++i)
        for (size_t t = 0; t < small[0].waypoints[i].size(); ++t) gap = std::max(gap, norm(small[0].waypoints[i][t] - whole[0].waypoints[i][t]));
    CHECK(gap < 1e-3);
}

TEST_CASE("scale: scenes that cover the team give every robot a window, from a scene it is in") {
    const ModelConfig c = tiny_config();
    for (int n : {1, 5, 6, 7, 24, 40})
        for (int cover : {1, 2, 3, 6})
          for (double radius : {0.0, 10.0}) {  // the default sensing radius, and one that sees everyone
            CAPTURE(n);
            CAPTURE(cover);
            CAPTURE(radius);
            DiffusionPlanner planner(MadbpModel(c, 1), 4);
            planner.settings.neighbourhood.cover = cover;
            planner.settings.neighbourhood.sensing_radius = radius;
            planner.settings.workspace.chunk_scenes = 3;
            const World w = make_random_world("empty", n, 2, 2.4);
            const Plan p = planner.plan(w);
            const SceneBatch& b = planner.last_scene_batch();
            REQUIRE((int)p.waypoints.size() == n);
            std::vector<int> kept(b.agents(), 0);
            for (int i = 0; i < n; ++i) {
                const int a = planner.last_window_agent(i);
                REQUIRE(a >= 0);
                REQUIRE(a < b.agents());
                CHECK(b.agent_mask[a] == 1.0f);
                CHECK(norm(b.position(a, c) - w.agents()[i].pos) < 1e-5);  // the robot's own slot
                CHECK(++kept[a] == 1);                                    // no window given twice
                for (Vec2 q : p.waypoints[i]) CHECK((std::isfinite(q.x) && std::isfinite(q.y)));
            }
            // Each scene keeps at most `cover` windows unless it holds the whole team, and at least one.
            for (int s = 0; s < b.B; ++s) {
                int windows = 0;
                for (int k = 0; k < b.n; ++k) windows += kept[s * b.n + k];
                CHECK(windows >= 1);
                CHECK((windows <= cover || b.count[s] == n));
            }
            if (n <= b.n && radius > 0) CHECK(b.B == 1);  // a team within one neighbourhood: one scene
            if (n > b.n && cover > 1) CHECK(b.B < n);
        }
    // A scene per robot (cover 0, the paper preset's): n scenes, robot i's window from slot 0 of scene i.
    DiffusionPlanner per_robot(MadbpModel(c, 1), 4, PlannerConfig::paper());
    const World w = make_random_world("empty", 9, 2, 2.4);
    per_robot.plan(w);
    CHECK(per_robot.last_scene_batch().B == 9);
    for (int i = 0; i < 9; ++i) CHECK(per_robot.last_window_agent(i) == i * per_robot.last_scene_batch().n);
}

TEST_CASE("scale: the planner's workspace is bounded by its chunks, linear in the team, and checked before a plan") {
    const ModelConfig c = tiny_config();
    // Linear in the scenes; one chunk's activations per thread, whatever the team.
    const double b0 = planner_workspace_bytes(c, 100, 6, 1, 8, 1), b1 = planner_workspace_bytes(c, 200, 6, 1, 8, 1),
                 b2 = planner_workspace_bytes(c, 400, 6, 1, 8, 1);
    CHECK(b2 - b1 == doctest::Approx(2 * (b1 - b0)));
    CHECK(planner_workspace_bytes(c, 400, 6, 1, 400, 1) > 10 * b2);  // without chunks it grows with the batch
    CHECK(planner_workspace_bytes(c, 400, 6, 1, 8, 2) > b2);          // a chunk per thread
    // A plan over the limit is refused before it allocates, naming the setting.
    DiffusionPlanner planner(MadbpModel(c, 1), 4);
    const World w = make_random_world("empty", 24, 2, 2.4);
    planner.settings.workspace.max_mb = 1;
    planner.settings.workspace.chunk_scenes = 1024;
    CHECK_THROWS_WITH_AS(planner.plan(w), doctest::Contains("workspace.max_mb"), std::invalid_argument);
    planner.settings.workspace.chunk_scenes = 2;  // small chunks fit
    CHECK(planner.plan(w).ids.size() == 24);
    planner.settings.workspace.chunk_scenes = 0;
    CHECK_THROWS_WITH_AS(planner.plan(w), doctest::Contains("workspace.chunk_scenes"), std::invalid_argument);
}

namespace {
// CrowdRoutes' targets for robots 0..n-1 in an empty world (half-size 4.8: 16 coarse cells of 0.6).
std::vector<Vec2> crowd_targets(const std::vector<Vec2>& pos, const std::vector<Vec2>& goal, const TrafficConfig& traffic,
                                long step = 0, CrowdRoutes* routes = nullptr, double half_size = 4.8) {
    CrowdRoutes own;
    CrowdRoutes& cr = routes ? *routes : own;
    RouteGuide guide;
    WorldMap map;
    map.half_size = half_size;
    const int n = (int)pos.size();
    std::vector<char> at_goal(n, 0);
    std::vector<int> ids(n);
    for (int i = 0; i < n; ++i) ids[i] = 10 + i;
    std::vector<Vec2> target;
    cr.update(guide, map, traffic, n, pos.data(), goal.data(), at_goal.data(), ids.data(), step, target);
    return target;
}
std::vector<Vec2> crowd_targets(const std::vector<Vec2>& pos, const std::vector<Vec2>& goal, double weight, long step = 0,
                                CrowdRoutes* routes = nullptr) {
    TrafficConfig traffic;
    traffic.crowd_weight = weight;
    return crowd_targets(pos, goal, traffic, step, routes);
}
}  // namespace

TEST_CASE("crowds: a robot whose straight way runs through others' routes goes around them, and only then") {
    // 24 robots cross the world west to east near y = 0, routed first; the last one crosses there too.
    std::vector<Vec2> pos, goal;
    for (int k = 0; k < 24; ++k) pos.push_back({-4.0, -0.25 + 0.02 * k}), goal.push_back({4.0, -0.25 + 0.02 * k});
    pos.push_back({-4.0, 0.0}), goal.push_back({4.0, 0.0});
    const std::vector<Vec2> around = crowd_targets(pos, goal, 0.5);
    CHECK(around[0] == goal[0]);                       // the first robot routed has the world to itself
    CHECK(!(around.back() == goal.back()));
    CHECK(std::fabs(around.back().y) > 0.25);          // the last goes around the lane the others fill (y in [-0.25, 0.21])
    CHECK(around.back().x > pos.back().x);              // still on its way east
    const std::vector<Vec2> straight = crowd_targets(pos, goal, 1e-6);
    for (size_t i = 0; i < pos.size(); ++i) CHECK(straight[i] == goal[i]);  // no crowd worth a detour: every robot heads for its goal
    // The same inputs give the same targets (routes depend on positions, goals, ids and the step only).
    CHECK(crowd_targets(pos, goal, 0.5) == around);
    // Kept between calls: a robot keeps its route as it goes along it, until kCrowdReroute steps pass.
    CrowdRoutes routes;
    crowd_targets(pos, goal, 0.5, 0, &routes);
    std::vector<Vec2> moved = pos;
    moved.back() = around.back();
    const std::vector<Vec2> later = crowd_targets(moved, goal, 0.5, 8, &routes);
    CHECK(later.back().x > around.back().x);  // the next point along the same detour
    CHECK(std::fabs(later.back().y) > 0.25);
}

TEST_CASE("crowds: a route is kept between plans where the world is not a whole number of coarse cells") {
    // Half-size 3.4: 12 cells of 0.567 for crowd_cell 0.6. The last robot is routed around the
    // lane the others fill; two steps later they have all arrived, and its route, kept, still goes around.
    std::vector<Vec2> pos, goal;
    for (int k = 0; k < 24; ++k) pos.push_back({-3.0, -0.25 + 0.02 * k}), goal.push_back({3.0, -0.25 + 0.02 * k});
    pos.push_back({-3.0, 0.0}), goal.push_back({3.0, 0.0});
    TrafficConfig traffic;
    traffic.crowd_weight = 0.5;
    CrowdRoutes routes;
    const Vec2 around = crowd_targets(pos, goal, traffic, 0, &routes, 3.4).back();
    REQUIRE(!(around == goal.back()));
    std::vector<Vec2> arrived = goal;
    arrived.back() = pos.back();
    CHECK(crowd_targets(arrived, goal, traffic, 2, &routes, 3.4).back() == around);        // kept: the same route point
    CHECK(crowd_targets(arrived, goal, traffic, 2, nullptr, 3.4).back() == goal.back());   // made now: straight
    // ... until kCrowdReroute steps pass: then it is made again, against the team as it stands.
    CHECK(crowd_targets(arrived, goal, traffic, CrowdRoutes::kCrowdReroute, &routes, 3.4).back() == goal.back());
}

TEST_CASE("crowds: with crowd_time, a robot goes around only the routes due where it crosses when it is") {
    // 24 robots go east from x = -1 along y near 0: they pass x = 0 about 28-45 steps from now.
    std::vector<Vec2> pos, goal;
    for (int k = 0; k < 24; ++k) pos.push_back({-1.0, -0.25 + 0.02 * k}), goal.push_back({4.0, -0.25 + 0.02 * k});
    // The last crosses their lane at x = 0, going south: from y = 4.5 it is due there after ~125
    // steps, long after them; from y = 1.2, with them.
    auto last_target = [&](double from_y, double crowd_time) {
        std::vector<Vec2> p = pos, g = goal;
        p.push_back({0.0, from_y}), g.push_back({0.0, -4.0});
        TrafficConfig traffic;
        traffic.crowd_weight = traffic.crowd_time_weight = 0.5;
        traffic.crowd_time = crowd_time, traffic.crowd_time_from = 1;  // in time in any team
        return crowd_targets(p, g, traffic).back();
    };
    const Vec2 south{0.0, -4.0};
    CHECK(!(last_target(4.5, 0) == south));   // routes counted whenever: it goes around the lane
    CHECK(last_target(4.5, 10) == south);     // counted when they are due: the lane is clear by then
    CHECK(!(last_target(1.2, 10) == south));  // due together: it goes around
}

TEST_CASE("crowds: teams of crowd_time_from robots or more count routes in time; smaller ones wherever they pass") {
    // The crossing above: counted whenever, the late robot goes around the lane; in time, it
    // goes straight. The defaults count in time from 512 robots: 25 here count wherever.
    std::vector<Vec2> pos, goal;
    for (int k = 0; k < 24; ++k) pos.push_back({-1.0, -0.25 + 0.02 * k}), goal.push_back({4.0, -0.25 + 0.02 * k});
    pos.push_back({0.0, 4.5}), goal.push_back({0.0, -4.0});
    TrafficConfig traffic;
    traffic.crowd_weight = traffic.crowd_time_weight = 0.5;
    CHECK(traffic.crowd_time > 0);
    CHECK(traffic.crowd_time_from > 25);
    const Vec2 whenever = crowd_targets(pos, goal, traffic).back();
    CHECK(!(whenever == goal.back()));
    traffic.crowd_time_from = 25;
    CHECK(crowd_targets(pos, goal, traffic).back() == goal.back());  // 25 robots: in time
    traffic.crowd_time_from = 26;
    CHECK(crowd_targets(pos, goal, traffic).back() == whenever);
    traffic.crowd_time_from = 1, traffic.crowd_time = 0;              // crowd_time 0: wherever, in every team
    CHECK(crowd_targets(pos, goal, traffic).back() == whenever);
}

TEST_CASE("crowds: with crowd_detour, a detour longer than that times the straight way is not taken") {
    // 24 robots fill a lane from x = -3 to 4 near y = 0; the last crosses it at x = 0, going
    // south. The way around the lane's west end is about 11 against 8.5 straight across.
    std::vector<Vec2> pos, goal;
    for (int k = 0; k < 24; ++k) pos.push_back({-3.0, -0.25 + 0.02 * k}), goal.push_back({4.0, -0.25 + 0.02 * k});
    pos.push_back({0.0, 4.5}), goal.push_back({0.0, -4.0});
    TrafficConfig traffic;
    traffic.crowd_weight = 0.5;
    const Vec2 around = crowd_targets(pos, goal, traffic).back();
    CHECK(!(around == goal.back()));
    CHECK(around.x < -0.6);                                       // around the west end
    traffic.crowd_detour = 1.6;
    CHECK(crowd_targets(pos, goal, traffic).back().x < -0.6);     // within 1.6 times: taken
    traffic.crowd_detour = 1.1;
    CHECK(crowd_targets(pos, goal, traffic).back() == goal.back());  // longer than 1.1 times: straight across
}

TEST_CASE("crowds: routes around crowds leave a team that fits one scene as it was, and plan a larger one") {
    auto plan_with = [](double weight, int n) {
        DiffusionPlanner planner(MadbpModel(tiny_config(), 3), 17);  // K = n_max = 6
        planner.settings.traffic.crowd_weight = weight;
        planner.settings.traffic.crowd_density = 0;  // 24 robots here are 0.6 a square unit: below the default gate
        World w = make_random_world("obstacles", n, 5, default_half_size(n) + 1.0);
        Plan first = planner.plan(w);
        for (int k = 0; k < 4; ++k) w.step(std::vector<Vec2>(w.size(), Vec2{0.2, 0.1}));
        return std::make_pair(first, planner.plan(w));
    };
    const auto off = plan_with(0, 6), on = plan_with(0.5, 6);
    for (int i = 0; i < 6; ++i) CHECK(off.second.waypoints[i] == on.second.waypoints[i]);
    const auto crowd = plan_with(0.5, 24);
    for (const auto& window : crowd.second.waypoints)
        for (Vec2 p : window) REQUIRE(std::isfinite(p.x + p.y));
}

TEST_CASE("crowds: routes around crowds act in a team as dense as a crowd, not in a sparser one (traffic.crowd_density)") {
    // The defaults: on from 1 robot per square world unit. 24 robots at constant density
    // (half-size 2.1, 1.36 a square unit) are routed; the same team in half-size 3.5 (0.5) is not,
    // and plans exactly as with the routes off.
    auto plan_in = [](double half_size, double weight) {
        DiffusionPlanner planner(MadbpModel(tiny_config(), 3), 17);  // K = n_max = 6
        planner.settings.traffic.crowd_weight = weight;
        World w = make_random_world("obstacles", 24, 5, half_size);
        Plan plan = planner.plan(w);
        return std::make_pair(plan, planner.last_crowd_targets().size());
    };
    CHECK(PlannerConfig{}.traffic.crowd_weight > 0);
    CHECK(plan_in(default_half_size(24), PlannerConfig{}.traffic.crowd_weight).second == 24);
    const auto sparse = plan_in(3.5, PlannerConfig{}.traffic.crowd_weight), off = plan_in(3.5, 0);
    CHECK(sparse.second == 0);
    for (int i = 0; i < 24; ++i) CHECK(sparse.first.waypoints[i] == off.first.waypoints[i]);
}
