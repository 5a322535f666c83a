// Tests of the world (SPEC 2): physics against hand-computed values, maps, spawning, metrics,
// dynamic teams, occupancy grid, scene files, and bad input (SPEC 12).
#include <doctest/doctest.h>

#include "madbp_sim.hpp"

using namespace madbp;

static World one_agent_world(Vec2 p, Vec2 v = {0, 0}, Vec2 goal = {0.9, 0.9}) {
    World w;
    int id = w.add_agent(p, goal);
    w.set_state(id, p, v);
    return w;
}

TEST_CASE("physics: one step of drag and force matches the hand computation") {
    // v0 = 0.2, u = 1. Substep 1: v = 0.2*0.75 + 0.05 = 0.2, p += 0.01.
    // Substep 2: v = 0.25, p += 0.0125. So p = 0.0225, v = 0.25.
    World w = one_agent_world({0, 0}, {0.2, -0.2});
    w.step({{1.0, 0.0}});
    const Agent& a = w.agents()[0];
    CHECK(a.pos.x == doctest::Approx(0.0225).epsilon(1e-12));
    CHECK(a.vel.x == doctest::Approx(0.25).epsilon(1e-12));
    // y: no force, only drag: v = -0.15 then unchanged; p = -0.15*0.1 = -0.015.
    CHECK(a.vel.y == doctest::Approx(-0.15).epsilon(1e-12));
    CHECK(a.pos.y == doctest::Approx(-0.015).epsilon(1e-12));
}

TEST_CASE("physics: top speed under constant force 1 is 0.4 per axis") {
    World w = one_agent_world({-1.0, -1.0});
    for (int k = 0; k < 30; ++k) w.step({{1.0, 1.0}});
    // The fixed point of v' = 0.75 v + 0.1 is 0.4; 30 steps leave 0.4 * 0.75^30 ~ 7e-5.
    CHECK(w.agents()[0].vel.x == doctest::Approx(0.4).epsilon(1e-3));
    CHECK(w.agents()[0].vel.y == doctest::Approx(0.4).epsilon(1e-3));
    CHECK(w.agents()[0].vel.x < 0.4);
}

TEST_CASE("physics: contact force direction and magnitude") {
    World w;
    // Overlap 0.01 between two discs: force 100 * 1e-3 * log(1 + e^10) = 1.00000454 along the
    // line of centres, pushing them apart.
    CHECK(w.penetration_force(0.19, 0.2) == doctest::Approx(0.1 * std::log1p(std::exp(10.0))).epsilon(1e-12));
    CHECK(w.penetration_force(0.19, 0.2) == doctest::Approx(1.00000454).epsilon(1e-8));
    CHECK(w.penetration_force(0.3, 0.2) < 1e-30);
    int a = w.add_agent({-0.095, 0}, {-0.5, 0.5});
    int b = w.add_agent({0.095, 0}, {0.5, 0.5});
    w.step({{0, 0}, {0, 0}});
    // Substep 1: f = 1.0000454 -> v = -0.0500002, p = -0.0975000. Substep 2: distance 0.1950000,
    // f = 0.1*log(1+e^5) = 0.5006715 -> v = -0.0750338, p = -0.1012517.
    double f1 = 0.1 * std::log1p(std::exp(10.0));
    double v1 = -f1 * 0.05, p1 = -0.095 + v1 * 0.05;
    double f2 = 0.1 * std::log1p(std::exp((0.2 - 2 * -p1) / 1e-3));
    double v2 = v1 - f2 * 0.05, p2 = p1 + v2 * 0.05;
    CHECK(w.agent(a).pos.x == doctest::Approx(p2).epsilon(1e-12));
    CHECK(w.agent(a).vel.x == doctest::Approx(v2).epsilon(1e-12));
    CHECK(w.agent(b).pos.x == doctest::Approx(-p2).epsilon(1e-12));
    CHECK(w.agent(a).pos.y == 0.0);
    // Wall at x = 1.2 pushes -x; a box pushes out through its nearest face.
    CHECK(w.static_contact_force({1.2 - 0.095, 0}).x == doctest::Approx(-0.1 * std::log1p(std::exp(5.0))));
    CHECK(w.static_contact_force({1.2 - 0.095, 0}).y == 0.0);
    WorldMap m;
    m.boxes.push_back({{-0.5, -0.05}, {0.5, 0.05}});
    World wb(m);
    Vec2 f = wb.static_contact_force({0.2, 0.05 + 0.099});  // 0.001 into the contact margin
    CHECK(f.x == 0.0);
    CHECK(f.y == doctest::Approx(0.1 * std::log1p(std::exp(1.0))));
    Vec2 g = wb.static_contact_force({0.5 + 0.095, 0.0});  // beside the right end
    CHECK(g.x > 0.4);
    CHECK(std::fabs(g.y) < 1e-12);
}

TEST_CASE("physics: agent order does not change the result (two-phase step)") {
    World w1 = make_random_world("obstacles", 5, 3);
    World w2(w1.map());
    for (int i = w1.size() - 1; i >= 0; --i) w2.add_agent(w1.agents()[i].pos, w1.agents()[i].goal, w1.agents()[i].id);
    Rng rng(1);
    for (int k = 0; k < 60; ++k) {
        std::vector<Vec2> u1, u2(w1.size());
        for (int i = 0; i < w1.size(); ++i) u1.push_back({rng.uniform(-1, 1), rng.uniform(-1, 1)});
        for (int i = 0; i < w1.size(); ++i) u2[w2.index_of(w1.agents()[i].id)] = u1[i];
        w1.step(u1);
        w2.step(u2);
    }
    for (const Agent& a : w1.agents()) {
        CHECK(w2.agent(a.id).pos.x == a.pos.x);
        CHECK(w2.agent(a.id).pos.y == a.pos.y);
    }
    CHECK(w1.metrics().collisions() == w2.metrics().collisions());
}

TEST_CASE("actions: out of range is clamped and counted, NaN and inf are errors naming the agent") {
    World w = one_agent_world({0, 0});
    w.step({{5.0, -0.5}});
    CHECK(w.metrics().clamped_actions == 1);
    CHECK(w.last_clamped() == 1);
    CHECK(w.agents()[0].vel.x == doctest::Approx(0.1));
    World w2 = one_agent_world({0, 0});
    w2.add_agent({0.5, 0.5}, {-0.5, -0.5}, 7);
    CHECK_THROWS_WITH_AS(w2.step({{0, 0}, {NAN, 0}}), doctest::Contains("agent 7"), std::invalid_argument);
    CHECK_THROWS_AS(w2.step({{INFINITY, 0}, {0, 0}}), std::invalid_argument);
    CHECK_THROWS_AS(w2.step({{0, 0}}), std::invalid_argument);
    CHECK(w2.t() == 0);
}

TEST_CASE("bad states: NaN, inf and agents outside the world raise clear errors") {
    World w;
    CHECK_THROWS_WITH_AS(w.add_agent({NAN, 0}, {0, 0}), doctest::Contains("start.x"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(w.add_agent({0, 0}, {0, INFINITY}), doctest::Contains("goal.y"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(w.add_agent({1.5, 0}, {0, 0}), doctest::Contains("outside the world"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(w.add_agent({0, 0}, {0, -1.19}), doctest::Contains("outside the world"), std::invalid_argument);
    int id = w.add_agent({0, 0}, {0.5, 0});
    CHECK_THROWS_AS(w.set_state(id, {0, 0}, {NAN, 0}), std::invalid_argument);
    CHECK_THROWS_AS(w.set_state(id, {1.21, 0}, {0, 0}), std::invalid_argument);
    w.set_state(id, {1.15, 0}, {0, 0});  // pressed into the wall: a state the physics can reach
    WorldMap bad;
    bad.discs.push_back({{0, 0}, -1});
    CHECK_THROWS_AS(World{bad}, std::invalid_argument);
    WorldMap nan_map;
    nan_map.half_size = NAN;
    CHECK_THROWS_AS(World{nan_map}, std::invalid_argument);
}

TEST_CASE("maps: the three generators and unknown names") {
    Rng rng(5);
    CHECK(make_map("empty", rng).discs.empty());
    for (int seed = 0; seed < 200; ++seed) {
        Rng r(seed);
        WorldMap m = make_map("obstacles", r);
        REQUIRE(m.discs.size() == 5);
        for (size_t i = 0; i < m.discs.size(); ++i) {
            CHECK(std::fabs(m.discs[i].c.x) <= 0.8);
            CHECK(std::fabs(m.discs[i].c.y) <= 0.8);
            for (size_t j = 0; j < i; ++j) CHECK(norm(m.discs[i].c - m.discs[j].c) - 0.2 >= 0.15);
        }
        WorldMap b = make_map("barrier", r);
        REQUIRE(b.boxes.size() == 2);
        double gap_lo = b.boxes[0].hi.x, gap_hi = b.boxes[1].lo.x;
        CHECK(gap_hi - gap_lo == doctest::Approx(0.5));
        CHECK(std::fabs((gap_lo + gap_hi) / 2) <= 0.5);
        CHECK(b.boxes[0].lo.x == -1.2);
        CHECK(b.boxes[1].hi.x == 1.2);
        CHECK(b.boxes[0].hi.y - b.boxes[0].lo.y == doctest::Approx(0.1));
    }
    Rng r2(0);
    CHECK(make_map("obstacles", r2, 2.4).discs.size() == 20);
    CHECK_THROWS_WITH_AS(make_map("maze", rng), doctest::Contains("maze"), std::invalid_argument);
    CHECK_THROWS_AS(make_random_world("nope", 2, 0), std::invalid_argument);
}

TEST_CASE("spawn: constraints hold over many seeds, and an impossible layout throws") {
    for (const char* name : {"empty", "obstacles", "barrier"})
        for (int n : {2, 4, 8})
            for (int seed = 0; seed < 60; ++seed) {
                World w = make_random_world(name, n, seed);
                REQUIRE(w.size() == n);
                std::vector<Vec2> pts;
                for (const Agent& a : w.agents()) pts.push_back(a.pos);
                for (const Agent& a : w.agents()) pts.push_back(a.goal);
                for (size_t i = 0; i < pts.size(); ++i) {
                    CHECK(std::fabs(pts[i].x) <= 1.0);
                    CHECK(std::fabs(pts[i].y) <= 1.0);
                    CHECK(static_clearance(w.map(), pts[i]) >= 0.15 - 1e-12);
                    for (size_t j = 0; j < i; ++j) CHECK(norm(pts[i] - pts[j]) >= 0.25);
                }
            }
    // Same seed, same world.
    World a = make_random_world("barrier", 4, 11), b = make_random_world("barrier", 4, 11);
    CHECK(a.agents()[3].goal.x == b.agents()[3].goal.x);
    CHECK(a.map().boxes[0].hi.x == b.map().boxes[0].hi.x);
    // 200 agents cannot fit 400 points 0.25 apart in [-1, 1]^2.
    CHECK_THROWS_WITH_AS(make_random_world("empty", 200, 0), doctest::Contains("could not place"), std::runtime_error);
    // A larger world spawns over [-2, 2]^2.
    World big = make_random_world("empty", 16, 0, 2.4);
    double extent = 0;
    for (const Agent& g : big.agents()) extent = std::max(extent, std::fabs(g.pos.x));
    CHECK(extent > 1.0);
    CHECK(extent <= 2.0);
}

TEST_CASE("metrics: goal, success at the same step, and the step limit") {
    World w;
    w.add_agent({0, 0}, {0.15, 0});
    w.add_agent({0.5, 0.5}, {0.5, 0.62});
    CHECK_FALSE(w.all_at_goal());
    w.step({{0, 0}, {0, 0}});
    CHECK_FALSE(w.metrics().success);
    // Move agent 0 next to its goal by hand; agent 1 is still 0.12 away: no success.
    w.set_state(0, {0.1, 0}, {0, 0});
    w.step({{0, 0}, {0, 0}});
    CHECK_FALSE(w.metrics().success);
    w.set_state(1, {0.5, 0.55}, {0, 0});
    w.step({{0, 0}, {0, 0}});
    CHECK(w.metrics().success);
    CHECK(w.metrics().success_step == 3);
    CHECK(w.done());
    WorldConfig cfg;
    cfg.max_steps = 5;
    World w2(WorldMap{}, cfg);
    w2.add_agent({0, 0}, {0.9, 0});
    for (int k = 0; k < 5; ++k) { CHECK_FALSE(w2.done()); w2.step({{0, 0}}); }
    CHECK(w2.done());
    CHECK_FALSE(w2.metrics().success);
}

TEST_CASE("metrics: collisions per step and pair, agent-agent and agent-static separately") {
    WorldMap m;
    m.discs.push_back({{0.5, 0.5}, 0.1});
    World w(m);
    w.add_agent({0, 0}, {0.9, 0.9});
    w.add_agent({0.19, 0}, {-0.9, 0.9});   // overlaps agent 0 (0.19 < 0.2)
    w.add_agent({0.5, 0.33}, {-0.9, -0.9});  // overlaps the disc (0.17 < 0.2)
    w.add_agent({1.05, -1.05}, {0, -0.9});   // 0.15 from both walls: no contact
    // Agents 0 and 1 push into each other with force 1: the contact balances at an overlap
    // of about 0.0005, so they stay in contact.
    w.step({{1, 0}, {-1, 0}, {0, 0}, {0, 0}});
    CHECK(w.metrics().agent_collisions == 1);
    CHECK(w.metrics().obstacle_collisions == 1);
    REQUIRE(w.last_agent_contacts().size() == 1);
    CHECK(w.last_agent_contacts()[0] == std::make_pair(0, 1));
    w.set_state(3, {1.13, -1.13}, {0, 0});  // now 0.07 from both walls: two pairs
    w.step({{1, 0}, {-1, 0}, {0, 0}, {0, 0}});
    CHECK(w.metrics().obstacle_collisions >= 3);
    CHECK(w.metrics().collisions() == w.metrics().agent_collisions + w.metrics().obstacle_collisions);
    // Far apart: nothing more is counted.
    World clean;
    clean.add_agent({-0.5, 0}, {0.5, 0});
    clean.add_agent({0.5, 0}, {-0.5, 0});
    clean.step({{0, 0}, {0, 0}});
    CHECK(clean.metrics().collisions() == 0);
}

TEST_CASE("dynamic teams: join and leave keep ids stable and metrics follow present agents") {
    World w;
    int a = w.add_agent({-0.5, 0}, {-0.5, 0.05});
    int b = w.add_agent({0.5, 0}, {0.9, 0.9});
    int c = w.add_agent({0, 0.5}, {0, 0.55});
    CHECK(a == 0);
    CHECK(b == 1);
    CHECK(c == 2);
    w.step({{0, 0}, {0, 0}, {0, 0}});
    CHECK_FALSE(w.metrics().success);  // b is far from its goal
    w.remove_agent(b);
    CHECK(w.size() == 2);
    CHECK(w.index_of(c) == 1);
    w.step({{0, 0}, {0, 0}});
    CHECK(w.metrics().success);  // the agents present are at their goals
    int d = w.add_agent({0.8, -0.8}, {0.2, 0.2});
    CHECK(d == 3);  // ids are never reused
    CHECK_THROWS_WITH_AS(w.add_agent({0.3, -0.3}, {0, 0}, d), doctest::Contains("duplicate"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(w.remove_agent(b), doctest::Contains("unknown agent id 1"), std::invalid_argument);
    CHECK_THROWS_AS(w.agent(42), std::invalid_argument);
    CHECK(w.add_agent({-0.8, -0.8}, {0, 0}, 10) == 10);
    CHECK(w.add_agent({-0.8, 0.8}, {0, 0}) == 11);
}

TEST_CASE("WorldBatch: stepping together equals stepping alone, any thread count") {
    WorldBatch batch;
    for (int s = 0; s < 16; ++s) batch.worlds.push_back(make_random_world("obstacles", 4, s));
    std::vector<World> alone = batch.worlds;
    std::vector<std::vector<Vec2>> acts(16, std::vector<Vec2>(4, Vec2{0.7, -0.3}));
    for (int k = 0; k < 20; ++k) {
        batch.step(acts);
        for (auto& w : alone) w.step(acts[0]);
    }
    for (int s = 0; s < 16; ++s) CHECK(batch.worlds[s].agents()[2].pos.x == alone[s].agents()[2].pos.x);
    acts[5][1].x = NAN;
    CHECK_THROWS_WITH_AS(batch.step(acts), doctest::Contains("world 5"), std::invalid_argument);
}

TEST_CASE("grid: rasterization of a known map, channels and layout") {
    WorldMap m;
    m.boxes.push_back({{-0.3, -0.3}, {0.3, 0.3}});
    m.discs.push_back({{0.75, -0.75}, 0.1});
    // G = 8 over [-1.2, 1.2]: cell width 0.3, centres at -1.05, -0.75, ..., 1.05.
    Grid g = occupancy_grid(m, 8);
    REQUIRE(g.cells.size() == 64);
    int ones = 0;
    for (float v : g.cells) ones += v == 1.f;
    CHECK(ones == 5);
    CHECK(g.at(0, 3, 3) == 1.f);
    CHECK(g.at(0, 4, 4) == 1.f);
    CHECK(g.at(0, 3, 4) == 1.f);
    CHECK(g.at(0, 4, 3) == 1.f);
    CHECK(g.at(0, 1, 6) == 1.f);  // row 1 = y -0.75 (row 0 is the lowest y), column 6 = x 0.75
    CHECK(g.at(0, 6, 1) == 0.f);
    World w(m);
    w.add_agent({-1.05, 1.05}, {1.05, 1.05});
    Grid g3 = occupancy_grid(w, 8, true, true);
    CHECK(g3.channels == 3);
    CHECK(g3.at(1, 7, 0) == 1.f);
    CHECK(g3.at(2, 7, 7) == 1.f);
    CHECK(g3.at(1, 7, 7) == 0.f);
    // The barrier at the default 32 x 32: the two rows around y = 0 are blocked except the gap.
    Rng rng(0);
    WorldMap b = make_map("barrier", rng);
    Grid gb = occupancy_grid(b);
    double gap_c = (b.boxes[0].hi.x + b.boxes[1].lo.x) / 2;
    for (int row : {15, 16}) {
        CHECK(gb.at(0, row, 0) == 1.f);
        CHECK(gb.at(0, row, 31) == 1.f);
        int col = (int)((gap_c + 1.2) / gb.cell_width());
        CHECK(gb.at(0, row, col) == 0.f);
    }
    CHECK(gb.at(0, 14, 0) == 0.f);
    CHECK_THROWS_AS(occupancy_grid(m, 1), std::invalid_argument);
}

TEST_CASE("scene files: a good file round-trips") {
    const char* text =
        "# a swap through a gap\n"
        "madbp-scene 1\n"
        "world 1.2              # half-size\n"
        "disc 0.3 -0.6 0.1\n"
        "box -1.2 -0.05 -0.25 0.05\n"
        "box 0.25 -0.05 1.2 0.05\n"
        "\n"
        "agent -0.9 0.5 0.9 -0.5\n"
        "agent 0.9 -0.5 -0.9 0.5   # start on the other's goal\n";
    Scene s = parse_scene(text);
    CHECK(s.map.half_size == 1.2);
    REQUIRE(s.map.discs.size() == 1);
    CHECK(s.map.discs[0].r == 0.1);
    REQUIRE(s.map.boxes.size() == 2);
    CHECK(s.map.boxes[1].lo.x == 0.25);
    REQUIRE(s.starts.size() == 2);
    CHECK(s.goals[1].x == -0.9);
    World w = make_world(s);
    CHECK(w.size() == 2);
    Scene again = parse_scene(scene_text(w));
    CHECK(again.map.boxes[0].hi.x == -0.25);
    CHECK(again.starts[1].y == -0.5);
    CHECK(parse_scene("madbp-scene 1\nworld 2.4\nagent 2 2 -2 -2\n").map.half_size == 2.4);
}

TEST_CASE("scene files: malformed lines are errors naming the line number") {
    auto err = [](const std::string& text) {
        try {
            parse_scene(text, "t.scene");
        } catch (const std::invalid_argument& e) {
            return std::string(e.what());
        }
        return std::string("no error");
    };
    CHECK(err("agent 0 0 1 1\n").find("t.scene:1: expected the header") == 0);
    CHECK(err("madbp-scene 2\nagent 0 0 1 1\n").find("t.scene:1: unsupported") == 0);
    CHECK(err("madbp-scene 1\n# c\nagent 0 0 0.5\n").find("t.scene:3: 'agent' takes 4 numbers, got 3") == 0);
    CHECK(err("madbp-scene 1\nagent 0 0 0.5 zero\n").find("t.scene:2: 'zero' is not a number") == 0);
    CHECK(err("madbp-scene 1\nagent 0 0 0.5 nan\n").find("t.scene:2: 'nan' is not finite") == 0);
    CHECK(err("madbp-scene 1\nrobot 0 0 0.5 0\n").find("t.scene:2: unknown keyword 'robot'") == 0);
    CHECK(err("madbp-scene 1\ndisc 0 0 -0.1\nagent 0.5 0.5 -0.5 -0.5\n").find("t.scene:2: disc radius") == 0);
    CHECK(err("madbp-scene 1\nbox 1 0 0 1\n").find("t.scene:2: box needs") == 0);
    CHECK(err("madbp-scene 1\nagent 0 0 0.5 0.5\nworld 2\n").find("t.scene:3: 'world' must come before") == 0);
    CHECK(err("madbp-scene 1\n").find("no 'agent' line") != std::string::npos);
    CHECK(err("").find("empty scene") != std::string::npos);
    CHECK(err("madbp-scene 1\nagent 1.15 0 0 0\n").find("t.scene:2: start is outside the world") == 0);
    CHECK(err("madbp-scene 1\nagent 0 0 0.5 0\nagent 0.1 0 -0.5 0\n").find("t.scene:3: start overlaps the start of the agent on line 2") == 0);
    CHECK(err("madbp-scene 1\nagent 0 0 0.5 0\nagent 0.5 0.5 0.55 0\n").find("t.scene:3: goal overlaps") == 0);
    CHECK(err("madbp-scene 1\ndisc 0 0 0.2\n\nagent 0.25 0 0.9 0\n").find("t.scene:4: start overlaps an obstacle") == 0);
    CHECK(err("madbp-scene 1\nbox -1 -0.05 1 0.05\nagent 0.5 0.5 0.5 0.1\n").find("t.scene:3: goal overlaps an obstacle") == 0);
    CHECK_THROWS_WITH_AS(load_scene("/nonexistent/x.scene"), doctest::Contains("cannot open"), std::runtime_error);
}
