// Interaction scenes and conflict-aware sampling (issue 12): scene generators (madbp_sim.hpp
// Section 4b), the scene mix of collect_demonstrations, the window cost and its gradient,
// guided DDIM and best-of-k (madbp.hpp, SamplerConfig::guidance / candidates).
#include <doctest/doctest.h>

#include <queue>

#include "madbp_train.hpp"
#include "tiny_model.hpp"

#include "alloc_counter_api.hpp"

using namespace madbp;

namespace {

// A map with a disc, a box and the border walls, and B scenes of n slots on it (scene b has
// counts[b] active agents) encoded as the planner does.
WorldMap test_map() {
    WorldMap m;
    m.discs.push_back({Vec2{0.3, -0.2}, 0.15});
    m.boxes.push_back({Vec2{-0.6, 0.3}, Vec2{-0.2, 0.4}});
    return m;
}
SceneBatch scene_batch(const ModelConfig& c, const WorldMap& map, int B, int n, const std::vector<int>& counts, Rng& rng) {
    SceneBatch s;
    s.resize(B, n, c, /*shared grid*/ true);
    encode_map(s, 0, map, c);
    for (int b = 0; b < B; ++b) {
        s.count[b] = counts[b];
        for (int i = 0; i < counts[b]; ++i) {
            const Vec2 p{rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5)}, g{rng.uniform(-1, 1), rng.uniform(-1, 1)};
            encode_agent(s, b * n + i, i, p, g, map, c);
        }
    }
    return s;
}

// Today's sampler (before issue 12), copied verbatim (with 9d18a81's fixed-size pin target):
// the reference that the default path of sample_windows must reproduce bit for bit.
template <class Denoiser>
void reference_sample_windows(Denoiser& model, const NoiseSchedule& schedule, const SceneBatch& batch, const SamplerConfig& sc,
                              Rng& rng, Mat& x, Mat& out, std::vector<int>& step_buf) {
    const ModelConfig& c = model.config;
    const int A = batch.agents(), H = c.horizon, B = batch.B, S = sc.sample_steps;
    if (S < 1 || S > schedule.K) throw std::invalid_argument("sample_steps: " + std::to_string(S) + " must be in [1, " + std::to_string(schedule.K) + "]");
    model.encode_context(batch);
    x.resize(2, (long)H * A);
    for (long j = 0; j < x.size(); ++j) x.data()[j] = (float)rng.normal();
    auto impose = [&]() {
        for (int a = 0; a < A; ++a) {
            auto w = x.middleCols((long)a * H, H);
            if (batch.agent_mask[a] == 0) { w.setZero(); continue; }
            w.col(0).setZero();
            Eigen::Vector2f end;
            if (sc.goal_inpaint && end_pinned(batch, a, c, sc.goal_reach, &end)) w.col(H - 1).template head<2>() = end;  // as 9d18a81: same values
        }
    };
    impose();
    step_buf.resize(B);
    for (int s = S; s >= 1; --s) {
        const int k = schedule.ddim_step(s, S), k_prev = schedule.ddim_step(s - 1, S);
        std::fill(step_buf.begin(), step_buf.end(), k);
        model.denoise(x, step_buf.data(), out);
        const double ab = schedule.alpha_bar[k], ab_prev = schedule.alpha_bar[k_prev];
        const float sa = (float)std::sqrt(ab), s1a = (float)std::sqrt(1 - ab);
        const float sap = (float)std::sqrt(ab_prev), s1ap = (float)std::sqrt(1 - ab_prev);
        const bool eps_mode = c.prediction == Prediction::Eps;
        for (long j = 0; j < x.size(); ++j) {
            const float xj = x.data()[j], oj = out.data()[j];
            const float x0 = std::clamp(eps_mode ? (xj - s1a * oj) / sa : oj, -sc.x0_clip, sc.x0_clip);
            const float e = (xj - sa * x0) / s1a;  // the noise consistent with the clipped x0
            x.data()[j] = sap * x0 + s1ap * e;
        }
        impose();
    }
}

// A denoiser that always predicts the same clean window x0 (as in test_model.cpp).
struct OracleDenoiser {
    ModelConfig config;
    Mat x0;
    void encode_context(const SceneBatch&) {}
    void denoise(const Mat& x, const int*, Mat& out) {
        // Every repeated scene (best-of-k) gets the same prediction.
        out.resize(2, x.cols());
        for (long j = 0; j < x.cols(); j += x0.cols()) out.middleCols(j, x0.cols()) = x0;
    }
};

}  // namespace

// ---------------------------------------------------------------------------------------------
// Scene generators

TEST_CASE("interaction scenes: every generator gives valid scenes on every map over many seeds") {
    const double r = 0.1;
    int scenes = 0;
    for (const std::string& scenario : interaction_scenarios())
        for (const char* map_name : {"empty", "obstacles", "barrier"})
            for (int n = 1; n <= kMaxScenarioAgents; ++n)
                for (uint64_t seed = 0; seed < 12; ++seed) {
                    CAPTURE(scenario);
                    CAPTURE(map_name);
                    CAPTURE(n);
                    CAPTURE(seed);
                    World w = make_interaction_world(scenario, map_name, n, seed);
                    ++scenes;
                    REQUIRE(w.size() == n);
                    const WorldMap& map = w.map();
                    // The guided expert's own planning grid and wavefront field (Section 12).
                    ExpertParams ep;
                    ClearanceGrid grid(map, ep.cell);
                    for (int i = 0; i < n; ++i) {
                        const Agent& a = w.agents()[i];
                        CHECK(static_clearance(map, a.pos) >= r + 0.05);
                        CHECK(static_clearance(map, a.goal) >= r + 0.05);
                        CHECK(!inside_obstacle(map, a.pos));
                        for (int j = 0; j < i; ++j) {
                            CHECK(norm(a.pos - w.agents()[j].pos) >= 2 * r + 0.05);   // no overlapping starts
                            CHECK(norm(a.goal - w.agents()[j].goal) >= 2 * r + 0.05); // nor goals
                        }
                        const std::vector<int> field = wavefront(grid, grid.index(a.goal), ep.inflate);
                        CHECK(field[grid.index(a.pos)] >= 0);  // the goal is reachable
                    }
                    // The map is the named one, plus walls for gap (not barrier) and corridor.
                    if (std::string(map_name) == "barrier" && scenario != "corridor") CHECK(map.boxes.size() == 2);
                    if (scenario == "corridor") CHECK(map.boxes.size() >= 2);
                }
    CHECK(scenes == 6 * 3 * 4 * 12);
}

TEST_CASE("interaction scenes: the layouts are the interactions they are named for, drawn from the seed") {
    auto starts_goals = [](const World& w) {
        std::vector<Vec2> v;
        for (const Agent& a : w.agents()) { v.push_back(a.pos); v.push_back(a.goal); }
        return v;
    };
    for (const char* map_name : {"empty", "obstacles", "barrier"})
        for (uint64_t seed = 0; seed < 5; ++seed) {
            // swap, cross, gap, corridor: pairs exchange start and goal exactly.
            for (const char* scenario : {"swap", "cross", "gap", "corridor"}) {
                World w = make_interaction_world(scenario, map_name, 4, seed);
                for (int i = 0; i < 4; ++i) {
                    bool partner = false;
                    for (int j = 0; j < 4; ++j)
                        partner = partner || (j != i && w.agents()[i].goal == w.agents()[j].pos && w.agents()[j].goal == w.agents()[i].pos);
                    CHECK(partner);
                }
            }
            // cross: the paths of robots 0 (N->S) and 1 (E->W) are perpendicular.
            World plus = make_interaction_world("cross", map_name, 2, seed);
            const Vec2 d0 = plus.agents()[0].goal - plus.agents()[0].pos, d1 = plus.agents()[1].goal - plus.agents()[1].pos;
            CHECK(std::fabs(dot(d0, d1)) < 1e-9 * norm(d0) * norm(d1) + 1e-9);
            // parked: robots 2 and 3 sit on their goals, near the movers' line.
            World parked = make_interaction_world("parked", map_name, 4, seed);
            const Vec2 s0 = parked.agents()[0].pos, g0 = parked.agents()[0].goal, u = normalized(g0 - s0);
            for (int i = 2; i < 4; ++i) {
                const Agent& a = parked.agents()[i];
                CHECK(a.pos == a.goal);
                CHECK(std::fabs(cross(u, a.pos - s0)) <= 0.05 + 1e-9);
                CHECK(dot(u, a.pos - s0) > 0);
                CHECK(dot(u, a.pos - s0) < norm(g0 - s0));
            }
            // circle: every goal is its start's antipode about one centre.
            World circle = make_interaction_world("circle", map_name, 4, seed);
            const Vec2 centre = (circle.agents()[0].pos + circle.agents()[0].goal) * 0.5;
            for (const Agent& a : circle.agents()) CHECK(norm((a.pos + a.goal) * 0.5 - centre) < 1e-9);
            // gap on the barrier map: starts on both sides of the wall, each goal across it.
            if (std::string(map_name) == "barrier") {
                World gap = make_interaction_world("gap", map_name, 4, seed);
                for (const Agent& a : gap.agents()) CHECK(a.pos.y * a.goal.y < 0);
            }
            // Drawn from the seed: the same seed gives the same scene, another seed another one.
            for (const std::string& scenario : interaction_scenarios()) {
                CHECK(starts_goals(make_interaction_world(scenario, map_name, 3, seed)) == starts_goals(make_interaction_world(scenario, map_name, 3, seed)));
                CHECK(starts_goals(make_interaction_world(scenario, map_name, 3, seed)) != starts_goals(make_interaction_world(scenario, map_name, 3, seed + 1)));
            }
        }
    CHECK_THROWS_AS(make_interaction_world("zigzag", "empty", 2, 0), std::invalid_argument);
    CHECK_THROWS_AS(make_interaction_world("swap", "maze", 2, 0), std::invalid_argument);
    CHECK_THROWS_AS(make_interaction_world("swap", "empty", 5, 0), std::invalid_argument);
    CHECK_THROWS_AS(make_interaction_world("swap", "empty", 0, 0), std::invalid_argument);
    // evaluate() builds the episode worlds from the scenario.
    EvalConfig ec;
    ec.map = "barrier";
    ec.agents = 3;
    ec.scenario = "corridor";
    CHECK(starts_goals(make_episode_world(ec, 7)) == starts_goals(make_interaction_world("corridor", "barrier", 3, 7)));
}

TEST_CASE("interaction scenes: the guided expert solves them") {
    // One scene of each kind at n = 4 on the barrier map (the hardest), with its step limit.
    int solved = 0;
    for (const std::string& scenario : interaction_scenarios()) {
        World w = make_interaction_world(scenario, "barrier", 4, 3);
        GuidedExpert expert(w.map());
        EpisodeResult r = run_episode(w, expert);
        CAPTURE(scenario);
        CHECK(r.collisions() == 0);
        solved += r.success;
    }
    CHECK(solved >= 5);
}

// ---------------------------------------------------------------------------------------------
// The scene mix of collect_demonstrations

TEST_CASE("collect: the default mix is today's random spawns; a mix draws the named scenes") {
    CollectConfig c;
    c.maps = {"obstacles", "barrier"};
    c.n_train_max = 2;
    c.episodes = 3;
    c.seed = 11;
    c.successful_only = false;
    const DemoSet got = collect_demonstrations(c, expert_demonstrator(), "expert");
    // Today's loop, by hand: cell = map index * n_train_max + (n - 1), seed + e + 100000 * cell.
    REQUIRE(got.episodes.size() == 2 * 2 * 3);
    size_t k = 0;
    for (int m = 0; m < 2; ++m)
        for (int n = 1; n <= 2; ++n)
            for (int e = 0; e < 3; ++e, ++k) {
                const uint64_t seed = c.seed + e + 100000ull * (m * 2 + (n - 1));
                World w = make_random_world(c.maps[m], n, seed);
                GuidedExpert expert(w.map());
                const Demonstration d = record_demonstration(w, expert, c.maps[m]);
                const Demonstration& g = got.episodes[k];
                CHECK(g.map_name == c.maps[m]);
                CHECK(g.map == d.map);
                CHECK(g.steps == d.steps);
                CHECK(g.goals == d.goals);
                CHECK(g.pos == d.pos);
                CHECK(g.act == d.act);
            }
    // One team size (n_train_min = n_train_max = 2, as MADiff collects): the same episodes as
    // those cells of the full run, each map's in order; a minimum above the maximum is refused.
    CollectConfig pairs = c;
    pairs.n_train_min = 2;
    const DemoSet two = collect_demonstrations(pairs, expert_demonstrator(), "expert");
    REQUIRE(two.episodes.size() == 2 * 3);
    for (int m = 0; m < 2; ++m)
        for (int e = 0; e < 3; ++e) {
            const Demonstration& full = got.episodes[(size_t)(m * 2 + 1) * 3 + e];
            CHECK(two.episodes[(size_t)m * 3 + e].pos == full.pos);
            CHECK(two.episodes[(size_t)m * 3 + e].agents == 2);
        }
    pairs.n_train_min = 3;
    CHECK_THROWS_WITH_AS(collect_demonstrations(pairs, expert_demonstrator(), "expert"), doctest::Contains("n_train_min"),
                         std::invalid_argument);
    // A mix: a quarter swap, half corridor, the rest random; by position in the cell.
    c.episodes = 4;
    c.scenarios = {{"swap", 0.25}, {"corridor", 0.5}};
    CHECK(collect_scenario(c, 2, 0) == "swap");
    CHECK(collect_scenario(c, 2, 1) == "corridor");
    CHECK(collect_scenario(c, 2, 2) == "corridor");
    CHECK(collect_scenario(c, 2, 3) == "");
    CHECK(collect_scenario(c, kMaxScenarioAgents + 1, 0) == "");  // larger teams: random spawns
    c.maps = {"empty"};
    c.n_train_max = 2;
    const DemoSet mixed = collect_demonstrations(c, expert_demonstrator(), "expert");
    REQUIRE(mixed.episodes.size() == 8);
    CHECK(mixed.episodes[4].map_name == "empty/swap");
    CHECK(mixed.episodes[5].map_name == "empty/corridor");
    CHECK(mixed.episodes[7].map_name == "empty");
    const World w = make_interaction_world("corridor", "empty", 2, c.seed + 1 + 100000ull * 1);
    CHECK(mixed.episodes[5].map == w.map());
    CHECK(mixed.episodes[5].pos[0] == w.agents()[0].pos);
    CHECK(mixed.episodes[5].goals[1] == w.agents()[1].goal);
    c.scenarios = {{"swap", 0.7}, {"circle", 0.7}};
    CHECK_THROWS_AS(collect_demonstrations(c, expert_demonstrator(), "expert"), std::invalid_argument);
    c.scenarios = {{"spiral", 0.1}};
    CHECK_THROWS_AS(collect_demonstrations(c, expert_demonstrator(), "expert"), std::invalid_argument);
}

// ---------------------------------------------------------------------------------------------
// The distance field and the window cost

TEST_CASE("distance field: exact at the nodes, close between them, gradient = finite differences") {
    const WorldMap map = test_map();
    DistanceField f(map);
    CHECK(f.built_for(map));
    Rng rng(3);
    for (int k = 0; k < 200; ++k) {
        const int row = (int)(rng.next_u64() % f.nodes), col = (int)(rng.next_u64() % f.nodes);
        const double x = f.lo + col * f.cell, y = f.lo + row * f.cell;
        CHECK(f.value(x, y) == doctest::Approx((float)static_clearance(map, {x, y})).epsilon(1e-6));
    }
    for (int k = 0; k < 500; ++k) {
        const double x = rng.uniform(-1.3, 1.3), y = rng.uniform(-1.3, 1.3);
        double gx, gy;
        const double v = f.value(x, y, &gx, &gy);
        CHECK(std::fabs(v - static_clearance(map, {x, y})) < f.cell);
        // Inside one cell the interpolant is bilinear: central differences there are exact up to rounding.
        const double h = 1e-5;
        const double u = (x - f.lo) / f.cell, w = (y - f.lo) / f.cell;
        if (std::fabs(u - std::round(u)) < 1e-3 || std::fabs(w - std::round(w)) < 1e-3) continue;
        CHECK((f.value(x + h, y) - f.value(x - h, y)) / (2 * h) == doctest::Approx(gx).epsilon(1e-4).scale(1));
        CHECK((f.value(x, y + h) - f.value(x, y - h)) / (2 * h) == doctest::Approx(gy).epsilon(1e-4).scale(1));
    }
}

TEST_CASE("goal fields: the distance to a goal around the map") {
    // Open world: the straight-line distance, up to the grid's 8-direction metric (<= 8% longer).
    MapFields open;
    open.set_map(WorldMap{});
    SceneBatch s;
    const ModelConfig c = tiny_config();
    s.resize(1, 1, c, true);
    encode_agent(s, 0, 0, {0, 0}, {0.5, 0.25}, WorldMap{}, c);
    open.add_goals(s, c, 0.1);
    REQUIRE(open.goals.size() == 1);
    const MapFields::GoalField& g = open.goals[0];
    for (Vec2 p : {Vec2{-0.7, -0.4}, Vec2{0.9, 0.9}, Vec2{0.45, 0.3}}) {
        const double d = open.goal_distance(g, p.x, p.y), straight = norm(p - Vec2{g.x, g.y});
        CHECK(d >= straight - 0.02);
        CHECK(d <= 1.08 * straight + 0.02);
    }
    open.add_goals(s, c, 0.1);
    CHECK(open.goals.size() == 1);  // made once per goal
    // Barrier with its gap at x = 0.5: from below the wall at x = -0.8 to above it, the way is
    // through the gap, and the gradient points away from the gap (uphill).
    WorldMap barrier;
    barrier.boxes = {{{-1.2, -0.05}, {0.25, 0.05}}, {{0.75, -0.05}, {1.2, 0.05}}};
    MapFields f;
    f.set_map(barrier);
    encode_agent(s, 0, 0, {-0.8, 0.3}, {-0.8, 0.3}, barrier, c);
    f.add_goals(s, c, 0.1);
    double gx, gy;
    const double d = f.goal_distance(f.goals[0], -0.8, -0.3, &gx, &gy);
    const double around = norm(Vec2{-0.8, -0.3} - Vec2{0.5, 0}) + norm(Vec2{0.5, 0} - Vec2{-0.8, 0.3});
    CHECK(d > 0.9 * around);
    CHECK(d < 1.1 * around);
    CHECK(gx < 0);  // walking towards the gap (+x) brings the goal nearer
    f.set_map(WorldMap{});
    CHECK(f.goals.empty());  // another map forgets them
}

TEST_CASE("goal fields: a team with more goals than the cache holds keeps its fields between plans") {
    // Before 2026-12-04 the cache was cleared when full, in the middle of add_goals: past
    // kMaxGoalFields goals every plan rebuilt every field, and its first agents lost theirs.
    const ModelConfig c = tiny_config();
    MapFields f;
    f.set_map(WorldMap{});
    const int cap = f.max_goal_fields(), n = cap + 40;
    REQUIRE(cap == MapFields::kMaxGoalFields);  // the standard world's fields are small
    Rng rng(3);
    std::vector<Vec2> goal(n);
    for (Vec2& g : goal) g = {rng.uniform(-1.1, 1.1), rng.uniform(-1.1, 1.1)};
    auto batch_of = [&](int first, int count) {  // one scene per robot, as a plan's scenes
        SceneBatch s;
        s.resize(count, 1, c, true);
        for (int a = 0; a < count; ++a) encode_agent(s, a, 0, {0, 0}, goal[first + a], WorldMap{}, c);
        return s;
    };
    auto held = [&](const SceneBatch& s) {
        int k = 0;
        for (int a = 0; a < s.agents(); ++a) k += f.find(s.goal(a, c).x, s.goal(a, c).y) != nullptr;
        return k;
    };
    const SceneBatch all = batch_of(0, n);
    f.add_goals(all, c, 0.1);
    REQUIRE(f.goals.size() == (size_t)cap);
    CHECK(held(batch_of(0, cap)) == cap);  // the first agents keep theirs; the last 40 use the straight-line term
    std::vector<Vec2> kept;
    for (const MapFields::GoalField& g : f.goals) kept.push_back({g.x, g.y});
    f.add_goals(all, c, 0.1);  // the next plan of the same team: nothing made again
    for (size_t i = 0; i < f.goals.size(); ++i) CHECK((f.goals[i].x == kept[i].x && f.goals[i].y == kept[i].y));
    // A plan without the first 40 robots: their fields make way for the last 40's.
    const SceneBatch later = batch_of(40, cap);
    f.add_goals(later, c, 0.1);
    CHECK(f.goals.size() == (size_t)cap);
    CHECK(held(later) == cap);
}

TEST_CASE("goal fields: a large world keeps at most kGoalFieldBytes of them") {
    // A whole episode of 256 robots held 64 MB of goal fields (docs/speed.md); the cap in bytes
    // bounds them, and a constant-density world of 64 robots still keeps a field for every robot.
    auto fields_of = [](double half_size) {
        WorldMap m;
        m.half_size = half_size;
        MapFields f;
        f.set_map(m);
        return f;
    };
    CHECK(fields_of(3.4).max_goal_fields() >= 64);
    MapFields f = fields_of(6.8);
    const int cap = f.max_goal_fields();
    CHECK(cap < MapFields::kMaxGoalFields);
    const ModelConfig c = tiny_config();
    Rng rng(5);
    const int n = cap + 10;
    SceneBatch s;
    s.resize(n, 1, c, true);
    for (int a = 0; a < n; ++a) {
        const Vec2 goal{rng.uniform(-6, 6), rng.uniform(-6, 6)};
        encode_agent(s, a, 0, goal + Vec2{0.3, 0}, goal, f.clearance.map, c);
    }
    f.add_goals(s, c, 0.1);
    CHECK(f.goals.size() == (size_t)cap);
    size_t bytes = 0;
    for (const MapFields::GoalField& g : f.goals) bytes += g.d.size() * sizeof(float);
    CHECK(bytes <= MapFields::kGoalFieldBytes);
    CHECK(bytes + f.goals[0].d.size() * sizeof(float) > MapFields::kGoalFieldBytes);  // no field more fits
}

TEST_CASE("goal fields: the bucket queue gives a binary heap's Dijkstra to the bit") {
    // The reference: textbook Dijkstra with a binary heap over the same graph (8-connected nodes,
    // a step into a node nearer than `radius` to the map costing kBlockedFactor times its length).
    auto heap_dijkstra = [](const MapFields& fields, double gx, double gy, double radius) {
        const NodeGrid& f = fields.goal_grid;
        const int N = f.nodes;
        std::vector<float> d((size_t)N * N, std::numeric_limits<float>::infinity());
        using Entry = std::pair<float, int>;
        std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> q;
        const int c0 = std::clamp((int)std::floor((gx - f.lo) / f.cell), 0, N - 2), r0 = std::clamp((int)std::floor((gy - f.lo) / f.cell), 0, N - 2);
        for (int dr = 0; dr <= 1; ++dr)
            for (int dc = 0; dc <= 1; ++dc) {
                const int k = (r0 + dr) * N + c0 + dc;
                d[k] = (float)std::hypot(f.lo + (c0 + dc) * f.cell - gx, f.lo + (r0 + dr) * f.cell - gy);
                q.push({d[k], k});
            }
        while (!q.empty()) {
            const auto [dist, k] = q.top();
            q.pop();
            if (dist > d[k]) continue;
            for (int dr = -1; dr <= 1; ++dr)
                for (int dc = -1; dc <= 1; ++dc) {
                    const int r2 = k / N + dr, c2 = k % N + dc;
                    if ((dr == 0 && dc == 0) || r2 < 0 || r2 >= N || c2 < 0 || c2 >= N) continue;
                    const int k2 = r2 * N + c2;
                    const double step = (dr && dc ? std::sqrt(2.0) : 1.0) * f.cell * (fields.clearance_at_goal_node(r2, c2) < radius ? MapFields::kBlockedFactor : 1.0);
                    const float nd = (float)(dist + step);
                    if (nd < d[k2]) q.push({d[k2] = nd, k2});
                }
        }
        return d;
    };
    const ModelConfig c = tiny_config();
    Rng rng(7);
    MapFields f;  // one for all three maps: what it keeps of a map must go with the map
    for (const char* name : {"empty", "obstacles", "barrier"}) {
        const WorldMap map = make_map(name, rng);
        f.set_map(map);
        SceneBatch s;
        s.resize(1, 6, c, true);
        for (int a = 0; a < 6; ++a)  // goals anywhere, some inside obstacles or on the border
            encode_agent(s, a, a, {0, 0}, {rng.uniform(-1.25, 1.25), rng.uniform(-1.25, 1.25)}, map, c);
        f.add_goals(s, c, 0.1);
        REQUIRE(f.goals.size() == 6);
        for (const MapFields::GoalField& g : f.goals) {
            const std::vector<float> want = heap_dijkstra(f, g.x, g.y, 0.1);
            long differ = 0;
            for (size_t k = 0; k < want.size(); ++k) differ += want[k] != g.d[k];
            CHECK_MESSAGE(differ == 0, name << ": goal (" << g.x << ", " << g.y << ")");
        }
    }
}

TEST_CASE("window cost: the guidance gradient matches central finite differences of the cost") {
    const ModelConfig c = tiny_config();
    const WorldMap map = test_map();
    MapFields fields;
    fields.set_map(map);
    const DistanceField& field = fields.clearance;
    Rng rng(17);
    WindowCost w;
    w.agent_margin = 0.3f;  // wide enough that most pairs are inside the hinge
    w.map_margin = 0.3f;
    for (int trial = 0; trial < 4; ++trial) {
        SceneBatch s = scene_batch(c, map, 2, 4, {4, 3}, rng);
        w.geodesic = trial % 2 == 0;  // the goal term around the obstacles, or straight
        if (w.geodesic) fields.add_goals(s, c, w.radius);
        // Windows that bunch the robots together near the obstacles, so every term is active.
        Mat x(2, (long)c.horizon * s.agents());
        for (long j = 0; j < x.size(); ++j) x.data()[j] = (float)rng.uniform(-0.6, 0.6);
        for (int b = 0; b < 2; ++b) {
            Mat grad = Mat::Zero(2, x.cols());
            const double cost = window_cost(s, b, x, c, w, fields, &grad);
            CHECK(cost > 0);
            long checked = 0, nonzero = 0;
            for (long col = 0; col < x.cols(); ++col)
                for (int row = 0; row < 2; ++row) {
                    const int a = (int)(col / c.horizon), t = (int)(col % c.horizon);
                    if (a / s.n != b || s.agent_mask[a] == 0 || t == 0) {  // other scenes, padding, the pinned start
                        CHECK(grad(row, col) == 0.0f);
                        continue;
                    }
                    // Skip waypoints within a step of a field cell line (the bilinear gradient jumps there).
                    const double px = s.pose(0, a) * c.position_scale + c.window_scale * x(0, col);
                    const double py = s.pose(1, a) * c.position_scale + c.window_scale * x(1, col);
                    const double u = (px - field.lo) / field.cell, v = (py - field.lo) / field.cell;
                    if (std::fabs(u - std::round(u)) < 0.05 || std::fabs(v - std::round(v)) < 0.05) continue;
                    const float keep = x(row, col);
                    x(row, col) = keep + 1e-3f;
                    const double up = window_cost(s, b, x, c, w, fields), hi = x(row, col);
                    x(row, col) = keep - 1e-3f;
                    const double down = window_cost(s, b, x, c, w, fields), lo = x(row, col);
                    x(row, col) = keep;
                    const double fd = (up - down) / (hi - lo);
                    CHECK(grad(row, col) == doctest::Approx(fd).epsilon(2e-3).scale(1));
                    checked++;
                    nonzero += std::fabs(fd) > 1e-3;
                }
            CHECK(checked > 20);
            CHECK(nonzero > 10);
        }
    }
    // The cost of two robots that keep their distance and sit on their goals is the goal term's floor.
    SceneBatch s;
    s.resize(1, 2, c, true);
    encode_map(s, 0, WorldMap{}, c);
    encode_agent(s, 0, 0, {-0.5, 0}, {-0.5, 0}, WorldMap{}, c);
    encode_agent(s, 1, 1, {0.5, 0}, {0.5, 0}, WorldMap{}, c);
    s.count[0] = 2;
    MapFields open;
    open.set_map(WorldMap{});
    const Mat still = Mat::Zero(2, (long)c.horizon * 2);
    const double gw = WindowCost{}.goal_weight;
    CHECK(window_cost(s, 0, still, c, WindowCost{}, open) == doctest::Approx(gw * 2 * 0.01));  // straight: no goal fields made
    open.add_goals(s, c, 0.1);
    // Around the map: at most half a goal-field cell's diagonal from 0 at the goal (the four nodes
    // around it hold their exact distances).
    CHECK(window_cost(s, 0, still, c, WindowCost{}, open) <= gw * 2 * open.goal_grid.cell * std::sqrt(0.5) + 1e-9);
    CHECK(window_cost(s, 0, still, c, WindowCost{}, open) > 0);
}

namespace {
// One scene, the open map, two robots 0.6 apart swapping ends: a heads +x, b heads -x, on one line.
SceneBatch swap_pair(const ModelConfig& c) {
    SceneBatch s;
    s.resize(1, 2, c, true);
    encode_map(s, 0, WorldMap{}, c);
    encode_agent(s, 0, 0, {-0.3, 0}, {0.3, 0}, WorldMap{}, c);
    encode_agent(s, 1, 1, {0.3, 0}, {-0.3, 0}, WorldMap{}, c);
    s.count[0] = 2;
    return s;
}
// swap_pair's windows running straight through each other: each waypoint where the other starts at the end.
Mat through_each_other(const ModelConfig& c) {
    const int H = c.horizon;
    Mat x = Mat::Zero(2, 2L * H);
    for (int a = 0; a < 2; ++a)
        for (int t = 0; t < H; ++t) x(0, (long)a * H + t) = (float)((a ? -0.6 : 0.6) * t / (H - 1) / c.window_scale);
    return x;
}
}  // namespace

TEST_CASE("window cost: the keep-right push turns a head-on pair to their right, equal and opposite, cost unchanged") {
    const ModelConfig c = tiny_config();
    const SceneBatch s = swap_pair(c);
    MapFields open;
    open.set_map(WorldMap{});
    const int H = c.horizon;
    auto start = [&](int a, int k) { return (k ? s.origin[0].y : s.origin[0].x) + s.pose(k, a) * c.position_scale; };
    const Mat x = through_each_other(c);
    const WindowCost w;
    Mat plain = Mat::Zero(2, x.cols()), pushed = Mat::Zero(2, x.cols());
    const float K = 50;
    const double cost = window_cost(s, 0, x, c, w, open, &plain);
    CHECK(window_cost(s, 0, x, c, w, open, &pushed, K) == cost);
    const double reach = 2.0 * w.radius + w.agent_margin;
    int inside = 0;
    for (int t = 1; t < H; ++t) {
        const double pa = start(0, 0) + c.window_scale * x(0, t), pb = start(1, 0) + c.window_scale * x(0, (long)H + t);
        const double h = reach - std::fabs(pa - pb);
        const Eigen::Vector2f da = pushed.col(t) - plain.col(t), db = pushed.col((long)H + t) - plain.col((long)H + t);
        CHECK(da.x() == 0.0f);  // the pair's relative motion is along x: the push is across it
        CHECK(db.x() == 0.0f);
        CHECK(db.y() == doctest::Approx(-da.y()));
        if (h <= 0) {
            CHECK(da.y() == 0.0f);
            continue;
        }
        inside++;
        // a (heading +x) is pushed to -y, its right: in the gradient, +K h window_scale (unit relative motion).
        const int t1 = std::min(t + 1, H - 1);
        const double v = c.window_scale * 2 * (x(0, t1) - x(0, t - 1));
        CHECK(da.y() == doctest::Approx(K * h * c.window_scale * v / std::max(v, kKeepRightFade)).epsilon(1e-4));
    }
    CHECK(inside >= 2);  // (a bad keep_right: "sampler: every option is checked ...")
}

TEST_CASE("window cost: priorities split a pair's pushes, the higher robot moved less, cost unchanged") {
    const ModelConfig c = tiny_config();
    SceneBatch s = swap_pair(c);
    MapFields open;
    open.set_map(WorldMap{});
    const int H = c.horizon;
    const Mat x = through_each_other(c);
    const WindowCost w;
    const float K = 50;
    Mat equal = Mat::Zero(2, x.cols()), split = Mat::Zero(2, x.cols());
    const double cost = window_cost(s, 0, x, c, w, open, &equal, K);
    s.priority = {3.0f, 1.0f};  // a first: a takes 2 * 1 / 4 of its push, b 2 * 3 / 4
    CHECK(window_cost(s, 0, x, c, w, open, &split, K) == cost);
    // Only the pair terms change: with no goal term both columns' differences are the pair's.
    WindowCost pairs_only = w;
    pairs_only.goal_weight = 0;
    pairs_only.map_weight = 0;
    Mat e = Mat::Zero(2, x.cols()), sp = Mat::Zero(2, x.cols());
    s.priority = {1.0f, 1.0f};
    window_cost(s, 0, x, c, pairs_only, open, &e, K);
    s.priority = {3.0f, 1.0f};
    window_cost(s, 0, x, c, pairs_only, open, &sp, K);
    int pushed = 0;
    for (int t = 1; t < H; ++t) {
        for (int k = 0; k < 2; ++k) {
            CHECK(sp(k, t) == doctest::Approx(0.5 * e(k, t)).epsilon(1e-5));
            CHECK(sp(k, (long)H + t) == doctest::Approx(1.5 * e(k, (long)H + t)).epsilon(1e-5));
        }
        pushed += e.col(t).norm() > 0;
    }
    CHECK(pushed >= 2);
    // Equal priorities of any value are today's pushes.
    s.priority = {2.0f, 2.0f};
    Mat same = Mat::Zero(2, x.cols());
    window_cost(s, 0, x, c, w, open, &same, K);
    CHECK(same == equal);
}

TEST_CASE("planner: guidance.priority ranks a scene's robots by their way to go when first seen, in teams larger than a scene") {
    const ModelConfig c = tiny_config();
    // Distance to go when first seen: robot at x = -1.0 2.0, at x = -0.5 1.0, at x = 0.0 0.5.
    auto team = [](double first_x) {
        World w;
        w.add_agent({first_x, 0.5}, {1.0, 0.5});
        w.add_agent({0.0, -0.5}, {0.5, -0.5});
        w.add_agent({-0.5, 0.0}, {0.5, 0.0});
        return w;
    };
    const World world = team(-1.0);
    auto first_seen_distance = [](double x) { return x < -0.9 ? 2.0 : x > -0.1 ? 0.5 : 1.0; };
    DiffusionPlanner planner(MadbpModel(c, 1), 2);
    planner.settings.neighbourhood.neighbours = 2;  // scenes of two among three
    planner.settings.guidance.priority = 4;
    // In each scene of two the robot with the longer way gets 4, the other 1.
    auto check_scenes = [&](const World& w, double x_first) {
        planner.plan(w);
        const SceneBatch& b = planner.last_scene_batch();
        REQUIRE(b.n == 2);
        int scenes = 0;
        for (int s = 0; s < b.B; ++s) {
            if (b.agent_mask[2 * s] == 0 || b.agent_mask[2 * s + 1] == 0) continue;
            ++scenes;
            auto key = [&](int a) { const double x = b.position(a, c).x; return x > 0.6 ? first_seen_distance(x_first) : first_seen_distance(x); };
            const int hi = key(2 * s) > key(2 * s + 1) ? 2 * s : 2 * s + 1, lo = 4 * s + 1 - hi;
            CHECK(b.priority[hi] == 4.0f);
            CHECK(b.priority[lo] == 1.0f);
        }
        CHECK(scenes >= 2);
    };
    check_scenes(world, -1.0);
    // The key is kept while the goal stays: robot 0, moved near its goal, still counts 2.0.
    check_scenes(team(0.7), -1.0);
    // One scene of the whole team, or priority 1: every robot alike.
    planner.settings.neighbourhood.neighbours = 0;
    planner.plan(world);
    for (float p : planner.last_scene_batch().priority) CHECK(p == 1.0f);
    planner.settings.neighbourhood.neighbours = 2;
    planner.settings.guidance.priority = 1;
    planner.plan(world);
    for (float p : planner.last_scene_batch().priority) CHECK(p == 1.0f);
}

// ---------------------------------------------------------------------------------------------
// The sampler

TEST_CASE("sampler: with guidance off and k = 1 it is today's sampler, bit for bit") {
    for (Prediction pred : {Prediction::X0, Prediction::Eps}) {
        ModelConfig c = tiny_config();
        c.prediction = pred;
        MadbpModel model(c, 5);
        model.set_training(false);
        NoiseSchedule sched(c.diffusion_steps);
        const WorldMap map = test_map();
        Rng pose_rng(9);
        const SceneBatch s = scene_batch(c, map, 3, 4, {4, 2, 3}, pose_rng);
        for (uint64_t seed : {1, 2, 3}) {
            SamplerConfig sc;
            sc.sample_steps = 4;
            Rng r1(seed), r2(seed);
            Mat x1, o1, x2, o2;
            std::vector<int> b1, b2;
            ConflictWorkspace cw;
            sample_windows(model, sched, s, sc, r1, x1, o1, b1, &cw);
            reference_sample_windows(model, sched, s, sc, r2, x2, o2, b2);
            CHECK(x1 == x2);
            // `out` is scratch: it ends holding the last step's clipped x0_hat (one DDIM loop,
            // 2026-11-27), the reference's the raw network output; the windows and the random
            // stream are the sampler's behaviour.
            CHECK(o1.size() == o2.size());
            CHECK(r1.next_u64() == r2.next_u64());
            CHECK(cw.fields.clearance.nodes == 0);  // the workspace is untouched
        }
    }
    // The planner with guidance off (its default is PlannerConfig{}.guidance.weight): a plan is the reference sampler's windows.
    ModelConfig c = tiny_config();
    DiffusionPlanner planner(MadbpModel(c, 4), 21);
    CHECK(planner.settings.guidance.weight == PlannerConfig{}.guidance.weight);
    CHECK(planner.settings.sampler.end_bend == PlannerConfig{}.sampler.end_bend);
    planner.settings.guidance.weight = 0;
    planner.settings.sampler.end_bend = 0;
    World world = make_random_world("barrier", 3, 6);
    const Plan p = planner.plan(world);
    MadbpModel copy(c, 4);
    copy.set_training(false);
    NoiseSchedule sched(c.diffusion_steps);
    SamplerConfig sc = planner.sampler();
    Rng rng(21);
    Mat x, o;
    std::vector<int> b;
    reference_sample_windows(copy, sched, planner.last_scene_batch(), sc, rng, x, o, b);
    for (int i = 0; i < 3; ++i) {
        auto at = [&](int t) {  // as plan_into writes waypoints (stride 1)
            return world.agents()[i].pos + Vec2{x(0, (long)i * c.horizon + t) * (double)c.window_scale,
                                                x(1, (long)i * c.horizon + t) * (double)c.window_scale};
        };
        for (int t = 1; t < c.horizon; ++t) CHECK(p.waypoints[i][t - 1] == at(t - 1) + (at(t) - at(t - 1)) * (1.0 / 1));
    }
}

TEST_CASE("sampler: best-of-k keeps each scene's lowest-cost candidate") {
    ModelConfig c = tiny_config();
    MadbpModel model(c, 8);
    model.set_training(false);
    NoiseSchedule sched(c.diffusion_steps);
    const WorldMap map = test_map();
    Rng pose_rng(2);
    const SceneBatch s = scene_batch(c, map, 3, 3, {3, 2, 3}, pose_rng);
    ConflictWorkspace cw;
    cw.set_map(map);
    for (auto [k, guidance] : {std::pair<int, float>{1, 0.01f}, {2, 0.01f}, {5, 0.0f}}) {
        SamplerConfig sc;
        sc.sample_steps = 4;
        sc.candidates = k;
        sc.guidance = guidance;
        Rng rng(40 + k);
        Mat x, out;
        std::vector<int> buf;
        sample_windows(model, sched, s, sc, rng, x, out, buf, &cw);
        REQUIRE(x.cols() == (long)c.horizon * s.agents());
        REQUIRE(cw.cost.size() == (size_t)3 * k);
        REQUIRE(cw.x.cols() == (long)c.horizon * s.agents() * k);
        const long W = (long)s.n * c.horizon;  // one scene's columns
        for (int b = 0; b < 3; ++b) {
            int best = 0;
            for (int j = 1; j < k; ++j)
                if (cw.cost[b * k + j] < cw.cost[b * k + best]) best = j;
            CHECK(cw.best[b] == best);
            CHECK(x.middleCols(b * W, W) == cw.x.middleCols((long)(b * k + best) * W, W));
            // The kept windows' cost, recomputed on the scene itself, is the lowest of the candidates'.
            const double kept = window_cost(s, b, x, c, sc.cost, cw.fields);
            CHECK(kept == cw.cost[b * k + best]);
            for (int j = 0; j < k; ++j) CHECK(kept <= cw.cost[b * k + j]);
            if (k == 5) CHECK(cw.x.middleCols((long)(b * k) * W, W) != cw.x.middleCols((long)(b * k + 1) * W, W));  // distinct draws
        }
    }
    SamplerConfig bad;
    bad.candidates = kMaxCandidates + 1;
    Rng rng(1);
    Mat x, out;
    std::vector<int> buf;
    CHECK_THROWS_AS(sample_windows(model, sched, s, bad, rng, x, out, buf, &cw), std::invalid_argument);
    bad.candidates = 2;
    CHECK_THROWS_AS(sample_windows(model, sched, s, bad, rng, x, out, buf), std::invalid_argument);  // no workspace
    bad.guidance = -1;
    bad.candidates = 1;
    CHECK_THROWS_AS(sample_windows(model, sched, s, bad, rng, x, out, buf, &cw), std::invalid_argument);
}

TEST_CASE("sampler: every option is checked on either path, and a bad one is named") {
    const ModelConfig c = tiny_config();
    const SceneBatch s = swap_pair(c);
    MadbpModel model(c, 5);
    NoiseSchedule sched(c.diffusion_steps);
    ConflictWorkspace cw;
    cw.set_map(WorldMap{});
    Rng rng(1);
    Mat x, out;
    std::vector<int> buf;
    const float nan = std::numeric_limits<float>::quiet_NaN();
    struct Bad { const char* field; std::function<void(SamplerConfig&)> set; };
    const Bad bad[] = {{"sample_steps", [](SamplerConfig& o) { o.sample_steps = 0; }},
                       {"sample_steps", [&](SamplerConfig& o) { o.sample_steps = c.diffusion_steps + 1; }},
                       {"x0_clip", [](SamplerConfig& o) { o.x0_clip = -1; }},  // a clamp to [1, -1] would be undefined
                       {"x0_clip", [&](SamplerConfig& o) { o.x0_clip = nan; }},
                       {"goal_reach", [&](SamplerConfig& o) { o.goal_reach = nan; }},
                       {"candidates", [](SamplerConfig& o) { o.candidates = 0; }},
                       {"guidance", [](SamplerConfig& o) { o.guidance = -1; }},
                       {"keep_right", [](SamplerConfig& o) { o.keep_right = -1; }},
                       {"end_bend", [](SamplerConfig& o) { o.end_bend = 1.5f; }},
                       {"end_bend", [&](SamplerConfig& o) { o.end_bend = nan; }},
                       {"warm_start", [](SamplerConfig& o) { o.warm_start = -1; }},
                       {"cost.agent_margin", [](SamplerConfig& o) { o.cost.agent_margin = -0.1f; }},
                       {"cost.goal_weight", [](SamplerConfig& o) { o.cost.goal_weight = INFINITY; }}};
    for (bool guided : {false, true})
        for (const Bad& b : bad) {
            CAPTURE(b.field);
            CAPTURE(guided);
            SamplerConfig sc;
            sc.guidance = guided ? 0.004f : 0.0f;  // the plain path (no workspace needed) and the conflict-aware one
            CHECK_NOTHROW(sc.validate(c.diffusion_steps));
            b.set(sc);
            CHECK_THROWS_WITH_AS(sc.validate(c.diffusion_steps), doctest::Contains(b.field), std::invalid_argument);
            CHECK_THROWS_WITH_AS(sample_windows(model, sched, s, sc, rng, x, out, buf, &cw), doctest::Contains(b.field), std::invalid_argument);
        }
}

// Two robots head-on, robot 0 at (-0.4, 0.01) heading +x, robot 1 at (0.4, -0.01) heading -x,
// and an oracle whose clean windows drive them through each other (0.1 world units a step
// each: they meet at t = 4).
namespace {
struct HeadOn {
    ModelConfig c = tiny_config();
    SceneBatch s;
    OracleDenoiser oracle{c, Mat::Zero(2, (long)c.horizon * 2)};
    HeadOn() {
        const int H = c.horizon;
        s.resize(1, 2, c, true);
        encode_map(s, 0, WorldMap{}, c);
        encode_agent(s, 0, 0, {-0.4, 0.01}, {0.8, 0.0}, WorldMap{}, c);
        encode_agent(s, 1, 1, {0.4, -0.01}, {-0.8, 0.0}, WorldMap{}, c);
        s.count[0] = 2;
        for (int t = 0; t < H; ++t) {
            oracle.x0(0, t) = (float)(0.1 * t / c.window_scale);
            oracle.x0(0, H + t) = -oracle.x0(0, t);
        }
    }
    // Robot 0's position minus robot 1's at waypoint t of windows x.
    Vec2 apart(const Mat& x, int t) const {
        const int H = c.horizon;
        return {-0.8 + c.window_scale * (x(0, t) - x(0, H + t)), 0.02 + c.window_scale * (x(1, t) - x(1, H + t))};
    }
    double closest(const Mat& x) const {
        double d = 1e9;
        for (int t = 1; t < c.horizon; ++t) d = std::min(d, norm(apart(x, t)));
        return d;
    }
};
}  // namespace

TEST_CASE("sampler: guidance moves windows that collide apart") {
    HeadOn head_on;
    const ModelConfig& c = head_on.c;
    const SceneBatch& s = head_on.s;
    auto& oracle = head_on.oracle;
    auto closest = [&](const Mat& x) { return head_on.closest(x); };
    NoiseSchedule sched(c.diffusion_steps);
    ConflictWorkspace cw;
    cw.set_map(WorldMap{});
    SamplerConfig sc;
    sc.sample_steps = 5;
    sc.goal_inpaint = false;
    sc.cost.goal_weight = 0;  // the robot-robot term alone
    Rng r1(5), r2(5);
    Mat plain, guided, out;
    std::vector<int> buf;
    sc.candidates = 2;  // the conflict-aware path, unguided
    sample_windows(oracle, sched, s, sc, r1, plain, out, buf, &cw);
    const double cost_plain = window_cost(s, 0, plain, c, sc.cost, cw.fields);
    sc.guidance = 2e-3f;
    sample_windows(oracle, sched, s, sc, r2, guided, out, buf, &cw);
    const double cost_guided = window_cost(s, 0, guided, c, sc.cost, cw.fields);
    CHECK(closest(plain) < 0.1);   // the oracle's windows pass through each other
    CHECK(cost_guided < cost_plain);
    CHECK(closest(guided) > closest(plain) + 0.05);
}

TEST_CASE("sampler: with keep-right a head-on pair passes each on its own right") {
    HeadOn head_on;
    NoiseSchedule sched(head_on.c.diffusion_steps);
    ConflictWorkspace cw;
    cw.set_map(WorldMap{});
    SamplerConfig sc;
    sc.sample_steps = 5;
    sc.goal_inpaint = false;
    sc.cost.goal_weight = 0;
    sc.guidance = 2e-3f;
    Mat plain, right, out;
    std::vector<int> buf;
    Rng r1(5), r2(5);
    sample_windows(head_on.oracle, sched, head_on.s, sc, r1, plain, out, buf, &cw);
    sc.keep_right = 300;
    sample_windows(head_on.oracle, sched, head_on.s, sc, r2, right, out, buf, &cw);
    // Where they meet (t = 4): without the push robot 0 passes on the side it started on (0.02
    // above robot 1: its left); with it, below (its right, and robot 1's right).
    CHECK(head_on.apart(plain, 4).y > 0);
    CHECK(head_on.apart(right, 4).y < 0);
    // The pair moves along x, so the push is along y only, robot 0 down and robot 1 up alike.
    const int H = head_on.c.horizon;
    int pushed = 0;
    for (int t = 1; t < H; ++t) {
        CHECK(right(0, t) == doctest::Approx(plain(0, t)).epsilon(1e-4).scale(1e-3));
        CHECK(right(0, H + t) == doctest::Approx(plain(0, H + t)).epsilon(1e-4).scale(1e-3));
        const float down = right(1, t) - plain(1, t), up = right(1, H + t) - plain(1, H + t);
        CHECK(down <= 1e-5f);
        CHECK(up == doctest::Approx(-down).epsilon(1e-3).scale(1e-4));
        pushed += down < -1e-3f;
    }
    CHECK(pushed >= 2);
}

TEST_CASE("planner: conflict-aware and warm-started plans allocate nothing in the steady state") {
    set_num_threads(1);
    ModelConfig c;  // the default configuration
    DiffusionPlanner planner(MadbpModel(c, 1), 3);
    planner.settings.guidance.weight = 0.01f;
    planner.settings.sampler.candidates = 3;
    World w = make_random_world("barrier", 4, 4), later = w;
    for (int k = 0; k < 8; ++k) later.step(std::vector<Vec2>(4, Vec2{0.1, 0}));
    Plan plan;
    // w and `later` in turn: a cold plan (the clock went back) and a warm one (SamplerConfig::warm_start).
    auto both = [&] { planner.plan_into(w, plan); planner.plan_into(later, plan); };
    for (int i = 0; i < 3; ++i) both();  // warm-up: workspaces and the distance field
    [[maybe_unused]] const long allocs = count_allocs([&] { for (int i = 0; i < 3; ++i) both(); });
#if MADBP_TEST_COUNT_ALLOCS
    CHECK(allocs == 0);
#endif
    CHECK(plan.ids.size() == 4);
    CHECK(planner.last_candidates().cost.size() == 3);
    CHECK(planner.last_candidates().fields.clearance.built_for(w.map()));
    CHECK(planner.last_candidates().fields.goals.size() == 4);
}

TEST_CASE("planner: a plan of at most 4 robot windows draws small_plan_candidates; a larger one sampler.candidates") {
    const ModelConfig c = tiny_config();  // n_max 6
    CHECK(PlannerConfig{}.sampler.small_plan_candidates == 2);
    auto drawn = [&](int n, int small, int candidates, Plan* out = nullptr) {
        DiffusionPlanner planner(MadbpModel(c, 1), 3);
        planner.settings.sampler.small_plan_candidates = small;
        planner.settings.sampler.candidates = candidates;
        const Plan p = planner.plan(make_random_world("obstacles", n, 5));
        if (out) *out = p;
        CHECK(planner.last_candidates().cost.size() == (size_t)planner.last_plan_candidates());  // one scene: k costs
        return planner.last_plan_candidates();
    };
    CHECK(drawn(1, 2, 1) == 2);
    CHECK(drawn(4, 2, 1) == 2);
    CHECK(drawn(4, 2, 3) == 3);  // never fewer than sampler.candidates
    CHECK(drawn(4, 1, 1) == 1);  // off
    CHECK(drawn(5, 2, 1) == 1);  // one scene of 5: the batch of a team of 8 would grow
    // The same plan as a planner told to draw 2 for every plan: the rule only picks k.
    Plan small, every;
    drawn(4, 2, 1, &small);
    drawn(4, 1, 2, &every);
    for (int i = 0; i < 4; ++i)
        for (size_t t = 0; t < small.waypoints[i].size(); ++t) {
            CHECK(small.waypoints[i][t].x == every.waypoints[i][t].x);
            CHECK(small.waypoints[i][t].y == every.waypoints[i][t].y);
        }
    // A scene per robot counts the team's windows (n scenes): a pair in a larger world draws 2,
    // three robots draw 1, and plan_robot counts as its team's plan would.
    for (int n : {2, 3}) {
        const World w = make_random_world("obstacles", n, 5, 2.4);
        DiffusionPlanner team(MadbpModel(c, 1), 3), robot(MadbpModel(c, 1), 3);
        team.settings.neighbourhood.cover = 0;
        team.plan(w);
        CHECK(team.last_scene_batch().B == n);
        CHECK(team.last_plan_candidates() == (n == 2 ? 2 : 1));
        std::vector<DiffusionPlanner::Neighbour> others;
        for (int j = 1; j < n; ++j) others.push_back({w.agents()[j].pos, w.agents()[j].goal, w.agents()[j].id});
        std::vector<Vec2> window;
        robot.plan_robot(w.map(), w.agents()[0].id, w.agents()[0].pos, w.agents()[0].goal, others, window);
        CHECK(robot.last_plan_candidates() == team.last_plan_candidates());
    }
    DiffusionPlanner bad(MadbpModel(c, 1), 3);
    bad.settings.sampler.small_plan_candidates = 0;
    CHECK_THROWS_WITH_AS(bad.plan(make_random_world("obstacles", 2, 5)), doctest::Contains("small_plan_candidates"), std::invalid_argument);
    bad.settings.sampler.small_plan_candidates = kMaxCandidates + 1;  // refused for a large team too, where the rule does not apply
    CHECK_THROWS_WITH_AS(bad.plan(make_random_world("obstacles", 6, 5)), doctest::Contains("small_plan_candidates"), std::invalid_argument);
}

TEST_CASE("route steps: the guided expert's wavefront, so around a barrier the longer way is the larger key") {
    RouteGuide guide;
    WorldMap barrier;
    barrier.boxes.push_back({Vec2{-1.2, -0.05}, Vec2{0.6, 0.05}});  // the way through is at x > 0.6
    CHECK(guide.route_steps(WorldMap{}, {-0.5, 0}, {0.5, 0}) == doctest::Approx(1.0 / guide.cell).epsilon(0.1));
    CHECK(guide.route_steps(barrier, {0, -0.5}, {0, 0.5}) > 1.5 * guide.route_steps(WorldMap{}, {0, -0.5}, {0, 0.5}));
}

TEST_CASE("sampler: the end bend makes a window that heads for its pinned goal arrive, and keeps one that leaves") {
    // Robot 0 heads for its goal 0.3 ahead but the oracle's window ends 0.1 short of it; robot 1's
    // goal is 0.2 away too, but its window leaves it (making way); robot 2's goal is out of reach.
    const ModelConfig c = tiny_config();
    const int H = c.horizon;
    SceneBatch s;
    s.resize(1, 3, c, true);
    encode_map(s, 0, WorldMap{}, c);
    encode_agent(s, 0, 0, {0, 0}, {0.3, 0}, WorldMap{}, c);
    encode_agent(s, 1, 1, {0.5, 0.5}, {0.5, 0.7}, WorldMap{}, c);
    encode_agent(s, 2, 2, {-0.5, 0.5}, {-0.5, -0.5}, WorldMap{}, c);
    s.count[0] = 3;
    OracleDenoiser oracle{c, Mat::Zero(2, (long)H * 3)};
    for (int t = 0; t < H; ++t) {
        oracle.x0(0, t) = (float)(std::min(0.04 * t, 0.2) / c.window_scale);
        oracle.x0(1, H + t) = (float)(-0.02 * t / c.window_scale);
        oracle.x0(1, 2 * H + t) = (float)(-0.02 * t / c.window_scale);
    }
    NoiseSchedule sched(c.diffusion_steps);
    ConflictWorkspace cw;
    cw.set_map(WorldMap{});
    for (int candidates : {1, 2}) {  // the plain path and the conflict-aware one
        CAPTURE(candidates);
        SamplerConfig sc;
        sc.candidates = candidates;
        Mat plain, bent, half, out;
        std::vector<int> buf;
        Rng r1(3), r2(3), r3(3);
        sample_windows(oracle, sched, s, sc, r1, plain, out, buf, &cw);
        sc.end_bend = 1;
        sample_windows(oracle, sched, s, sc, r2, bent, out, buf, &cw);
        sc.end_bend = 0.5f;
        sample_windows(oracle, sched, s, sc, r3, half, out, buf, &cw);
        const float end = (float)(0.3 / c.window_scale);
        REQUIRE(plain(0, H - 1) == doctest::Approx(end));            // pinned
        REQUIRE(plain(0, H - 2) == doctest::Approx(0.2 / c.window_scale).epsilon(1e-3));  // stops short
        CHECK(bent(0, 0) == 0);
        CHECK(bent(0, H - 2) == doctest::Approx(end).epsilon(1e-5));  // arrives one waypoint early
        CHECK(half(0, H - 2) == doctest::Approx(0.5 * (plain(0, H - 2) + end)).epsilon(1e-5));
        for (int t = 1; t <= H - 2; ++t) {
            const float moved = (end - plain(0, H - 2)) * (float)t / (float)(H - 2);
            CHECK(bent(0, t) == doctest::Approx(plain(0, t) + moved).epsilon(1e-5));
            CHECK(bent(1, t) == doctest::Approx(plain(1, t)).epsilon(1e-5).scale(1e-6));
        }
        CHECK(bent.middleCols(H, 2 * H) == plain.middleCols(H, 2 * H));  // robot 1 leaves its goal, robot 2's is out of reach
        sc.goal_inpaint = false;  // nothing is pinned: nothing bends
        Rng r4(3);
        sample_windows(oracle, sched, s, sc, r4, bent, out, buf, &cw);
        CHECK(bent.middleCols(0, H) != plain.middleCols(0, H));
        CHECK(bent(0, H - 2) == doctest::Approx(plain(0, H - 2)).epsilon(1e-5));
    }
}

// ---------------------------------------------------------------------------------------------
// Warm start (SamplerConfig::warm_start)

namespace {
// Predicts zero noise (eps mode): each DDIM step then only rescales x by sqrt(ab_prev / ab), so a
// draw ends at x_top / sqrt(ab_top), which shows exactly where it started and from what.
struct ZeroNoiseDenoiser {
    ModelConfig config;
    void encode_context(const SceneBatch&) {}
    void denoise(const Mat& x, const int*, Mat& out) { out.setZero(2, x.cols()); }
};
}  // namespace

TEST_CASE("sampler: a warm start runs the last warm_start DDIM steps from the warm windows noised to that level") {
    ModelConfig c = tiny_config();
    c.prediction = Prediction::Eps;
    ZeroNoiseDenoiser zero{c};
    NoiseSchedule sched(c.diffusion_steps);
    const WorldMap map = test_map();
    Rng pose_rng(4);
    const SceneBatch s = scene_batch(c, map, 2, 3, {3, 2}, pose_rng);  // agent 5 is an empty slot
    const int H = c.horizon, S = 5, W = 2;
    const long A = s.agents();
    Mat warm(2, (long)H * A);
    Rng warm_rng(8);
    for (long j = 0; j < warm.size(); ++j) warm.data()[j] = (float)warm_rng.uniform(-0.5, 0.5);
    ConflictWorkspace cw;
    cw.set_map(map);
    const double ab_top = sched.alpha_bar[sched.ddim_step(S, S)], ab_w = sched.alpha_bar[sched.ddim_step(W, S)];
    for (int k : {1, 2}) {  // the plain path, and the conflict-aware one (every candidate from its scene's warm windows)
        CAPTURE(k);
        SamplerConfig sc;
        sc.sample_steps = S;
        sc.goal_inpaint = false;
        sc.x0_clip = 1e6f;
        sc.candidates = k;
        Mat cold, warmed, ignored, out;
        std::vector<int> buf;
        Rng r1(7), r2(7), r3(7);
        sample_windows(zero, sched, s, sc, r1, cold, out, buf, &cw, &warm);  // warm_start 0: the warm windows are ignored
        const Mat cold_all = k > 1 ? cw.x : cold;
        sc.warm_start = W;
        sample_windows(zero, sched, s, sc, r2, warmed, out, buf, &cw, &warm);
        const Mat warm_all = k > 1 ? cw.x : warmed;
        sc.warm_start = S;  // all S steps: a cold draw, bit for bit
        sample_windows(zero, sched, s, sc, r3, ignored, out, buf, &cw, &warm);
        CHECK(ignored == cold);
        // cold = noise / sqrt(ab_top); warm = warm + sqrt((1 - ab_w) / ab_w) noise, with the same noise.
        for (int j = 0; j < k; ++j)
            for (long a = 0; a < A; ++a)
                for (int t = 0; t < H; ++t) {
                    const long col = (long)(a / s.n * k + j) * s.n * H + (a % s.n) * H + t, wcol = a * H + t;
                    for (int r = 0; r < 2; ++r) {
                        const double noise = cold_all(r, col) * std::sqrt(ab_top);
                        const double expect = s.agent_mask[a] == 0 || t == 0 ? 0.0 : warm(r, wcol) + std::sqrt((1 - ab_w) / ab_w) * noise;
                        CHECK(warm_all(r, col) == doctest::Approx(expect).epsilon(1e-4).scale(1));
                    }
                }
    }
    SamplerConfig sc;
    sc.sample_steps = S;
    sc.warm_start = W;
    Mat x, out, wrong = Mat::Zero(2, H);
    std::vector<int> buf;
    Rng rng(1);
    CHECK_THROWS_WITH_AS(sample_windows(zero, sched, s, sc, rng, x, out, buf, &cw, &wrong), doctest::Contains("warm windows"), std::invalid_argument);
}

TEST_CASE("warm window: the last window from now on, as displacements from where the robot is, held past its end") {
    for (int stride : {1, 2}) {
        CAPTURE(stride);
        ModelConfig c = tiny_config();
        c.waypoint_stride = stride;
        const int H = c.horizon, L = (H - 1) * stride;
        std::vector<Vec2> last(L);
        for (int k = 0; k < L; ++k) last[k] = {0.1 + 0.03 * (k + 1), -0.2 + 0.01 * (k + 1) * (k + 1)};  // waypoint for step k + 1
        const Vec2 pos{0.2, -0.15};
        Mat x = Mat::Constant(2, 3 * H, 9.f);
        for (long elapsed : {1L, 3L, (long)L - 1}) {
            CAPTURE(elapsed);
            REQUIRE(detail::warm_window(last, elapsed, pos, c, x, H));
            CHECK(x(0, H) == 0);
            CHECK(x(1, H) == 0);
            for (int t = 1; t < H; ++t) {
                const Vec2 w = last[(size_t)std::min(elapsed + (long)t * stride, (long)L) - 1];
                CHECK(x(0, H + t) == doctest::Approx((w.x - pos.x) / c.window_scale));
                CHECK(x(1, H + t) == doctest::Approx((w.y - pos.y) / c.window_scale));
            }
            CHECK(x(0, 0) == 9.f);  // other robots' columns untouched
            CHECK(x(0, 2 * H) == 9.f);
        }
        // Waypoint t = 1 after 3 steps is the one planned for step 3 + stride; past the end, the last.
        detail::warm_window(last, 3, pos, c, x, 0);
        CHECK(x(0, 1) == doctest::Approx((last[3 + stride - 1].x - pos.x) / c.window_scale));
        CHECK(x(0, H - 1) == doctest::Approx((last[L - 1].x - pos.x) / c.window_scale));
        // Nothing left for now, or no time passed: no warm window, x untouched.
        const Mat before = x;
        CHECK_FALSE(detail::warm_window(last, 0, pos, c, x, 0));
        CHECK_FALSE(detail::warm_window(last, L, pos, c, x, 0));
        CHECK_FALSE(detail::warm_window({}, 1, pos, c, x, 0));
        CHECK(x == before);
    }
}

// The plan's waypoints are the windows x (2, H*n) drawn by hand, one scene of the world's n robots.
static void check_plan_is(const Mat& x, const World& w, const Plan& p, const ModelConfig& c) {
    const int H = c.horizon;
    for (int i = 0; i < w.size(); ++i)
        for (int t = 1; t < H; ++t) {
            const Vec2 q = w.agents()[i].pos + Vec2{x(0, (long)i * H + t) * (double)c.window_scale, x(1, (long)i * H + t) * (double)c.window_scale};
            CHECK(p.waypoints[i][t - 1].x == doctest::Approx(q.x));
            CHECK(p.waypoints[i][t - 1].y == doctest::Approx(q.y));
        }
}

TEST_CASE("planner: a warm start draws each robot's window from its last one shifted to now; a new episode draws cold") {
    const ModelConfig c = tiny_config();
    const int H = c.horizon, n = 3;
    DiffusionPlanner warm(MadbpModel(c, 2), 11), cold(MadbpModel(c, 2), 11);
    CHECK(warm.settings.sampler.warm_start == PlannerConfig{}.sampler.warm_start);
    // The planner's S: PlannerConfig{}.sampler.sample_steps, or the model's own where fewer (the tiny model's 5).
    CHECK(warm.sampler().sample_steps == std::min(PlannerConfig{}.sampler.sample_steps, c.sample_steps));
    ModelConfig shipped_steps = c;
    shipped_steps.sample_steps = 10;
    CHECK(DiffusionPlanner(MadbpModel(shipped_steps, 2)).sampler().sample_steps == PlannerConfig{}.sampler.sample_steps);
    cold.settings.sampler.warm_start = 0;
    for (DiffusionPlanner* p : {&warm, &cold}) {  // the plain path, first plans from noise (line_start's own test below)
        p->settings.guidance.weight = 0;
        p->settings.sampler.end_bend = 0;
        p->settings.sampler.line_start = false;
        p->settings.sampler.small_plan_candidates = 1;  // one window a robot, as the hand-drawn reference
    }
    warm.settings.sampler.warm_start = 2;  // of the tiny model's 5 steps
    // The same draws by hand: the reference sampler's rng and model.
    MadbpModel copy(c, 2);
    copy.set_training(false);
    NoiseSchedule sched(c.diffusion_steps);
    Rng rng(11);
    Mat x, out, warm_x;
    std::vector<int> buf;
    auto expect_plan = [&](const World& w, const Plan& p) { check_plan_is(x, w, p, c); };
    World world = make_random_world("obstacles", n, 3);
    const Plan first = warm.plan(world), first_cold = cold.plan(world);  // no last window yet: both draw cold
    CHECK(first.waypoints == first_cold.waypoints);
    sample_windows(copy, sched, warm.last_scene_batch(), warm.sampler(), rng, x, out, buf);
    expect_plan(world, first);
    for (int k = 0; k < 3; ++k) world.step(std::vector<Vec2>(n, Vec2{0.2, 0.1}));
    const Plan second = warm.plan(world), second_cold = cold.plan(world);
    warm_x.setZero(2, (long)H * n);
    for (int i = 0; i < n; ++i) REQUIRE(detail::warm_window(first.waypoints[i], 3, world.agents()[i].pos, c, warm_x, (long)i * H));
    sample_windows(copy, sched, warm.last_scene_batch(), warm.sampler(), rng, x, out, buf, nullptr, &warm_x);
    expect_plan(world, second);
    CHECK(second.waypoints != second_cold.waypoints);
    // A new episode (the world's clock went back): cold again.
    World next = make_random_world("obstacles", n, 4);
    const Plan third = warm.plan(next);
    SamplerConfig no_warm = warm.sampler();
    no_warm.warm_start = 0;
    sample_windows(copy, sched, warm.last_scene_batch(), no_warm, rng, x, out, buf);
    expect_plan(next, third);
}

TEST_CASE("planner: line_start: a robot without a last window starts from a straight line toward its goal") {
    const ModelConfig c = tiny_config();  // no route subgoals: each robot heads for its goal
    const int H = c.horizon, n = 3;
    DiffusionPlanner planner(MadbpModel(c, 2), 11);
    CHECK(planner.settings.sampler.line_start == PlannerConfig{}.sampler.line_start);
    planner.settings.sampler.line_start = true;
    planner.settings.guidance.weight = 0;  // the plain path
    planner.settings.sampler.end_bend = 0;
    planner.settings.sampler.warm_start = 2;  // of the tiny model's 5 DDIM steps
    planner.settings.sampler.small_plan_candidates = 1;  // one window a robot, as the hand-drawn reference
    MadbpModel copy(c, 2);
    copy.set_training(false);
    NoiseSchedule sched(c.diffusion_steps);
    Rng rng(11);
    Mat x, out;
    std::vector<int> buf;
    World world = make_random_world("empty", n, 3);
    const Vec2 near{world.agents()[1].pos.x > 0 ? -0.2 : 0.2, 0.1};  // a goal nearer than a window's reach, inside the world
    world.set_goal(world.agents()[1].id, world.agents()[1].pos + near);
    const Plan first = planner.plan(world);
    // The line by hand: waypoint t at t / (H - 1) of the reach, which stops at a goal nearer than window_scale.
    Mat line = Mat::Zero(2, (long)H * n);
    for (int i = 0; i < n; ++i) {
        const Vec2 d = world.agents()[i].goal - world.agents()[i].pos;
        const double reach = std::min(1.0, norm(d) / c.window_scale);
        for (int t = 1; t < H; ++t) {
            line(0, (long)i * H + t) = (float)(reach * t / (H - 1) * d.x / norm(d));
            line(1, (long)i * H + t) = (float)(reach * t / (H - 1) * d.y / norm(d));
        }
    }
    CHECK(line(0, 2L * H - 1) == doctest::Approx(near.x / c.window_scale));  // robot 1's line ends on its goal
    CHECK(line(1, 2L * H - 1) == doctest::Approx(near.y / c.window_scale));
    sample_windows(copy, sched, planner.last_scene_batch(), planner.sampler(), rng, x, out, buf, nullptr, &line);
    check_plan_is(x, world, first, c);
    // Without line_start the same first plan draws all S steps from noise.
    DiffusionPlanner from_noise(MadbpModel(c, 2), 11);
    from_noise.settings = planner.settings;
    from_noise.settings.sampler.line_start = false;
    CHECK(from_noise.plan(world).waypoints != first.waypoints);
}
