// One-lane passages (issue 12): PassageControl (madbp_sim.hpp Section 12) finds the corridors
// robots must take turns in and says who waits where; DiffusionPlanner::take_turns hands a waiting
// robot its waiting point as its goal, and one that goes around a corridor with a way around
// its route with the corridor closed.
#include <doctest/doctest.h>

#include "madbp.hpp"
#include "tiny_model.hpp"

using namespace madbp;

namespace {

// A wall across the world at y = 0 with a gap of `width` at x = x0, and (when half_length > 0)
// a corridor of that width through the gap, from y = -half_length to half_length. free_standing:
// the corridor walls only, no wall across the world (a way around).
WorldMap corridor_map(double width, double half_length, bool free_standing = false, double x0 = 0, double half_size = WorldMap{}.half_size) {
    WorldMap m;
    m.half_size = half_size;
    const double h = m.half_size, w = 0.5 * width, t = 0.05;
    if (!free_standing) {
        m.boxes.push_back({{-h, -t}, {x0 - w, t}});
        m.boxes.push_back({{x0 + w, -t}, {h, t}});
    }
    if (half_length > 0) {
        m.boxes.push_back({{x0 - w - 2 * t, -half_length}, {x0 - w, half_length}});
        m.boxes.push_back({{x0 + w, -half_length}, {x0 + w + 2 * t, half_length}});
    }
    return m;
}
int count_passages(const WorldMap& map, double free_clear = TrafficConfig{}.free_clear) {
    RouteGuide guide;
    PassageControl pc;
    pc.params.free_clear = free_clear;
    const std::vector<int>& p = pc.passage(guide, map);
    return 1 + *std::max_element(p.begin(), p.end());
}
struct Turns {
    std::vector<char> wait;
    std::vector<Vec2> point;
};
Turns arbitrate(const WorldMap& map, const std::vector<Vec2>& pos, const std::vector<Vec2>& goal, std::vector<char> at_goal = {},
                PassageControl* control = nullptr) {
    RouteGuide guide;
    PassageControl own;
    PassageControl& pc = control ? *control : own;
    at_goal.resize(pos.size(), 0);
    Turns t;
    pc.arbitrate(guide, map, (int)pos.size(), pos.data(), goal.data(), at_goal.data(), t.wait, t.point);
    return t;
}
constexpr char kGoOn = PassageControl::kGoOn, kWait = PassageControl::kWait, kAround = PassageControl::kGoAround;
// The point fits a waiting robot: free of the map and outside the passage.
void check_waiting_point(const WorldMap& map, Vec2 q) {
    RouteGuide guide;
    PassageControl pc;
    const std::vector<int>& p = pc.passage(guide, map);
    CHECK(static_clearance(map, q) >= 0.14);
    CHECK(p[guide.grid().index(q)] < 0);
}

// Walks the route subgoals (0.3 apart) from `from` to `to` keeping out of `closed`: the points
// along the way, every tenth of a leg; empty when it does not arrive within 40 legs.
std::vector<Vec2> walk_route(const WorldMap& map, Vec2 from, Vec2 to, ClosedCells closed) {
    RouteGuide guide;
    std::vector<Vec2> points;
    Vec2 p = from;
    for (int leg = 0; leg < 40; ++leg) {
        const RouteGoal r = guide.subgoal(map, p, to, 0.3, closed);
        for (int k = 1; k <= 10; ++k) points.push_back(p + (r.goal - p) * (k / 10.0));
        if (r.final && norm(r.goal - to) < 1e-9) return points;
        p = r.goal;
    }
    return {};
}

// follow_order's `ahead` for two robots that both go on (required).
std::vector<int> ahead_of_two(const WorldMap& map, const std::vector<Vec2>& pos, const std::vector<Vec2>& goal) {
    RouteGuide guide;
    PassageControl pc;
    std::vector<char> at_goal(pos.size(), 0), turn;
    std::vector<Vec2> point;
    pc.arbitrate(guide, map, (int)pos.size(), pos.data(), goal.data(), at_goal.data(), turn, point);
    REQUIRE(turn == std::vector<char>{kGoOn, kGoOn});
    std::vector<int> ahead;
    pc.follow_order(guide, turn, pos.data(), goal.data(), ahead);
    return ahead;
}

}  // namespace

TEST_CASE("passages: a long one-lane corridor, avoidable when it has a way around; not a doorway or a wide corridor") {
    CHECK(count_passages(corridor_map(0.44, 0.4)) == 1);
    CHECK(count_passages(corridor_map(0.45, 0.4)) == 1);
    CHECK(count_passages(corridor_map(0.50, 0.4)) == 0);                        // two robots pass side by side
    CHECK(count_passages(corridor_map(0.70, 0.4)) == 0);
    CHECK(count_passages(corridor_map(0.44, 0)) == 0);                          // a doorway in the wall
    CHECK(count_passages(WorldMap{}) == 0);                                     // corners are no passages
    RouteGuide guide;
    PassageControl pc;
    pc.passage(guide, corridor_map(0.44, 0.4));
    CHECK(pc.avoidable() == std::vector<char>{0});
    const WorldMap free_standing = corridor_map(0.44, 0.4, /*free standing*/ true);
    const std::vector<int>& around = pc.passage(guide, free_standing);  // robots can go around it
    CHECK(pc.avoidable() == std::vector<char>{1});
    CHECK(around[guide.grid().index({0, 0})] == 0);
    pc.params.go_around = false;  // then it is left to the model: found again, none
    const std::vector<int>& none = pc.passage(guide, free_standing);
    CHECK(*std::max_element(none.begin(), none.end()) == -1);
    pc.params.go_around = true;
    const std::vector<int>& p = pc.passage(guide, corridor_map(0.44, 0.4));
    const ClearanceGrid& g = guide.grid();
    CHECK(p[g.index({0, 0.2})] == 0);
    CHECK(p[g.index({0, -0.3})] == 0);
    CHECK(p[g.index({0, 0.8})] == -1);
    REQUIRE(pc.mouths().size() == 2);
    for (const auto& m : pc.mouths()) CHECK(std::abs(m.in.y) > 0.9);  // the ways in run along the corridor
    CHECK(pc.mouth_of_cell()[g.index(pc.mouths()[0].at)] == 0);
    pc.params.one_lane_width = 0.4;  // narrower than this corridor: found again, none
    const std::vector<int>& q = pc.passage(guide, corridor_map(0.44, 0.4));
    CHECK(*std::max_element(q.begin(), q.end()) == -1);
}

TEST_CASE("passages: the one-lane line (0.47): corridors up to 0.45 wide wherever their walls fall on the grid, 0.50 at few offsets, none from 0.55") {
    // Two robots (radius 0.1) pass side by side in a corridor 0.46 wide; narrower, they take turns.
    // The line is drawn on 0.036 cells, so near 0.47 it depends on where the walls fall: with
    // free_clear 0.102 a 0.50 corridor is one-lane at 1 of these 11 offsets (0.12: none).
    int one_lane_050 = 0;
    for (int k = 0; k < 11; ++k) {
        const double x0 = -0.3 + 0.0547 * k;  // offsets across a cell and more
        INFO("offset " << x0);
        for (double width : {0.40, 0.43, 0.45}) CHECK(count_passages(corridor_map(width, 0.4, false, x0)) == 1);
        one_lane_050 += count_passages(corridor_map(0.50, 0.4, false, x0));
        CHECK(count_passages(corridor_map(0.50, 0.4, false, x0), 0.12) == 0);
        CHECK(count_passages(corridor_map(0.55, 0.4, false, x0)) == 0);
    }
    CHECK(one_lane_050 <= 1);
}

TEST_CASE("passages: a 0.25 corridor is found wherever it falls with the default free_clear (0.102), only at some offsets with 0.12") {
    // A MovingAI aisle at cell 0.25 leaves a centre band of 0.25 - 2 free_clear: 0.046 with the
    // default (RouteClearance::min), wider than a 0.036 cell; 0.01 with 0.12.
    CHECK(TrafficConfig{}.free_clear == RouteClearance{}.min);
    int found_012 = 0;
    for (int k = 0; k < 11; ++k) {
        const double x0 = -0.3 + 0.0547 * k;
        INFO("offset " << x0);
        const WorldMap map = corridor_map(0.25, 0.4, false, x0);
        CHECK(count_passages(map) == 1);
        found_012 += count_passages(map, 0.12);
    }
    CHECK(found_012 < 11);
}

TEST_CASE("passages: obstacle groups; a corridor is found when narrow gaps around it join its ends") {
    WorldMap m;
    m.discs.push_back({{0.9, 0.9}, 0.2});     // 0.1 from two borders: one with them
    m.discs.push_back({{0, 0}, 0.05});        // 0.25 from the nearest box: alone
    m.boxes.push_back({{0.3, -0.5}, {0.4, 0.5}});
    m.boxes.push_back({{0.4, -0.5}, {0.6, -0.4}});  // meets the first box: one with it
    m.boxes.push_back({{-0.6, -0.5}, {-0.5, 0.5}});  // 0.45 from the disc at the centre: alone
    CHECK(detail::surface_groups(m, 0.24) == std::vector<int>{0, 0, 0, 0, 0, 1, 2, 2, 3});
    CHECK(detail::surface_groups(m, 0.3) == std::vector<int>{0, 0, 0, 0, 0, 1, 1, 1, 2});
    CHECK(detail::nearest_surface(m, {0.35, 0.7}) == 6);
    CHECK(detail::nearest_surface(m, {-1.1, 0.7}) == 1);
    // The generator's corridor scenes put discs near the corridors' ends on the obstacle map; the
    // narrow gaps between them, the walls' ends and the border are one-lane too. Before the
    // one-lane cells were told apart by the obstacles on either side, they joined the corridor
    // into a junction in a fifth of the obstacle map's scenes, and no robot took turns there.
    int corridors = 0;
    for (const char* map : {"obstacles", "empty"})
        for (uint64_t seed = 0; seed < 40; ++seed) {
            const World w = make_interaction_world("corridor", map, 4, seed, 1.2, WorldConfig{});
            const std::vector<Box>& b = w.map().boxes;
            REQUIRE(b.size() >= 2);
            const Box& wall0 = b[b.size() - 2];
            const Box& wall1 = b[b.size() - 1];
            const double apart = std::max({wall0.lo.x - wall1.hi.x, wall1.lo.x - wall0.hi.x, wall0.lo.y - wall1.hi.y, wall1.lo.y - wall0.hi.y});
            if (apart >= 0.46) continue;  // two robots may pass side by side (0.47 is the rule's line, drawn on the grid)
            ++corridors;
            RouteGuide guide;
            PassageControl pc;
            const std::vector<int>& p = pc.passage(guide, w.map());
            const Vec2 centre = (wall0.lo + wall0.hi + wall1.lo + wall1.hi) * 0.25;
            INFO(std::string(map) << " seed " << seed);
            CHECK(p[guide.grid().index(centre)] >= 0);
        }
    CHECK(corridors >= 25);
}

TEST_CASE("passages: head-on, the nearer robot goes and the other waits outside, beside its mouth") {
    const WorldMap map = corridor_map(0.44, 0.4);
    for (int flip = 0; flip < 2; ++flip) {  // robot `near` is 0.3 from its mouth, the other 0.5
        const int near = flip, far = 1 - flip;
        std::vector<Vec2> pos(2), goal(2);
        pos[near] = {0, -0.7}, goal[near] = {0, 0.9};
        pos[far] = {0, 0.9}, goal[far] = {0, -0.9};
        const Turns t = arbitrate(map, pos, goal);
        CHECK(t.wait[near] == kGoOn);
        CHECK(t.point[near] == goal[near]);
        REQUIRE(t.wait[far] == kWait);
        check_waiting_point(map, t.point[far]);
        CHECK(t.point[far].y > 0.45);                    // on its own side
        CHECK(t.point[far].x < -0.1);                    // to the right of its way in (heading -y)
        CHECK(norm(t.point[far] - pos[far]) < 0.6);      // near the mouth, not sent away
    }
    // Going the same way, both go; an arrived robot claims nothing.
    Turns same = arbitrate(map, {{0, -0.7}, {0.1, -1.0}}, {{0, 0.9}, {0.1, 0.8}});
    CHECK(same.wait == std::vector<char>{kGoOn, kGoOn});
    Turns parked = arbitrate(map, {{0, -0.7}, {0, 0.6}}, {{0, 0.9}, {0, 0.6}}, {0, 1});
    CHECK(parked.wait == std::vector<char>{kGoOn, kGoOn});
}

TEST_CASE("passages: a robot that arrives after the other is out goes on; one in the passage the wrong way backs out") {
    const WorldMap map = corridor_map(0.44, 0.4);
    // Robot 0 is near the top end on its way up: robot 1 far above arrives after it is out.
    Turns late = arbitrate(map, {{0, 0.3}, {0, 1.05}}, {{0, 0.9}, {0, -0.9}});
    CHECK(late.wait == std::vector<char>{kGoOn, kGoOn});
    // With robot 0 deeper in, robot 1 would meet it inside, and waits.
    Turns meets = arbitrate(map, {{0, 0.0}, {0, 0.7}}, {{0, 0.9}, {0, -0.9}});
    CHECK(meets.wait == std::vector<char>{kGoOn, kWait});
    // Both in the passage, head-on, as deep: the lower index goes on, the other backs out to its
    // own side.
    const std::vector<Vec2> both{{0, 0.15}, {0, -0.15}}, ends{{0, -0.9}, {0, 0.9}};
    Turns inside = arbitrate(map, both, ends);
    CHECK(inside.wait[0] == kGoOn);
    REQUIRE(inside.wait[1] == kWait);
    CHECK(inside.point[1].y < -0.45);
    check_waiting_point(map, inside.point[1]);
    // Given ids, the lower id goes on whatever the order the robots are listed in (a robot that
    // plans for itself lists itself first); a robot without an id (-1) after one with.
    RouteGuide guide;
    PassageControl pc;
    const std::vector<char> moving{0, 0};
    std::vector<char> wait;
    std::vector<Vec2> point;
    for (const std::vector<int>& ids : {std::vector<int>{7, 3}, std::vector<int>{-1, 3}}) {
        pc.arbitrate(guide, map, 2, both.data(), ends.data(), moving.data(), wait, point, ids.data());
        CHECK(wait == std::vector<char>{kWait, kGoOn});
    }
    // Both in it, one just inside its mouth: the one with less of the passage ahead goes on,
    // whatever its index (a robot passing the mouth on its way around once took the corridor
    // from one halfway through).
    Turns deeper = arbitrate(map, {{0, -0.35}, {0, -0.1}}, {{0, 0.9}, {0, -0.9}});
    CHECK(deeper.wait == std::vector<char>{kWait, kGoOn});
    CHECK(deeper.point[0].y < -0.45);
    // A queue: two robots waiting at one mouth take different places.
    Turns queue = arbitrate(map, {{0, -0.6}, {0, 0.7}, {0, 1.0}}, {{0, 0.9}, {0, -0.9}, {0.1, -0.7}});
    REQUIRE(queue.wait == std::vector<char>{kGoOn, kWait, kWait});
    CHECK(norm(queue.point[1] - queue.point[2]) >= 0.25);
}

TEST_CASE("passages: a robot parked in a corridor makes way for one passing through, out of the mouth that one leaves by") {
    // A one-lane corridor 0.3 wide from y = -1.5 to 1.5, the only way between the world's halves.
    const WorldMap map = corridor_map(0.3, 1.5, false, 0, 2.4);
    const std::vector<Vec2> pos{{0, 0.3}, {0, -0.6}}, goal{{0, 0.3}, {0, 2.2}};
    const Turns t = arbitrate(map, pos, goal, {1, 0});
    CHECK(t.wait[1] == kGoOn);
    REQUIRE(t.wait[0] == kWait);
    CHECK(t.point[0].y > 1.5);  // ahead of robot 1, out of the top
    check_waiting_point(map, t.point[0]);
    // Without make_way it stays (and the two meet nose to nose).
    PassageControl off;
    off.params.make_way = false;
    CHECK(arbitrate(map, pos, goal, {1, 0}, &off).wait == std::vector<char>{kGoOn, kGoOn});
    // Behind robot 1, or beyond where its route reaches, it stays.
    CHECK(arbitrate(map, {{0, -1.2}, {0, -0.6}}, {{0, -1.2}, {0, 2.2}}, {1, 0}).wait == std::vector<char>{kGoOn, kGoOn});
    // On its way to a goal in the corridor it lets robot 1 through first, even though it is nearer.
    const Turns on_its_way = arbitrate(map, {{0, 0.1}, {0, -0.6}}, {{0, 0.5}, {0, 2.2}});
    CHECK(on_its_way.wait[1] == kGoOn);
    REQUIRE(on_its_way.wait[0] == kWait);
    CHECK(on_its_way.point[0].y > 1.5);
}

TEST_CASE("passages: of two robots whose goals lie in one corridor, the one that would pass the other goes around it, or both queue on its side") {
    // Robot 0 (goal 0.6) would pass robot 1, parked at its goal (-0.2), and its goal.
    const std::vector<Vec2> pos{{0, -0.7}, {0, -0.2}}, goal{{0, 0.6}, {0, -0.2}};
    const std::vector<char> at_goal{0, 1};
    // The corridor is the only way (as in a maze): both queue at the bottom, robot 0 nearer, so it
    // leaves first and enters first.
    const WorldMap walled = corridor_map(0.3, 1.5, false, 0, 2.4);
    const Turns queue = arbitrate(walled, pos, goal, at_goal);
    REQUIRE(queue.wait == std::vector<char>{kWait, kWait});
    CHECK(queue.point[0].y < -1.5);
    CHECK(queue.point[1].y < -1.5);
    CHECK(queue.point[0].y > queue.point[1].y);
    // Robot 0 ahead of robot 1, going deeper: nobody passes anybody, both go on.
    CHECK(arbitrate(walled, {{0, -0.2}, {0, -0.7}}, {{0, 0.6}, {0, -0.2}}).wait == std::vector<char>{kGoOn, kGoOn});
    // Robot 0's goal short of robot 1's: it does not pass robot 1.
    CHECK(arbitrate(walled, {{0, -0.9}, {0, 0.4}}, {{0, -0.3}, {0, 0.4}}, at_goal).wait == std::vector<char>{kGoOn, kGoOn});
    // With a way around, robot 0 takes it, kept out of the cells at robot 1 but not its own goal's.
    const WorldMap open = corridor_map(0.3, 1.5, true, 0, 2.4);
    PassageControl pc;
    const Turns around = arbitrate(open, pos, goal, at_goal, &pc);
    REQUIRE(around.wait == std::vector<char>{kAround, kGoOn});
    const ClosedCells plug = pc.closed_to(0);
    REQUIRE(plug.any());
    RouteGuide guide;
    const ClearanceGrid& grid = guide.grid(open);
    CHECK(plug.closes(grid.index(pos[1])));
    CHECK_FALSE(plug.closes(grid.index(goal[0])));
    CHECK_FALSE(plug.closes(grid.index(pos[0])));
    const std::vector<Vec2> route = walk_route(open, pos[0], goal[0], plug);
    REQUIRE(!route.empty());
    for (Vec2 q : route) CHECK(norm(q - pos[1]) >= 0.2);  // around, in by the top
    CHECK(norm(route.back() - goal[0]) < 0.1);
}

TEST_CASE("passages: of two robots coming in by one mouth to goals in a corridor, the one going deeper goes first") {
    const WorldMap map = corridor_map(0.44, 0.4);  // walled: no way around
    // Robot 0, nearer the mouth, parks just inside; robot 1 goes past that goal to one deeper.
    const std::vector<Vec2> pos{{0, -0.55}, {0.05, -0.85}}, goal{{0, -0.2}, {0, 0.3}};
    const Turns t = arbitrate(map, pos, goal);
    CHECK(t.wait == std::vector<char>{kWait, kGoOn});
    check_waiting_point(map, t.point[0]);
    // In the other order (the nearer goes deeper) both go on, one after the other.
    CHECK(arbitrate(map, pos, {goal[1], goal[0]}).wait == std::vector<char>{kGoOn, kGoOn});
    // Without make_way neither waits: the nearer parks in the other's way.
    PassageControl plain;
    plain.params.make_way = false;
    CHECK(arbitrate(map, pos, goal, {}, &plain).wait == std::vector<char>{kGoOn, kGoOn});
}

TEST_CASE("passages: a robot past the middle of a long corridor came in by the mouth behind it, not the nearer one ahead") {
    // Robot 0 at y = 0.6 on its way up a corridor from -2 to 2, its route in view not yet out of it;
    // robot 1 comes down into it from the top: robot 0 holds, robot 1 waits at the top.
    const WorldMap map = corridor_map(0.3, 2.0, false, 0, 3.0);
    const Turns t = arbitrate(map, {{0, 0.6}, {0, 2.3}}, {{-1.5, 2.5}, {0, -2.3}});
    REQUIRE(t.wait == std::vector<char>{kGoOn, kWait});
    CHECK(t.point[1].y > 2.0);
}

TEST_CASE("passages: at a corridor with a way around, the robot that would wait goes around it, and its route keeps out") {
    const WorldMap map = corridor_map(0.44, 0.4, /*free standing*/ true);
    PassageControl pc;
    const Turns t = arbitrate(map, {{0, -0.7}, {0, 0.9}}, {{0, 0.9}, {0, -0.9}}, {}, &pc);
    REQUIRE(t.wait == std::vector<char>{kGoOn, kAround});
    CHECK(t.point[1] == Vec2{0, -0.9});
    const ClosedCells closed = pc.closed_to(1);
    REQUIRE(closed.any());
    CHECK_FALSE(pc.closed_to(0).any());
    // Walking robot 1's route subgoals with the corridor closed: it arrives without entering it,
    // out of the corridor's strip (|x| <= 0.32) while level with it.
    RouteGuide guide;
    const std::vector<Vec2> route = walk_route(map, {0, 0.9}, {0, -0.9}, closed);
    CHECK(!route.empty());
    for (Vec2 q : route) {
        CHECK(!closed.closes(guide.grid(map).index(q)));
        if (std::abs(q.y) < 0.4) CHECK(std::abs(q.x) > 0.32);
    }
    // A closed set that does not match the grid is named.
    const std::vector<int> wrong(7, 0);
    CHECK_THROWS_WITH_AS(guide.subgoal(map, {0, 0.9}, {0, -0.9}, 0.3, {&wrong, 0, 5}), doctest::Contains("ClosedCells.label"), std::invalid_argument);
    // Without the corridor closed the route runs through it.
    CHECK(std::abs(guide.subgoal(map, {0, 0.9}, {0, -0.9}, 0.6).goal.x) < 0.1);
    // A robot already in the corridor the wrong way backs out, as where there is no way around.
    const Turns inside = arbitrate(map, {{0, 0.15}, {0, -0.15}}, {{0, -0.9}, {0, 0.9}});
    CHECK(inside.wait == std::vector<char>{kGoOn, kWait});
    // From inside the closed corridor there is no way around: the route is the way through, not
    // the goal straight across the corridor's wall.
    const RouteGoal from_inside = guide.subgoal(map, {0, 0.15}, {0.8, -0.9}, 0.3, closed);
    CHECK_FALSE(from_inside.final);
    CHECK(from_inside.goal == guide.subgoal(map, {0, 0.15}, {0.8, -0.9}, 0.3).goal);
    CHECK(std::abs(from_inside.goal.x) < 0.12);
}

TEST_CASE("passages: robots going around a corridor take its two sides in turn; with spread 0, the same side") {
    // One robot comes up the corridor; two wait to come down it, both on its axis, where the two
    // ways around are equally long. Each robot's side: the sign of x while level with the corridor.
    const WorldMap map = corridor_map(0.44, 0.4, /*free standing*/ true);
    const std::vector<Vec2> pos{{0, -0.7}, {0, 0.75}, {0, 1.0}}, goal{{0, 0.95}, {0, -0.8}, {0, -1.05}};
    auto sides = [&](double spread) {
        PassageControl pc;
        pc.params.spread = spread;
        const Turns t = arbitrate(map, pos, goal, {}, &pc);
        REQUIRE(t.wait == std::vector<char>{kGoOn, kAround, kAround});
        RouteGuide guide;
        const std::vector<int>& passage = pc.passage(guide, map);
        std::vector<int> side;
        for (int i : {1, 2}) {
            const ClosedCells closed = pc.closed_to(i);
            REQUIRE(closed.any());
            for (size_t k = 0; k < passage.size(); ++k)
                if (passage[k] >= 0) REQUIRE(closed.closes((int)k));  // a side's cells include the corridor's
            const std::vector<Vec2> route = walk_route(map, pos[i], goal[i], closed);
            REQUIRE(!route.empty());
            double x = 0;
            for (Vec2 q : route)
                if (std::abs(q.y) < 0.4) x += q.x;
            side.push_back(x > 0 ? 1 : -1);
        }
        return side;
    };
    const std::vector<int> spread = sides(0.3), shortest = sides(0);
    CHECK(spread[0] == -spread[1]);
    CHECK(shortest[0] == shortest[1]);
    // Where one side has no way round (the corridor near the border: 0.06 on its right), both
    // take the other.
    WorldMap near_border = corridor_map(0.44, 0.4, true);
    for (Box& b : near_border.boxes) b.lo.x += 0.82, b.hi.x += 0.82;
    PassageControl pc;
    const std::vector<Vec2> p2{{0.82, -0.7}, {0.82, 0.75}, {0.82, 1.0}}, g2{{0.82, 0.95}, {0.82, -0.8}, {0.82, -1.05}};
    const Turns t = arbitrate(near_border, p2, g2, {}, &pc);
    REQUIRE(t.wait == std::vector<char>{kGoOn, kAround, kAround});
    for (int i : {1, 2}) {
        const std::vector<Vec2> route = walk_route(near_border, p2[i], g2[i], pc.closed_to(i));
        REQUIRE(!route.empty());
        for (Vec2 q : route)
            if (std::abs(q.y) < 0.4) CHECK(q.x < 0.5);
    }
}

TEST_CASE("passages: spare, the room a claim from the other mouth leaves the holder; contested, claims from two mouths") {
    const WorldMap map = corridor_map(0.44, 0.4);
    // Robot 0 is near the top end on its way up; robot 1 comes down from 1.05.
    const std::vector<Vec2> pos{{0, 0.3}, {0, 1.05}}, goal{{0, 0.9}, {0, -0.9}};
    PassageControl pc;
    CHECK(arbitrate(map, pos, goal, {}, &pc).wait == std::vector<char>{kGoOn, kGoOn});
    CHECK(pc.contested());
    pc.params.spare = 1.0;  // robot 1 would enter before robot 0 is 1.0 out: it waits
    CHECK(arbitrate(map, pos, goal, {}, &pc).wait == std::vector<char>{kGoOn, kWait});
    pc.params.spare = 0;
    CHECK(arbitrate(map, pos, goal, {}, &pc).wait == std::vector<char>{kGoOn, kGoOn});
    // Going the same way, or robot 1 parked on its goal: no claims from two mouths.
    arbitrate(map, pos, {{0, 0.9}, {0, 1.05}}, {0, 1}, &pc);
    CHECK_FALSE(pc.contested());
    arbitrate(map, {{0, -0.7}, {0.1, -1.0}}, {{0, 0.9}, {0.1, 0.8}}, {}, &pc);
    CHECK_FALSE(pc.contested());
}

TEST_CASE("passages: queues keep their order: a robot behind one that queues queues too, though it would enter after the holder left") {
    const WorldMap map = corridor_map(0.44, 0.4);  // walled: no way around
    // Robot 0 holds the corridor on its way up; robot 1 would meet it inside; robot 2, behind
    // robot 1, would enter only after robot 0 is out.
    const std::vector<Vec2> pos{{0, 0.0}, {0, 0.6}, {0.05, 1.05}}, goal{{0, 0.9}, {0, -0.9}, {0, -0.9}};
    PassageControl pc;
    const Turns t = arbitrate(map, pos, goal, {}, &pc);
    REQUIRE(t.wait == std::vector<char>{kGoOn, kWait, kWait});
    CHECK(norm(t.point[1] - t.point[2]) >= 0.25);  // places of their own
    // Alone, robot 2 would go on (it arrives after the holder is out), and so it did before
    // queues kept their order: then it pushed robot 1 into the mouth robot 0 leaves by.
    CHECK(arbitrate(map, {pos[0], pos[2]}, {goal[0], goal[2]}).wait == std::vector<char>{kGoOn, kGoOn});
    pc.params.queue_in_order = false;
    CHECK(arbitrate(map, pos, goal, {}, &pc).wait == std::vector<char>{kGoOn, kWait, kGoOn});
    // At a corridor with a way around the robot that would meet the holder goes around, and no
    // queue forms: the one behind goes on.
    const WorldMap open = corridor_map(0.44, 0.4, /*free_standing=*/true);
    const Turns around = arbitrate(open, pos, goal);
    CHECK(around.wait[1] == kAround);
    CHECK(around.wait[2] == kGoOn);
}

TEST_CASE("passages: at a mouth in a corner the queue's places follow the free space: clear of the walls and apart") {
    // A one-lane corridor (0.25 wide along y = 0, x from 0 to 1.4) whose left mouth opens into the
    // bottom right corner of a shaft 0.8 wide going up: the line out of that mouth (-x) meets the
    // shaft's left wall 0.8 out, so a queue's second place on it would lie in the wall (as at
    // maze-32-32-4's corners). A robot coming from the right holds the corridor; four in the shaft
    // queue at its left mouth.
    WorldMap map;
    map.half_size = 2;
    const double w = 0.125;
    map.boxes.push_back({{-2, -2}, {2, -w}});      // the floor
    map.boxes.push_back({{-2, -w}, {-0.8, 2}});    // the shaft's left wall
    map.boxes.push_back({{0, w}, {1.4, 2}});       // above the corridor (the shaft's right wall)
    REQUIRE(count_passages(map) == 1);
    const std::vector<Vec2> pos{{1.0, 0}, {-0.3, 0.4}, {-0.55, 0.6}, {-0.3, 0.8}, {-0.55, 1.0}},
        goal{{-0.4, 1.6}, {1.7, 1.5}, {1.7, 1.0}, {1.7, 0.5}, {1.7, 1.8}};
    const Turns t = arbitrate(map, pos, goal);
    REQUIRE(t.wait == std::vector<char>{kGoOn, kWait, kWait, kWait, kWait});
    for (int i = 1; i <= 4; ++i) {
        CAPTURE(i);
        check_waiting_point(map, t.point[i]);
        CHECK(t.point[i].x < 0);  // in the shaft, on the mouth's side
        for (int j = 1; j < i; ++j) CHECK(norm(t.point[i] - t.point[j]) >= 0.8 * TrafficConfig{}.queue_spacing);
    }
    // Each mouth's places are kept: a control that placed four places three as a fresh one does,
    // and one whose queue parameters change places as a fresh one with those parameters.
    const std::vector<Vec2> pos3{pos[0], pos[1], pos[2], pos[3]}, goal3{goal[0], goal[1], goal[2], goal[3]};
    PassageControl kept, fresh;
    CHECK(arbitrate(map, pos, goal, {}, &kept).point == t.point);
    const Turns three = arbitrate(map, pos3, goal3, {}, &kept);
    CHECK(three.point == arbitrate(map, pos3, goal3, {}, &fresh).point);
    CHECK(std::count(three.wait.begin(), three.wait.end(), kWait) == 3);
    kept.params.queue_spacing = fresh.params.queue_spacing = 0.45;
    const Turns wider = arbitrate(map, pos, goal, {}, &kept);
    CHECK(wider.point == arbitrate(map, pos, goal, {}, &fresh).point);
    CHECK(wider.point != t.point);
}

TEST_CASE("passages: asked robots' turns are those of a call for all; robots far from their passages are not routed") {
    // A wall across a world of half-size 3 with three corridors through it (x = -2, 0, 2) and a
    // free-standing corridor (a way around) below; 40 robots crossing and walking beside them.
    WorldMap map;
    map.half_size = 3;
    const double t = 0.05, w = 0.22;
    double x_from = -3;
    for (double x0 : {-2.0, 0.0, 2.0}) {
        map.boxes.push_back({{x_from, -t}, {x0 - w, t}});
        map.boxes.push_back({{x0 - w - 2 * t, -0.4}, {x0 - w, 0.4}});
        map.boxes.push_back({{x0 + w, -0.4}, {x0 + w + 2 * t, 0.4}});
        x_from = x0 + w;
    }
    map.boxes.push_back({{x_from, -t}, {3, t}});
    map.boxes.push_back({{-1.0 - w - 2 * t, -2.2}, {-1.0 - w, -1.4}});
    map.boxes.push_back({{-1.0 + w, -2.2}, {-1.0 + w + 2 * t, -1.4}});
    Rng rng(7);
    auto free_point = [&] {
        for (;;) {
            const Vec2 q{rng.uniform(-2.8, 2.8), rng.uniform(-2.8, 2.8)};
            if (static_clearance(map, q) >= 0.15) return q;
        }
    };
    const int n = 40;
    std::vector<Vec2> pos(n), goal(n);
    std::vector<char> at_goal(n, 0);
    std::vector<int> ids(n);
    for (int i = 0; i < n; ++i) pos[i] = free_point(), goal[i] = free_point(), ids[i] = n - i;
    RouteGuide guide;
    PassageControl all;
    std::vector<char> wait, one_wait;
    std::vector<Vec2> point, one_point;
    all.arbitrate(guide, map, n, pos.data(), goal.data(), at_goal.data(), wait, point, ids.data());
    const size_t routed_all = guide.fields_cached();
    REQUIRE(std::count(wait.begin(), wait.end(), kWait) + std::count(wait.begin(), wait.end(), kAround) >= 2);  // turns are taken
    bool any_asked_replan = false;
    size_t routed_most = 0;
    for (int r = 0; r < n; ++r) {
        // Robot r and its nearest other robot asked, as in a scene of two.
        int near = r == 0 ? 1 : 0;
        for (int j = 0; j < n; ++j)
            if (j != r && norm(pos[j] - pos[r]) < norm(pos[near] - pos[r])) near = j;
        std::vector<char> asked(n, 0);
        asked[r] = asked[near] = 1;
        RouteGuide own_guide;
        PassageControl own;
        own.arbitrate(own_guide, map, n, pos.data(), goal.data(), at_goal.data(), one_wait, one_point, ids.data(), asked.data());
        routed_most = std::max(routed_most, own_guide.fields_cached());
        for (int k : {r, near}) {
            CHECK(one_wait[k] == wait[k]);
            CHECK(one_point[k] == point[k]);
            CHECK(own.closed_to(k).key == all.closed_to(k).key);
            CHECK(own.closed_to(k).any() == all.closed_to(k).any());
        }
        any_asked_replan = any_asked_replan || own.contested() || one_wait[r] == kWait;
    }
    // A team whose robots ask for themselves replans as the team does (DecentralisedTeam).
    CHECK(any_asked_replan == (all.contested() || std::count(wait.begin(), wait.end(), kWait) > 0));
    CHECK(routed_most < routed_all);
}

TEST_CASE("passages: bad parameters are named") {
    RouteGuide guide;
    PassageControl pc;
    pc.params.lookahead = -1;
    std::vector<Vec2> pos{{0, 0}}, goal{{0, 0.5}};
    std::vector<char> at{0}, wait;
    std::vector<Vec2> point;
    CHECK_THROWS_WITH_AS(pc.arbitrate(guide, WorldMap{}, 1, pos.data(), goal.data(), at.data(), wait, point),
                         doctest::Contains("traffic: every length"), std::invalid_argument);
    pc.params.lookahead = std::nan("");
    CHECK_THROWS_AS(pc.arbitrate(guide, WorldMap{}, 1, pos.data(), goal.data(), at.data(), wait, point), std::invalid_argument);
    pc.params.lookahead = 1.2;
    pc.params.spread = -0.3;
    CHECK_THROWS_AS(pc.arbitrate(guide, WorldMap{}, 1, pos.data(), goal.data(), at.data(), wait, point), std::invalid_argument);
    pc.params.spread = 0.3;
    pc.params.spare = -0.1;
    CHECK_THROWS_AS(pc.arbitrate(guide, WorldMap{}, 1, pos.data(), goal.data(), at.data(), wait, point), std::invalid_argument);
}

TEST_CASE("planner: with take_turns a waiting robot is given its waiting point as its goal; without, its own") {
    ModelConfig c = tiny_config();
    World world(corridor_map(0.44, 0.4));
    world.add_agent({0, -0.7}, {0, 0.9});
    world.add_agent({0, 0.9}, {0, -0.9});
    for (int turns = 0; turns < 2; ++turns) {
        DiffusionPlanner planner(MadbpModel(c, 1), 2);
        planner.settings.traffic.take_turns = turns != 0;
        planner.plan(world);
        CHECK(planner.last_waiting() == std::vector<char>{kGoOn, turns ? kWait : kGoOn});
        const SceneBatch& b = planner.last_scene_batch();
        // The model's input: robot 1 is column 1 of its scene (one scene of the team).
        REQUIRE(b.B == 1);
        const Vec2 told = b.goal(1, planner.config());
        if (turns) {
            CHECK(norm(told - planner.last_wait_points()[1]) < 1e-5);
            CHECK(b.goal_final[1] == 1.0f);
        } else {
            CHECK(told.y < 0.5);  // heading through: its goal or a subgoal on the way
        }
    }
}

TEST_CASE("planner: while robots may meet in a passage the plan asks to be replaced after passage_replan steps") {
    ModelConfig c = tiny_config();
    World head_on(corridor_map(0.44, 0.4));  // robot 1 waits
    head_on.add_agent({0, -0.7}, {0, 0.9});
    head_on.add_agent({0, 0.9}, {0, -0.9});
    World apart(corridor_map(0.44, 0.4));  // both on the lower side, going right: no passage on their way
    apart.add_agent({-0.8, -0.7}, {0.8, -0.7});
    apart.add_agent({-0.8, -1.0}, {0.8, -1.0});
    DiffusionPlanner planner(MadbpModel(c, 1), 2);
    CHECK(planner.settings.traffic.passage_replan == PlannerConfig{}.traffic.passage_replan);
    planner.settings.traffic.passage_replan = 3;
    CHECK(planner.plan(head_on).replan_after == 3);
    CHECK(planner.replan_after() == 3);
    CHECK(planner.plan(apart).replan_after == 0);
    planner.settings.traffic.passage_replan = 0;
    CHECK(planner.plan(head_on).replan_after == 0);
    planner.settings.traffic.passage_replan = 3;
    planner.settings.traffic.take_turns = false;
    CHECK(planner.plan(head_on).replan_after == 0);
}

TEST_CASE("planner: plan_robot takes the team plan's turns when the neighbours' ids are given") {
    // Head-on in the corridor, as deep: a tie, which the lower id wins.
    ModelConfig c = tiny_config();
    World world(corridor_map(0.44, 0.4));
    world.add_agent({0, 0.15}, {0, -0.9});  // id 0
    world.add_agent({0, -0.15}, {0, 0.9});  // id 1
    DiffusionPlanner team(MadbpModel(c, 1), 2);
    team.plan(world);
    REQUIRE(team.last_waiting() == std::vector<char>{kGoOn, kWait});
    // Robot 1 planning for itself lists itself first: with robot 0's id it waits, as in the
    // team's plan; without it (an unknown id ranks after a known one) it would go on.
    DiffusionPlanner own(MadbpModel(c, 1), 2);
    std::vector<Vec2> window;
    own.plan_robot(world.map(), 1, {0, -0.15}, {0, 0.9}, {{{0, 0.15}, {0, -0.9}, 0}}, window);
    CHECK(own.last_waiting()[0] == kWait);
    own.plan_robot(world.map(), 1, {0, -0.15}, {0, 0.9}, {{{0, 0.15}, {0, -0.9}, -1}}, window);
    CHECK(own.last_waiting()[0] == kGoOn);
}

TEST_CASE("planner: a robot going around a corridor is given a subgoal beside it, not its goal") {
    ModelConfig c = tiny_config();
    c.subgoal_distance = 0.6;
    World world(corridor_map(0.44, 0.4, /*free standing*/ true));
    world.add_agent({0, -0.7}, {0, 0.9});
    world.add_agent({0, 0.9}, {0, -0.9});
    DiffusionPlanner planner(MadbpModel(c, 1), 2);
    planner.plan(world);
    REQUIRE(planner.last_waiting() == std::vector<char>{kGoOn, kAround});
    const SceneBatch& b = planner.last_scene_batch();
    REQUIRE(b.B == 1);
    const Vec2 told = b.goal(1, planner.config());
    CHECK(b.goal_final[1] == 0.0f);        // a subgoal, never pinned
    CHECK(std::abs(told.x) > 0.2);         // off the corridor's axis: around it
    CHECK(told.y < 0.9);                   // and on the way down
}

TEST_CASE("expert: with passage_traffic, robots meeting head-on inside a long one-lane corridor take turns") {
    // Three robots in a 0.3-wide corridor 5 long, one going down and two coming up: each plan of
    // the plain expert sends them all on (soft reservations), and the filter holds them nose to
    // nose until the step limit (issue 46's maze: its border aisles).
    auto run = [](ExpertTraffic traffic) {
        WorldConfig wc;
        wc.max_steps = 600;
        World w(corridor_map(0.3, 2.5, false, 0, 3.0), wc);
        w.add_agent({0, 1.5}, {0.5, -2.8});
        w.add_agent({0, -0.5}, {-0.5, 2.8});
        w.add_agent({0, -1.0}, {0.5, 2.8});
        GuidedExpert expert(w.map(), ExpertParams{}, std::move(traffic));
        return run_episode(w, expert);
    };
    const EpisodeResult turns = run(passage_traffic());
    CHECK(turns.success);
    CHECK(turns.collisions() == 0);
    CHECK(turns.steps < 400);
    CHECK_FALSE(run(nullptr).success);  // the scene needs the rule
    ExpertParams bad;
    bad.give_way_buffer = -0.1;
    CHECK_THROWS_WITH_AS(GuidedExpert(corridor_map(0.3, 2.5), bad), doctest::Contains("ExpertParams.give_way_buffer"), std::invalid_argument);
    TrafficConfig off;
    off.take_turns = false;
    CHECK(passage_traffic(off) == nullptr);  // no rule: each robot heads for its goal
}

TEST_CASE("passages: follow_order lines robots up through a corridor, the one farthest in first") {
    // A corridor 0.3 wide from y = -1 to 1 (world half-size 2, a wall across at y = 0): robots
    // 0 and 1 going up in it (1 farther in), 2 below it coming up, 3 parked at its goal in the
    // corridor, in their way; 4 going down from above waits (another mouth).
    const WorldMap map = corridor_map(0.3, 1.0, false, 0, 2.0);
    const std::vector<Vec2> pos = {{0, -0.6}, {0, -0.3}, {0, -1.3}, {0, 0.5}, {0.3, 1.3}};
    const std::vector<Vec2> goal = {{0.6, 1.5}, {-0.6, 1.5}, {0.6, 1.6}, {0, 0.6}, {0.3, -1.5}};
    RouteGuide guide;
    PassageControl pc;
    std::vector<char> at_goal(pos.size(), 0), turn;
    std::vector<Vec2> point;
    pc.arbitrate(guide, map, (int)pos.size(), pos.data(), goal.data(), at_goal.data(), turn, point);
    REQUIRE(turn == std::vector<char>{kGoOn, kGoOn, kGoOn, kWait, kWait});  // 3 is sent out ahead of them, 4 waits
    std::vector<int> ahead;
    pc.follow_order(guide, turn, pos.data(), goal.data(), ahead);
    CHECK(ahead == std::vector<int>{1, 3, 0, -1, -1});  // 2 after 0 after 1 after 3; 4 in no line
}

TEST_CASE("expert: a robot no nearer its goal for stall_steps plans first, which ends a deadlock at a doorway") {
    // room-64-64-8 at cell 0.25, seed 30 with 32 robots (results/maps, 2026-12-03), at step 600
    // of the expert's run, robots parked more than 1 from the one-cell door at (3.375, 3.875)
    // left out: robot 4 in the door bound north, 1 below it bound north, 3 above it bound
    // south. With fixed priorities they stand nose to nose to the end; with robots that have
    // stalled planned first, in an order drawn afresh every stall_steps, one backs out.
    const MovingAiMap room = load_movingai_map("maps/movingai/room-64-64-8.map");
    Scene scene = movingai_scene(room, random_movingai_scenario(room, 1, 0), "random", 1, 0.25);  // the map at cell 0.25
    scene.starts = {{-1.098, 6.886}, {3.412, 3.639}, {2.467, -1.639}, {3.369, 4.134}, {3.369, 3.904}, {-1.629, 5.968}};
    scene.goals = {{-0.375, 7.625}, {-0.875, 7.375}, {7.375, -7.875}, {-2.625, 0.625}, {-2.625, 6.875}, {-1.625, 5.625}};
    auto run = [&](int stall_steps) {
        WorldConfig wc;
        wc.max_steps = 500;
        World w = make_world(scene, wc);
        ExpertParams ep;
        ep.stall_steps = stall_steps;
        GuidedExpert expert(w.map(), ep, passage_traffic());
        return run_episode(w, expert);
    };
    CHECK(ExpertParams{}.stall_steps == 150);
    const EpisodeResult rotated = run(150);
    CHECK(rotated.success);
    CHECK(rotated.collisions() == 0);
    CHECK(rotated.steps < 450);  // 420 when measured
    CHECK_FALSE(run(0).success);  // fixed priorities: the scene needs the rule
    ExpertParams bad;
    bad.stall_steps = -1;
    CHECK_THROWS_WITH_AS(GuidedExpert(scene.map, bad), doctest::Contains("ExpertParams.stall_steps"), std::invalid_argument);
}

TEST_CASE("expert: robots in a line through a corridor are planned from the front, so the one ahead goes on") {
    // Four robots in a line going up a one-lane corridor, those behind with the longer routes,
    // so the expert's priorities plan them first: planned before the robot ahead, each routes
    // through it (maze-32-32-4, seed 2 at cell 0.25 with 32 robots). Planned from the front
    // (ExpertHeading::after), the line takes half the steps.
    auto run = [](bool follow) {
        WorldConfig wc;
        wc.max_steps = 600;
        World w(corridor_map(0.3, 2.5, false, 0, 3.0), wc);
        const double goal_x[] = {0.3, -2.5, 2.5, -1.5};
        for (int i = 0; i < 4; ++i) w.add_agent({0, -0.5 - 0.25 * i}, {goal_x[i], 2.8});
        ExpertTraffic turns = passage_traffic();
        ExpertTraffic rule = follow ? turns : [turns](const World& world, RouteGuide& guide, std::vector<ExpertHeading>& heading) {
            turns(world, guide, heading);
            for (ExpertHeading& h : heading) h.after = -1;
        };
        GuidedExpert expert(w.map(), ExpertParams{}, rule);
        return run_episode(w, expert);
    };
    const EpisodeResult line = run(true), unordered = run(false);
    CHECK(line.success);
    CHECK(line.collisions() == 0);
    CHECK(line.steps < 250);
    CHECK(unordered.steps > 350);  // 435 when measured: the scene needs the order
}

TEST_CASE("passages: follow_order, a robot coming in by the far mouth after the holder follows it") {
    // spare's scene (above): robot 0 near the top end on its way up holds the corridor; robot 1,
    // coming down, would enter after it is out, so it goes on, planned after it (the expert: one
    // planned first sends the holder back out, and the two take turns for good).
    CHECK(ahead_of_two(corridor_map(0.44, 0.4), {{0, 0.3}, {0, 1.05}}, {{0, 0.9}, {0, -0.9}}) == std::vector<int>{-1, 0});
}

namespace {
// A dead end 0.3 wide from y = -1.1 up to its mouth at y = 0, in a world of half-size 2.
WorldMap dead_end_map() {
    WorldMap m;
    m.half_size = 2.0;
    m.boxes.push_back({{-0.25, -1.1}, {-0.15, 0}});
    m.boxes.push_back({{0.15, -1.1}, {0.25, 0}});
    m.boxes.push_back({{-0.25, -1.2}, {0.25, -1.1}});
    return m;
}
}  // namespace

TEST_CASE("passages: pocket_order, a robot whose goal would close off a dead end another's route enters waits beside it, off that route") {
    // Robot 0's goal is just inside the mouth of a one-lane dead end; robot 1's is at its far end.
    const WorldMap map = dead_end_map();
    const std::vector<Vec2> pos{{0.6, 0.6}, {-1.2, 1.4}}, goal{{0, -0.2}, {0, -0.9}};
    PassageControl pc;
    pc.params.pocket_order = true;
    const Turns t = arbitrate(map, pos, goal, {}, &pc);
    REQUIRE(t.wait == std::vector<char>{kWait, kGoOn});
    const Vec2 q = t.point[0];
    CHECK(q.y > 0);  // out of the dead end, beside its mouth
    CHECK(static_clearance(map, q) >= 0.1);
    RouteGuide guide;
    std::vector<int> route;
    guide.route_cells(map, pos[1], goal[1], 1000, route);
    REQUIRE(!route.empty());
    for (int c : route) CHECK(norm(guide.grid().centre(c) - q) >= 0.3);  // off robot 1's way in
    // Once robot 1 has arrived, robot 0 goes on. With the goals swapped, robot 1 (farther out)
    // would arrive after robot 0 is past: both go on; from nearer, it waits.
    CHECK(arbitrate(map, pos, goal, {0, 1}, &pc).wait == std::vector<char>{kGoOn, kGoOn});
    CHECK(arbitrate(map, pos, {goal[1], goal[0]}, {}, &pc).wait == std::vector<char>{kGoOn, kGoOn});
    CHECK(arbitrate(map, {pos[0], {-0.3, 0.3}}, {goal[1], goal[0]}, {}, &pc).wait == std::vector<char>{kGoOn, kWait});
    // A robot coming out of the dead end is waited for too.
    CHECK(arbitrate(map, {pos[0], {0, -0.9}}, {goal[0], {-1.2, 1.4}}, {}, &pc).wait == std::vector<char>{kWait, kGoOn});
    // The planner's default: off; the expert's: on.
    CHECK_FALSE(TrafficConfig{}.pocket_order);
    CHECK(expert_traffic().pocket_order);
    CHECK(arbitrate(map, pos, goal).wait == std::vector<char>{kGoOn, kGoOn});
}

TEST_CASE("expert: a robot parked at the mouth of a one-cell dead end lets one bound for its far end in first (pocket_order)") {
    // maze-32-32-4 at cell 0.25, seed 38 with 16 robots (results/maps, 2026-12-03): robot 12
    // parks at its goal in the first cell of the dead end at column 31, rows 15-19; robot 9,
    // bound for row 19, pushes it deeper, and the two hold each other to the end.
    const MovingAiMap maze = load_movingai_map("maps/movingai/maze-32-32-4.map");
    Scene scene = movingai_scene(maze, random_movingai_scenario(maze, 1, 0), "random", 1, 0.25);
    auto at = [](double c, double r) { return Vec2{-4 + (c + 0.5) * 0.25, 4 - (r + 0.5) * 0.25}; };  // map cell (c, r)
    scene.starts = {at(31, 15), at(20.2, 18.9)};
    scene.goals = {at(31, 15), at(31, 19)};
    auto run = [&](bool pocket_order) {
        WorldConfig wc;
        wc.max_steps = 500;
        World w = make_world(scene, wc);
        TrafficConfig traffic = expert_traffic();
        traffic.pocket_order = pocket_order;
        GuidedExpert expert(w.map(), ExpertParams{}, passage_traffic(traffic));
        return run_episode(w, expert);
    };
    const EpisodeResult ordered = run(true);
    CHECK(ordered.success);
    CHECK(ordered.collisions() == 0);
    CHECK(ordered.steps < 150);  // 117 when measured
    CHECK_FALSE(run(false).success);  // the scene needs the rule
}

TEST_CASE("passages: follow_order, a robot going on to a goal in a corridor follows the one ahead of it that goes deeper") {
    // Two robots coming in by one mouth, the nearer bound deeper: both go on, and the one behind
    // follows (the expert plans it after: planned first it routes through the one ahead, which
    // steps back, and the two creep along a one-lane aisle: maze-32-32-4, seed 87 at cell 0.25).
    CHECK(ahead_of_two(corridor_map(0.44, 0.4), {{0, -0.55}, {0.05, -0.85}}, {{0, 0.3}, {0, -0.2}}) == std::vector<int>{-1, 0});
}
