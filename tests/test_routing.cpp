// Routing at any scale (issue 46 item 1; docs/design.md, "Routing at any scale"): the routing
// grid (ClearanceGrid, wavefront, RouteGuide, GuidedExpert; madbp_sim.hpp Sections 2 and 12)
// finds every passage at least 0.25 wide wherever it falls in worlds of half-size 2-40, the
// expert crosses large worlds, and its workspace stays within the bounds of docs/limits.md.
#include <doctest/doctest.h>

#include "madbp_sim.hpp"

using namespace madbp;

namespace {

// A wall of thickness `width` across the world at y = y0 with one gap of `width` centred at x0
// (a one-cell aisle of a map converted at `width` per cell).
WorldMap aisle_map(double half, double width, double x0, double y0) {
    WorldMap m;
    m.half_size = half;
    const double w = 0.5 * width;
    m.boxes.push_back({{-half, y0 - w}, {x0 - w, y0 + w}});
    m.boxes.push_back({{x0 + w, y0 - w}, {half, y0 + w}});
    return m;
}

// Shelves of a warehouse at half-size `half`: rows of boxes 0.3 deep, 0.6 apart, split by a
// cross aisle at x = 0; robots stand in the aisles.
WorldMap warehouse_map(double half) {
    WorldMap m;
    m.half_size = half;
    for (double y = -half + 1; y + 0.3 < half - 1; y += 0.9) {
        m.boxes.push_back({{-half + 1, y}, {-1, y + 0.3}});
        m.boxes.push_back({{1, y}, {half - 1, y + 0.3}});
    }
    return m;
}
Vec2 aisle_point(double half, Rng& rng) {
    const int rows = (int)((2 * half - 2.3) / 0.9);
    const double y = -half + 1 + 0.3 + 0.3 + 0.9 * rng.uniform_int(rows - 1);  // an aisle's centre line
    const double x = (rng.uniform() < 0.5 ? -1 : 1) * rng.uniform(2, half - 2);
    return {x, y};
}

}  // namespace

TEST_CASE("routing: a one-cell aisle 0.25-0.4 wide is routable in worlds of half-size 2-40, wherever it falls") {
    Rng rng(46);
    for (int config = 0; config < 20; ++config) {
        const double half = rng.uniform(2, 40), width = rng.uniform(0.25, 0.4);
        const double x0 = rng.uniform(-0.5, 0.5) * (half - 2), y0 = rng.uniform(-0.5, 0.5) * (half - 2);
        const WorldMap map = aisle_map(half, width, x0, y0);
        const Vec2 start{x0 - 0.8, y0 - 1.2}, goal{x0 + 0.8, y0 + 1.2};  // the straight way is blocked
        CAPTURE(config);
        CAPTURE(half);
        CAPTURE(width);
        CAPTURE(x0);
        CAPTURE(y0);
        // The route guide: a route exists, and its cells cross the wall inside the gap.
        RouteGuide guide;
        REQUIRE(guide.route_steps(map, start, goal) < RouteGuide::kRouteUnreachable);
        std::vector<int> cells;
        guide.route_cells(map, start, goal, 1 << 20, cells);
        REQUIRE(!cells.empty());
        CHECK(cells.back() == guide.grid().index(goal));
        bool through_gap = false;
        for (int k : cells) {
            const Vec2 c = guide.grid().centre(k);
            if (std::abs(c.y - y0) < 0.5 * width) through_gap = std::abs(c.x - x0) < 0.5 * width;
            CHECK(static_clearance(map, c) >= 0.1);  // every route cell keeps the robot off the map
        }
        CHECK(through_gap);
        // The subgoal walk leads toward the gap, not straight at the goal through the wall.
        const RouteGoal sub = guide.subgoal(map, start, goal, 0.6);
        CHECK_FALSE(sub.final);
        CHECK(norm(sub.goal - Vec2{x0, y0}) < norm(start - Vec2{x0, y0}));
        // The guided expert's planning grid: the same cells and its own wavefront reach through.
        const ExpertParams ep;
        const GuidedExpert expert(map, ep);
        CHECK(expert.grid().n == guide.grid().n);
        CHECK(expert.grid().cell == doctest::Approx(guide.grid().cell));
        const std::vector<int> steps = wavefront(expert.grid(), expert.grid().index(goal), ep.route());
        CHECK(steps[expert.grid().index(start)] >= 0);
    }
}

TEST_CASE("routing: a gap narrower than a robot is no route, and the soft clearance keeps wide ways first") {
    // 0.2 wide: no centre fits (control for the test above).
    const WorldMap narrow = aisle_map(6, 0.2, 0.3, 0.1);
    RouteGuide guide;
    CHECK(guide.route_steps(narrow, {-0.5, -1}, {1.1, 1.2}) == RouteGuide::kRouteUnreachable);
    // A 0.25 gap (its centre keeps 0.125 < the preferred 0.13) beside a 1.0 gap 0.8 away: the
    // route takes the wide one (the narrow one costs narrow_cost extra per cell), unless
    // narrow_cost is 0.
    WorldMap two;
    two.half_size = 3;
    two.boxes = {{{-3, -0.15}, {-0.125, 0.15}}, {{0.125, -0.15}, {0.8, 0.15}}, {{1.8, -0.15}, {3, 0.15}}};
    auto crossing_x = [&](RouteGuide& g) {
        std::vector<int> cells;
        g.route_cells(two, {0, -1}, {0, 1}, 1 << 20, cells);
        for (int k : cells)
            if (std::abs(g.grid().centre(k).y) < 0.05) return g.grid().centre(k).x;
        return -100.0;
    };
    RouteGuide soft;
    CHECK(crossing_x(soft) > 0.8);
    RouteGuide hard_free;
    hard_free.narrow_cost = 0;
    CHECK(std::abs(crossing_x(hard_free)) < 0.15);
    // Bad settings are refused naming the field.
    RouteGuide bad;
    bad.narrow_cost = -1;
    CHECK_THROWS_WITH_AS(bad.grid(two), doctest::Contains("RouteGuide.narrow_cost"), std::invalid_argument);
    ExpertParams ep;
    ep.min_clear = 0.2;  // above inflate
    CHECK_THROWS_WITH_AS(GuidedExpert(two, ep), doctest::Contains("ExpertParams.min_clear"), std::invalid_argument);
}

TEST_CASE("routing: the expert crosses large empty worlds and reaches a near goal in a huge one") {
    {  // Two robots crossing paths over 28 units in half-size 28.8.
        WorldConfig wc;
        wc.max_steps = 1800;
        World w(WorldMap{28.8, {}, {}}, wc);
        w.add_agent({-10, -10}, {10, 10});
        w.add_agent({10, -10}, {-10, 10});
        GuidedExpert expert(w.map());
        const EpisodeResult r = run_episode(w, expert);
        CHECK(r.success);
        CHECK(r.collisions() == 0);
        CHECK(r.steps < 1200);  // about 790 steps at cruise
    }
    {  // One robot 1.4 from its goal in half-size 34.
        WorldConfig wc;
        wc.max_steps = 200;
        World w(WorldMap{34, {}, {}}, wc);
        w.add_agent({3.013, -2.021}, {3.013 + 0.99, -2.021 + 0.99});
        GuidedExpert expert(w.map());
        const EpisodeResult r = run_episode(w, expert);
        CHECK(r.success);
        CHECK(r.steps < 100);
    }
    {  // Through a 0.3 aisle off the grid's lines in half-size 20.
        WorldConfig wc;
        wc.max_steps = 500;
        World w(aisle_map(20, 0.3, 3.317, -5.123), wc);
        w.add_agent({3.317 - 1.5, -5.123 - 1.5}, {3.317 + 1.5, -5.123 + 1.5});
        GuidedExpert expert(w.map());
        const EpisodeResult r = run_episode(w, expert);
        CHECK(r.success);
        CHECK(r.collisions() == 0);
    }
}

TEST_CASE("routing: the expert's and the route guide's workspace stay within their bounds at half-size 25") {
    const double half = 25;
    const WorldMap map = warehouse_map(half);
    Rng rng(7);
    WorldConfig wc;
    wc.max_steps = 2000;
    World w(map, wc);
    for (int i = 0; i < 16; ++i) w.add_agent(aisle_point(half, rng), aisle_point(half, rng));
    GuidedExpert expert(w.map());
    for (int t = 0; t < 12; ++t) w.step(expert.act(w));
    const ClearanceGrid& g = expert.grid();
    CHECK(g.n == 1389);  // cells of 0.036 at half-size 25 (no coarsening)
    // A field of this world's routes fits 2 bytes a cell (RouteField).
    const size_t grid_bytes = (size_t)g.n * g.n * sizeof(float), field_bytes = (size_t)g.n * g.n * sizeof(uint16_t);
    const ExpertParams ep;
    const size_t states = 8 * (size_t)ep.max_expansions + 1;
    const size_t search_bound = 48 * states;  // nodes (16 bytes, capacity <= 2x) + table (4 bytes, <= 4x)
    // The grid, the cache and near_field's wavefront (4 bytes a cell, once a near goal is asked).
    const size_t near_bytes = (size_t)g.n * g.n * sizeof(int);
    CHECK(expert.guide().workspace_bytes() <= grid_bytes + near_bytes + RouteGuide::kFieldCacheBytes);
    CHECK(expert.workspace_bytes() <= grid_bytes + near_bytes + RouteGuide::kFieldCacheBytes + search_bound + (16u << 20));
    // The dense space-time arrays of before 0.4 held (T + 1) x cells bytes of reservations alone.
    const size_t dense = (size_t)(kExpertMaxHorizon + ep.extra_horizon + 1) * g.n * g.n;
    CHECK(expert.workspace_bytes() < dense / 2);
    // A route guide asked for more goals than its cache holds drops the least recently used
    // (whole fields here, of a known size).
    RouteGuide guide;
    guide.band = 0;
    const size_t holds = RouteGuide::kFieldCacheBytes / field_bytes;
    Rng rng2(8);
    for (size_t i = 0; i < holds + 4; ++i) {
        const Vec2 p = aisle_point(half, rng2), goal{-p.x, p.y + 0.9 * (p.y < 0 ? 3 : -3)};
        guide.subgoal(map, p, goal, 0.8);
    }
    CHECK(guide.fields_cached() <= holds);
    CHECK(guide.fields_cached() >= holds - 1);
    CHECK(guide.workspace_bytes() <= grid_bytes + near_bytes + RouteGuide::kFieldCacheBytes);
}

TEST_CASE("routing: a cached field reads back its wavefront in 2 bytes a cell, or 4 when a cost reaches 65535") {
    // The guide's whole field of a warehouse goal is the wavefront, cell for cell.
    const WorldMap map = warehouse_map(8);
    Rng rng(3);
    const Vec2 goal = aisle_point(8, rng);
    RouteGuide guide;
    const RouteField& field = guide.steps_to(map, goal);
    const ClearanceGrid& g = guide.grid();
    const std::vector<int> steps = wavefront(g, g.index(goal), guide.route());
    size_t differ = 0, unreachable = 0;
    for (size_t k = 0; k < steps.size(); ++k) differ += field[k] != steps[k], unreachable += steps[k] < 0;
    CHECK(differ == 0);
    CHECK(unreachable > 0);  // the shelves' cells: -1 survives the 2-byte form
    CHECK(field.whole());
    CHECK(field.bytes() == steps.size() * sizeof(uint16_t));
    // A cost of 65535 or more keeps 4 bytes a cell (a 2-byte form would clip it).
    const RouteField wide(std::vector<int>{0, -1, 65535, 70000}, 2);
    CHECK(wide[0] == 0);
    CHECK(wide[1] == -1);
    CHECK(wide[2] == 65535);
    CHECK(wide[3] == 70000);
    CHECK(wide.bytes() == 4 * sizeof(int));
    const RouteField narrow(std::vector<int>{0, -1, 65534, 7}, 2);
    CHECK(narrow[2] == 65534);
    CHECK(narrow[1] == -1);
    CHECK(narrow.bytes() == 4 * sizeof(uint16_t));
    // A band field holds the tiles within `band` cells of its route, exactly, and nothing else.
    const int n = g.n, from = g.index(Vec2{-goal.x, -goal.y});
    const std::vector<int> route{from};
    const RouteField band(steps, n, &route, 20);
    CHECK_FALSE(band.whole());
    CHECK(band.bytes() < field.bytes() / 10);
    const int r0 = from / n, c0 = from % n;
    size_t held = 0;
    for (int k = 0; k < n * n; ++k) {
        const int dr = std::abs(k / n - r0), dc = std::abs(k % n - c0);
        if (dr <= 20 && dc <= 20) CHECK(band[k] == steps[k]);  // within the band: the wavefront's value
        if (band[k] != RouteField::kAbsent) {
            CHECK(band[k] == steps[k]);
            ++held;
        }
        if (dr > 20 + RouteField::kTile || dc > 20 + RouteField::kTile) CHECK(band[k] == RouteField::kAbsent);
    }
    CHECK(held >= 41 * 41);                                           // the band's square
    CHECK(held <= (41 + 2 * RouteField::kTile) * (41 + 2 * RouteField::kTile));  // and the tiles it touches
}

TEST_CASE("routing: band fields give the routes whole fields give, in a fraction of the bytes") {
    // Robots walk their routes across a warehouse, some pushed off them; a guide with band fields
    // (the default) and one with whole fields answer every query alike.
    const double half = 10;
    const WorldMap map = warehouse_map(half);
    RouteGuide banded, whole;
    whole.band = 0;
    banded.near_reach = whole.near_reach = 0;  // the cached fields only (near fields: the next test)
    REQUIRE(banded.band > 0);
    Rng rng(11);
    int subgoals = 0, pushed = 0;
    for (int robot = 0; robot < 12; ++robot) {
        Vec2 p = aisle_point(half, rng);
        const Vec2 goal = aisle_point(half, rng);
        for (int step = 0; step < 60; ++step) {
            const RouteGoal a = banded.subgoal(map, p, goal, 0.8), b = whole.subgoal(map, p, goal, 0.8);
            CHECK(a.goal.x == b.goal.x);
            CHECK(a.goal.y == b.goal.y);
            CHECK(a.final == b.final);
            CHECK(banded.route_steps(map, p, goal) == whole.route_steps(map, p, goal));
            std::vector<int> ca, cb;
            banded.route_cells(map, p, goal, 200, ca);
            whole.route_cells(map, p, goal, 200, cb);
            CHECK(ca == cb);
            ++subgoals;
            if (a.final) break;
            p = p + (a.goal - p) * std::min(1.0, 0.3 / norm(a.goal - p));
            if (step % 15 == 14) {  // pushed off the route, beyond the band
                const Vec2 q = aisle_point(half, rng);
                if (banded.route_steps(map, q, goal) < RouteGuide::kRouteUnreachable) p = q, ++pushed;
            }
        }
    }
    CHECK(subgoals > 100);
    CHECK(pushed > 5);
    CHECK(banded.workspace_bytes() < whole.workspace_bytes() / 2);
}

TEST_CASE("routing: fields made ahead, several at once, are the fields made one at a time") {
    // RouteGuide::expect lists the goals of the walks about to make fields; run_ahead makes the
    // wavefronts of a batch of them at once (here in reverse order, as threads may finish), and
    // they wait until their walks ask. Every walk must read what a guide making its fields one at
    // a time reads, both must cache the same fields, and the batches must have been made ahead.
    const double half = 10;
    const WorldMap map = warehouse_map(half);
    RouteGuide ahead, alone;
    ahead.near_reach = alone.near_reach = 0;  // cached fields only
    int runs = 0, made_ahead = 0;
    ahead.run_ahead = [&](int count, const std::function<void(int)>& fn) {
        ++runs;
        made_ahead += count - 1;
        for (int j = count - 1; j >= 0; --j) fn(j);
    };
    Rng rng(12);
    std::vector<Vec2> starts, goals;
    for (int robot = 0; robot < 24; ++robot) starts.push_back(aisle_point(half, rng)), goals.push_back(aisle_point(half, rng));
    std::vector<Vec2> expected = goals;
    expected.insert(expected.begin() + 5, goals[9]);           // a goal listed twice
    expected.insert(expected.begin() + 3, aisle_point(half, rng));  // goals no walk asks for: a later batch drops
    expected.push_back(aisle_point(half, rng));                // them, and the Expecting's end does
    int walked = 0;
    size_t most_held = 0;  // bytes the guide held beyond the one-at-a-time guide's
    {
        const RouteGuide::Expecting expecting = ahead.expect(map, expected, 4);
        for (int robot = 0; robot < 24; ++robot) {
            const RouteGoal a = ahead.subgoal(map, starts[robot], goals[robot], 0.8), b = alone.subgoal(map, starts[robot], goals[robot], 0.8);
            CHECK(a.goal.x == b.goal.x);
            CHECK(a.goal.y == b.goal.y);
            CHECK(a.final == b.final);
            CHECK(ahead.route_steps(map, starts[robot], goals[robot]) == alone.route_steps(map, starts[robot], goals[robot]));
            walked += !ahead.straight(map, starts[robot], goals[robot]);
            most_held = std::max(most_held, ahead.workspace_bytes() - std::min(ahead.workspace_bytes(), alone.workspace_bytes()));
        }
    }
    const size_t wavefront_bytes = sizeof(int) * (size_t)alone.grid().n * alone.grid().n;
    CHECK(walked > 12);
    CHECK(runs >= 4);
    CHECK(made_ahead >= 12);
    CHECK(most_held > 0);
    CHECK(most_held <= 3 * wavefront_bytes);  // at most batch - 1 wait
    CHECK(ahead.fields_cached() == alone.fields_cached());
    CHECK(ahead.workspace_bytes() == alone.workspace_bytes());  // nothing left waiting
    // Without run_ahead the guide makes every field itself, expected or not.
    RouteGuide unset;
    unset.near_reach = 0;
    const RouteGuide::Expecting expecting = unset.expect(map, goals, 4);
    for (int robot = 0; robot < 24; ++robot) CHECK(unset.route_steps(map, starts[robot], goals[robot]) == alone.route_steps(map, starts[robot], goals[robot]));
    CHECK(unset.workspace_bytes() == alone.workspace_bytes());
}

TEST_CASE("routing: a straight way clear on the grid costs at most its chebyshev cells + 2") {
    // CrowdRoutes::update (madbp.hpp) takes such a way as open ground without open_ground's field,
    // on this bound: its half-cell samples step between neighbouring cells, none narrow.
    int straight = 0, diagonal = 0;
    Rng rng(21);
    for (int world = 0; world < 5; ++world) {
        Rng map_rng(300 + world);
        const double half = world < 4 ? 3.4 : 6.8;
        const WorldMap map = make_map(world < 4 ? "obstacles" : "empty", map_rng, half);
        RouteGuide guide;
        const double cell = guide.grid(map).cell;
        for (int q = 0; q < 120; ++q) {
            const Vec2 a{rng.uniform(-half + 0.2, half - 0.2), rng.uniform(-half + 0.2, half - 0.2)};
            Vec2 b{rng.uniform(-half + 0.2, half - 0.2), rng.uniform(-half + 0.2, half - 0.2)};
            if (q % 3 == 0) {  // near 45 degrees, where the samples turn most often
                const double d = rng.uniform(0.5, half - 0.3) * (rng.uniform() < 0.5 ? -1 : 1);
                b = {std::clamp(a.x + d, -half + 0.2, half - 0.2), std::clamp(a.y + d * rng.uniform(0.97, 1.03), -half + 0.2, half - 0.2)};
            }
            if (!guide.straight(map, a, b)) continue;
            const double chebyshev = std::max(std::fabs(b.x - a.x), std::fabs(b.y - a.y)) / cell;
            CHECK(guide.route_steps(map, a, b) <= chebyshev + 2);
            ++straight;
            diagonal += q % 3 == 0;
        }
    }
    CHECK(straight > 150);
    CHECK(diagonal > 40);
}

TEST_CASE("routing: obstacles_near answers a clearance threshold as the whole map does, and crops read it") {
    // Random discs and boxes over a large world; for points in a rectangle, the clearance is
    // below t (<= margin) on the near obstacles exactly when it is on the whole map.
    Rng rng(21);
    WorldMap map;
    map.half_size = 10;
    for (int i = 0; i < 120; ++i) {
        const Vec2 c{rng.uniform(-9.5, 9.5), rng.uniform(-9.5, 9.5)};
        if (i % 2) map.discs.push_back({c, rng.uniform(0.05, 0.4)});
        else map.boxes.push_back({c, c + Vec2{rng.uniform(0.05, 0.8), rng.uniform(0.05, 0.8)}});
    }
    WorldMap near;
    size_t kept = 0, checked = 0;
    for (int r = 0; r < 40; ++r) {
        const Vec2 lo{rng.uniform(-10, 8), rng.uniform(-10, 8)}, hi = lo + Vec2{rng.uniform(0.1, 2), rng.uniform(0.1, 2)};
        const double margin = rng.uniform(0.05, 0.3);
        obstacles_near(map, lo, hi, margin, near);
        kept += near.discs.size() + near.boxes.size();
        for (int i = 0; i < 50; ++i) {
            const Vec2 q{rng.uniform(lo.x, hi.x), rng.uniform(lo.y, hi.y)};
            for (double t : {margin, 0.5 * margin, 0.0}) {
                CHECK((static_clearance(near, q) < t) == (static_clearance(map, q) < t));
                ++checked;
            }
        }
    }
    CHECK(checked == 40 * 50 * 3);
    CHECK(kept < 40 * (map.discs.size() + map.boxes.size()) / 10);  // a small part of the map each time
    // A robot's crop (local_crop reads the near obstacles) is the crop of the whole map.
    for (int i = 0; i < 20; ++i) {
        const Vec2 p{rng.uniform(-9, 9), rng.uniform(-9, 9)};
        const int Gl = 16;
        const double extent = 0.8, w = 2 * extent / Gl;
        std::vector<float> crop(Gl * Gl);
        local_crop(map, p, Gl, extent, crop.data());
        for (int row = 0; row < Gl; ++row)
            for (int col = 0; col < Gl; ++col) {
                const Vec2 c{p.x - extent + (col + 0.5) * w, p.y - extent + (row + 0.5) * w};
                CHECK(crop[row * Gl + col] == (static_clearance(map, c) < 0.5 * w ? 1.0f : 0.0f));
            }
    }
}

TEST_CASE("routing: a near goal's subgoal, walked on a wavefront made only as far as the walk reads, is the cached field's") {
    // RouteGuide::near_field stops once the walk's start and a step past it are settled; the
    // subgoals must be those of whole cached fields: from open ground, from beside obstacles
    // (a start cell no robot centre fits in), with cells closed, with narrow cells, and from
    // outside a closed room (no route: near_field then makes the whole wavefront).
    RouteGuide near, whole;
    whole.near_reach = 0;
    whole.band = 0;
    REQUIRE(near.near_reach >= 1.5);
    Rng rng(5);
    int compared = 0, beside = 0, closed_runs = 0, from_outside_room = 0;
    for (int world = 0; world < 6; ++world) {
        Rng map_rng(100 + world);
        WorldMap map = make_map("obstacles", map_rng, 3.4);
        const bool room = world == 5;
        if (room) {  // a closed room around (1, 1)
            map.boxes.push_back({{0.4, 0.4}, {1.6, 0.5}});
            map.boxes.push_back({{0.4, 1.5}, {1.6, 1.6}});
            map.boxes.push_back({{0.4, 0.4}, {0.5, 1.6}});
            map.boxes.push_back({{1.5, 0.4}, {1.6, 1.6}});
        }
        const ClearanceGrid& g = whole.grid(map);
        std::vector<int> closed_cells;  // a block of cells beside the middle, closed in half the queries
        for (int k = 0; k < g.n * g.n; ++k)
            if (std::fabs(g.centre(k).x + 0.5) < 0.2 && std::fabs(g.centre(k).y) < 0.6) closed_cells.push_back(k);
        const ClosedCells closed{nullptr, -1, 77, &closed_cells};
        for (int q = 0; q < 150; ++q) {
            Vec2 p{rng.uniform(-3.2, 3.2), rng.uniform(-3.2, 3.2)};
            Vec2 goal = p + Vec2{rng.uniform(-1.4, 1.4), rng.uniform(-1.4, 1.4)};
            if (room && q % 2 == 0) goal = {rng.uniform(0.6, 1.4), rng.uniform(0.6, 1.4)};
            goal = {std::clamp(goal.x, -3.3, 3.3), std::clamp(goal.y, -3.3, 3.3)};
            const bool use_closed = q % 2 == 1;
            const ClosedCells c = use_closed ? closed : ClosedCells{};
            const RouteGoal a = near.subgoal(map, p, goal, 0.8, c), b = whole.subgoal(map, p, goal, 0.8, c);
            CHECK(a.goal.x == b.goal.x);
            CHECK(a.goal.y == b.goal.y);
            CHECK(a.final == b.final);
            ++compared;
            beside += g.clear[g.index(p)] < kPassableClearance;
            closed_runs += use_closed;
            const bool inside = p.x > 0.4 && p.x < 1.6 && p.y > 0.4 && p.y < 1.6;
            from_outside_room += room && q % 2 == 0 && !inside && norm(goal - p) <= near.near_reach;
        }
        if (!room) {  // every goal near: none cached
            CHECK(near.fields_cached() == 0);
            CHECK(whole.fields_cached() > 50);
        }
    }
    CHECK(compared == 900);
    CHECK(beside > 20);
    CHECK(closed_runs == 450);
    CHECK(from_outside_room > 5);  // near goals no route reaches: the whole wavefront
}
