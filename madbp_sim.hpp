// madbp_sim.hpp - the 2-D multi-robot navigation world and classical controllers.
// Part of madbp (Multi-Agent Diffusion Based Planner), header-only C++17. MIT licence.
//
// What it is
//   A C++ counterpart of the VMAS "navigation" scenario (SPEC.md section 2): holonomic discs
//   with drag and soft contacts, the empty / obstacles / barrier maps as plain data, scene
//   files, an occupancy-grid rasterizer, metrics, SVG rendering, and the classical
//   controllers of SPEC section 3 (CLF-QP, tracker + safety filter, straight line, guided
//   expert).
//
// Use
//   #include "madbp_sim.hpp"
//   madbp::World world = madbp::make_random_world("barrier", 4, /*seed=*/0);
//   madbp::GuidedExpert expert(world.map());
//   while (!world.done()) world.step(expert.act(world));
//
// Configuration macros (define before including)
//   MADBP_ASSERT(cond)   programmer-error check; default: assert(cond).
//
// Changelog
//   0.4  Routing at any scale (docs/design.md): ClearanceGrid keeps 0.036 cells up to half-size 41.4
//        (kRouteMaxGridSide replaces kExpertMaxGridSide = 192) and fills clearance per obstacle
//        (exact below kClearanceReach); RouteClearance: passable from 0.102, narrow below 0.13 costs
//        8 extra steps (was a hard 0.13); wavefront(grid, goal, RouteClearance); RouteGuide caches
//        fields within kFieldCacheBytes (LRU; kMaxFields is gone), needs none where the straight way
//        is clear (straight(), steps_to(), workspace_bytes()); GuidedExpert plans on a RouteGuide
//        (ExpertParams::min_clear, narrow_cost) with a sparse space-time A* and bucketed
//        reservations, and its plans start from the robot's position. RouteField: a cached
//        wavefront in 2 bytes a cell (4 only when a cost reaches 65535), whole or, by default, a
//        band of tiles around one robot's route (RouteGuide::band = 32 cells; the expert: 0),
//        made again when a walk reads past it, so routes are those of whole fields; steps_to()
//        returns a whole one. obstacles_near: a map's obstacles near an area (local_crop and
//        RouteGuide's views read only those).
//        kPassableClearance (0.102): routes and passages share it. follower_filter() keeps 0.005
//        to the map (was SPEC's 0.01, which froze robots in gaps their routes pass).
//        FollowerConfig::unjam 15 (paper preset and the straight line: 0): a robot the filter
//        holds with no progress backs out to its most open side (crowds among obstacles);
//        FollowerConfig::unjam_near (0, off): one standing still beside another robot counts as held.
//        GuidedExpert takes an ExpertTraffic rule (ExpertHeading: a robot's target, closed cells,
//        whether it gives way); madbp.hpp's passage_traffic() is the planner's one-lane turns.
//        RouteGuide::steps_to takes ClosedCells.
//        ExpertHeading::after: a robot is planned right after the one it follows (a line
//        through a one-lane aisle is planned from the front).
//        EvalResult::failed_seeds: the seeds of the episodes that failed.
//        ExpertParams::stall_steps (150): a robot no nearer its goal for that long plans first,
//        in an order drawn afresh every stall_steps (deadlocks at doorways; 0: fixed priorities).
//        RouteGuide::near_reach (2.0): a subgoal toward a goal that near walks a wavefront made
//        only as far as the walk reads, not cached (same subgoals; routes around crowds).
//        RouteGuide::run_ahead, expect() (an Expecting scope), expect_none(): fields about to be
//        made are made several at once (the planner's threads), the same fields.
//        RouteGuideSettings: RouteGuide's public settings (settings_only(): a guide with the same);
//        RouteGuide::walks_near().
//   0.3  PassageControl and its parameters move to madbp.hpp (the planner's traffic conventions).
//        ClearanceGrid moves to Section 2; ReachGrid is gone (detail::all_reachable on its layout).
//        movingai_scene / load_movingai_scene: MovingAI MAPF benchmark maps and scenarios as scenes.
//        random_movingai_scenario: seeded scenario rows for a MovingAI map without .scen files;
//        MovingAiMap and MovingAiScenarioRow are the parsed map and rows.
//        Scene::comments (scene_text writes them); scene_text(Scene).
//        default_max_steps moves here from the tool; scene_step_limit follows the longest route.
//        default_half_size(n): random worlds at constant density (1.2 up to 8 robots, 13.6 at 1024).
//        A team its world cannot hold fails naming half_size; evaluate's progress notes the steps.
//   0.2  ProgressFn instead of printing; Policy::decision_ms.
//        Map is now WorldMap (no clash with Eigen::Map), with operator==; local_crop moved here.
//        PlanFollower's filter weighs robots as the expert does (FollowerConfig::priority_weight).
//        priority_order over any n robots; RouteGuide::route_steps (the expert's priority key).
//        FollowerConfig::lookahead: the tracker aims ahead of the plan (0 = the 0.1 follower).
//        PassageControl: robots take turns through one-lane corridors (who waits, and where).
//        PassageParams::go_around: at a corridor with a short way around, the waiter goes round.
//        RouteGuide keeps out of ClosedCells; RouteGuide::route_cells, grid(map), walk_steps.
//        follower_filter(): the follower's barrier rate 4/s (expert, SafetyFilterParams{}: 2.5).
//        safety_filter refuses a rate outside (0, 1/dt), where its barrier would not hold.
//        FollowerConfig::replan_error 0.15: replan when a robot is off its plan (after m/2 steps).
//        PassageControl keys one-lane cells by the obstacles either side: gaps no longer hide them.
//        PassageParams::spread: robots going around a corridor take its two sides in turn.
//        Plan::replan_after: a planner may ask PlanFollower for its next plan sooner.
//        PassageParams::spare 0 (was 0.25), wait_back 0.45 (was 0.3); PassageControl::contested.
//        PassageParams::one_lane_width 0.47 (was 0.54): robots pass side by side where two fit.
//        FollowerConfig::lookahead 2.0 (was 1.5), with the planner's keep-right 500.
//   0.1  world, maps, controllers.

#ifndef MADBP_SIM_HPP
#define MADBP_SIM_HPP

// The release of the three headers; madbp.hpp and madbp_train.hpp check that they come from it.
#define MADBP_VERSION_MAJOR 0
#define MADBP_VERSION_MINOR 4
#define MADBP_VERSION_PATCH 0

#ifndef MADBP_ASSERT
#include <cassert>
#ifdef NDEBUG  // unevaluated, but the condition's variables still count as used (no warnings)
#define MADBP_ASSERT(cond) ((void)(false && (cond)))
#else
#define MADBP_ASSERT(cond) assert(cond)
#endif
#endif

#include <chrono>
#include <functional>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <stdexcept>
#include <string>
#include <unistd.h>

namespace madbp {

// ---------------------------------------------------------------------------------------------
// Random numbers: our own generator so that a seed gives the same stream on every platform
// (std:: distributions are implementation-defined). xoshiro256** seeded through splitmix64.
struct Rng {
    uint64_t s[4];
    explicit Rng(uint64_t seed = 0) { reseed(seed); }
    void reseed(uint64_t seed) {
        for (auto& w : s) {  // splitmix64
            seed += 0x9E3779B97F4A7C15ull;
            uint64_t z = seed;
            z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
            z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
            w = z ^ (z >> 31);
        }
    }
    static uint64_t rotl(uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
    uint64_t next_u64() {
        uint64_t result = rotl(s[1] * 5, 7) * 9, t = s[1] << 17;
        s[2] ^= s[0]; s[3] ^= s[1]; s[1] ^= s[2]; s[0] ^= s[3]; s[2] ^= t; s[3] = rotl(s[3], 45);
        return result;
    }
    double uniform() { return (next_u64() >> 11) * 0x1.0p-53; }                 // [0, 1)
    double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
    int uniform_int(int n) { return (int)(uniform() * n); }                     // [0, n)
    double normal() {                                                           // N(0, 1)
        double u1 = uniform(), u2 = uniform();
        if (u1 < 1e-300) u1 = 1e-300;
        return std::sqrt(-2.0 * std::log(u1)) * std::cos(6.283185307179586 * u2);
    }
};

// ---------------------------------------------------------------------------------------------
// Progress of long work (evaluation, collection, training): `done` of `total` units and a short
// note such as the current loss. The library never prints; a caller that wants a progress line
// passes one (the madbp tool draws "label  120/1000  37.2/s  ETA 24s" on a terminal).
using ProgressFn = std::function<void(long done, long total, const std::string& note)>;

// Throws std::invalid_argument("<field>: <why>") when a value is not finite.
inline void require_finite(double v, const std::string& field) {
    if (!std::isfinite(v)) throw std::invalid_argument(field + ": value is not finite (" + std::to_string(v) + ")");
}

// Limits on every size that comes from a file, a flag or the API, checked before anything is
// allocated; a refusal names the limit. docs/limits.md lists these and the limits of madbp.hpp
// (checkpoints, model configuration) and madbp_train.hpp (datasets).
constexpr double kMaxHalfSize = 100;           // world half-size, world units (World, make_map, scenes, datasets)
constexpr int kMaxObstacles = 4096;            // discs + boxes of one map (World, make_map, scenes, datasets)
constexpr int kMaxSceneAgents = 1024;          // 'agent' lines of one scene
constexpr size_t kMaxSceneBytes = 1 << 20;     // size of a scene file or text, bytes
constexpr int kMaxAgentId = (1 << 30) - 1;     // largest agent id World::add_agent accepts or hands out
constexpr int kRouteMaxGridSide = 2304;        // routing grid side, cells: 0.036 up to half-size 41.4, coarser beyond
constexpr int kExpertMaxHorizon = 256;         // guided expert: world steps planned ahead (plus extra_horizon)
constexpr double kMaxSvgPixels = 4096;         // side of a rendered picture, pixels (larger worlds are drawn smaller)
constexpr double kMaxSceneCoordinate = 1000;   // |number| of a scene's disc or box (10 x kMaxHalfSize)

// `s` for an error message: bytes outside printable ASCII as \xNN (a NUL no longer cuts the
// message short), at most `max` input bytes, then "...".
inline std::string printable(const std::string& s, size_t max = 64) {
    std::string out;
    for (size_t i = 0; i < s.size() && i < max; ++i) {
        const unsigned char c = (unsigned char)s[i];
        if (c >= 0x20 && c < 0x7f) { out += (char)c; continue; }
        char b[8];
        std::snprintf(b, sizeof b, "\\x%02x", c);
        out += b;
    }
    if (s.size() > max) out += "...";
    return out;
}
// A number for an error message, "%.6g": 100, 1e+09, 0.25.
inline std::string number_text(double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%.6g", v);
    return b;
}

}  // namespace madbp

// ============================ WORLD AND CONTROLLERS BELOW ===================================
//
// Contents (section numbers below; SPEC sections in brackets)
//   1 geometry: Vec2, Disc, Box, WorldMap, for_each_surface, static_clearance, obstacles_near
//   2 maps: make_map("empty" | "obstacles" | "barrier"), ClearanceGrid (the routing cells) [2]
//   3 the world: WorldConfig, Agent, Metrics, World (add/remove agents, step)    [2]
//   4 spawning: default_half_size, spawn_agents, make_random_world, WorldBatch   [2]
//   4b interaction scenes: interaction_scenarios, make_interaction_world      (issue 12)
//   5 occupancy grid: Grid, occupancy_grid, local_crop                           [2, 5]
//   6 scene files: Scene, parse_scene, load_scene, scene_text, make_world        [2]
//     MovingAI benchmark maps: MovingAiMap, parse_movingai_map, parse_movingai_scenario,
//       movingai_scene, load_movingai_scene, random_movingai_scenario (rows for a map
//       without .scen files), movingai_path_length, movingai_scenario_text
//     files: read_bounded, EnvironmentError, check_output, OutputLock, write_file_atomic
//   7 controllers: Policy, StepModel                                             [3]
//   8 CLF-QP: ClfQpParams, clf_qp_solve, clf_qp_action, ClfQp                    [3.1]
//   9 tracker and safety filter: track_waypoint, track_plan, kPassableClearance,
//     safety_filter                                                               [3.2]
//  10 plans: Plan, Planner, validate_plan, waypoint_now, LinePlanner, PlanFollower [3.2, 3.5, 8]
//  11 episodes and evaluation: EpisodeLog, run_episode, default_max_steps, evaluate [9, 10]
//  12 guided expert: ClosedCells, RouteClearance, wavefront, RouteGoal, RouteField (whole or band
//     wavefronts), RouteGuideSettings, RouteGuide (route subgoals; fields made ahead on threads),
//     ExpertHeading, ExpertTraffic, ExpertParams, GuidedExpert (one-lane passages: the
//     planner's, madbp.hpp's passage_traffic),
//     scene_step_limit (a scene's default step limit follows its routes)     [3.6]
//  13 SVG: render_svg, write_text_file                                           [2]

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <fcntl.h>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <queue>
#include <sstream>
#include <sys/file.h>
#include <sys/stat.h>
#include <tuple>
#include <unordered_map>
#include <utility>
#include <vector>

namespace madbp {

// =============================================================================================
// Section 1. Geometry
// =============================================================================================

// A point or vector in the plane, in world units (the world is [-half_size, half_size]^2).
struct Vec2 {
    double x = 0, y = 0;
    Vec2() = default;
    Vec2(double x_, double y_) : x(x_), y(y_) {}
    Vec2 operator+(Vec2 o) const { return {x + o.x, y + o.y}; }
    Vec2 operator-(Vec2 o) const { return {x - o.x, y - o.y}; }
    Vec2 operator-() const { return {-x, -y}; }
    Vec2 operator*(double s) const { return {x * s, y * s}; }
    Vec2 operator/(double s) const { return {x / s, y / s}; }
    Vec2& operator+=(Vec2 o) { x += o.x; y += o.y; return *this; }
    Vec2& operator-=(Vec2 o) { x -= o.x; y -= o.y; return *this; }
    Vec2& operator*=(double s) { x *= s; y *= s; return *this; }
    bool operator==(Vec2 o) const { return x == o.x && y == o.y; }
};
inline Vec2 operator*(double s, Vec2 v) { return v * s; }
inline double dot(Vec2 a, Vec2 b) { return a.x * b.x + a.y * b.y; }
inline double cross(Vec2 a, Vec2 b) { return a.x * b.y - a.y * b.x; }
inline double norm(Vec2 a) { return std::sqrt(dot(a, a)); }
inline Vec2 perp(Vec2 a) { return {-a.y, a.x}; }  // a rotated by +90 degrees
inline Vec2 clamp_box(Vec2 a, double lim) { return {std::clamp(a.x, -lim, lim), std::clamp(a.y, -lim, lim)}; }
inline Vec2 normalized(Vec2 a) {
    double n = norm(a);
    return n > 1e-12 ? a / n : Vec2{0, 0};
}

// A static disc obstacle: centre and radius (> 0).
struct Disc { Vec2 c; double r = 0.1; };
// A static axis-aligned box (a wall piece): lower-left and upper-right corners, lo < hi.
struct Box { Vec2 lo, hi; };

// The static part of a problem: the square world [-half_size, half_size]^2 with walls on its
// border, plus obstacles. Plain data, so users can build their own maps (SPEC 2).
struct WorldMap {
    double half_size = 1.2;
    std::vector<Disc> discs;
    std::vector<Box> boxes;
};
inline bool operator==(const Disc& a, const Disc& b) { return a.c == b.c && a.r == b.r; }
inline bool operator==(const Box& a, const Box& b) { return a.lo == b.lo && a.hi == b.hi; }
inline bool operator==(const WorldMap& a, const WorldMap& b) { return a.half_size == b.half_size && a.discs == b.discs && a.boxes == b.boxes; }
inline bool operator!=(const WorldMap& a, const WorldMap& b) { return !(a == b); }

// Closest point of `b` to `p` (p itself when inside).
inline Vec2 closest_point(const Box& b, Vec2 p) { return {std::clamp(p.x, b.lo.x, b.hi.x), std::clamp(p.y, b.lo.y, b.hi.y)}; }

// Signed distance from `p` to the surface of a box (negative inside) and the unit direction
// that points away from the box (the separating direction for a contact).
inline double box_distance(const Box& b, Vec2 p, Vec2* away = nullptr) {
    Vec2 q = closest_point(b, p);
    Vec2 d = p - q;
    double n = norm(d);
    if (n > 0) {
        if (away) *away = d / n;
        return n;
    }
    // Inside: the nearest face gives both the depth and the way out.
    double faces[4] = {p.x - b.lo.x, b.hi.x - p.x, p.y - b.lo.y, b.hi.y - p.y};
    const Vec2 dirs[4] = {{-1, 0}, {1, 0}, {0, -1}, {0, 1}};
    int k = (int)(std::min_element(faces, faces + 4) - faces);
    if (away) *away = dirs[k];
    return -faces[k];
}

// Calls fn(distance, away) for every static surface of `map` as seen from `p`: the four
// border walls, each disc and each box. `distance` is from `p` to the surface (negative
// inside an obstacle); `away` is the unit direction from the surface toward `p`. Contacts,
// collision counts, clearances and the safety filter all read the map through this.
template <class Fn>
inline void for_each_surface(const WorldMap& map, Vec2 p, Fn&& fn) {
    double h = map.half_size;
    fn(h - p.x, Vec2{-1, 0});
    fn(p.x + h, Vec2{1, 0});
    fn(h - p.y, Vec2{0, -1});
    fn(p.y + h, Vec2{0, 1});
    for (const Disc& o : map.discs) {
        Vec2 d = p - o.c;
        double n = norm(d);
        fn(n - o.r, n > 1e-12 ? d / n : Vec2{1, 0});
    }
    for (const Box& b : map.boxes) {
        Vec2 a;
        double d = box_distance(b, p, &a);
        fn(d, a);
    }
}

// Distance from `p` to the nearest static surface of `map` (obstacle or border wall), and the
// unit direction pointing away from it. Negative when `p` is inside an obstacle.
inline double static_clearance(const WorldMap& map, Vec2 p, Vec2* away = nullptr) {
    double best = std::numeric_limits<double>::infinity();
    Vec2 dir;
    for_each_surface(map, p, [&](double d, Vec2 a) { if (d < best) { best = d; dir = a; } });
    if (away) *away = dir;
    return best;
}

// The obstacles of `map` within `margin` of the rectangle [lo, hi], into `near` (same walls;
// its vectors keep their capacity). For a point q in the rectangle and t <= margin,
// static_clearance(near, q) < t exactly when static_clearance(map, q) < t: every obstacle left
// out is farther than margin (+ 1e-9, for rounding) from all of the rectangle. Queries over a small area of a large
// map (a robot's crop, a line of sight) then cost its nearby obstacles, not all of them.
inline void obstacles_near(const WorldMap& map, Vec2 lo, Vec2 hi, double margin, WorldMap& near) {
    near.half_size = map.half_size;
    near.discs.clear();
    near.boxes.clear();
    const Box area{lo, hi};
    for (const Disc& o : map.discs)
        if (norm(o.c - closest_point(area, o.c)) - o.r <= margin + 1e-9) near.discs.push_back(o);
    for (const Box& b : map.boxes) {
        const double gx = std::max({0.0, b.lo.x - hi.x, lo.x - b.hi.x}), gy = std::max({0.0, b.lo.y - hi.y, lo.y - b.hi.y});
        if (std::hypot(gx, gy) <= margin + 1e-9) near.boxes.push_back(b);
    }
}

// True when `p` lies inside an obstacle (not the border walls), or outside the world.
inline bool inside_obstacle(const WorldMap& map, Vec2 p) {
    if (std::fabs(p.x) > map.half_size || std::fabs(p.y) > map.half_size) return true;
    for (const Disc& o : map.discs) if (norm(p - o.c) < o.r) return true;
    for (const Box& b : map.boxes)
        if (p.x > b.lo.x && p.x < b.hi.x && p.y > b.lo.y && p.y < b.hi.y) return true;
    return false;
}

// =============================================================================================
// Section 2. Maps (SPEC 2): empty, obstacles, barrier
// =============================================================================================

// Builds a named map. `half_size` (> 0, default 1.2) scales the layouts: obstacle centres
// are drawn in [-0.8, 0.8]^2 * half_size/1.2 and the obstacle count grows with the area
// (5 discs at 1.2, 20 at 2.4) so density stays the same; the barrier always spans the
// world with one gap of width 0.5. Throws std::invalid_argument on an unknown name, a
// half_size above kMaxHalfSize, or more than kMaxObstacles discs (obstacles beyond ~34).
// The names make_map knows (case-sensitive).
inline const std::vector<std::string>& map_names() {
    static const std::vector<std::string> names = {"empty", "obstacles", "barrier"};
    return names;
}
inline WorldMap make_map(const std::string& name, Rng& rng, double half_size = 1.2) {
    if (!(half_size > 0.5) || !std::isfinite(half_size))
        throw std::invalid_argument("half_size: must be a finite number > 0.5 (got " + std::to_string(half_size) + ")");
    if (half_size > kMaxHalfSize)
        throw std::invalid_argument("half_size: " + number_text(half_size) + " exceeds the limit kMaxHalfSize = " + number_text(kMaxHalfSize));
    double scale = half_size / 1.2;
    WorldMap map;
    map.half_size = half_size;
    if (name == "empty") return map;
    if (name == "obstacles") {
        // 5 discs of radius 0.1 (VMAS "flocking"), >= 0.15 apart surface to surface.
        int count = (int)std::lround(5 * scale * scale);
        if (count > kMaxObstacles)
            throw std::invalid_argument("obstacles: half_size " + number_text(half_size) + " needs " + std::to_string(count) +
                                        " discs, over the limit kMaxObstacles = " + std::to_string(kMaxObstacles));
        double lim = 0.8 * scale, r = 0.1, min_gap = 0.15;
        for (int tries = 0; (int)map.discs.size() < count; ++tries) {
            if (tries > 100000) throw std::runtime_error("obstacles: could not place " + std::to_string(count) + " discs");
            Vec2 c{rng.uniform(-lim, lim), rng.uniform(-lim, lim)};
            bool ok = true;
            for (const Disc& o : map.discs) ok = ok && norm(c - o.c) >= 2 * r + min_gap;
            if (ok) map.discs.push_back({c, r});
        }
        return map;
    }
    if (name == "barrier") {
        // A wall along y = 0 of thickness 0.1 spanning the world, one gap of width 0.5 whose
        // centre is uniform in [-0.5, 0.5] (scaled). Harder than the paper's (SPEC 2).
        double gap_c = rng.uniform(-0.5, 0.5) * scale, half_gap = 0.25, t = 0.05;
        map.boxes.push_back({{-half_size, -t}, {gap_c - half_gap, t}});
        map.boxes.push_back({{gap_c + half_gap, -t}, {half_size, t}});
        return map;
    }
    throw std::invalid_argument("map: unknown map name '" + name + "' (expected empty, obstacles or barrier)");
}

// Static clearance (distance from the cell centre to the nearest obstacle or wall surface) on
// a square grid over the world; cell k is (row k / n, column k % n), row 0 = lowest y. The
// side is the world's width in cells of about `cell_wanted`, at most `max_side` (>= 2): only a
// world wider than max_side cells gets coarser cells, `stretch` = (side wanted) / n > 1 times as
// wide (1 when not capped). The routing grid (Section 12: wavefront, RouteGuide, GuidedExpert)
// keeps cells of 0.036 up to half-size 41.4 (kRouteMaxGridSide): docs/design.md, "Routing at any
// scale". `clear` is exact below kClearanceReach and kClearanceReach beyond it (routing reads
// thresholds of 0.1-0.3), so each obstacle fills only the cells within reach of it: a grid of
// 2304^2 cells over 4096 boxes fills in well under a second.
// The interaction scenes check reachability on its layout (Section 4b); the model's occupancy
// raster is Grid (Section 5), the planner's node-sampled fields DistanceField (madbp.hpp).
constexpr double kClearanceReach = 1.0;
struct ClearanceGrid {
    int n = 0;
    double cell = 0.04, half = 1.2, stretch = 1;
    std::vector<float> clear;
    ClearanceGrid() = default;
    // fill = false: the layout only (n, cell, stretch; `clear` left empty).
    ClearanceGrid(const WorldMap& map, double cell_wanted, int max_side = kRouteMaxGridSide, bool fill = true) : half(map.half_size) {
        if (!(cell_wanted > 0) || !std::isfinite(cell_wanted) || max_side < 2)
            throw std::invalid_argument("ClearanceGrid: needs cell > 0 and max_side >= 2 (got " + std::to_string(cell_wanted) + ", " +
                                        std::to_string(max_side) + ")");
        const double wanted = std::max(2.0, std::round(2 * half / cell_wanted));  // a double: a huge world cannot wrap
        n = (int)std::min(wanted, (double)max_side);
        stretch = wanted > n ? wanted / n : 1.0;
        cell = 2 * half / n;
        if (fill) fill_clearance(map);
    }
    int index(Vec2 p) const {
        int col = std::clamp((int)std::floor((p.x + half) / cell), 0, n - 1);
        int row = std::clamp((int)std::floor((p.y + half) / cell), 0, n - 1);
        return row * n + col;
    }
    Vec2 centre(int k) const { return {-half + (k % n + 0.5) * cell, -half + (k / n + 0.5) * cell}; }

private:
    void fill_clearance(const WorldMap& map) {
        clear.resize((size_t)n * n);
        for (int k = 0; k < n * n; ++k) {  // the border walls, then each obstacle over the cells within reach
            const Vec2 c = centre(k);
            clear[k] = (float)std::min(kClearanceReach, half - std::max(std::fabs(c.x), std::fabs(c.y)));
        }
        auto lower = [&](Vec2 lo, Vec2 hi, auto&& distance) {
            auto at = [&](double v) { return std::clamp((int)std::floor((v + half) / cell), 0, n - 1); };
            for (int row = at(lo.y - kClearanceReach); row <= at(hi.y + kClearanceReach); ++row)
                for (int col = at(lo.x - kClearanceReach); col <= at(hi.x + kClearanceReach); ++col) {
                    float& v = clear[(size_t)row * n + col];
                    v = std::min(v, (float)distance(centre(row * n + col)));
                }
        };
        for (const Disc& d : map.discs) lower(d.c - Vec2{d.r, d.r}, d.c + Vec2{d.r, d.r}, [&](Vec2 p) { return norm(p - d.c) - d.r; });
        for (const Box& b : map.boxes) lower(b.lo, b.hi, [&](Vec2 p) { return box_distance(b, p); });
    }
};

// =============================================================================================
// Section 3. The world (SPEC 2)
// =============================================================================================

// Physics and episode constants. Defaults are VMAS v1.5.2 navigation (SPEC 2).
struct WorldConfig {
    double radius = 0.1;           // agent disc radius, world units, > 0
    double mass = 1.0;             // agent mass, > 0
    double dt = 0.1;               // seconds per step, > 0
    int substeps = 2;              // integration substeps per step, >= 1
    double drag = 0.25;            // fraction of velocity removed once per step (first substep), [0, 1)
    double contact_k = 1e-3;       // softness of the contact penalty, world units, > 0
    double contact_force = 100.0;  // contact force per unit penetration, > 0
    double max_action = 1.0;       // action components are clamped to [-max_action, max_action]
    double goal_tolerance = 0.1;   // an agent is at its goal when |p - g| < goal_tolerance
    int max_steps = 100;           // an episode ends after this many steps, >= 1
    // A robot at p with goal g is at its goal (World::at_goal; planners and training without a World).
    bool reached(Vec2 p, Vec2 g) const { return norm(p - g) < goal_tolerance; }
};

// One robot. `id` is stable across joins and leaves.
struct Agent {
    int id = 0;
    Vec2 pos, vel, goal;
};

// Episode metrics; they follow the agents present at each step (SPEC 2).
struct Metrics {
    int steps = 0;                 // steps taken
    bool success = false;          // all present agents were at their goals at the same step
    int success_step = -1;         // first step at which that happened (-1: not yet)
    long agent_collisions = 0;     // agent-agent pairs with centres closer than 2 r, summed over steps
    long obstacle_collisions = 0;  // agent-obstacle and agent-wall pairs in contact, summed over steps
    long clamped_actions = 0;      // action components that were outside [-1, 1] and got clamped
    long collisions() const { return agent_collisions + obstacle_collisions; }
};

// The navigation world: holonomic discs pushed by forces, with drag and soft contacts.
// Two-phase step (all forces first, then all updates), so agent order never changes the
// result. Agents are addressed by stable ids; `agents()` lists the present ones in order of
// joining, and `step` takes one action per present agent in that order.
class World {
public:
    explicit World(WorldMap map = WorldMap{}, WorldConfig cfg = WorldConfig{}) : map_(std::move(map)), cfg_(cfg) {
        require_finite(map_.half_size, "map.half_size");
        if (!(map_.half_size > 0)) throw std::invalid_argument("map.half_size: must be > 0");
        if (map_.half_size > kMaxHalfSize)
            throw std::invalid_argument("map.half_size: " + number_text(map_.half_size) + " exceeds the limit kMaxHalfSize = " +
                                        number_text(kMaxHalfSize));
        if (map_.discs.size() + map_.boxes.size() > (size_t)kMaxObstacles)
            throw std::invalid_argument("map: " + std::to_string(map_.discs.size() + map_.boxes.size()) +
                                        " obstacles exceed the limit kMaxObstacles = " + std::to_string(kMaxObstacles));
        for (size_t i = 0; i < map_.discs.size(); ++i) {
            const Disc& d = map_.discs[i];
            std::string f = "map.discs[" + std::to_string(i) + "]";
            require_finite(d.c.x, f + ".x"); require_finite(d.c.y, f + ".y"); require_finite(d.r, f + ".r");
            if (!(d.r > 0)) throw std::invalid_argument(f + ".r: must be > 0");
        }
        for (size_t i = 0; i < map_.boxes.size(); ++i) {
            const Box& b = map_.boxes[i];
            std::string f = "map.boxes[" + std::to_string(i) + "]";
            for (double v : {b.lo.x, b.lo.y, b.hi.x, b.hi.y}) require_finite(v, f);
            if (!(b.lo.x < b.hi.x && b.lo.y < b.hi.y)) throw std::invalid_argument(f + ": needs x0 < x1 and y0 < y1");
        }
        if (!(cfg_.radius > 0 && cfg_.mass > 0 && cfg_.dt > 0 && cfg_.substeps >= 1 && cfg_.drag >= 0 &&
              cfg_.drag < 1 && cfg_.contact_k > 0 && cfg_.max_steps >= 1 && cfg_.goal_tolerance > 0))
            throw std::invalid_argument("WorldConfig: a constant is out of its range (see its comments)");
    }

    // Adds an agent at `start` (at rest) heading for `goal`; returns its id. Both points must
    // be finite and the disc inside the world walls. `id` < 0 picks the next free id; a given
    // id must be in [0, kMaxAgentId] and not in use (std::invalid_argument otherwise).
    int add_agent(Vec2 start, Vec2 goal, int id = -1) {
        check_point(start, "start", cfg_.radius);
        check_point(goal, "goal", cfg_.radius);
        if (id > kMaxAgentId)
            throw std::invalid_argument("add_agent: id " + std::to_string(id) + " exceeds the limit kMaxAgentId = " + std::to_string(kMaxAgentId));
        if (id >= 0 && index_of(id) >= 0) throw std::invalid_argument("add_agent: duplicate agent id " + std::to_string(id));
        if (id < 0 && next_id_ > kMaxAgentId)
            throw std::invalid_argument("add_agent: no free id left below the limit kMaxAgentId = " + std::to_string(kMaxAgentId));
        if (id < 0) id = next_id_;
        next_id_ = std::max(next_id_, id + 1);
        agents_.push_back({id, start, {0, 0}, goal});
        return id;
    }
    // Removes an agent (it leaves the team between steps). Throws on an unknown id.
    void remove_agent(int id) { agents_.erase(agents_.begin() + checked_index(id, "remove_agent")); }
    // Overwrites an agent's state (tests, resets). The centre must be finite and inside the
    // walls (a disc pressed into a wall by the soft contact is a valid state).
    void set_state(int id, Vec2 pos, Vec2 vel) {
        int i = checked_index(id, "set_state");
        check_point(pos, "pos", 0);
        require_finite(vel.x, "vel.x of agent " + std::to_string(id));
        require_finite(vel.y, "vel.y of agent " + std::to_string(id));
        agents_[i].pos = pos;
        agents_[i].vel = vel;
    }
    void set_goal(int id, Vec2 goal) {
        int i = checked_index(id, "set_goal");
        check_point(goal, "goal", cfg_.radius);
        agents_[i].goal = goal;
    }

    const std::vector<Agent>& agents() const { return agents_; }
    int size() const { return (int)agents_.size(); }
    const Agent& agent(int id) const { return agents_[checked_index(id, "agent")]; }
    // Position of `id` in agents(), or -1.
    int index_of(int id) const {
        for (size_t i = 0; i < agents_.size(); ++i) if (agents_[i].id == id) return (int)i;
        return -1;
    }
    const WorldMap& map() const { return map_; }
    const WorldConfig& config() const { return cfg_; }
    const Metrics& metrics() const { return metrics_; }
    int t() const { return metrics_.steps; }
    // The episode is over: success, or max_steps taken.
    bool done() const { return metrics_.success || metrics_.steps >= cfg_.max_steps; }
    bool at_goal(const Agent& a) const { return cfg_.reached(a.pos, a.goal); }
    // Every present agent is at its goal (false for an empty team).
    bool all_at_goal() const {
        if (agents_.empty()) return false;
        for (const Agent& a : agents_) if (!at_goal(a)) return false;
        return true;
    }
    // Collisions of the last step (agent-agent, agent-static), for rendering.
    const std::vector<std::pair<int, int>>& last_agent_contacts() const { return last_agent_contacts_; }
    const std::vector<int>& last_static_contacts() const { return last_static_contacts_; }
    // Action components clamped in the last step.
    int last_clamped() const { return last_clamped_; }

    // Advances one step of dt. `actions[i]` is the force on agents()[i], each component in
    // [-1, 1]: larger values are clamped and counted (metrics().clamped_actions); a NaN or
    // infinite component throws std::invalid_argument naming the agent.
    void step(const std::vector<Vec2>& actions) {
        if (actions.size() != agents_.size())
            throw std::invalid_argument("step: got " + std::to_string(actions.size()) + " actions for " +
                                        std::to_string(agents_.size()) + " agents");
        const int n = size();
        force_.assign(n, Vec2{});
        last_clamped_ = 0;
        for (int i = 0; i < n; ++i) {
            Vec2 u = actions[i];
            if (!std::isfinite(u.x) || !std::isfinite(u.y))
                throw std::invalid_argument("action of agent " + std::to_string(agents_[i].id) + ": not finite (" +
                                            std::to_string(u.x) + ", " + std::to_string(u.y) + ")");
            last_clamped_ += (std::fabs(u.x) > cfg_.max_action) + (std::fabs(u.y) > cfg_.max_action);
            force_[i] = clamp_box(u, cfg_.max_action);
        }
        metrics_.clamped_actions += last_clamped_;
        double sub_dt = cfg_.dt / cfg_.substeps;
        for (int s = 0; s < cfg_.substeps; ++s) {
            // Phase 1: every force from the current positions.
            total_.assign(force_.begin(), force_.end());
            for (int i = 0; i < n; ++i) total_[i] += static_contact_force(agents_[i].pos);
            for (int i = 0; i < n; ++i)
                for (int j = i + 1; j < n; ++j) {
                    Vec2 d = agents_[i].pos - agents_[j].pos;
                    double dist = norm(d);
                    if (dist <= 0 || dist > 2 * cfg_.radius + kContactCutoff * cfg_.contact_k) continue;
                    Vec2 f = d / dist * penetration_force(dist, 2 * cfg_.radius);
                    total_[i] += f;
                    total_[j] -= f;
                }
            // Phase 2: integrate. Drag on the first substep only (VMAS core.py).
            for (int i = 0; i < n; ++i) {
                Agent& a = agents_[i];
                if (s == 0) a.vel *= (1 - cfg_.drag);
                a.vel += total_[i] / cfg_.mass * sub_dt;
                a.pos += a.vel * sub_dt;
            }
        }
        for (const Agent& a : agents_)
            if (!std::isfinite(a.pos.x) || !std::isfinite(a.pos.y) || !std::isfinite(a.vel.x) || !std::isfinite(a.vel.y))
                throw std::runtime_error("step: state of agent " + std::to_string(a.id) + " became non-finite");
        metrics_.steps++;
        count_collisions();
        if (!metrics_.success && all_at_goal()) {
            metrics_.success = true;
            metrics_.success_step = metrics_.steps;
        }
    }

    // Contact force on a disc of this world's radius at `p` from obstacles and walls. For a
    // disc obstacle, d_min - d = (r + r_o) - |p - c| = r - (surface distance), so every
    // surface uses penetration_force(surface distance, r).
    Vec2 static_contact_force(Vec2 p) const {
        Vec2 f{0, 0};
        double r = cfg_.radius, reach = r + kContactCutoff * cfg_.contact_k;
        for_each_surface(map_, p, [&](double dist, Vec2 away) {
            if (dist < reach) f += away * penetration_force(dist, r);
        });
        return f;
    }
    // VMAS soft contact: force magnitude 100 * k * log(1 + exp((d_min - d) / k)) (SPEC 2).
    double penetration_force(double d, double d_min) const {
        double z = (d_min - d) / cfg_.contact_k;
        double softplus = z > 30 ? z : std::log1p(std::exp(z));  // exact to 1e-13 above 30
        return cfg_.contact_force * cfg_.contact_k * softplus;
    }

private:
    // Contacts further than d_min + 25 k are skipped: their force is below 100*k*e^-25 ~ 1e-12.
    static constexpr double kContactCutoff = 25.0;

    WorldMap map_;
    WorldConfig cfg_;
    std::vector<Agent> agents_;
    Metrics metrics_;
    int next_id_ = 0, last_clamped_ = 0;
    std::vector<Vec2> force_, total_;
    std::vector<std::pair<int, int>> last_agent_contacts_;
    std::vector<int> last_static_contacts_;

    int checked_index(int id, const char* who) const {
        int i = index_of(id);
        if (i < 0) throw std::invalid_argument(std::string(who) + ": unknown agent id " + std::to_string(id));
        return i;
    }
    // `margin` = radius: the whole disc inside the walls; 0: only the centre.
    void check_point(Vec2 p, const std::string& what, double margin) const {
        require_finite(p.x, what + ".x");
        require_finite(p.y, what + ".y");
        double lim = map_.half_size - margin;
        if (std::fabs(p.x) > lim || std::fabs(p.y) > lim)
            throw std::invalid_argument(what + ": (" + std::to_string(p.x) + ", " + std::to_string(p.y) +
                                        ") is outside the world (|x|, |y| must be <= " + std::to_string(lim) + ")");
    }
    // Per step and pair: centres closer than the sum of radii (SPEC 2).
    void count_collisions() {
        last_agent_contacts_.clear();
        last_static_contacts_.clear();
        double r = cfg_.radius;
        for (size_t i = 0; i < agents_.size(); ++i) {
            Vec2 p = agents_[i].pos;
            for (size_t j = i + 1; j < agents_.size(); ++j)
                if (norm(p - agents_[j].pos) < 2 * r) last_agent_contacts_.push_back({agents_[i].id, agents_[j].id});
            for_each_surface(map_, p, [&](double dist, Vec2) {
                if (dist < r) last_static_contacts_.push_back(agents_[i].id);
            });
        }
        metrics_.agent_collisions += (long)last_agent_contacts_.size();
        metrics_.obstacle_collisions += (long)last_static_contacts_.size();
    }
};

// =============================================================================================
// Section 4. Spawning (SPEC 2)
// =============================================================================================

// The half-size of a random world for `n` robots at constant density: that of 64 robots in
// half-size 3.4 (about 0.425 sqrt(n)), rounded to 0.1 and never below the standard 1.2. Teams
// of <= 8 get exactly 1.2 (0.425 sqrt(8) = 1.202 rounds to it), so the standard world and every
// result measured in it stay as they were; 16 -> 1.7, 32 -> 2.4, 64 -> 3.4, 256 -> 6.8,
// 1024 -> 13.6. The tool's default for --half-size (eval, render, bench --plan).
inline double default_half_size(int n) {
    if (n <= 8) return 1.2;
    return std::max(1.2, std::round(4.25 * std::sqrt((double)n)) / 10);
}

// Draws `n` starts and then `n` goals by rejection sampling: uniform in [-1, 1]^2 scaled by
// half_size/1.2; every centre >= `min_separation` (0.25) from every earlier centre (starts and
// goals alike) and >= radius + 0.05 from any obstacle or wall surface. Each point gets at most
// `max_tries` draws; a layout that cannot be placed throws std::runtime_error naming half_size
// (the world is too small for the team) and default_half_size(n) (never hangs: with the checks
// O(points placed) per draw, 1024 robots at default_half_size(1024) take a few ms).
struct SpawnConfig {
    double min_separation = 0.25;  // between centres, world units
    double clearance = 0.05;       // extra gap to obstacle and wall surfaces beyond the radius
    int max_tries = 20000;         // draws per point before giving up
};
inline void spawn_agents(World& world, int n, Rng& rng, const SpawnConfig& sc = SpawnConfig{}) {
    if (n < 0) throw std::invalid_argument("agents: must be >= 0 (got " + std::to_string(n) + ")");
    const WorldMap& map = world.map();
    double lim = map.half_size / 1.2, min_static = world.config().radius + sc.clearance;
    std::vector<Vec2> placed;
    for (const Agent& a : world.agents()) { placed.push_back(a.pos); placed.push_back(a.goal); }
    auto draw = [&](const char* what, int k) {
        for (int tries = 0; tries < sc.max_tries; ++tries) {
            Vec2 p{rng.uniform(-lim, lim), rng.uniform(-lim, lim)};
            if (static_clearance(map, p) < min_static) continue;
            bool ok = true;
            for (Vec2 q : placed) if (norm(p - q) < sc.min_separation) { ok = false; break; }
            if (!ok) continue;
            placed.push_back(p);
            return p;
        }
        throw std::runtime_error("half_size: " + number_text(map.half_size) + " is too small for " + std::to_string(n) +
                                 " robots on this map: could not place " + what + " " + std::to_string(k) + " of " +
                                 std::to_string(n) + " after " + std::to_string(sc.max_tries) +
                                 " tries (constant density: default_half_size(" + std::to_string(n) + ") = " +
                                 number_text(default_half_size(n)) + ")");
    };
    std::vector<Vec2> starts, goals;
    for (int i = 0; i < n; ++i) starts.push_back(draw("start", i));
    for (int i = 0; i < n; ++i) goals.push_back(draw("goal", i));
    for (int i = 0; i < n; ++i) world.add_agent(starts[i], goals[i]);
}

// A random problem: the named map and `n` agents, everything drawn from `seed`.
inline World make_random_world(const std::string& map_name, int n, uint64_t seed, double half_size = 1.2,
                               WorldConfig cfg = WorldConfig{}) {
    Rng rng(seed);
    World world(make_map(map_name, rng, half_size), cfg);
    spawn_agents(world, n, rng);
    return world;
}

// A batch of independent worlds stepping together (MAPPO rollouts, benchmarks). Worlds are
// stepped in parallel with OpenMP; each world's result does not depend on the thread count.
struct WorldBatch {
    std::vector<World> worlds;
    // actions[w][i] is the action of agent i of world w.
    void step(const std::vector<std::vector<Vec2>>& actions) {
        if (actions.size() != worlds.size())
            throw std::invalid_argument("WorldBatch::step: got " + std::to_string(actions.size()) + " action lists for " +
                                        std::to_string(worlds.size()) + " worlds");
        std::string error;
#pragma omp parallel for schedule(dynamic, 16)
        for (long w = 0; w < (long)worlds.size(); ++w) {
            try {
                worlds[w].step(actions[w]);
            } catch (const std::exception& e) {
#pragma omp critical
                if (error.empty()) error = "world " + std::to_string(w) + ": " + e.what();
            }
        }
        if (!error.empty()) throw std::invalid_argument(error);
    }
};

// =============================================================================================
// Section 4b. Interaction scenes (issue 12)
// =============================================================================================
// Randomised scenes in which robots must get past each other, for demonstrations (`madbp
// collect --scenarios`) and evaluation (`madbp eval --scenario NAME`). Each draws the named map
// from the seed as make_random_world does, then a layout on it (L = half_size / 1.2 scales
// every length; "rotated" = a uniform angle, or one of the 4 axis directions where walls are
// added, since walls are axis-aligned boxes):
//   swap      head-on swaps: ceil(n/2) robots at one end of 1-2 parallel lanes, floor(n/2) at
//             the other, each robot going to the far end of its lane (lanes 1.0-1.8 L long,
//             0.3-0.45 apart; exact swaps of start and goal); random centre and rotation.
//   cross     a plus sign: arms of 0.5-0.85 L from a random centre, rotated; N <-> S and
//             E <-> W (n < 4: the first n of N->S, E->W, S->N, W->E).
//   gap       swaps through a wall's gap: on the barrier map its own gap; on the others a wall
//             (thickness 0.1) with a gap of 0.45-0.6 is added across the world (horizontal or
//             vertical, discs near it removed). Robots 0.25-0.75 L from the wall swap with
//             their point reflections through the gap's centre.
//   corridor  swaps through a corridor: two walls (thickness 0.1) 0.4-0.6 apart and 0.5-1.0 L
//             long (axis-aligned, random centre; discs near it removed; on the barrier map it
//             runs through the gap, at most the gap's width), ceil(n/2) robots queued outside
//             one end and floor(n/2) outside the other, exact swaps.
//   parked    robots parked on their goals (start = goal) on the path of the movers: one mover
//             (n <= 2) or a head-on pair (n >= 3) along a rotated line of 1.2-1.8 L, the other
//             robots parked between, up to 0.05 off the line.
//   circle    antipodal swaps on a circle of radius 0.6-1.0 L (random centre, angles evenly
//             spaced from a random one, each jittered by up to min(0.1, pi / 4n) rad); the
//             classic benchmark scene, for up to kMaxCircleAgents robots.
// Every scene is checked and redrawn (at most kMaxScenarioTries draws, then std::runtime_error):
// starts >= 0.25 apart, goals >= 0.25 apart (a start may equal another robot's goal), every
// start and goal >= radius + 0.06 from every obstacle and wall surface, and every goal reachable
// from its start on the guided expert's planning grid (cells of ~0.036, clearance >= 0.13 at cell
// centres: the wavefront of Section 12). n is in [1, kMaxScenarioAgents] (circle: kMaxCircleAgents).
constexpr int kMaxScenarioTries = 2000;
constexpr int kMaxScenarioAgents = 4;
constexpr int kMaxCircleAgents = 64;

inline const std::vector<std::string>& interaction_scenarios() {
    static const std::vector<std::string> names = {"swap", "cross", "gap", "corridor", "parked", "circle"};
    return names;
}

namespace detail {
// Whether, for every i, a breadth-first search in 8 directions from to[i]'s cell (always
// allowed) reaches from[i]'s cell over the cells of a ClearanceGrid layout of ~`cell` whose
// centre has clearance >= min_clear (measured in double precision: the float clearances of a
// filled grid could round a cell across the line, and the scenes drawn would change).
inline bool all_reachable(const WorldMap& map, const std::vector<Vec2>& from, const std::vector<Vec2>& to, double cell = 0.036,
                          double min_clear = 0.13) {
    const ClearanceGrid g(map, cell, kRouteMaxGridSide, /*fill*/ false);
    const int n = g.n;
    std::vector<uint8_t> free((size_t)n * n), seen;
    for (int k = 0; k < n * n; ++k) free[k] = static_clearance(map, g.centre(k)) >= min_clear;
    std::vector<int> queue;
    auto reach = [&](int start, int goal) {
        if (start == goal) return true;
        seen.assign((size_t)n * n, 0);
        queue.assign(1, goal);
        seen[goal] = 1;
        for (size_t head = 0; head < queue.size(); ++head) {
            const int k = queue[head], row = k / n, col = k % n;
            for (int dr = -1; dr <= 1; ++dr)
                for (int dc = -1; dc <= 1; ++dc) {
                    const int r2 = row + dr, c2 = col + dc;
                    if ((dr == 0 && dc == 0) || r2 < 0 || r2 >= n || c2 < 0 || c2 >= n) continue;
                    const int k2 = r2 * n + c2;
                    if (seen[k2] || !free[k2]) continue;
                    if (k2 == start) return true;
                    seen[k2] = 1;
                    queue.push_back(k2);
                }
        }
        return false;
    };
    for (size_t i = 0; i < from.size(); ++i)
        if (!reach(g.index(from[i]), g.index(to[i]))) return false;
    return true;
}

// Distance between two boxes' surfaces (0 when they touch or overlap).
inline double box_gap(const Box& a, const Box& b) {
    const double dx = std::max({0.0, a.lo.x - b.hi.x, b.lo.x - a.hi.x}), dy = std::max({0.0, a.lo.y - b.hi.y, b.lo.y - a.hi.y});
    return std::sqrt(dx * dx + dy * dy);
}
// A box given in a frame rotated by quarter turns q (0..3) about the origin, then shifted by c.
inline Box turned_box(Vec2 lo, Vec2 hi, int q, Vec2 c) {
    auto turn = [&](Vec2 p) {
        for (int i = 0; i < q; ++i) p = perp(p);
        return p + c;
    };
    const Vec2 a = turn(lo), b = turn(hi);
    return {{std::min(a.x, b.x), std::min(a.y, b.y)}, {std::max(a.x, b.x), std::max(a.y, b.y)}};
}
// Adds walls to a map: drops the discs closer than `keep_off` (surface to surface) to any of
// them; false when a wall pokes out of the world or (with check_boxes) comes closer than
// `keep_off` to an existing box.
inline bool add_walls(WorldMap& map, const std::vector<Box>& walls, double keep_off, bool check_boxes = true) {
    for (const Box& w : walls) {
        if (w.lo.x < -map.half_size || w.hi.x > map.half_size || w.lo.y < -map.half_size || w.hi.y > map.half_size) return false;
        if (check_boxes)
            for (const Box& b : map.boxes) if (box_gap(w, b) < keep_off) return false;
    }
    std::vector<Disc> kept;
    for (const Disc& d : map.discs) {
        bool near = false;
        for (const Box& w : walls) near = near || box_distance(w, d.c) - d.r < keep_off;
        if (!near) kept.push_back(d);
    }
    map.discs = std::move(kept);
    map.boxes.insert(map.boxes.end(), walls.begin(), walls.end());
    return true;
}
// The checks of Section 4b on one drawn layout.
inline bool interaction_scene_valid(const WorldMap& map, const std::vector<Vec2>& starts, const std::vector<Vec2>& goals, double radius) {
    const double min_sep = 0.25, min_clear = radius + 0.06;
    for (size_t i = 0; i < starts.size(); ++i) {
        if (!std::isfinite(starts[i].x + starts[i].y + goals[i].x + goals[i].y)) return false;
        if (static_clearance(map, starts[i]) < min_clear || static_clearance(map, goals[i]) < min_clear) return false;
        for (size_t j = 0; j < i; ++j)
            if (norm(starts[i] - starts[j]) < min_sep || norm(goals[i] - goals[j]) < min_sep) return false;
    }
    return all_reachable(map, starts, goals);
}
}  // namespace detail

// A scene of the named interaction scenario (see above) on the named map, for n robots, all drawn
// from `seed`. Throws std::invalid_argument on an unknown scenario or map name or n outside
// [1, kMaxScenarioAgents] ([1, kMaxCircleAgents] for circle), std::runtime_error when no valid layout was found.
inline World make_interaction_world(const std::string& scenario, const std::string& map_name, int n, uint64_t seed,
                                    double half_size = 1.2, WorldConfig cfg = WorldConfig{}) {
    const auto& names = interaction_scenarios();
    if (std::find(names.begin(), names.end(), scenario) == names.end())
        throw std::invalid_argument("scenario: unknown scenario '" + printable(scenario) +
                                    "' (expected swap, cross, gap, corridor, parked or circle)");
    const int max_agents = scenario == "circle" ? kMaxCircleAgents : kMaxScenarioAgents;
    if (n < 1 || n > max_agents)
        throw std::invalid_argument("scenario " + scenario + ": agents must be in [1, " + std::to_string(max_agents) + "] (got " +
                                    std::to_string(n) + ")");
    Rng rng(seed);
    const WorldMap base = make_map(map_name, rng, half_size);
    const double L = half_size / 1.2, r = cfg.radius, t = 0.05;  // t: half a wall's thickness
    const double pi = std::acos(-1.0);
    auto dir = [](double a) { return Vec2{std::cos(a), std::sin(a)}; };
    for (int tries = 0; tries < kMaxScenarioTries; ++tries) {
        WorldMap map = base;
        std::vector<Vec2> s, g;
        const Vec2 c{rng.uniform(-0.5, 0.5) * L, rng.uniform(-0.5, 0.5) * L};
        if (scenario == "swap") {
            const Vec2 u = dir(rng.uniform(0, 2 * pi)), v = perp(u);
            const double len = rng.uniform(1.0, 1.8) * L, gap = rng.uniform(0.3, 0.45);
            const int lanes = (n + 1) / 2;
            for (int i = 0; i < n; ++i) {
                const int lane = i % lanes, side = i < lanes ? -1 : 1;
                const Vec2 off = v * ((lane - 0.5 * (lanes - 1)) * gap);
                s.push_back(c + off + u * (side * 0.5 * len));
                g.push_back(c + off - u * (side * 0.5 * len));
            }
        } else if (scenario == "cross") {
            const Vec2 u = dir(rng.uniform(0, 2 * pi)), v = perp(u);
            const Vec2 arms[4] = {v, u, v * -1.0, u * -1.0};  // N, E, S, W
            double len[4];
            for (double& a : len) a = rng.uniform(0.5, 0.85) * L;
            for (int i = 0; i < n; ++i) {  // N->S, E->W, S->N, W->E
                s.push_back(c + arms[i] * len[i]);
                g.push_back(c + arms[(i + 2) % 4] * len[(i + 2) % 4]);
            }
        } else if (scenario == "gap" || scenario == "corridor") {
            // A frame turned by q quarter turns: the passage runs along its y axis (gap) or x axis (corridor).
            int q = (int)(rng.next_u64() % 4);
            Vec2 gc;          // the passage's centre
            double reach;     // how far from the centre along the passage robots start
            if (scenario == "gap") {
                if (map_name == "barrier" && map.boxes.size() == 2) {
                    q = 0;
                    gc = {0.5 * (map.boxes[0].hi.x + map.boxes[1].lo.x), 0};
                } else {
                    const double half_gap = 0.5 * rng.uniform(0.45, 0.6), along = rng.uniform(-0.5, 0.5) * L, at = rng.uniform(-0.3, 0.3) * L;
                    const double h = map.half_size;
                    // In the turned frame the wall runs along x at y = at, the gap at x = along.
                    std::vector<Box> walls = {detail::turned_box({-h - 1, at - t}, {along - half_gap, at + t}, q, {0, 0}),
                                              detail::turned_box({along + half_gap, at - t}, {h + 1, at + t}, q, {0, 0})};
                    for (Box& w : walls) {  // clip to the world
                        w.lo = clamp_box(w.lo, h);
                        w.hi = clamp_box(w.hi, h);
                    }
                    if (!detail::add_walls(map, walls, 0.25)) continue;
                    gc = Vec2{along, at};
                    for (int i = 0; i < q; ++i) gc = perp(gc);
                }
                reach = 0;
            } else {
                // On the barrier map the corridor runs through the gap, its walls meeting the barrier's.
                const bool through_gap = map_name == "barrier" && map.boxes.size() == 2;
                double half_w = 0.5 * rng.uniform(0.4, 0.6);
                const double half_len = 0.5 * rng.uniform(0.5, 1.0) * L;
                gc = c;
                if (through_gap) {
                    q = 1;
                    half_w = std::min(half_w, 0.5 * (map.boxes[1].lo.x - map.boxes[0].hi.x));
                    gc = {0.5 * (map.boxes[0].hi.x + map.boxes[1].lo.x), 0};
                }
                std::vector<Box> walls = {detail::turned_box({-half_len, half_w}, {half_len, half_w + 2 * t}, q, gc),
                                          detail::turned_box({-half_len, -half_w - 2 * t}, {half_len, -half_w}, q, gc)};
                if (!detail::add_walls(map, walls, 0.25, /*check boxes*/ !through_gap)) continue;
                reach = half_len;
            }
            // Unit vectors of the turned frame: `a` along the passage, `b` across it.
            Vec2 a = scenario == "gap" ? Vec2{0, 1} : Vec2{1, 0};
            for (int i = 0; i < q; ++i) a = perp(a);
            const Vec2 b = perp(a);
            const int first = (n + 1) / 2;
            if (scenario == "gap") {
                // Pairs of point reflections through the gap's centre; an odd robot goes to its own reflection.
                for (int i = 0; i < first; ++i) {
                    const Vec2 p = gc + a * (rng.uniform(0.25, 0.75) * L) + b * (rng.uniform(-0.5, 0.5) * L);
                    s.push_back(p);
                    g.push_back(gc * 2.0 - p);
                }
                for (int i = first; i < n; ++i) {
                    s.push_back(g[i - first]);
                    g.push_back(s[i - first]);
                }
            } else {
                // Queues outside both ends, 0.3 apart; robot i of one end swaps with robot i of the other.
                const double lead = reach + rng.uniform(0.2, 0.35);
                for (int i = 0; i < first; ++i) {
                    const Vec2 p = gc - a * (lead + 0.3 * i) + b * rng.uniform(-0.05, 0.05);
                    s.push_back(p);
                    g.push_back(gc * 2.0 - p);
                }
                for (int i = first; i < n; ++i) {
                    s.push_back(g[i - first]);
                    g.push_back(s[i - first]);
                }
            }
        } else if (scenario == "parked") {
            const Vec2 u = dir(rng.uniform(0, 2 * pi)), v = perp(u);
            const double len = rng.uniform(1.2, 1.8) * L;
            const int movers = n >= 3 ? 2 : 1, parked = n - movers;
            s.push_back(c - u * (0.5 * len));
            g.push_back(c + u * (0.5 * len));
            if (movers == 2) {
                s.push_back(g[0]);
                g.push_back(s[0]);
            }
            for (int i = 0; i < parked; ++i) {
                const double f = (i + 1.0) / (parked + 1) + rng.uniform(-0.08, 0.08);
                const Vec2 p = c + u * ((f - 0.5) * len) + v * rng.uniform(-0.05, 0.05);
                s.push_back(p);
                g.push_back(p);
            }
        } else {  // circle
            const double R = rng.uniform(0.6, 1.0) * L, a0 = rng.uniform(0, 2 * pi), jitter = std::min(0.1, 0.25 * pi / n);
            for (int i = 0; i < n; ++i) {
                const Vec2 p = c + dir(a0 + 2 * pi * i / n + rng.uniform(-jitter, jitter)) * R;
                s.push_back(p);
                g.push_back(c * 2.0 - p);
            }
        }
        if (!detail::interaction_scene_valid(map, s, g, r)) continue;
        World world(map, cfg);
        for (int i = 0; i < n; ++i) world.add_agent(s[i], g[i]);
        return world;
    }
    throw std::runtime_error("scenario " + scenario + " on " + map_name + " with " + std::to_string(n) + " agents (seed " + std::to_string(seed) +
                             "): no valid layout in " + std::to_string(kMaxScenarioTries) + " draws");
}

// =============================================================================================
// Section 5. Occupancy grid (SPEC 2)
// =============================================================================================

// The map rasterized to G x G cells over [-half, half]^2. Layout: channel-major, then
// row-major, row 0 = lowest y, column 0 = lowest x: value (c, row, col) is at
// [(c * G + row) * G + col]. A cell is 1 when its centre lies inside an obstacle (not
// inflated), else 0. Channel 0: static obstacles. With `agents`: a channel with 1 where the
// cell centre is inside an agent disc. With `goals`: a channel with 1 where the cell centre is
// within goal_tolerance of a goal. Channels appear in that order.
struct Grid {
    int size = 32, channels = 1;
    double half_size = 1.2;
    std::vector<float> cells;
    float at(int c, int row, int col) const { return cells[((size_t)c * size + row) * size + col]; }
    double cell_width() const { return 2 * half_size / size; }
    Vec2 centre(int row, int col) const {
        double w = cell_width();
        return {-half_size + (col + 0.5) * w, -half_size + (row + 0.5) * w};
    }
};
namespace detail {
// Sets cells whose centre is within `r` of `c` in channel `ch`.
inline void rasterize_disc(Grid& g, int ch, Vec2 c, double r) {
    double w = g.cell_width();
    int c0 = std::max(0, (int)std::floor((c.x - r + g.half_size) / w)), c1 = std::min(g.size - 1, (int)((c.x + r + g.half_size) / w));
    int r0 = std::max(0, (int)std::floor((c.y - r + g.half_size) / w)), r1 = std::min(g.size - 1, (int)((c.y + r + g.half_size) / w));
    for (int row = r0; row <= r1; ++row)
        for (int col = c0; col <= c1; ++col)
            if (norm(g.centre(row, col) - c) < r) g.cells[((size_t)ch * g.size + row) * g.size + col] = 1;
}
}  // namespace detail
inline Grid occupancy_grid(const WorldMap& map, int size = 32) {
    if (size < 2 || size > 4096) throw std::invalid_argument("grid size: must be in [2, 4096] (got " + std::to_string(size) + ")");
    Grid g;
    g.size = size;
    g.half_size = map.half_size;
    g.cells.assign((size_t)size * size, 0.f);
    for (int row = 0; row < size; ++row)
        for (int col = 0; col < size; ++col)
            if (inside_obstacle(map, g.centre(row, col))) g.cells[(size_t)row * size + col] = 1;
    return g;
}
inline Grid occupancy_grid(const World& world, int size = 32, bool agents = false, bool goals = false) {
    Grid g = occupancy_grid(world.map(), size);
    g.channels = 1 + agents + goals;
    g.cells.resize((size_t)g.channels * size * size, 0.f);
    int ch = 1;
    if (agents) {
        for (const Agent& a : world.agents()) detail::rasterize_disc(g, ch, a.pos, world.config().radius);
        ch++;
    }
    if (goals)
        for (const Agent& a : world.agents()) detail::rasterize_disc(g, ch, a.goal, world.config().goal_tolerance);
    return g;
}

// A robot's own view of the static map: Gl x Gl cells of width 2 * extent / Gl centred on p
// (world units), row-major from the lowest y, written to out (Gl * Gl). A cell is 1 when an
// obstacle or wall surface is within half a cell of its centre (so thin walls are never
// missed) or it lies beyond the walls.
inline void local_crop(const WorldMap& map, Vec2 p, int Gl, double extent, float* out) {
    const double w = 2 * extent / Gl;
    // The obstacles near the crop only (the same cells: obstacles_near), kept per thread so a
    // crop allocates nothing once the scratch has grown.
    thread_local WorldMap near;
    obstacles_near(map, {p.x - extent, p.y - extent}, {p.x + extent, p.y + extent}, 0.5 * w, near);
    for (int row = 0; row < Gl; ++row)
        for (int col = 0; col < Gl; ++col) {
            const Vec2 c{p.x - extent + (col + 0.5) * w, p.y - extent + (row + 0.5) * w};
            out[row * Gl + col] = static_clearance(near, c) < 0.5 * w ? 1.0f : 0.0f;
        }
}

// =============================================================================================
// Section 6. Scene files (SPEC 2)
// =============================================================================================

// A whole problem given by hand: a map plus agents' starts and goals.
struct Scene {
    WorldMap map;
    std::vector<Vec2> starts, goals;
    // Lines scene_text writes as '# ' comments after the header (where the scene came from, e.g.
    // a MovingAI import's files and rows); parse_scene skips comments, so reading leaves it empty.
    std::vector<std::string> comments;
};

// Parses the line-based scene format:
//   madbp-scene 1               header, first non-comment line
//   world H                     half-size of the square world (optional, default 1.2, once)
//   disc X Y R                  static disc obstacle
//   box X0 Y0 X1 Y1             static axis-aligned box, X0 < X1, Y0 < Y1
//   agent SX SY GX GY           one robot: start, goal
// '#' starts a comment. Errors are std::invalid_argument("<source>:<line>: <why>"), quoting
// input with odd bytes escaped (printable). Checks: numbers finite, radii > 0, H <= kMaxHalfSize,
// at most kMaxObstacles discs + boxes, kMaxSceneAgents agents and kMaxSceneBytes of text, starts
// and goals inside the walls (|x|,|y| <= H - 0.1), starts >= 0.2 apart (no overlap), goals >= 0.2
// apart, starts and goals >= 0.1 clear of every obstacle surface. A start may coincide with
// another agent's goal (swaps).
inline Scene parse_scene(const std::string& text, const std::string& source = "scene", double radius = 0.1) {
    Scene scene;
    std::vector<int> agent_lines;
    if (text.size() > kMaxSceneBytes)
        throw std::invalid_argument(source + ": " + std::to_string(text.size()) + " bytes exceed the limit kMaxSceneBytes = " +
                                    std::to_string(kMaxSceneBytes));
    std::istringstream in(text);
    std::string line;
    int line_no = 0;
    bool header = false, world_seen = false;
    auto fail = [&](int ln, const std::string& why) {
        throw std::invalid_argument(source + ":" + std::to_string(ln) + ": " + why);
    };
    while (std::getline(in, line)) {
        ++line_no;
        auto hash = line.find('#');
        if (hash != std::string::npos) line.resize(hash);
        std::istringstream ls(line);
        std::vector<std::string> tok;
        for (std::string t; ls >> t;) tok.push_back(t);
        if (tok.empty()) continue;
        if (!header) {
            if (tok.size() != 2 || tok[0] != "madbp-scene") fail(line_no, "expected the header 'madbp-scene 1'");
            if (tok[1] != "1") fail(line_no, "unsupported scene version '" + printable(tok[1]) + "' (this reader knows 1)");
            header = true;
            continue;
        }
        const std::string& kw = tok[0];
        size_t want = kw == "world" ? 1 : kw == "disc" ? 3 : kw == "box" ? 4 : kw == "agent" ? 4 : 0;
        if (want == 0) fail(line_no, "unknown keyword '" + printable(kw) + "' (expected world, disc, box or agent)");
        if (tok.size() != want + 1)
            fail(line_no, "'" + kw + "' takes " + std::to_string(want) + " numbers, got " + std::to_string(tok.size() - 1));
        double v[4];
        for (size_t k = 0; k < want; ++k) {
            size_t pos = 0;
            try { v[k] = std::stod(tok[k + 1], &pos); } catch (...) { pos = 0; }
            if (pos != tok[k + 1].size()) fail(line_no, "'" + printable(tok[k + 1]) + "' is not a number");
            if (!std::isfinite(v[k])) fail(line_no, "'" + printable(tok[k + 1]) + "' is not finite");
        }
        if (kw == "world") {
            if (world_seen) fail(line_no, "'world' given twice");
            if (!scene.starts.empty() || !scene.map.discs.empty() || !scene.map.boxes.empty())
                fail(line_no, "'world' must come before obstacles and agents");
            if (!(v[0] > 2 * radius)) fail(line_no, "world half-size must be > " + std::to_string(2 * radius));
            if (v[0] > kMaxHalfSize)
                fail(line_no, "world half-size " + printable(tok[1]) + " exceeds the limit kMaxHalfSize = " + number_text(kMaxHalfSize));
            scene.map.half_size = v[0];
            world_seen = true;
        } else if (kw != "agent" && scene.map.discs.size() + scene.map.boxes.size() >= (size_t)kMaxObstacles) {
            fail(line_no, "more than kMaxObstacles = " + std::to_string(kMaxObstacles) + " discs and boxes");
        } else if (kw == "disc" || kw == "box") {
            // Plausible obstacles: bounded numbers (a 1e308 box was drawn at -inf) that reach
            // into the world (one wholly outside it is a mistake in the file, not a wall).
            for (size_t k = 0; k < want; ++k)
                if (std::fabs(v[k]) > kMaxSceneCoordinate)
                    fail(line_no, "'" + printable(tok[k + 1]) + "' exceeds the limit kMaxSceneCoordinate = " + number_text(kMaxSceneCoordinate));
            const double h = scene.map.half_size;
            if (kw == "disc") {
                if (!(v[2] > 0)) fail(line_no, "disc radius must be > 0");
                if (std::fabs(v[0]) - v[2] >= h || std::fabs(v[1]) - v[2] >= h)
                    fail(line_no, "disc lies wholly outside the world (half-size " + number_text(h) + ")");
                scene.map.discs.push_back({{v[0], v[1]}, v[2]});
            } else {
                if (!(v[0] < v[2] && v[1] < v[3])) fail(line_no, "box needs x0 < x1 and y0 < y1");
                if (v[2] <= -h || v[0] >= h || v[3] <= -h || v[1] >= h)
                    fail(line_no, "box lies wholly outside the world (half-size " + number_text(h) + ")");
                scene.map.boxes.push_back({{v[0], v[1]}, {v[2], v[3]}});
            }
        } else {
            if (scene.starts.size() >= (size_t)kMaxSceneAgents)
                fail(line_no, "more than kMaxSceneAgents = " + std::to_string(kMaxSceneAgents) + " agents");
            scene.starts.push_back({v[0], v[1]});
            scene.goals.push_back({v[2], v[3]});
            agent_lines.push_back(line_no);
        }
    }
    if (!header) fail(line_no, "empty scene: expected the header 'madbp-scene 1'");
    if (scene.starts.empty()) fail(line_no, "no 'agent' line");
    // Validation needs the whole map, so it runs after parsing; errors name the agent's line.
    double lim = scene.map.half_size - radius;
    WorldMap obstacles_only = scene.map;
    obstacles_only.half_size = 1e9;  // walls are checked separately below
    for (size_t i = 0; i < scene.starts.size(); ++i) {
        for (int which = 0; which < 2; ++which) {
            Vec2 p = which == 0 ? scene.starts[i] : scene.goals[i];
            const char* name = which == 0 ? "start" : "goal";
            if (std::fabs(p.x) > lim || std::fabs(p.y) > lim)
                fail(agent_lines[i], std::string(name) + " is outside the world (|x|, |y| must be <= " + std::to_string(lim) + ")");
            if (static_clearance(obstacles_only, p) < radius) fail(agent_lines[i], std::string(name) + " overlaps an obstacle");
            const std::vector<Vec2>& same = which == 0 ? scene.starts : scene.goals;
            for (size_t j = 0; j < i; ++j)
                if (norm(same[j] - p) < 2 * radius)
                    fail(agent_lines[i], std::string(name) + " overlaps the " + name + " of the agent on line " + std::to_string(agent_lines[j]));
        }
    }
    return scene;
}
namespace detail {
// Reads the whole of `path` (a regular file or a pipe) into `out` (std::string or
// std::vector<uint8_t>). Refuses a directory or a device, and a file of more than `max_bytes`
// (`limit` names the limit), before reading it; a file that does not start with `magic`
// (when given) after its first bytes, not after max_bytes of a pipe; std::runtime_error
// naming the path otherwise.
template <class Bytes>
inline void read_bounded(const std::string& path, uint64_t max_bytes, const std::string& limit, Bytes& out,
                         const std::string& magic = "", const std::string& kind = "") {
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) throw std::runtime_error(path + ": cannot open: " + std::strerror(errno));
    struct FdCloser { int fd; ~FdCloser() { ::close(fd); } } closer{fd};
    struct stat sb;
    if (::fstat(fd, &sb) != 0) throw std::runtime_error(path + ": cannot stat: " + std::strerror(errno));
    if (S_ISDIR(sb.st_mode)) throw std::runtime_error(path + ": is a directory, not a file");
    if (!S_ISREG(sb.st_mode) && !S_ISFIFO(sb.st_mode)) throw std::runtime_error(path + ": is a device, not a regular file");
    const auto too_big = [&](uint64_t n) {
        return std::runtime_error(path + ": " + (S_ISREG(sb.st_mode) ? std::to_string(n) : "more than " + std::to_string(max_bytes)) +
                                  " bytes exceed the limit " + limit + " = " + std::to_string(max_bytes));
    };
    if (S_ISREG(sb.st_mode) && (uint64_t)sb.st_size > max_bytes) throw too_big((uint64_t)sb.st_size);
    out.clear();
    if (S_ISREG(sb.st_mode)) out.reserve((size_t)sb.st_size);
    char buf[1 << 16];
    for (;;) {
        const ssize_t got = ::read(fd, buf, sizeof buf);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0) throw std::runtime_error(path + ": read failed: " + std::strerror(errno));
        if (got == 0) break;
        if (out.size() + (uint64_t)got > max_bytes) throw too_big(out.size() + (uint64_t)got);
        const bool was_short = out.size() < magic.size();
        out.insert(out.end(), buf, buf + got);
        if (was_short && out.size() >= magic.size() && !std::equal(magic.begin(), magic.end(), out.begin()))
            throw std::runtime_error(path + ": not a " + kind + " (magic '" + magic + "' missing)");
    }
}
}  // namespace detail

// ---------------------------------------------------------------------------------------------
// Writing files: every output of madbp (models, training states, datasets, CSV, SVG, results)
// goes through write_file_atomic (docs/limits.md, "Writing files").

// A failure of the environment, not of the input: a write the system refused (disk full, I/O
// error), lost standard output. The madbp tool exits 1 on it and 2 on bad input.
struct EnvironmentError : std::runtime_error {
    using std::runtime_error::runtime_error;
};

namespace detail {
// Throws "<path>: <what>: <strerror(errno)>": an EnvironmentError when `environment` or errno
// says the system failed (ENOSPC, EDQUOT, EIO), else std::runtime_error (a bad path).
[[noreturn]] inline void io_fail(const std::string& path, const std::string& what, bool environment = false) {
    const int err = errno;
    const std::string msg = printable(path, 256) + ": " + what + ": " + std::strerror(err);
    if (environment || err == ENOSPC || err == EDQUOT || err == EIO) throw EnvironmentError(msg);
    throw std::runtime_error(msg);
}

// The locks this process holds, by the lock file's device and inode, so that locks on one
// output nest (flock conflicts between two open()s of one file even within a process).
struct HeldLock {
    int fd, count;
    std::string lock_path;
};
inline std::map<std::pair<dev_t, ino_t>, HeldLock>& held_locks() {
    static std::map<std::pair<dev_t, ino_t>, HeldLock> locks;
    return locks;
}
inline std::mutex& held_locks_mutex() {
    static std::mutex m;
    return m;
}
}  // namespace detail

// Refuses an output madbp must not replace, before any work: a symbolic link (refused, never
// followed: name the link's target to write there), a directory, a device, FIFO or socket, a
// read-only file (no write permission bit, or not writable by this user). Returns the existing
// file's permission bits, which the new file keeps, or -1 when there is no file yet.
// std::runtime_error naming the path.
inline int check_output(const std::string& path) {
    if (path.empty()) throw std::invalid_argument("output path is empty");
    struct stat sb;
    if (::lstat(path.c_str(), &sb) != 0) {
        if (errno == ENOENT) return -1;
        detail::io_fail(path, "cannot check the output");
    }
    const std::string p = printable(path, 256);
    if (S_ISLNK(sb.st_mode))
        throw std::runtime_error(p + ": is a symbolic link; madbp does not write through links (name the link's target instead)");
    if (S_ISDIR(sb.st_mode)) throw std::runtime_error(p + ": is a directory, not a file to write");
    if (!S_ISREG(sb.st_mode)) throw std::runtime_error(p + ": is a device, FIFO or socket, not a regular file to write");
    if ((sb.st_mode & 0222) == 0 || ::access(path.c_str(), W_OK) != 0)
        throw std::runtime_error(p + ": is read-only; madbp does not replace it (make it writable or choose another output)");
    return (int)(sb.st_mode & 07777);
}

// An advisory lock on the output `path` while it lives: flock on the sidecar file path + ".lock"
// (created without following links, removed on release). Another process that holds it makes
// the constructor throw std::runtime_error "<path>: another run is writing it". Locks on one
// output within a process nest: the madbp tool holds each --out for its whole run, and
// write_file_atomic takes it again around each write.
class OutputLock {
public:
    explicit OutputLock(const std::string& path) {
        const std::string lock_path = path + ".lock";
        std::lock_guard<std::mutex> guard(detail::held_locks_mutex());
        for (int attempt = 0;; ++attempt) {
            const int fd = ::open(lock_path.c_str(), O_RDWR | O_CREAT | O_NOFOLLOW | O_CLOEXEC, 0666);
            if (fd < 0) detail::io_fail(path, "cannot create its lock file " + printable(lock_path, 256));
            struct stat sb;
            if (::fstat(fd, &sb) != 0) {
                ::close(fd);
                detail::io_fail(lock_path, "cannot stat the lock file");
            }
            key_ = {sb.st_dev, sb.st_ino};
            auto it = detail::held_locks().find(key_);
            if (it != detail::held_locks().end()) {
                ::close(fd);
                ++it->second.count;
                return;
            }
            if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
                const int err = errno;
                ::close(fd);
                if (err == EWOULDBLOCK)
                    throw std::runtime_error(printable(path, 256) + ": another run is writing it (" + printable(lock_path, 256) +
                                             " is locked); wait for it or choose another output");
                errno = err;
                detail::io_fail(lock_path, "cannot lock");
            }
            // The holder before us may have removed the file between our open and flock: then
            // we hold a lock on a file nobody else will open; start again on the new one.
            struct stat now;
            if (::stat(lock_path.c_str(), &now) == 0 && now.st_dev == sb.st_dev && now.st_ino == sb.st_ino) {
                detail::held_locks()[key_] = {fd, 1, lock_path};
                return;
            }
            ::close(fd);
            if (attempt >= 100) throw std::runtime_error(printable(lock_path, 256) + ": the lock file keeps changing");
        }
    }
    ~OutputLock() {
        std::lock_guard<std::mutex> guard(detail::held_locks_mutex());
        auto it = detail::held_locks().find(key_);
        if (it == detail::held_locks().end() || --it->second.count > 0) return;
        ::unlink(it->second.lock_path.c_str());  // before the unlock: a waiter then sees a new file (above)
        ::close(it->second.fd);
        detail::held_locks().erase(it);
    }
    OutputLock(const OutputLock&) = delete;
    OutputLock& operator=(const OutputLock&) = delete;

private:
    std::pair<dev_t, ino_t> key_;
};

// Writes `size` bytes to `path` so that a crash, a full disk or a second run leaves either the
// old file or the new one, never a mix: under the output's OutputLock, check_output refuses a
// link, a non-regular or a read-only target; the bytes go to a temporary file of a unique name
// in the target's directory, created exclusively (never an existing file or a planted link),
// given the old file's mode, fsynced, then renamed over `path` (and the directory fsynced).
// A bad path throws std::runtime_error; a failed write, fsync or rename EnvironmentError.
inline void write_file_atomic(const std::string& path, const void* data, size_t size) {
    check_output(path);  // first, so that a refused target (/dev/null) gets no lock file beside it
    OutputLock lock(path);
    const int mode = check_output(path);
    static std::atomic<unsigned> serial{0};
    std::string tmp;
    int fd = -1;
    for (int attempt = 0; fd < 0; ++attempt) {
        tmp = path + ".tmp." + std::to_string(::getpid()) + "." + std::to_string(serial++);
        fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0666);  // 0666 & ~umask
        if (fd < 0 && (errno != EEXIST || attempt >= 100)) detail::io_fail(tmp, "cannot create the temporary file");
    }
    auto fail = [&](const std::string& what, const std::string& where) {
        const int err = errno;
        if (fd >= 0) ::close(fd);
        ::unlink(tmp.c_str());
        errno = err;
        detail::io_fail(where, what, true);
    };
    if (mode >= 0 && ::fchmod(fd, (mode_t)mode) != 0) fail("cannot keep the mode of the file it replaces", tmp);
    const uint8_t* bytes = (const uint8_t*)data;
    for (size_t done = 0; done < size;) {
        const ssize_t w = ::write(fd, bytes + done, size - done);
        if (w < 0 && errno == EINTR) continue;
        if (w <= 0) fail("write failed", tmp);
        done += (size_t)w;
    }
    if (::fsync(fd) != 0) fail("fsync failed", tmp);
    const int closed = ::close(fd);
    fd = -1;
    if (closed != 0) fail("close failed", tmp);
    if (::rename(tmp.c_str(), path.c_str()) != 0) fail("rename from " + printable(tmp, 256) + " failed", path);
    const size_t slash = path.find_last_of('/');
    const std::string dir = slash == std::string::npos ? "." : slash == 0 ? "/" : path.substr(0, slash);
    const int dfd = ::open(dir.c_str(), O_RDONLY | O_CLOEXEC);
    if (dfd >= 0) {  // best effort: some file systems refuse fsync on directories
        ::fsync(dfd);
        ::close(dfd);
    }
}
inline void write_file_atomic(const std::string& path, const std::vector<uint8_t>& bytes) {
    write_file_atomic(path, bytes.data(), bytes.size());
}
inline void write_file_atomic(const std::string& path, const std::string& text) { write_file_atomic(path, text.data(), text.size()); }

// Reads and parses a scene file (at most kMaxSceneBytes; a directory or device is refused).
inline Scene load_scene(const std::string& path) {
    std::string text;
    detail::read_bounded(path, kMaxSceneBytes, "kMaxSceneBytes", text);
    return parse_scene(text, path);
}
// The scene format of `scene`: numbers with 17 digits (parse_scene reads back the same
// doubles), comments after the header (a line break inside one becomes a space).
inline std::string scene_text(const Scene& scene) {
    std::ostringstream o;
    o.precision(17);
    o << "madbp-scene 1\n";
    for (std::string c : scene.comments) {
        std::replace(c.begin(), c.end(), '\n', ' ');
        std::replace(c.begin(), c.end(), '\r', ' ');
        o << "# " << c << "\n";
    }
    o << "world " << scene.map.half_size << "\n";
    for (const Disc& d : scene.map.discs) o << "disc " << d.c.x << " " << d.c.y << " " << d.r << "\n";
    for (const Box& b : scene.map.boxes) o << "box " << b.lo.x << " " << b.lo.y << " " << b.hi.x << " " << b.hi.y << "\n";
    for (size_t i = 0; i < scene.starts.size(); ++i)
        o << "agent " << scene.starts[i].x << " " << scene.starts[i].y << " " << scene.goals[i].x << " " << scene.goals[i].y << "\n";
    return o.str();
}
// The scene format of a world's current problem (agents at their current positions).
inline std::string scene_text(const World& world) {
    Scene scene;
    scene.map = world.map();
    for (const Agent& a : world.agents()) scene.starts.push_back(a.pos), scene.goals.push_back(a.goal);
    return scene_text(scene);
}
inline World make_world(const Scene& scene, WorldConfig cfg = WorldConfig{}) {
    World world(scene.map, cfg);
    for (size_t i = 0; i < scene.starts.size(); ++i) world.add_agent(scene.starts[i], scene.goals[i]);
    return world;
}

// ---------------------------------------------------------------------------------------------
// MovingAI MAPF benchmark import (Sturtevant, "Benchmarks for grid-based pathfinding", 2012;
// Stern et al., SoCS 2019). A .map file is the header "type octile", "height H", "width W",
// "map", then H rows of W characters; a .scen file is "version 1", then rows of 9 tab-separated
// fields: bucket, map name, map width, map height, start x, start y, goal x, goal y, optimal
// length; x is the column, y the row, row 0 at the top. docs/formats.md has the placement.
constexpr size_t kMaxMovingAiBytes = 1 << 24;  // a .map or .scen file, bytes
constexpr int kMaxMovingAiSide = 4096;         // width or height of a .map, cells

namespace detail {
// The terrain of a .map character: 0 passable ('.', 'G' ground, 'S' swamp: slow for a walker,
// not a wall), 1 blocked ('@', 'O' out of bounds, 'T' trees, 'W' water: a robot cannot cross
// it), -1 not a terrain character.
inline int movingai_blocked(char c) {
    if (c == '.' || c == 'G' || c == 'S') return 0;
    if (c == '@' || c == 'O' || c == 'T' || c == 'W') return 1;
    return -1;
}
// `text` split at '\n', each line without a trailing '\r' (files written on Windows).
inline std::vector<std::string> text_lines(const std::string& text) {
    std::vector<std::string> lines;
    std::istringstream in(text);
    for (std::string line; std::getline(in, line);) {
        if (!line.empty() && line.back() == '\r') line.pop_back();
        lines.push_back(line);
    }
    return lines;
}
inline std::vector<std::string> split_fields(const std::string& line, char sep) {
    std::vector<std::string> out;
    size_t start = 0;
    for (size_t at; (at = line.find(sep, start)) != std::string::npos; start = at + 1) out.push_back(line.substr(start, at - start));
    out.push_back(line.substr(start));
    return out;
}
inline std::vector<std::string> words(const std::string& line) {
    std::istringstream ls(line);
    std::vector<std::string> out;
    for (std::string w; ls >> w;) out.push_back(w);
    return out;
}
// `s` is wholly an integer (long) or a finite number; false when not.
inline bool parse_whole(const std::string& s, long& v) {
    size_t pos = 0;
    try { v = std::stol(s, &pos); } catch (...) { return false; }
    return !s.empty() && pos == s.size();
}
inline bool parse_whole(const std::string& s, double& v) {
    size_t pos = 0;
    try { v = std::stod(s, &pos); } catch (...) { return false; }
    return !s.empty() && pos == s.size() && std::isfinite(v);
}
[[noreturn]] inline void fail_at(const std::string& source, size_t line, const std::string& why) {
    throw std::invalid_argument(printable(source, 256) + ":" + std::to_string(line) + ": " + why);
}
inline std::string base_name(const std::string& path) {
    const size_t slash = path.find_last_of("/\\");
    return slash == std::string::npos ? path : path.substr(slash + 1);
}
// The blocked cells of a W x H map (blocked[row * W + col], row 0 at the top) as boxes: the
// runs of each row, and a run repeated on the rows below it merged into one taller box. The
// map's left edge is x0 and its top edge y_top, cells `cell` wide.
inline std::vector<Box> merge_blocked(const std::vector<uint8_t>& blocked, long W, long H, double cell, double x0, double y_top) {
    std::vector<Box> boxes;
    std::map<std::pair<long, long>, long> open, still;  // run [c0, c1) -> its top row
    auto close = [&](std::pair<long, long> run, long top, long bottom) {  // rows [top, bottom)
        boxes.push_back({{x0 + run.first * cell, y_top - bottom * cell}, {x0 + run.second * cell, y_top - top * cell}});
    };
    for (long row = 0; row <= H; ++row) {
        still.clear();
        for (long col = 0; row < H && col < W;) {
            if (!blocked[row * W + col]) { ++col; continue; }
            const long c0 = col;
            while (col < W && blocked[row * W + col]) ++col;
            auto it = open.find({c0, col});
            still[{c0, col}] = it == open.end() ? row : it->second;
            if (it != open.end()) open.erase(it);
        }
        for (const auto& run : open) close(run.first, run.second, row);
        open.swap(still);
    }
    return boxes;
}
}  // namespace detail

// A parsed .map: width x height cells, blocked[row * width + col] = 1 for a blocked cell, row 0
// at the top. `rows` keeps the text rows (messages quote a cell's character); `source` names
// the file; `first_row_line` is the 1-based line of row 0 (messages give file:line).
struct MovingAiMap {
    std::string source;
    long width = 0, height = 0;
    std::vector<uint8_t> blocked;
    std::vector<std::string> rows;
    size_t first_row_line = 0;
    bool passable(long col, long row) const { return col >= 0 && col < width && row >= 0 && row < height && !blocked[row * width + col]; }
};
// One row of a .scen file, its 9 fields; `line` is its 1-based line in the file (0 when drawn,
// not read).
struct MovingAiScenarioRow {
    long bucket = 0;
    std::string map_name;
    long map_width = 0, map_height = 0, start_x = 0, start_y = 0, goal_x = 0, goal_y = 0;
    double optimal_length = 0;
    size_t line = 0;
};

// A .map text (`source` names it in messages). Throws std::invalid_argument "<source>:<line>:
// <why>" on a bad header, row length or character, too few or too many rows.
inline MovingAiMap parse_movingai_map(const std::string& text, const std::string& source) {
    if (text.size() > kMaxMovingAiBytes)
        throw std::invalid_argument(printable(source, 256) + ": " + std::to_string(text.size()) + " bytes exceed the limit kMaxMovingAiBytes = " +
                                    std::to_string(kMaxMovingAiBytes));
    MovingAiMap map;
    map.source = source;
    const std::vector<std::string> mlines = detail::text_lines(text);
    long W = -1, H = -1;
    bool typed = false;
    size_t ln = 0;  // index of the line after 'map'
    for (bool at_map = false; !at_map; ++ln) {
        if (ln == mlines.size()) detail::fail_at(source, ln, "no 'map' line (expected the header 'type octile', 'height H', 'width W', 'map')");
        const std::vector<std::string> w = detail::words(mlines[ln]);
        if (w.empty()) continue;
        if (w.size() == 1 && w[0] == "map") {
            if (!typed || W < 0 || H < 0) detail::fail_at(source, ln + 1, "'map' before the header's 'type', 'height' and 'width' lines");
            at_map = true;
        } else if (w.size() == 2 && w[0] == "type") {
            if (w[1] != "octile") detail::fail_at(source, ln + 1, "map type '" + printable(w[1]) + "' (this reader knows octile)");
            typed = true;
        } else if (w.size() == 2 && (w[0] == "height" || w[0] == "width")) {
            long& v = w[0] == "height" ? H : W;
            if (v >= 0) detail::fail_at(source, ln + 1, "'" + w[0] + "' given twice");
            if (!detail::parse_whole(w[1], v) || v < 1 || v > kMaxMovingAiSide)
                detail::fail_at(source, ln + 1, w[0] + ": '" + printable(w[1]) + "' is not an integer in [1, kMaxMovingAiSide = " +
                                                    std::to_string(kMaxMovingAiSide) + "]");
        } else {
            detail::fail_at(source, ln + 1, "unexpected header line '" + printable(mlines[ln]) + "' (expected 'type octile', 'height H', 'width W' or 'map')");
        }
    }
    map.width = W, map.height = H, map.first_row_line = ln + 1;
    map.blocked.assign((size_t)(W * H), 0);
    for (long row = 0; row < H; ++row) {
        const size_t at = ln + (size_t)row;
        if (at >= mlines.size())
            detail::fail_at(source, mlines.size(), "the map has " + std::to_string(row) + " rows, its header says height " + std::to_string(H));
        const std::string& s = mlines[at];
        if ((long)s.size() != W)
            detail::fail_at(source, at + 1, "row " + std::to_string(row) + " has " + std::to_string(s.size()) + " characters, the header says width " + std::to_string(W));
        for (long col = 0; col < W; ++col) {
            const int b = detail::movingai_blocked(s[col]);
            if (b < 0) detail::fail_at(source, at + 1, "unknown terrain '" + printable(s.substr(col, 1)) + "' in column " + std::to_string(col) + " (expected . G S passable, @ O T W blocked)");
            map.blocked[row * W + col] = (uint8_t)b;
        }
        map.rows.push_back(s);
    }
    for (size_t at = ln + H; at < mlines.size(); ++at)
        if (!detail::words(mlines[at]).empty()) detail::fail_at(source, at + 1, "more rows than the header's height " + std::to_string(H));
    return map;
}

namespace detail {
// The rows of a .scen text for `map`, each field checked (not yet the cells: movingai_scene
// checks the rows it uses); `line_count` gets the text's line count for messages at its end.
inline std::vector<MovingAiScenarioRow> parse_movingai_rows(const std::string& text, const std::string& source, const MovingAiMap& map,
                                                            size_t& line_count) {
    if (text.size() > kMaxMovingAiBytes)
        throw std::invalid_argument(printable(source, 256) + ": " + std::to_string(text.size()) + " bytes exceed the limit kMaxMovingAiBytes = " +
                                    std::to_string(kMaxMovingAiBytes));
    static const char* const names[] = {"bucket", "map name", "map width", "map height", "start x", "start y", "goal x", "goal y", "optimal length"};
    const std::vector<std::string> slines = text_lines(text);
    line_count = slines.size();
    std::vector<MovingAiScenarioRow> rows;
    bool versioned = false;
    const std::string map_base = base_name(map.source);
    const bool named = map_base.size() > 4 && map_base.compare(map_base.size() - 4, 4, ".map") == 0;
    for (size_t at = 0; at < slines.size(); ++at) {
        const std::vector<std::string> w = words(slines[at]);
        if (w.empty()) continue;
        if (!versioned) {
            if (w.size() != 2 || w[0] != "version" || (w[1] != "1" && w[1] != "1.0")) fail_at(source, at + 1, "expected the header 'version 1'");
            versioned = true;
            continue;
        }
        const std::vector<std::string> f = split_fields(slines[at], '\t');
        if (f.size() != 9)
            fail_at(source, at + 1, "expected 9 tab-separated fields (bucket, map, width, height, start x, start y, goal x, goal y, optimal length), got " + std::to_string(f.size()));
        MovingAiScenarioRow r;
        r.line = at + 1;
        r.map_name = f[1];
        long* const integers[] = {&r.bucket, nullptr, &r.map_width, &r.map_height, &r.start_x, &r.start_y, &r.goal_x, &r.goal_y};
        for (int k = 0; k < 9; ++k) {
            if (k == 1) continue;
            if (k == 8 ? !parse_whole(f[k], r.optimal_length) : !parse_whole(f[k], *integers[k]))
                fail_at(source, at + 1, std::string(names[k]) + ": '" + printable(f[k]) + "' is not " + (k == 8 ? "a number" : "an integer"));
        }
        if (named && base_name(r.map_name) != map_base)
            fail_at(source, at + 1, "the row is for map '" + printable(r.map_name) + "', not " + printable(map_base));
        if (r.map_width != map.width || r.map_height != map.height)
            fail_at(source, at + 1, "map size " + std::to_string(r.map_width) + " x " + std::to_string(r.map_height) + " differs from the map's " +
                                        std::to_string(map.width) + " x " + std::to_string(map.height));
        rows.push_back(r);
    }
    if (!versioned) fail_at(source, slines.size(), "empty scenario: expected the header 'version 1'");
    return rows;
}
}  // namespace detail

// The rows of a .scen text (`source` names it) for `map`: the header 'version 1', then rows of
// 9 tab-separated fields, each checked, and the map name and size checked against `map` (the
// cells are checked where a scene is made: movingai_scene). Throws std::invalid_argument
// "<source>:<line>: <why>".
inline std::vector<MovingAiScenarioRow> parse_movingai_scenario(const std::string& text, const std::string& source, const MovingAiMap& map) {
    size_t line_count = 0;
    return detail::parse_movingai_rows(text, source, map, line_count);
}

namespace detail {
// Calls visit(col, row, step length) for each octile move of the benchmark from (col, row): the
// 8 neighbours that are passable, a diagonal only when both cells beside it are passable too (no
// corner cutting: a robot cannot squeeze between two blocked corners).
template <class Visit>
inline void for_each_octile_move(const MovingAiMap& map, long col, long row, Visit visit) {
    for (long dr = -1; dr <= 1; ++dr)
        for (long dc = -1; dc <= 1; ++dc) {
            if ((dr == 0 && dc == 0) || !map.passable(col + dc, row + dr)) continue;
            const bool diagonal = dr != 0 && dc != 0;
            if (diagonal && !(map.passable(col + dc, row) && map.passable(col, row + dr))) continue;
            visit(col + dc, row + dr, diagonal ? std::sqrt(2.0) : 1.0);
        }
}
// The connected component of every cell under octile moves (-1 for a blocked cell) and, in
// `sizes`, the cell count of each component.
inline std::vector<int> movingai_components(const MovingAiMap& map, std::vector<long>& sizes) {
    std::vector<int> label(map.blocked.size(), -1);
    sizes.clear();
    std::vector<long> stack;
    for (long seed = 0; seed < (long)label.size(); ++seed) {
        if (map.blocked[seed] || label[seed] >= 0) continue;
        const int id = (int)sizes.size();
        sizes.push_back(0);
        label[seed] = id;
        stack.assign(1, seed);
        while (!stack.empty()) {
            const long at = stack.back();
            stack.pop_back();
            ++sizes[id];
            for_each_octile_move(map, at % map.width, at / map.width, [&](long c, long r, double) {
                if (label[r * map.width + c] < 0) label[r * map.width + c] = id, stack.push_back(r * map.width + c);
            });
        }
    }
    return label;
}
}  // namespace detail

// The length of a shortest octile path (straight steps 1, diagonal steps sqrt 2, no corner
// cutting) on `map` from cell (start_x, start_y) to (goal_x, goal_y), x the column and y the
// row; -1 when none exists. A* with the octile distance, which never overestimates.
inline double movingai_path_length(const MovingAiMap& map, long start_x, long start_y, long goal_x, long goal_y) {
    if (!map.passable(start_x, start_y) || !map.passable(goal_x, goal_y)) return -1;
    auto estimate = [&](long c, long r) {
        const double dx = std::abs(c - goal_x), dy = std::abs(r - goal_y);
        return std::max(dx, dy) + (std::sqrt(2.0) - 1) * std::min(dx, dy);
    };
    std::vector<double> g(map.blocked.size(), std::numeric_limits<double>::infinity());
    using Entry = std::pair<double, long>;  // (g + estimate, cell)
    std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> open;
    g[start_y * map.width + start_x] = 0;
    open.push({estimate(start_x, start_y), start_y * map.width + start_x});
    const long goal = goal_y * map.width + goal_x;
    while (!open.empty()) {
        const auto [f, at] = open.top();
        open.pop();
        if (at == goal) return g[at];
        const long col = at % map.width, row = at / map.width;
        if (f > g[at] + estimate(col, row) + 1e-9) continue;  // a stale entry: `at` was reached shorter since
        detail::for_each_octile_move(map, col, row, [&](long c, long r, double step) {
            const long next = r * map.width + c;
            if (g[at] + step < g[next]) g[next] = g[at] + step, open.push({g[next] + estimate(c, r), next});
        });
    }
    return -1;
}

// `count` scenario rows drawn on `map` from `seed`, for a map that comes without .scen files
// (madbp::Rng: the same rows on every platform). A row's start and goal are two passable cells
// of one connected component under octile moves (the benchmark's: 8 directions, no corner
// cutting); no two rows share a start, no two share a goal (one robot's start may be another's
// goal, as in the benchmark's files). Each row has the benchmark's fields: bucket = floor(optimal
// length / 4), the map's file name, its size, the cells, and the optimal octile path length
// (movingai_path_length). Throws std::invalid_argument naming `count` outside [1,
// kMaxSceneAgents], and naming the map when no two passable cells are connected or fewer than
// `count` rows can be drawn.
inline std::vector<MovingAiScenarioRow> random_movingai_scenario(const MovingAiMap& map, int count, uint64_t seed) {
    if (count < 1 || count > kMaxSceneAgents)
        throw std::invalid_argument("count: " + std::to_string(count) + " is out of range [1, kMaxSceneAgents = " + std::to_string(kMaxSceneAgents) + "]");
    std::vector<long> sizes;
    const std::vector<int> label = detail::movingai_components(map, sizes);
    // Candidate starts: every cell with a neighbour to go to; the unused goals of each component,
    // with each cell's place in its list (-1 once used) so a draw removes it in O(1).
    std::vector<long> starts, goal_place(label.size(), -1);
    std::vector<std::vector<long>> goals(sizes.size());
    for (long at = 0; at < (long)label.size(); ++at)
        if (label[at] >= 0 && sizes[label[at]] >= 2) {
            starts.push_back(at);
            goal_place[at] = (long)goals[label[at]].size();
            goals[label[at]].push_back(at);
        }
    if (starts.empty())
        throw std::invalid_argument(printable(map.source, 256) + ": no two passable cells are connected (octile moves, no corner cutting); "
                                    "a random scenario needs a start and a goal in one component");
    auto swap_to_back = [&](std::vector<long>& list, long cell) {
        const long last = list.back();
        std::swap(list[goal_place[cell]], list.back());
        std::swap(goal_place[cell], goal_place[last]);
    };
    Rng rng(seed);
    std::vector<MovingAiScenarioRow> rows;
    const size_t usable = starts.size();
    while ((int)rows.size() < count && !starts.empty()) {
        const size_t k = (size_t)rng.uniform_int((int)starts.size());
        const long start = starts[k];
        starts[k] = starts.back();
        starts.pop_back();
        std::vector<long>& unused = goals[label[start]];
        // The goal: any unused goal of the component but the start itself (moved out of reach).
        const bool start_unused = goal_place[start] >= 0;
        if (start_unused) swap_to_back(unused, start);
        const long choices = (long)unused.size() - (start_unused ? 1 : 0);
        if (choices == 0) continue;  // every other cell of the component is some row's goal
        const long goal = unused[(size_t)rng.uniform_int((int)choices)];
        swap_to_back(unused, goal);
        unused.pop_back();
        goal_place[goal] = -1;
        MovingAiScenarioRow r;
        r.map_name = detail::base_name(map.source);
        r.map_width = map.width, r.map_height = map.height;
        r.start_x = start % map.width, r.start_y = start / map.width, r.goal_x = goal % map.width, r.goal_y = goal / map.width;
        r.optimal_length = movingai_path_length(map, r.start_x, r.start_y, r.goal_x, r.goal_y);
        r.bucket = (long)std::floor(r.optimal_length / 4);
        rows.push_back(r);
    }
    if ((int)rows.size() < count)
        throw std::invalid_argument(printable(map.source, 256) + ": drew only " + std::to_string(rows.size()) + " of count = " + std::to_string(count) +
                                    " scenario rows (distinct starts, distinct goals; " + std::to_string(usable) +
                                    " passable cells lie in components of two or more)");
    return rows;
}

// `rows` as a version-1 .scen text: 'version 1', then the 9 tab-separated fields of each row
// (the optimal length with 8 decimals, as in the benchmark's files). Throws
// std::invalid_argument naming "map name" when a row's map name holds a tab or line break.
inline std::string movingai_scenario_text(const std::vector<MovingAiScenarioRow>& rows) {
    std::string text = "version 1\n";
    char length[32];
    for (const MovingAiScenarioRow& r : rows) {
        if (r.map_name.find_first_of("\t\r\n") != std::string::npos)
            throw std::invalid_argument("map name: '" + printable(r.map_name) + "' holds a tab or line break");
        std::snprintf(length, sizeof length, "%.8f", r.optimal_length);
        text += std::to_string(r.bucket) + "\t" + r.map_name + "\t" + std::to_string(r.map_width) + "\t" + std::to_string(r.map_height) + "\t" +
                std::to_string(r.start_x) + "\t" + std::to_string(r.start_y) + "\t" + std::to_string(r.goal_x) + "\t" + std::to_string(r.goal_y) + "\t" +
                length + "\n";
    }
    return text;
}

// A scene from a parsed MovingAI map and scenario rows (`scen_source` names the rows in
// messages and comments): robots i = 0..agents-1 take rows offset + i. Placement, tight fit: the
// W x H cells, each `cell` wide, centred in a square world of half-size max(W, H) * cell / 2;
// the margin beside a map that is not square is blocked by boxes (robots stay on the map); map
// row r, column c has its centre at (-W cell / 2 + (c + 0.5) cell, H cell / 2 - (r + 0.5) cell).
// Blocked cells become boxes (detail::merge_blocked); starts and goals sit at cell centres. The
// scene's comments name the map, the rows and their lines. Throws std::invalid_argument
// "<scen_source>:<line>: <why>" ("<scen_source> row K: <why>" for a drawn row) on a start or goal
// outside the map, on a blocked cell, closer than `radius` to an obstacle (cell < 2 radius) or
// closer than 2 radius to another's; "<source>: <why>" on too few rows, a world over
// kMaxHalfSize or more boxes than kMaxObstacles.
inline Scene movingai_scene(const MovingAiMap& map, const std::vector<MovingAiScenarioRow>& rows, const std::string& scen_source, int agents,
                            double cell = 0.3, int offset = 0, double radius = 0.1) {
    if (agents < 1 || agents > kMaxSceneAgents)
        throw std::invalid_argument("agents: " + std::to_string(agents) + " is out of range [1, kMaxSceneAgents = " + std::to_string(kMaxSceneAgents) + "]");
    if (offset < 0) throw std::invalid_argument("offset: must be >= 0 (got " + std::to_string(offset) + ")");
    if (!(cell > 0) || !std::isfinite(cell)) throw std::invalid_argument("cell: must be a finite number > 0 (got " + number_text(cell) + ")");
    if (rows.size() < (size_t)offset + (size_t)agents)
        throw std::invalid_argument(printable(scen_source, 256) + ": has " + std::to_string(rows.size()) + " scenario rows; offset " +
                                    std::to_string(offset) + " + " + std::to_string(agents) + " agents needs " + std::to_string((size_t)offset + agents));
    const long W = map.width, H = map.height;
    // Placement: the map's square, centred; blocked cells and the margin become boxes.
    const double half = std::max(W, H) * cell / 2, x0 = -W * cell / 2, y_top = H * cell / 2;
    if (half > kMaxHalfSize)
        throw std::invalid_argument(printable(map.source, 256) + ": " + std::to_string(std::max(W, H)) + " cells of " + number_text(cell) +
                                    " make a world of half-size " + number_text(half) + ", over the limit kMaxHalfSize = " + number_text(kMaxHalfSize) + " (use a smaller cell)");
    if (!(half > 2 * radius))
        throw std::invalid_argument(printable(map.source, 256) + ": the world's half-size " + number_text(half) + " must be > " + number_text(2 * radius) + " (use a larger cell)");
    Scene scene;
    scene.map.half_size = half;
    scene.map.boxes = detail::merge_blocked(map.blocked, W, H, cell, x0, y_top);
    if (W < H) scene.map.boxes.insert(scene.map.boxes.end(), {Box{{-half, -half}, {x0, half}}, Box{{-x0, -half}, {half, half}}});
    if (H < W) scene.map.boxes.insert(scene.map.boxes.end(), {Box{{-half, -half}, {half, -y_top}}, Box{{-half, y_top}, {half, half}}});
    if (scene.map.boxes.size() > (size_t)kMaxObstacles)
        throw std::invalid_argument(printable(map.source, 256) + ": its blocked cells need " + std::to_string(scene.map.boxes.size()) +
                                    " boxes (row runs merged), over the limit kMaxObstacles = " + std::to_string(kMaxObstacles));
    scene.comments.push_back("MovingAI map " + printable(map.source, 256) + " (" + std::to_string(W) + " x " + std::to_string(H) + " cells of " +
                             number_text(cell) + "), scenario " + printable(scen_source, 256) + " rows " + std::to_string(offset) + ".." +
                             std::to_string(offset + agents - 1) + " (row 0 follows 'version 1'); cell (c, r) at (" + number_text(x0) +
                             " + (c + 0.5) " + number_text(cell) + ", " + number_text(y_top) + " - (r + 0.5) " + number_text(cell) + ")");
    // A row's place in messages: its file line, or its index for drawn rows (line 0).
    auto fail_row = [&](const MovingAiScenarioRow& r, int index, const std::string& why) {
        if (r.line > 0) detail::fail_at(scen_source, r.line, why);
        throw std::invalid_argument(printable(scen_source, 256) + " row " + std::to_string(index) + ": " + why);
    };
    for (int i = 0; i < agents; ++i) {
        const MovingAiScenarioRow& r = rows[(size_t)offset + i];
        for (int which = 0; which < 2; ++which) {
            const long col = which == 0 ? r.start_x : r.goal_x, row = which == 0 ? r.start_y : r.goal_y;
            const char* name = which == 0 ? "start" : "goal";
            const std::string at = " (" + std::to_string(col) + ", " + std::to_string(row) + ")";
            if (col < 0 || col >= W || row < 0 || row >= H)
                fail_row(r, offset + i, std::string(name) + at + " is outside the " + std::to_string(W) + " x " + std::to_string(H) + " map");
            if (map.blocked[row * W + col]) fail_row(r, offset + i, std::string(name) + at + " is on a blocked cell '" + map.rows[row][col] + "'");
            const Vec2 p{x0 + (col + 0.5) * cell, y_top - (row + 0.5) * cell};
            if (static_clearance(scene.map, p) < radius)
                fail_row(r, offset + i, std::string(name) + at + " is closer than a robot's radius " + number_text(radius) +
                                            " to a blocked cell or wall (cell " + number_text(cell) + " < " + number_text(2 * radius) + ")");
            std::vector<Vec2>& same = which == 0 ? scene.starts : scene.goals;
            for (int j = 0; j < i; ++j)
                if (norm(same[j] - p) < 2 * radius) {
                    const size_t other = rows[(size_t)offset + j].line;
                    fail_row(r, offset + i, std::string(name) + at + " overlaps the " + name + " of scenario row " + std::to_string(offset + j) +
                                                (other > 0 ? " (line " + std::to_string(other) + ")" : ""));
                }
            same.push_back(p);
        }
        scene.comments.push_back("agent " + std::to_string(i) + ": scenario row " + std::to_string(offset + i) +
                                 (r.line > 0 ? " (line " + std::to_string(r.line) + ")" : "") + ": start (" + std::to_string(r.start_x) + ", " +
                                 std::to_string(r.start_y) + ") goal (" + std::to_string(r.goal_x) + ", " + std::to_string(r.goal_y) +
                                 ") optimal length " + number_text(r.optimal_length));
    }
    return scene;
}

// A scene from a MovingAI map and scenario (texts; the sources name them in messages): the
// map (parse_movingai_map) and rows (parse_movingai_scenario) as above. Errors read
// "<file>:<line>: <why>", too few rows included; "<file>: <why>" for the world's size limits.
inline Scene movingai_scene(const std::string& map_text, const std::string& map_source, const std::string& scen_text,
                            const std::string& scen_source, int agents, double cell = 0.3, int offset = 0, double radius = 0.1) {
    if (agents < 1 || agents > kMaxSceneAgents)
        throw std::invalid_argument("agents: " + std::to_string(agents) + " is out of range [1, kMaxSceneAgents = " + std::to_string(kMaxSceneAgents) + "]");
    if (offset < 0) throw std::invalid_argument("offset: must be >= 0 (got " + std::to_string(offset) + ")");
    if (!(cell > 0) || !std::isfinite(cell)) throw std::invalid_argument("cell: must be a finite number > 0 (got " + number_text(cell) + ")");
    if (scen_text.size() > kMaxMovingAiBytes)  // before the map is parsed, as each text's own limit
        throw std::invalid_argument(printable(scen_source, 256) + ": " + std::to_string(scen_text.size()) +
                                    " bytes exceed the limit kMaxMovingAiBytes = " + std::to_string(kMaxMovingAiBytes));
    const MovingAiMap map = parse_movingai_map(map_text, map_source);
    size_t line_count = 0;
    const std::vector<MovingAiScenarioRow> rows = detail::parse_movingai_rows(scen_text, scen_source, map, line_count);
    if (rows.size() < (size_t)offset + (size_t)agents)
        detail::fail_at(scen_source, line_count, "has " + std::to_string(rows.size()) + " scenario rows; offset " + std::to_string(offset) +
                                                     " + " + std::to_string(agents) + " agents needs " + std::to_string((size_t)offset + agents));
    return movingai_scene(map, rows, scen_source, agents, cell, offset, radius);
}
// A .map file parsed (at most kMaxMovingAiBytes; a directory or device is refused).
inline MovingAiMap load_movingai_map(const std::string& path) {
    std::string text;
    detail::read_bounded(path, kMaxMovingAiBytes, "kMaxMovingAiBytes", text);
    return parse_movingai_map(text, path);
}
// movingai_scene of two files (each at most kMaxMovingAiBytes; a directory or device is refused).
inline Scene load_movingai_scene(const std::string& map_path, const std::string& scen_path, int agents, double cell = 0.3, int offset = 0) {
    std::string map_text, scen_text;
    detail::read_bounded(map_path, kMaxMovingAiBytes, "kMaxMovingAiBytes", map_text);
    detail::read_bounded(scen_path, kMaxMovingAiBytes, "kMaxMovingAiBytes", scen_text);
    return movingai_scene(map_text, map_path, scen_text, scen_path, agents, cell, offset);
}


// =============================================================================================
// Section 7. Controllers: the common interface and the world's one-step model
// =============================================================================================

// Anything that drives a whole team: one action (force, components in [-1, 1]) per present
// agent, in world.agents() order. Policies may keep state across the steps of one episode;
// make a new one per episode.
struct Policy {
    virtual ~Policy() = default;
    virtual std::vector<Vec2> act(const World& world) = 0;
    // Mean wall time of one decision in milliseconds so far: one plan for a planner (a
    // PlanFollower replans every m steps), one act() for a timed reactive policy (MAPPO,
    // MADiff); 0 when not measured.
    virtual double decision_ms() const { return 0; }
};

// The world's motion without contacts over one step with a constant force u, exactly:
// p' = p + pv*v + pu*u, v' = vv*v + vu*u. With the defaults pv = 0.075, pu = 0.0075,
// vv = 0.75, vu = 0.1 (two substeps of 0.05 s, drag 0.25 on the first).
struct StepModel {
    double pv, pu, vv, vu;
    explicit StepModel(const WorldConfig& c) {
        double h = c.dt / c.substeps, keep = 1 - c.drag;
        vv = keep;
        vu = c.dt / c.mass;
        pv = c.dt * keep;
        pu = h * h * c.substeps * (c.substeps + 1) / 2 / c.mass;
    }
    // Force that makes the velocity after one step `v_target` (deadbeat), before clamping.
    Vec2 force_for_velocity(Vec2 v, Vec2 v_target) const { return (v_target - v * vv) / vu; }
    // End-of-step velocity of steady motion covering `displacement` every step. It is not
    // displacement/dt: within a step the velocity dips by drag and recovers under the force
    // (0.32 units/s end-of-step for 0.03 per step with the defaults).
    Vec2 steady_velocity(Vec2 displacement) const { return displacement / (pv + pu * (1 - vv) / vu); }
};

// =============================================================================================
// Section 8. CLF-QP (SPEC 3.1)
// =============================================================================================

// Per agent, e = p - g, V = sum_axes(e^2 + c_ev e v + c_vv v^2). With drag the velocity obeys
// dv/dt = u - gamma v, gamma = -ln(1 - drag)/dt (2.877 1/s), so
//   LfV = (2e + c_ev v).v - gamma (c_ev e + 2 c_vv v).v,   LgV = c_ev e + 2 c_vv v,
// and the QP is: minimise |u|^2 + w s^2 s.t. |u_i| <= 1, LfV + LgV.u + eps V + s <= 0.
// VMAS's HeuristicPolicy is c_ev = 0.5, c_vv = 1, eps = 0.2, w = 100, no drag term; it reaches
// no goal within 100 steps (SPEC 3.1 "measured fact"). Our defaults are SPEC 3.1's
// suggestion plus drag in LfV; a 48-setting sweep found none better beyond the noise (docs/experiments.md).
// It ignores other agents and obstacles (that is the point of the baseline).
struct ClfQpParams {
    double c_ev = 1.0;           // weight of the e*v cross term in V, >= 0, 1/s
    double c_vv = 0.2;           // weight of v^2 in V, > 0, s^2
    double eps = 3.0;            // required decay rate of V, > 0, 1/s
    double slack_weight = 100;   // w, cost of relaxing the CLF constraint, > 0
    bool drag_in_lfv = true;     // account for drag in LfV
};

// Exact minimiser of f(u) = |u|^2 + w * max(0, a + b.u)^2 over the box |u_i| <= lim.
// (The free slack s of the QP is optimal at s = min(0, -(a + b.u)), which gives this f.)
// f is convex and C1: the minimiser is the unconstrained one when it lies in the box, else
// the best of the four faces, each a 1-D convex problem solved exactly and clipped.
inline Vec2 clf_qp_solve(double a, Vec2 b, double w, double lim = 1.0) {
    auto f = [&](Vec2 u) { double c = std::max(0.0, a + dot(b, u)); return dot(u, u) + w * c * c; };
    if (a <= 0) return {0, 0};  // u = 0 already satisfies the constraint at zero cost
    Vec2 inner = b * (-w * a / (1 + w * dot(b, b)));
    if (std::fabs(inner.x) <= lim && std::fabs(inner.y) <= lim) return inner;
    // Face with coordinate `k` fixed at `fixed`: minimise t^2 + w max(0, alpha + beta t)^2.
    auto face = [&](int k, double fixed) {
        double alpha = a + (k == 0 ? b.x : b.y) * fixed, beta = k == 0 ? b.y : b.x;
        double t = alpha > 0 ? -w * alpha * beta / (1 + w * beta * beta) : 0.0;
        t = std::clamp(t, -lim, lim);
        return k == 0 ? Vec2{fixed, t} : Vec2{t, fixed};
    };
    Vec2 best = face(0, lim);
    for (Vec2 c : {face(0, -lim), face(1, lim), face(1, -lim)})
        if (f(c) < f(best)) best = c;
    return best;
}

// The CLF-QP action of one agent with position error e = p - g and velocity v.
inline Vec2 clf_qp_action(Vec2 e, Vec2 v, const ClfQpParams& prm, const WorldConfig& wc = WorldConfig{}) {
    double gamma = prm.drag_in_lfv ? -std::log(1 - wc.drag) / wc.dt : 0.0;
    Vec2 dv = e * 2 + v * prm.c_ev;        // dV/de
    Vec2 lgv = e * prm.c_ev + v * (2 * prm.c_vv);  // dV/dv
    double V = dot(e, e) + prm.c_ev * dot(e, v) + prm.c_vv * dot(v, v);
    double lfv = dot(dv, v) - gamma * dot(lgv, v);
    return clf_qp_solve(lfv + prm.eps * V, lgv, prm.slack_weight, wc.max_action);
}

struct ClfQp : Policy {
    ClfQpParams params;
    explicit ClfQp(ClfQpParams p = ClfQpParams{}) : params(p) {}
    std::vector<Vec2> act(const World& world) override {
        std::vector<Vec2> u;
        for (const Agent& a : world.agents()) u.push_back(clf_qp_action(a.pos - a.goal, a.vel, params, world.config()));
        return u;
    }
};

// =============================================================================================
// Section 9. Tracker and safety filter (SPEC 3.2)
// =============================================================================================

// PD tracking of a planned waypoint with drag feed-forward, as a one-step model-predictive
// law: the force minimising |p' - w1|^2 + velocity_weight * |v' - v_ref|^2 under the exact
// one-step model, where w1 is the waypoint for the next step and v_ref the planned velocity
// there. Expanded, u = Kp (w1 - p - pv v) + Kd (v_ref - vv v): a PD law whose "- vv v" terms
// feed drag forward. Components are clamped to [-1, 1].
struct TrackerParams {
    double velocity_weight = 0.01;  // s^2; 0 = position only (deadbeat), larger = smoother
};
inline Vec2 track_waypoint(Vec2 p, Vec2 v, Vec2 w1, Vec2 v_ref, const StepModel& m, const TrackerParams& prm,
                           double lim = 1.0) {
    double lam = prm.velocity_weight, den = m.pu * m.pu + lam * m.vu * m.vu;
    Vec2 u = ((w1 - p - v * m.pv) * m.pu + (v_ref - v * m.vv) * (lam * m.vu)) / den;
    return clamp_box(u, lim);
}
// The tracker's action for robot `a` following the waypoints `w` of a plan (w[k]: where it is
// planned to be after step k + 1), `ahead` steps into the plan: the point there (on the segment
// between two waypoints for a fractional `ahead`; the last waypoint past the end), with the
// plan's velocity there (toward the next waypoint; zero once the window ends).
inline Vec2 track_plan(const Agent& a, const std::vector<Vec2>& w, double ahead, const StepModel& m, const TrackerParams& prm,
                       double lim = 1.0) {
    const int last = (int)w.size() - 1, k = (int)ahead;
    const double frac = ahead - k;
    auto at = [&](int j) { return w[std::min(j, last)]; };
    const Vec2 target = frac > 0 ? at(k) + (at(k + 1) - at(k)) * frac : at(k);
    const Vec2 v_ref = k + 1 <= last ? m.steady_velocity(w[k + 1] - w[k]) : Vec2{0, 0};
    return track_waypoint(a.pos, a.vel, target, v_ref, m, prm, lim);
}

// Where a robot's centre may go: clearance (distance to the nearest obstacle or wall) at least
// the robot radius 0.1 plus 0.002. Routes pass cells from here (RouteClearance::min) and passages
// count from here (traffic.free_clear); the plan follower's filter keeps a little more
// (follower_filter).
constexpr double kPassableClearance = 0.102;

// A control-barrier-function filter, solved for the whole team at once. For every pair of
// agents closer than `range` (and every obstacle or wall surface within `range` of an agent),
// with gap h = distance - (sum of radii + margin) and unit direction n from the neighbour to
// the agent, the velocity after the step must not close the gap faster than `rate * h`:
//   agent pair:  n.(v_i' - v_j') >= -rate * h
//   static:      n.v_i'          >= -rate * h
// With v' = vv v + vu u (StepModel) these are linear in the actions. The filter returns the
// actions closest to the nominal ones, min sum_i w_i |u_i - u_nom_i|^2, under them and the box
// |u| <= 1: a small convex QP solved by dual coordinate ascent (Hildreth's method), which
// converges to the exact optimum when the constraints can hold. Weights w_i > 0 (default 1)
// set priorities: a heavier agent deviates less and its partners make way. Because drag
// removes 25% of the closing speed every step and rate * dt = 0.25, braking keeps the
// constraints feasible unless a nominal action pushes hard into a jam; then the iteration
// stops at its budget with the constraints nearly met (reported through `violated`).
// The filter never adds a goal-directed term: with a "hold position" nominal it only ever
// pushes agents apart.
struct SafetyFilterParams {
    double margin = 0.03;         // gap kept between agents beyond touching, world units, >= 0
    double static_margin = 0.01;  // gap kept to obstacles and walls beyond touching, world units, >= 0
    double rate = 2.5;            // rate of the barrier, 1/s, in (0, 1/dt)
    double range = 0.6;           // neighbours whose centres are within this distance count, world units
    int max_sweeps = 300;         // budget of the QP iteration (sweeps over all constraints)
};

namespace detail {
// One linear constraint a.u_i - a.u_j >= b (j = -1: a.u_i >= b).
struct TeamConstraint { int i, j; Vec2 a; double b; double lambda = 0; };
// Hildreth's method for min sum_i w_i |u_i - u0_i|^2 s.t. the constraints. Returns the
// largest violation left.
inline double solve_team_qp(std::vector<Vec2>& u, std::vector<TeamConstraint>& cons, const std::vector<double>& w,
                            int max_sweeps) {
    double worst = 0;
    for (int sweep = 0; sweep < max_sweeps; ++sweep) {
        worst = 0;
        for (TeamConstraint& c : cons) {
            double lhs = dot(c.a, u[c.i]) - (c.j >= 0 ? dot(c.a, u[c.j]) : 0.0);
            double aa = dot(c.a, c.a) * (1 / w[c.i] + (c.j >= 0 ? 1 / w[c.j] : 0.0));
            worst = std::max(worst, c.b - lhs);
            double delta = std::max(-c.lambda, (c.b - lhs) / aa);
            if (delta == 0) continue;
            c.lambda += delta;
            u[c.i] += c.a * (delta / w[c.i]);
            if (c.j >= 0) u[c.j] -= c.a * (delta / w[c.j]);
        }
        if (worst < 1e-10) break;
    }
    return worst;
}
}  // namespace detail

// Filters `nominal` (one action per agent, in agents() order) and returns safe actions in
// the box. `weights`: per agent, > 0, empty = all 1. `violated`, when given, receives the
// largest constraint violation left (0 when every constraint holds).
inline std::vector<Vec2> safety_filter(const World& world, const std::vector<Vec2>& nominal, const SafetyFilterParams& prm,
                                       const std::vector<double>& weights = {}, double* violated = nullptr) {
    const auto& ag = world.agents();
    const int n = (int)ag.size();
    MADBP_ASSERT((int)nominal.size() == n);
    MADBP_ASSERT(weights.empty() || (int)weights.size() == n);
    // At rate x dt >= 1 one step could close a whole gap: the barrier no longer holds.
    if (!(prm.rate > 0) || !(prm.rate * world.config().dt < 1))
        throw std::invalid_argument("filter.rate: must be in (0, 1/dt = " + std::to_string(1 / world.config().dt) + ") per second (got " +
                                    std::to_string(prm.rate) + ")");
    StepModel m(world.config());
    const double r = world.config().radius, lim = world.config().max_action;
    std::vector<detail::TeamConstraint> cons;
    for (int i = 0; i < n; ++i) {
        const Agent& a = ag[i];
        for (int j = i + 1; j < n; ++j) {
            Vec2 d = a.pos - ag[j].pos;
            double dist = norm(d);
            if (dist > prm.range) continue;
            Vec2 nrm = dist > 1e-12 ? d / dist : Vec2{1, 0};
            double h = dist - 2 * r - prm.margin;
            // vu n.(u_i - u_j) >= -rate h - vv n.(v_i - v_j)
            cons.push_back({i, j, nrm, (-prm.rate * h - m.vv * dot(nrm, a.vel - ag[j].vel)) / m.vu});
        }
        for_each_surface(world.map(), a.pos, [&](double dist_to_surface, Vec2 away) {
            if (dist_to_surface > prm.range) return;
            double h = dist_to_surface - r - prm.static_margin;
            cons.push_back({i, -1, away, (-prm.rate * h - m.vv * dot(away, a.vel)) / m.vu});
        });
        // The box |u| <= lim.
        cons.push_back({i, -1, {1, 0}, -lim});
        cons.push_back({i, -1, {-1, 0}, -lim});
        cons.push_back({i, -1, {0, 1}, -lim});
        cons.push_back({i, -1, {0, -1}, -lim});
    }
    std::vector<Vec2> u(n);
    for (int i = 0; i < n; ++i) u[i] = clamp_box(nominal[i], lim);
    std::vector<double> w = weights.empty() ? std::vector<double>(n, 1.0) : weights;
    double left = detail::solve_team_qp(u, cons, w, prm.max_sweeps);
    if (violated) *violated = left;
    for (Vec2& x : u) x = clamp_box(x, lim);
    return u;
}

// =============================================================================================
// Section 10. Plans, the straight-line planner and the plan follower (SPEC 3.2, 3.5, 8)
// =============================================================================================

// A window of waypoints for the active agents: waypoints[i][k] is the planned position of
// agent ids[i] at step t0 + k + 1 (k = 0 .. horizon-1), where t0 is the step at which the
// plan was made. plan_ms: the planner's wall time for this plan.
struct Plan {
    std::vector<int> ids;
    std::vector<std::vector<Vec2>> waypoints;
    double plan_ms = 0;
    int replan_after = 0;  // > 0: the planner asks for the next plan after this many steps
};
// Any planner: a function from the current world to a plan for all its present agents.
using Planner = std::function<Plan(const World&)>;

// Where a plan made k >= 1 steps ago puts its agent now: waypoints[k - 1], or the last waypoint
// once the plan has run out (non-empty waypoints). Followers replan when a robot is far from it.
inline Vec2 waypoint_now(const std::vector<Vec2>& waypoints, int k) { return waypoints[std::min(k, (int)waypoints.size()) - 1]; }

// Throws std::invalid_argument unless `plan` covers exactly the present agents of `world`,
// once each, with at least one finite waypoint each.
inline void validate_plan(const Plan& plan, const World& world) {
    if (plan.waypoints.size() != plan.ids.size())
        throw std::invalid_argument("plan: " + std::to_string(plan.ids.size()) + " ids but " +
                                    std::to_string(plan.waypoints.size()) + " waypoint lists");
    std::vector<int> seen;
    for (size_t i = 0; i < plan.ids.size(); ++i) {
        int id = plan.ids[i];
        if (std::find(seen.begin(), seen.end(), id) != seen.end()) throw std::invalid_argument("plan: duplicate agent id " + std::to_string(id));
        seen.push_back(id);
        if (world.index_of(id) < 0) throw std::invalid_argument("plan: agent id " + std::to_string(id) + " is not in the world");
        if (plan.waypoints[i].empty()) throw std::invalid_argument("plan: agent " + std::to_string(id) + " has no waypoints");
        for (size_t k = 0; k < plan.waypoints[i].size(); ++k) {
            Vec2 w = plan.waypoints[i][k];
            if (!std::isfinite(w.x) || !std::isfinite(w.y))
                throw std::invalid_argument("plan: waypoint " + std::to_string(k) + " of agent " + std::to_string(id) + " is not finite");
        }
    }
    if ((int)seen.size() != world.size()) throw std::invalid_argument("plan: covers " + std::to_string(seen.size()) + " of " + std::to_string(world.size()) + " agents");
}

// The straight-line plan (SPEC 3.5): each agent moves toward its goal along a straight line
// at `speed`, stopping there.
struct LinePlanner {
    int horizon = 16;     // waypoints per plan, >= 1
    double speed = 0.35;  // world units per second, (0, 0.4]
    Plan operator()(const World& world) const {
        Plan plan;
        double step = speed * world.config().dt;
        for (const Agent& a : world.agents()) {
            Vec2 d = a.goal - a.pos;
            double dist = norm(d);
            std::vector<Vec2> w;
            for (int k = 1; k <= horizon; ++k) w.push_back(dist > 0 ? a.pos + d * (std::min(dist, step * k) / dist) : a.pos);
            plan.ids.push_back(a.id);
            plan.waypoints.push_back(w);
        }
        return plan;
    }
};

// Priorities of the guided expert and the plan follower (one rule for both; the expert puts
// robots that have stalled first, ExpertParams::stall_steps): robots still
// travelling go before robots at their goals, then the larger `key` (how far the robot had to go
// when first seen), then the lower id. `order` receives 0 .. n-1, first first.
template <class AtGoal, class Key, class Id>
void priority_order(int n, AtGoal at_goal, Key key, Id id, std::vector<int>& order) {
    order.resize(n);
    for (int i = 0; i < n; ++i) order[i] = i;
    std::sort(order.begin(), order.end(), [&](int a, int b) {
        const bool ra = at_goal(a), rb = at_goal(b);
        if (ra != rb) return rb;
        const double ka = key(a), kb = key(b);
        if (ka != kb) return ka > kb;
        return id(a) < id(b);
    });
}
// The same over a world's agents: `order` receives agents() indices.
inline void priority_order(const World& world, const std::function<double(const Agent&)>& key, std::vector<int>& order) {
    const auto& ag = world.agents();
    priority_order((int)ag.size(), [&](int i) { return world.at_goal(ag[i]); }, [&](int i) { return key(ag[i]); },
                   [&](int i) { return ag[i].id; }, order);
}
// Safety-filter weight of rank `rank` of n: `first` for rank 0, falling linearly to 1.
inline double priority_weight_of(int rank, int n, double first) { return n > 1 ? 1 + (first - 1) * (n - 1 - rank) / (n - 1) : 1.0; }

constexpr double kMaxLookahead = 1000;  // FollowerConfig::lookahead: past a window's end the tracker holds its last waypoint

// The plan follower's safety filter: SPEC 3.2's, with a barrier rate of 4/s where the expert's
// is 2.5/s. The rate bounds the closing speed to rate x gap, so at 2.5 two robots meeting
// head-on start braking ~0.3 apart and crawl past each other; MA-DBP's guided windows already
// keep them apart, and at 4 its teams of four took 2-3 % fewer steps with 0 collisions
// (docs/experiments.md, "The follower's filter rate"). Demonstrations and the expert keep 2.5.
//
// It keeps 0.005 beyond touching to the map where SPEC's filter keeps 0.01: a gap whose
// narrowest clearance is 0.102-0.11 (0.204-0.22 wide between two discs) is on a route, and SPEC's
// margin froze the robot at its mouth for the rest of the episode; in crowds among obstacles that
// was most of the timeouts. Keeping only what routes pass (0.002) let robots jammed by their
// neighbours touch a wedge between two obstacles (256 robots); 0.005 absorbs that and leaves the
// freeze to gaps of 0.204-0.21 (docs/experiments.md, "Routes the filter lets through").
inline SafetyFilterParams follower_filter() {
    SafetyFilterParams p;
    p.rate = 4;
    p.static_margin = 0.005;
    return p;
}

// Executes plans (SPEC 8): replans every `replan_every` steps (and whenever the set of agents
// changed or the window ran out), tracks the waypoints with the tracker, then applies the
// safety filter when enabled. Make one per episode.
struct FollowerConfig {
    // m, steps executed per plan, >= 1. SPEC 8 executes half the window (8 of the shipped model's
    // 16 steps; --preset paper). A quarter window reacts sooner to robots that change course:
    // on the tuning seeds it solved more in 21 random cells summed (20.56 -> 20.83; barrier 8
    // .86 -> .92, two cells .01 lower) and in crowds among obstacles (32 robots .93 -> .95 over 150
    // seeds), in fewer steps in 18 of the 21, at
    // twice the plans per step (docs/experiments.md, "Replanning every quarter window").
    int replan_every = 4;
    bool safety_filter = true;   // run the SPEC 3.2 filter after the tracker
    TrackerParams tracker;
    SafetyFilterParams filter = follower_filter();
    // Safety-filter weight of the robot that goes first, >= 1 (1: all equal, SPEC 3.2). As in
    // the guided expert (and with its default, 4): robots still travelling go before robots at
    // their goals, then the one farther from its goal when the follower first saw it, then the
    // lower id; the weights fall linearly to 1. In a symmetric standoff, equal weights bend both
    // robots' actions alike and can hold them nose to nose; unequal weights make one give way
    // (issue 12: corridor swaps of two robots .72-.84 -> .91-.98 with MA-DBP, docs/experiments.md).
    double priority_weight = 4;
    // Steps ahead of the plan's current waypoint that the tracker aims at, >= 0 (0: the
    // waypoint planned for this step, SPEC 8). A robot falls behind a moving waypoint whenever
    // the plan asks for more acceleration than |u| <= 1 gives (0.2 steps after one step, 0.7-0.95
    // after eight), and each replan starts from where the robot is, so the lag adds up: MA-DBP's
    // robots took 4-13 % more steps than the expert's. 1.5 removed most of it (docs/experiments.md,
    // "Tracking lookahead"); 2.0, with keep-right 500, takes 1.8 % fewer steps again over the 50
    // tuning cells at the same success ("Pace at the same success").
    double lookahead = 2.0;
    // Replan before replan_every steps are up (but not before half of them) when a robot is
    // farther than this from the waypoint its plan has for now, world units, >= 0 (0: only every
    // replan_every steps). The guided expert does the same (ExpertParams::replan_error). A robot
    // the filter held back, or one that squeezed past another, has left the window it was given;
    // planning again from where it is raised barrier 6 from .96 to .97 on the tuning seeds at no
    // measurable cost (docs/experiments.md, "Replanning off the plan").
    double replan_error = 0.15;
    // Backing out of a jam, steps, >= 0 (0: off; off without the safety filter, which is what
    // holds a robot). A robot not at its goal that the filter holds
    // (it asks for |u| > 0.3 and is let through less than 30 % of it) for `unjam` steps in a row,
    // and has come no nearer its goal by 0.05 for 2 unjam steps, backs out for 2 unjam / 3 steps:
    // its action points to its most open side (away from the robots within filter.range and the
    // surfaces, each by 1 / gap), then the filter. Four robots wedged among discs, each pinned by
    // another and a disc, stand still for good; backing out opens a way (docs/experiments.md,
    // "Backing out of jams").
    int unjam = 15;
    // With unjam: a robot that stands still (speed below 0.05) with another robot's centre within
    // this distance, world units, also counts as held (0, the default: only the filter holds). In
    // a knot among discs the windows themselves stand still, so the filter holds no one and nobody
    // backs out; 0.35 solves such knots at 64 robots but loses others at 128, so it is off
    // (docs/experiments.md, "Standing still in a knot").
    double unjam_near = 0;
};
class PlanFollower : public Policy {
public:
    explicit PlanFollower(Planner planner, FollowerConfig cfg = FollowerConfig{}) : planner_(std::move(planner)), cfg_(cfg) {
        if (cfg_.replan_every < 1) throw std::invalid_argument("replan_every: must be >= 1 (got " + std::to_string(cfg_.replan_every) + ")");
        if (!(cfg_.priority_weight >= 1) || !std::isfinite(cfg_.priority_weight))
            throw std::invalid_argument("priority_weight: must be finite and >= 1 (got " + std::to_string(cfg_.priority_weight) + ")");
        if (!(cfg_.lookahead >= 0) || !(cfg_.lookahead <= kMaxLookahead))
            throw std::invalid_argument("lookahead: must be in [0, " + std::to_string(kMaxLookahead) + "] steps (got " + std::to_string(cfg_.lookahead) + ")");
        // Here what needs no world; the rate's bound 1/dt is the world's, and safety_filter checks it.
        if (!(cfg_.filter.rate > 0) || !std::isfinite(cfg_.filter.rate))
            throw std::invalid_argument("filter.rate: must be finite and > 0 (got " + std::to_string(cfg_.filter.rate) + ")");
        if (cfg_.unjam < 0) throw std::invalid_argument("unjam: must be >= 0 steps (got " + std::to_string(cfg_.unjam) + ")");
        for (auto [field, v] : {std::pair<const char*, double>{"filter.margin", cfg_.filter.margin},
                                {"filter.static_margin", cfg_.filter.static_margin}, {"filter.range", cfg_.filter.range},
                                {"replan_error", cfg_.replan_error}, {"unjam_near", cfg_.unjam_near}})
            if (!(v >= 0)) throw std::invalid_argument(std::string(field) + ": must be >= 0 (got " + std::to_string(v) + ")");
    }
    std::vector<Vec2> act(const World& world) override {
        if (needs_plan(world)) {
            auto t0 = std::chrono::steady_clock::now();
            Plan p = planner_(world);
            double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
            validate_plan(p, world);
            if (p.plan_ms <= 0) p.plan_ms = ms;
            plan_ = std::move(p);
            plan_t0_ = world.t();
            total_ms_ += plan_.plan_ms;
            max_ms_ = std::max(max_ms_, plan_.plan_ms);
            plans_++;
        }
        StepModel model(world.config());
        // The point tracked: the one planned for this step, or `lookahead` steps later.
        const double ahead = world.t() - plan_t0_ + cfg_.lookahead;
        std::vector<Vec2> u(world.size());
        for (size_t i = 0; i < plan_.ids.size(); ++i) {
            const int j = world.index_of(plan_.ids[i]);
            u[j] = track_plan(world.agents()[j], plan_.waypoints[i], ahead, model, cfg_.tracker, world.config().max_action);
        }
        const bool unjam = cfg_.unjam > 0 && cfg_.safety_filter;  // a robot is "held" only by the filter
        if (unjam) back_out(world, u);
        if (cfg_.safety_filter) {
            if (unjam) nominal_ = u;
            u = safety_filter(world, u, cfg_.filter, filter_weights(world));
            if (unjam)
                for (int i = 0; i < world.size(); ++i) {
                    Jam& jam = jams_[world.agents()[i].id];
                    jam.asked = norm(nominal_[i]), jam.got = norm(u[i]);
                }
        }
        return u;
    }
    double decision_ms() const override { return plans_ ? total_ms_ / plans_ : 0; }
    double max_decision_ms() const { return max_ms_; }  // the longest plan so far: a controller's worst latency
    int plans() const { return plans_; }
    const Plan& plan() const { return plan_; }

    // The safety-filter weights of this step (FollowerConfig::priority_weight), in agents()
    // order; empty when all are equal.
    std::vector<double> filter_weights(const World& world) {
        const int n = world.size();
        if (cfg_.priority_weight == 1 || n < 2) return {};
        for (const Agent& a : world.agents())
            if (!first_distance_.count(a.id)) first_distance_[a.id] = norm(a.goal - a.pos);
        std::vector<int> order;
        priority_order(world, [&](const Agent& a) { return first_distance_[a.id]; }, order);
        std::vector<double> w(n);
        for (int rank = 0; rank < n; ++rank) w[order[rank]] = priority_weight_of(rank, n, cfg_.priority_weight);
        return w;
    }

private:
    Planner planner_;
    FollowerConfig cfg_;
    Plan plan_;
    int plan_t0_ = 0, plans_ = 0;
    double total_ms_ = 0, max_ms_ = 0;
    std::map<int, double> first_distance_;  // agent id -> distance to its goal when first seen
    struct Jam {  // per robot (unjam): how it has fared
        double nearest = std::numeric_limits<double>::infinity();  // to its goal so far
        int nearer_at = 0, held = 0, out_until = -1;  // step it last came 0.05 nearer; steps held; backing out until
        double asked = 0, got = 0;                    // |action| before and after the filter, last step
    };
    std::map<int, Jam> jams_;     // agent id -> its jam state
    std::vector<Vec2> nominal_;  // act: the actions before the filter
    // unjam: counts the steps each robot is held, and points the action of a robot held too long
    // to its most open side.
    void back_out(const World& world, std::vector<Vec2>& u) {
        const int t = world.t(), n = world.size();
        const double r = world.config().radius, range = cfg_.filter.range;
        for (int i = 0; i < n; ++i) {
            const Agent& a = world.agents()[i];
            Jam& jam = jams_[a.id];
            const double d = norm(a.pos - a.goal);
            if (d < jam.nearest - 0.05) jam.nearest = d, jam.nearer_at = t;
            if (world.at_goal(a)) {
                jam.held = 0;
                continue;
            }
            const bool held = jam.asked > 0.3 && jam.got < 0.3 * jam.asked;
            jam.held = held || stands_in_knot(world, i) ? jam.held + 1 : 0;
            if (jam.out_until < t && jam.held >= cfg_.unjam && t - jam.nearer_at >= 2 * cfg_.unjam)
                jam.out_until = t + 2 * cfg_.unjam / 3, jam.held = 0;
            if (jam.out_until < t) continue;
            Vec2 open{0, 0};
            for (int j = 0; j < n; ++j) {
                const Vec2 away = a.pos - world.agents()[j].pos;
                const double dist = norm(away);
                if (j != i && dist < range && dist > 1e-9) open += away / dist / std::max(dist - 2 * r, 0.01);
            }
            for_each_surface(world.map(), a.pos, [&](double gap, Vec2 away) {
                if (gap < range) open += away / std::max(gap - r, 0.01);
            });
            if (norm(open) > 1e-9) u[i] = open / norm(open) * world.config().max_action;
        }
    }
    // unjam_near: robot i stands still beside another robot.
    bool stands_in_knot(const World& world, int i) const {
        const Agent& a = world.agents()[i];
        if (cfg_.unjam_near <= 0 || norm(a.vel) >= 0.05) return false;
        for (const Agent& b : world.agents())
            if (b.id != a.id && norm(b.pos - a.pos) < cfg_.unjam_near) return true;
        return false;
    }
    bool needs_plan(const World& world) const {
        if (plans_ == 0 || world.t() < plan_t0_ || world.t() - plan_t0_ >= cfg_.replan_every) return true;
        if ((int)plan_.ids.size() != world.size()) return true;
        const int k = world.t() - plan_t0_;
        if (plan_.replan_after > 0 && k >= plan_.replan_after) return true;
        // Early (replan_error), but not before half the interval: a planner whose windows cannot
        // be followed costs at most twice the plans, not one every step.
        const bool early = cfg_.replan_error > 0 && k >= (cfg_.replan_every + 1) / 2;
        int longest = 0;
        for (size_t i = 0; i < plan_.ids.size(); ++i) {
            const int j = world.index_of(plan_.ids[i]);
            if (j < 0) return true;
            const std::vector<Vec2>& w = plan_.waypoints[i];
            longest = std::max(longest, (int)w.size());
            if (early && norm(world.agents()[j].pos - waypoint_now(w, k)) > cfg_.replan_error) return true;
        }
        return k >= longest;
    }
};


// =============================================================================================
// Section 11. Episodes and evaluation (SPEC 9, 10)
// =============================================================================================

// What an episode looked like, for rendering: frames[0] is the start, frames[t] the state
// after step t. Agents can differ between frames (joins and leaves).
struct Frame {
    std::vector<int> ids;
    std::vector<Vec2> pos, goal;
    std::vector<Vec2> collisions;  // points where a collision was counted at this step
};
struct EpisodeLog {
    WorldMap map;
    double radius = 0.1, goal_tolerance = 0.1, dt = 0.1;
    std::vector<Frame> frames;
    void record(const World& w) {
        Frame f;
        for (const Agent& a : w.agents()) { f.ids.push_back(a.id); f.pos.push_back(a.pos); f.goal.push_back(a.goal); }
        for (auto pr : w.last_agent_contacts()) f.collisions.push_back((w.agent(pr.first).pos + w.agent(pr.second).pos) * 0.5);
        for (int id : w.last_static_contacts()) f.collisions.push_back(w.agent(id).pos);
        frames.push_back(std::move(f));
    }
};

struct EpisodeResult {
    bool success = false;
    int steps = 0;               // steps to success, or steps taken when it failed
    int agents = 0;              // agents present at the end
    long agent_collisions = 0, obstacle_collisions = 0;
    double decision_ms = 0;      // the policy's mean time per decision (Policy::decision_ms)
    EpisodeLog log;              // filled when recording
    long collisions() const { return agent_collisions + obstacle_collisions; }
};

// Runs `policy` on `world` until done(). `on_step(world)`, when given, runs before every
// step (e.g. to add or remove agents).
inline EpisodeResult run_episode(World& world, Policy& policy, bool record = false,
                                 const std::function<void(World&)>& on_step = nullptr) {
    EpisodeResult r;
    if (record) {
        r.log.map = world.map();
        r.log.radius = world.config().radius;
        r.log.goal_tolerance = world.config().goal_tolerance;
        r.log.dt = world.config().dt;
        r.log.record(world);
    }
    while (!world.done()) {
        if (on_step) on_step(world);
        world.step(policy.act(world));
        if (record) r.log.record(world);
    }
    const Metrics& m = world.metrics();
    r.success = m.success;
    r.steps = m.success ? m.success_step : m.steps;
    r.agents = world.size();
    r.agent_collisions = m.agent_collisions;
    r.obstacle_collisions = m.obstacle_collisions;
    r.decision_ms = policy.decision_ms();
    return r;
}

// Makes the policy for one episode from its fresh world and seed. Called from several
// threads when EvalConfig::threads > 1.
using PolicyFactory = std::function<std::unique_ptr<Policy>(const World& world, uint64_t seed)>;

struct EvalConfig {
    std::string map = "empty";   // map name (ignored with a scene)
    int agents = 2;              // agents per episode (ignored with a scene)
    int episodes = 100;          // >= 1
    uint64_t seed = 0;           // episode i uses seed + i (SPEC 10)
    double half_size = 1.2;      // world half-size for random maps
    const Scene* scene = nullptr;  // a fixed problem; then seeds vary only the policy's randomness
    std::string scenario;        // an interaction scenario (make_interaction_world) on `map` instead of random spawns
    int threads = 1;             // episodes run in parallel
    ProgressFn progress;         // called after each episode, and before each step with the note "step s/limit" (optional)
    WorldConfig world;
};
struct EvalResult {
    int episodes = 0;
    double success = 0, success_se = 0;  // fraction and its standard error sqrt(p(1-p)/N)
    double collisions = 0;               // per episode (agent-agent + agent-static)
    double agent_collisions = 0, obstacle_collisions = 0;  // per episode
    double steps = 0;                    // mean steps of successful episodes (NaN if none)
    double decision_ms = 0;              // mean of the episodes' mean decision times
    std::vector<EpisodeResult> runs;     // per episode, without logs
    std::vector<uint64_t> failed_seeds;  // the seeds of the episodes that failed, in order (to render or trace them)
};
inline World make_episode_world(const EvalConfig& c, uint64_t seed) {
    if (c.scene) return make_world(*c.scene, c.world);
    if (!c.scenario.empty()) return make_interaction_world(c.scenario, c.map, c.agents, seed, c.half_size, c.world);
    return make_random_world(c.map, c.agents, seed, c.half_size, c.world);
}
// The default episode step limit of a world of half-size h: 100 steps in the standard world
// (half-size 1.2), scaled with the world's side, since crossing it takes proportionally longer.
// A scene's default is scene_step_limit (Section 12), which also follows its routes.
inline int default_max_steps(double half_size) { return (int)std::ceil(100 * half_size / 1.2 - 1e-9); }

inline EvalResult evaluate(const EvalConfig& c, const PolicyFactory& factory) {
    if (c.episodes < 1) throw std::invalid_argument("episodes: must be >= 1 (got " + std::to_string(c.episodes) + ")");
    if (!c.scene) make_episode_world(c, c.seed);  // fail early and clearly on a bad map name or count
    EvalResult r;
    r.episodes = c.episodes;
    r.runs.resize(c.episodes);
    long done = 0;
    std::string error;
#pragma omp parallel for schedule(dynamic) num_threads(std::max(1, c.threads))
    for (int e = 0; e < c.episodes; ++e) {
        try {
            World w = make_episode_world(c, c.seed + e);
            std::unique_ptr<Policy> policy = factory(w, c.seed + e);
            // Steps as notes: one episode of 1024 robots can take minutes, and a progress line
            // that only moves per episode would look stuck.
            std::function<void(World&)> on_step;
            if (c.progress)
                on_step = [&](World& world) {
                    const std::string note = "step " + std::to_string(world.metrics().steps) + "/" + std::to_string(world.config().max_steps);
#pragma omp critical
                    c.progress(done, c.episodes, note);
                };
            r.runs[e] = run_episode(w, *policy, false, on_step);
        } catch (const std::exception& ex) {
#pragma omp critical
            if (error.empty()) error = "episode with seed " + std::to_string(c.seed + e) + ": " + ex.what();
        }
#pragma omp critical
        if (c.progress) c.progress(++done, c.episodes, "");
    }
    if (!error.empty()) throw std::runtime_error(error);
    int wins = 0;
    double steps = 0;
    for (int i = 0; i < c.episodes; ++i) {
        const EpisodeResult& e = r.runs[i];
        if (!e.success) r.failed_seeds.push_back(c.seed + i);
        wins += e.success;
        if (e.success) steps += e.steps;
        r.agent_collisions += e.agent_collisions;
        r.obstacle_collisions += e.obstacle_collisions;
        r.decision_ms += e.decision_ms;
    }
    double N = c.episodes;
    r.success = wins / N;
    r.success_se = std::sqrt(r.success * (1 - r.success) / N);
    r.agent_collisions /= N;
    r.obstacle_collisions /= N;
    r.collisions = r.agent_collisions + r.obstacle_collisions;
    r.steps = wins ? steps / wins : std::numeric_limits<double>::quiet_NaN();
    r.decision_ms /= N;
    return r;
}


// =============================================================================================
// Section 12. Guided expert (SPEC 3.6)
// =============================================================================================

namespace detail {
// Calls fn(k2) for each of the (up to 8) neighbours of cell k of an n x n grid, row by row.
template <class Fn>
inline void for_each_neighbour(int n, int k, Fn&& fn) {
    const int row = k / n, col = k % n;
    for (int dr = -1; dr <= 1; ++dr)
        for (int dc = -1; dc <= 1; ++dc) {
            const int r2 = row + dr, c2 = col + dc;
            if ((dr == 0 && dc == 0) || r2 < 0 || r2 >= n || c2 < 0 || c2 >= n) continue;
            fn(r2 * n + c2);
        }
}

// The obstacles of `map` that no robot centre fits between, as groups: group[i] for surface i
// in for_each_surface's order (the four border walls, the discs, the boxes), numbered from 0.
// Two surfaces are one group when the gap between them is below `gap` (boxes that meet, a disc
// against a wall); the border walls are one group.
inline std::vector<int> surface_groups(const WorldMap& map, double gap) {
    const int discs = (int)map.discs.size(), count = 4 + discs + (int)map.boxes.size();
    std::vector<int> parent(count);
    for (int i = 0; i < count; ++i) parent[i] = i < 4 ? 0 : i;
    auto root = [&](int i) { while (parent[i] != i) i = parent[i] = parent[parent[i]]; return i; };
    const double h = map.half_size;
    auto box_of = [&](int i) { return i < 4 + discs ? Box{map.discs[i - 4].c, map.discs[i - 4].c} : map.boxes[i - 4 - discs]; };
    auto radius = [&](int i) { return i < 4 + discs ? map.discs[i - 4].r : 0.0; };
    for (int i = 4; i < count; ++i) {
        // A disc is the box of its centre grown by its radius: exact for the distances below.
        const Box a = box_of(i);
        const double to_border = std::min({h - a.hi.x, a.lo.x + h, h - a.hi.y, a.lo.y + h}) - radius(i);
        if (to_border < gap) parent[root(i)] = root(0);
        for (int j = 4; j < i; ++j) {
            const Box b = box_of(j);
            const double dx = std::max({0.0, a.lo.x - b.hi.x, b.lo.x - a.hi.x}), dy = std::max({0.0, a.lo.y - b.hi.y, b.lo.y - a.hi.y});
            if (std::hypot(dx, dy) - radius(i) - radius(j) < gap) parent[root(i)] = root(j);
        }
    }
    std::vector<int> group(count, -1), number(count, -1);
    int groups = 0;
    for (int i = 0; i < count; ++i) {
        int& g = number[root(i)];
        if (g < 0) g = groups++;
        group[i] = g;
    }
    return group;
}
// The index (for_each_surface's order) of the surface nearest `p`.
inline int nearest_surface(const WorldMap& map, Vec2 p) {
    int i = 0, best = 0;
    double nearest = std::numeric_limits<double>::infinity();
    for_each_surface(map, p, [&](double d, Vec2) {
        if (d < nearest) nearest = d, best = i;
        ++i;
    });
    return best;
}
}  // namespace detail


// Cells of a grid a route keeps out of: those k with (*label)[k] == id (a PassageControl
// passage: its passage() labels and index), and those listed in `cells` (sorted; a sparse set,
// such as the side of a passage a robot going around keeps out of, whose memory follows its
// cells, not the grid). `key` names the set in a RouteGuide's wavefront cache: the same key must
// mean the same cells on the same map. Default: none closed.
struct ClosedCells {
    const std::vector<int>* label = nullptr;
    int id = -1;
    uint64_t key = 0;
    const std::vector<int>* cells = nullptr;
    bool any() const { return label || cells; }
    bool closes(int k) const {
        return (label && (*label)[k] == id) || (cells && std::binary_search(cells->begin(), cells->end(), k));
    }
};

// Which cells a route may use and which it would rather not (RouteGuide and GuidedExpert share
// it; docs/design.md, "Routing at any scale"). A cell is passable when its centre's clearance is
// >= `min`, just above the robot radius, so that an axis-aligned passage >= 0.25 wide always holds
// a row of passable 0.036 cells (its centre band, 0.046 wide, cannot fall between two rows). A
// step into a cell below `preferred` costs `narrow_cost` extra steps: wide ways are taken where
// they are not much longer, as when `preferred` was a hard limit (before 0.4).
struct RouteClearance {
    double min = kPassableClearance;  // passable at this clearance or more, world units (radius 0.1 + 0.002)
    double preferred = 0.13;  // a step into a cell with less costs narrow_cost extra, world units
    int narrow_cost = 8;      // extra cost of such a step, steps, in [0, 1000]
    int step_cost(float clear) const { return 1 + (clear < preferred ? narrow_cost : 0); }
    void check(const char* owner) const {
        if (!(min >= 0) || !std::isfinite(min) || !(preferred >= min) || !std::isfinite(preferred))
            throw std::invalid_argument(std::string(owner) + ".min_clear: needs 0 <= min_clear <= preferred clearance (got " + number_text(min) + ", " +
                                        number_text(preferred) + ")");
        if (narrow_cost < 0 || narrow_cost > 1000)
            throw std::invalid_argument(std::string(owner) + ".narrow_cost: must be in [0, 1000] (got " + std::to_string(narrow_cost) + ")");
    }
};

namespace detail {
// wavefront()'s search, into `steps` (-1 on entry wherever it may set a cell; `touched`, when
// given, receives each cell it sets) with `ring` as its bucket queue. `settled(k, d)` is told each
// cell as its cost d becomes final and returns the last cost to settle (INT_MAX: every cell);
// the search stops after that cost's bucket (RouteGuide::near_field).
template <class Settled>
void wavefront_into(const ClearanceGrid& cg, int goal_cell, const RouteClearance& route, ClosedCells closed, std::vector<int>& steps,
                    std::vector<std::vector<int>>& ring, std::vector<int>* touched, Settled settled) {
    const int buckets = route.narrow_cost + 2;  // costs are 1 or 1 + narrow_cost: a ring of this many levels
    ring.resize(buckets);
    for (auto& level : ring) level.clear();
    steps[goal_cell] = 0;
    if (touched) touched->push_back(goal_cell);
    ring[0].push_back(goal_cell);
    long pending = 1;
    int stop = std::numeric_limits<int>::max();
    for (int d = 0; pending > 0 && d <= stop; ++d) {
        std::vector<int>& level = ring[d % buckets];
        for (size_t i = 0; i < level.size(); ++i) {
            const int k = level[i];
            --pending;
            if (steps[k] != d) continue;  // reached more cheaply since it was queued
            stop = std::min(stop, settled(k, d));
            const int d2 = d + route.step_cost(cg.clear[k]);  // moving from a neighbour into k
            for_each_neighbour(cg.n, k, [&](int k2) {
                if ((steps[k2] >= 0 && steps[k2] <= d2) || cg.clear[k2] < route.min || closed.closes(k2)) return;
                if (touched && steps[k2] < 0) touched->push_back(k2);
                steps[k2] = d2;
                ring[d2 % buckets].push_back(k2);
                ++pending;
            });
        }
        level.clear();
    }
}
}  // namespace detail

// The wavefront: the cost from every cell to `goal_cell` moving one cell per step in 8
// directions through passable cells (the goal cell always counts) that `closed` does not close,
// each step costing route.step_cost of the cell it enters (1 when narrow_cost is 0: the steps of
// a breadth-first search). Dial's bucket queue (costs are small integers); -1 where the goal
// cannot be reached. Memory: 4 bytes a cell, plus the queue.
inline std::vector<int> wavefront(const ClearanceGrid& cg, int goal_cell, const RouteClearance& route, ClosedCells closed = {}) {
    std::vector<int> steps((size_t)cg.n * cg.n, -1);
    std::vector<std::vector<int>> ring;
    detail::wavefront_into(cg, goal_cell, route, closed, steps, ring, nullptr, [](int, int) { return std::numeric_limits<int>::max(); });
    return steps;
}
// Steps through cells with clearance >= min_clear (a breadth-first search, no narrow cost).
inline std::vector<int> wavefront(const ClearanceGrid& cg, int goal_cell, double min_clear, ClosedCells closed = {}) {
    return wavefront(cg, goal_cell, RouteClearance{min_clear, min_clear, 0}, closed);
}

// Route subgoals (issue 13): where a robot should head next on its shortest way around the
// static map to a goal that may be far away. When the segment to the goal keeps the preferred
// clearance `clear` (an exact test, like the view's below), that is the way: the subgoal lies
// `distance` along it and no field is made. Otherwise
// the wavefront of the goal's cell (made once per map, goal cell and closed set, and cached) is
// walked downhill from the robot's cell; the subgoal is the last cell centre of that walk that
// is still in straight view of the robot's position (the segment keeps `view_clear` from the
// map, checked every half cell) and at most `distance` from it. When the goal itself is within
// `distance` and in view, or the walk arrives, the goal is returned and `final` is set.
// A route may be asked to keep out of some cells (ClosedCells: a corridor others are using; the
// walk, the view and the wavefront then avoid them).
// Memory: the grid (4 bytes a cell, <= kRouteMaxGridSide^2) plus wavefronts (RouteField: 2 bytes
// a cell, of the tiles within `band` cells of a robot's route: about 60 KB a robot in a world of
// half-size 10) up to kFieldCacheBytes; beyond, the least recently used ones are dropped. Making
// a field takes a whole-grid wavefront (4 bytes a cell) for a moment.
struct RouteGoal {
    Vec2 goal;           // where to head: the goal itself or a subgoal on the way
    bool final = true;   // goal is the robot's real goal (the planner may pin the window's end to it)
};
// A cached wavefront: the route cost per cell, -1 where the goal cannot be reached. Stored in 2
// bytes a cell when every cost is below 65535 (a cost is at most 1 + narrow_cost a cell), else
// in 4; and either for the whole grid or, for a band field, only for the tiles of kTile x kTile
// cells within `band` cells of one route's cells: reading a cell outside them gives kAbsent. What
// is held reads back the wavefront's own ints, so a walk that reads only held cells takes the
// route a whole field gives (RouteGuide makes a band again when a walk reads past it).
class RouteField {
public:
    static constexpr int kAbsent = -2;  // a cell a band field does not hold
    static constexpr int kTile = 16;    // tile side, cells
    RouteField() = default;
    // `steps`: the wavefront of an n x n grid; `route` (with band > 0): the cells to keep `band` around.
    RouteField(const std::vector<int>& steps, int n, const std::vector<int>* route = nullptr, int band = 0) : n_(n) {
        const std::vector<int>* kept = &steps;
        std::vector<int> tiled;
        if (route && band > 0) {
            side_ = (n + kTile - 1) / kTile;
            tile_of_.assign((size_t)side_ * side_, -1);
            int tiles = 0;
            for (int k : *route) {
                const int r = k / n, c = k % n;
                for (int tr = std::max(0, r - band) / kTile; tr <= std::min(n - 1, r + band) / kTile; ++tr)
                    for (int tc = std::max(0, c - band) / kTile; tc <= std::min(n - 1, c + band) / kTile; ++tc)
                        if (tile_of_[(size_t)tr * side_ + tc] < 0) tile_of_[(size_t)tr * side_ + tc] = tiles++;
            }
            if ((size_t)tiles == tile_of_.size()) {
                tile_of_.clear();  // every tile: the whole grid is smaller
            } else {
                tiled.assign((size_t)tiles * kTile * kTile, -1);  // cells past the grid's edge stay -1, never read
                for (int tr = 0; tr < side_; ++tr)
                    for (int tc = 0; tc < side_; ++tc) {
                        const int t = tile_of_[(size_t)tr * side_ + tc];
                        if (t < 0) continue;
                        for (int r = tr * kTile; r < std::min(n, (tr + 1) * kTile); ++r)
                            for (int c = tc * kTile; c < std::min(n, (tc + 1) * kTile); ++c)
                                tiled[(size_t)t * kTile * kTile + (r % kTile) * kTile + c % kTile] = steps[(size_t)r * n + c];
                    }
                kept = &tiled;
            }
        }
        const int top = kept->empty() ? 0 : *std::max_element(kept->begin(), kept->end());
        if (top >= kNone) {
            wide_ = *kept;
            return;
        }
        narrow_.resize(kept->size());
        for (size_t i = 0; i < kept->size(); ++i) narrow_[i] = (*kept)[i] < 0 ? kNone : (uint16_t)(*kept)[i];
    }
    int operator[](size_t k) const {
        if (tile_of_.empty()) return value(k);
        const int r = (int)(k / n_), c = (int)(k % n_);
        const int t = tile_of_[(size_t)(r / kTile) * side_ + c / kTile];
        return t < 0 ? kAbsent : value((size_t)t * kTile * kTile + (r % kTile) * kTile + c % kTile);
    }
    bool whole() const { return tile_of_.empty(); }
    size_t bytes() const { return narrow_.capacity() * sizeof(uint16_t) + wide_.capacity() * sizeof(int) + tile_of_.capacity() * sizeof(int); }

private:
    static constexpr int kNone = 0xFFFF;  // unreachable, in the 2-byte form
    int n_ = 0, side_ = 0;                // grid side; tiles a side (band fields)
    std::vector<int> tile_of_;            // band fields: tile -> its place in the values, -1 not held
    std::vector<uint16_t> narrow_;
    std::vector<int> wide_;
    int value(size_t i) const { return wide_.empty() ? (narrow_[i] == kNone ? -1 : narrow_[i]) : wide_[i]; }
};
// A RouteGuide's settings (its public fields): two guides with the same settings walk the same
// routes on the same map.
struct RouteGuideSettings {
    double cell = 0.036;        // planning cells, world units (the expert's)
    double clear = 0.13;        // the route prefers cells with this clearance (RouteClearance::preferred; the expert's inflate)
    double min_clear = kPassableClearance;  // and passes cells with this much (RouteClearance::min)
    int narrow_cost = 8;        // extra cost of a step into a cell below `clear` (RouteClearance::narrow_cost)
    double view_clear = 0.1;    // a subgoal is visible when the segment to it keeps this clearance (robot radius)
    // Cells either side of a robot's route a cached field keeps (RouteField's band; 0: the whole
    // grid; else >= 2, the cells a walk reads around its start). Routes are the same either way:
    // a walk that reads past the band makes it again around the walk's own route.
    int band = 32;
    // A subgoal toward a goal at most this far (world units) is walked on a wavefront made only
    // as far as the walk reads (near_field), not cached: the same subgoal as the cached field
    // gives, for a point a robot heads for a moment (a route around a crowd). 0: cached fields.
    double near_reach = 2.0;
};

class RouteGuide : public RouteGuideSettings {
public:
    static constexpr size_t kFieldCacheBytes = size_t(128) << 20;

    RouteClearance route() const { return {min_clear, clear, narrow_cost}; }
    // A guide with these settings and nothing made yet: another thread's guide that walks the
    // same routes.
    RouteGuide settings_only() const {
        RouteGuide g;
        static_cast<RouteGuideSettings&>(g) = *this;
        return g;
    }
    // A subgoal from p toward goal walks a near field (near_reach), never a cached field.
    bool walks_near(Vec2 p, Vec2 goal) const { return norm(goal - p) <= near_reach; }

    // The subgoal from p toward goal on `map`, at most `distance` (> 0) world units from p.
    RouteGoal subgoal(const WorldMap& map, Vec2 p, Vec2 goal, double distance, ClosedCells closed = {}) {
        if (!(distance > 0) || !std::isfinite(distance)) throw std::invalid_argument("RouteGuide: distance must be a positive number");
        set_map(map);
        check(closed);
        const bool within = norm(goal - p) <= distance;
        if (within && visible(p, goal, closed)) return {goal, true};
        // Far, with the straight way keeping the preferred clearance: no field needed. (Near and
        // not in view, the walk decides: with the defaults, clear > view_clear, that straight way
        // is not clear either, and a point `distance` along it would pass the goal.)
        if (!within && visible(p, goal, closed, clear)) return {p + (goal - p) * (distance / norm(goal - p)), false};
        bool no_route = false;
        const auto walk = [&](const auto& steps) -> RouteGoal {
            int k = start_cell(steps, grid_.index(p));
            no_route = k < 0;
            if (no_route) return {goal, true};  // no route known from here: head straight for the goal
            Vec2 sub = grid_.centre(k);
            while (steps[k] > 0) {
                const int next = downhill(steps, k, goal);
                if (next < 0) break;
                k = next;
                const Vec2 c = steps[k] == 0 ? goal : grid_.centre(k);
                if (norm(c - p) > distance || !visible(p, c, closed)) break;
                sub = c;
                if (steps[k] == 0) return {goal, true};
            }
            return {sub, false};
        };
        const RouteGoal found = walks_near(p, goal) ? walk(near_field(grid_.index(goal), grid_.index(p), closed))
                                                             : walk_field(grid_.index(p), goal, closed, walk);
        // No way from here with cells closed (a robot told to go around a passage it already
        // stands in or beside): the way through them, not straight at the goal through the map,
        // which wedged robots against discs for good (docs/experiments.md, "Going around from
        // where a robot stands").
        if (no_route && closed.any()) return subgoal(map, p, goal, distance);
        return found;
    }
    // The route's cells (grid() indices) from p toward goal: p's cell (or its best reachable
    // neighbour when p is too close to the map), then downhill to the goal's cell, at most
    // `max_cells` of them; empty when no route is known.
    void route_cells(const WorldMap& map, Vec2 p, Vec2 goal, int max_cells, std::vector<int>& cells) {
        set_map(map);
        walk_field(grid_.index(p), goal, {}, [&](const RouteField& steps) {
            cells.clear();
            append_walk(steps, grid_.index(p), goal, (size_t)std::max(0, max_cells), cells);
            return 0;
        });
    }
    // The segment a-b keeps view_clear from `map` (checked every half cell) and out of `closed`.
    bool in_view(const WorldMap& map, Vec2 a, Vec2 b, ClosedCells closed = {}) {
        set_map(map);
        check(closed);
        return visible(a, b, closed);
    }
    // The segment a-b crosses only cells with the preferred clearance (`clear`), none closed:
    // read from the grid (no distance to the map is computed), so it is cheap at any length.
    bool straight(const WorldMap& map, Vec2 a, Vec2 b, ClosedCells closed = {}) {
        set_map(map);
        check(closed);
        return straight_way(a, b, closed);
    }
    const ClearanceGrid& grid() const { return grid_; }
    const ClearanceGrid& grid(const WorldMap& map) { set_map(map); return grid_; }  // the grid made for `map`
    // The wavefront (route cost per cell, -1: unreachable) of goal's cell on `map`, keeping out of
    // `closed`, over the whole grid whatever `band`; valid until the next call that may make a field.
    const RouteField& steps_to(const WorldMap& map, Vec2 goal, ClosedCells closed = {}) {
        set_map(map);
        check(closed);
        return field(grid_.index(goal), closed, -1, goal, false);
    }
    // Wavefront steps from p's cell to goal's, the guided expert's priority key (its plan cells
    // and clearance; a step into a narrow cell counts 1 + narrow_cost); kRouteUnreachable when no
    // route is known.
    static constexpr int kRouteUnreachable = 1 << 20;
    int route_steps(const WorldMap& map, Vec2 p, Vec2 goal) {
        set_map(map);
        const int k = grid_.index(p);
        const int s = walk_field(k, goal, {}, [&](const RouteField& steps) { return read(steps, k); });
        return s >= 0 ? s : kRouteUnreachable;
    }
    // Steps of the walk subgoal() takes from p to goal keeping out of `closed` (from the cell it
    // starts at, which may be a neighbour of p's); kRouteUnreachable when no route is known.
    int walk_steps(const WorldMap& map, Vec2 p, Vec2 goal, ClosedCells closed) {
        set_map(map);
        check(closed);
        return walk_field(grid_.index(p), goal, closed, [&](const RouteField& steps) {
            const int k = start_cell(steps, grid_.index(p));
            return k >= 0 ? steps[k] : kRouteUnreachable;
        });
    }
    // Bytes held: the grid and the cached wavefronts (capacities), <= grid + kFieldCacheBytes
    // (one field more while it is being made; with expect(), batch - 1 whole wavefronts more).
    size_t workspace_bytes() const {
        size_t bytes = grid_.clear.capacity() * sizeof(float);
        for (const auto& f : fields_) bytes += f.second.steps.bytes();
        for (const auto& w : made_ahead_) bytes += w.second.capacity() * sizeof(int);
        return bytes + near_steps_.capacity() * sizeof(int);
    }
    size_t fields_cached() const { return fields_.size(); }

    // Fields made ahead, several at once (the planner's threads, issue 47). `run_ahead(count, fn)`
    // runs fn(j) for every j in [0, count), in any order or at once (unset: fields are made one at
    // a time). expect() lists, in order, the goals of the walks about to make fields (keeping out
    // of no cells), until the Expecting it returns ends. A walk that must make an expected goal's
    // field makes its wavefront together with those of the next `batch` - 1 expected goals whose
    // fields are not cached, in one run_ahead; those wait (at most batch - 1 wavefronts of 4
    // bytes a cell: a new batch drops the ones no walk asked for) until their walks ask. Fields,
    // routes and the cache are those made one at a time: a wavefront depends on the grid and its
    // goal only.
    std::function<void(int count, const std::function<void(int)>& fn)> run_ahead;
    class Expecting {
    public:
        explicit Expecting(RouteGuide& guide) : guide_(guide) {}
        Expecting(const Expecting&) = delete;
        Expecting& operator=(const Expecting&) = delete;
        ~Expecting() { guide_.expect_none(); }
    private:
        RouteGuide& guide_;
    };
    [[nodiscard]] Expecting expect(const WorldMap& map, const std::vector<Vec2>& goals, int batch) {
        expect_none();
        if (!goals.empty()) {  // no grid made for a plan whose walks make no field
            set_map(map);
            for (Vec2 g : goals) expected_.push_back(grid_.index(g));
            ahead_batch_ = batch;
        }
        return Expecting(*this);
    }
    void expect_none() {
        expected_.clear();
        made_ahead_.clear();
        next_expected_ = 0;
    }

private:
    ClearanceGrid grid_;
    WorldMap map_;
    struct Field {
        RouteField steps;
        uint64_t used = 0;  // when last asked for (least recently used goes first)
    };
    std::map<std::tuple<int, uint64_t, bool>, Field> fields_;  // (goal cell, closed key, whole) -> wavefront
    uint64_t clock_ = 0;
    size_t field_bytes_ = 0;
    bool read_absent_ = false;  // a walk read a cell its band field does not hold
    WorldMap near_;             // visible()'s obstacles near its segment
    std::vector<int> near_steps_, near_touched_;  // near_field's wavefront (-1 where untouched) and the cells it set
    std::vector<std::vector<int>> near_ring_;     // its bucket queue
    std::vector<int> expected_;                   // expect(): goal cells, in the order walks ask
    size_t next_expected_ = 0;                    // the first not yet made
    int ahead_batch_ = 1;
    std::map<int, std::vector<int>> made_ahead_;  // goal cell -> its wavefront, made ahead

    void set_map(const WorldMap& map) {
        if (grid_.n > 0 && map == map_) return;
        route().check("RouteGuide");
        if (band != 0 && (band < 2 || band > kRouteMaxGridSide))
            throw std::invalid_argument("RouteGuide.band: must be 0 (whole grid) or in [2, " + std::to_string(kRouteMaxGridSide) + "] (got " + std::to_string(band) + ")");
        grid_ = ClearanceGrid(map, cell);
        map_ = map;
        fields_.clear();
        field_bytes_ = 0;
        near_steps_.clear();
        near_touched_.clear();
        expect_none();
    }
    // The wavefront of goal_cell (wavefront()'s costs, keeping out of `closed`) made only until a
    // walk from cell `from` reads nothing else: it stops one step's cost (1 + narrow_cost) past
    // the cost of the cell start_cell() starts from (`from`, or when `from` is not passable, the
    // cheapest within two cells). Then every cell costing up to that holds its final cost and
    // every other cell -1 or more than that, so start_cell() and downhill() choose as on the
    // whole field. A passable `from` that cannot be reached makes the whole wavefront.
    // Memory: one int a grid cell, kept from the first call; time: the cells within that cost of the goal.
    const std::vector<int>& near_field(int goal_cell, int from, ClosedCells closed) {
        const RouteClearance r = route();
        const int n = grid_.n, from_row = from / n, from_col = from % n;
        if (near_steps_.size() != (size_t)n * n) near_steps_.assign((size_t)n * n, -1);  // made on first use
        for (int k : near_touched_) near_steps_[k] = -1;
        near_touched_.clear();
        const bool from_passable = from == goal_cell || (grid_.clear[from] >= r.min && !closed.closes(from));
        // The first start cell settled sets the stop (wavefront_into keeps the least returned).
        detail::wavefront_into(grid_, goal_cell, r, closed, near_steps_, near_ring_, &near_touched_, [&](int k, int d) {
            const bool start = from_passable ? k == from : std::abs(k / n - from_row) <= 2 && std::abs(k % n - from_col) <= 2;
            return start ? d + 1 + r.narrow_cost : std::numeric_limits<int>::max();  // one step's cost past the walk's start
        });
        return near_steps_;
    }
    // The field of goal_cell keeping out of `closed`, cached: a band field around the route from
    // cell `from` (from < 0 or band == 0: the whole grid); `remake` makes a cached band again
    // around from's route.
    const RouteField& field(int goal_cell, ClosedCells closed, int from, Vec2 goal, bool remake) {
        const bool whole = band == 0 || from < 0;
        const std::tuple<int, uint64_t, bool> key{goal_cell, closed.any() ? closed.key : 0, whole};
        auto it = fields_.find(key);
        if (it != fields_.end() && remake) {
            field_bytes_ -= it->second.steps.bytes();
            fields_.erase(it);
            it = fields_.end();
        }
        if (it == fields_.end()) {
            const std::vector<int> steps = closed.any() ? wavefront(grid_, goal_cell, route(), closed) : wavefront_ahead(goal_cell);
            std::vector<int> cells;
            if (!whole) cells.assign(1, from), append_walk(steps, from, goal, steps.size() + 1, cells);
            RouteField made(steps, grid_.n, whole ? nullptr : &cells, band);
            while (!fields_.empty() && field_bytes_ + made.bytes() > kFieldCacheBytes) {
                auto oldest = fields_.begin();
                for (auto f = fields_.begin(); f != fields_.end(); ++f) if (f->second.used < oldest->second.used) oldest = f;
                field_bytes_ -= oldest->second.steps.bytes();
                fields_.erase(oldest);
            }
            field_bytes_ += made.bytes();
            it = fields_.emplace(key, Field{std::move(made), 0}).first;
        }
        it->second.used = ++clock_;
        return it->second.steps;
    }
    // goal_cell's wavefront (no cells closed): made ahead, or made now, with the next expected
    // ones when goal_cell is expected (expect()).
    std::vector<int> wavefront_ahead(int goal_cell) {
        auto w = made_ahead_.find(goal_cell);
        if (w != made_ahead_.end()) {
            std::vector<int> steps = std::move(w->second);
            made_ahead_.erase(w);
            return steps;
        }
        size_t j = std::find(expected_.begin() + next_expected_, expected_.end(), goal_cell) - expected_.begin();
        if (!run_ahead || ahead_batch_ <= 1 || j == expected_.size()) return wavefront(grid_, goal_cell, route(), {});
        made_ahead_.clear();  // the walks they were made for did not come
        std::vector<int> cells{goal_cell};
        for (++j; j < expected_.size() && (int)cells.size() < ahead_batch_; ++j) {
            const int k = expected_[j];
            if (!fields_.count({k, 0, band == 0}) && std::find(cells.begin(), cells.end(), k) == cells.end()) cells.push_back(k);
        }
        next_expected_ = j;
        std::vector<std::vector<int>> made(cells.size());
        run_ahead((int)cells.size(), [&](int b) { made[b] = wavefront(grid_, cells[b], route(), {}); });
        for (size_t b = 1; b < cells.size(); ++b) made_ahead_[cells[b]] = std::move(made[b]);
        return std::move(made[0]);
    }
    // walk(field) on goal's field for a walk from cell `from`. When the walk read a cell its band
    // field does not hold, the band is made again around the route from `from` (it then holds
    // every cell that walk reads: the walk's cells and their neighbours, and 2 cells around its
    // start) and walked again: the result is the whole field's.
    template <class Walk>
    auto walk_field(int from, Vec2 goal, ClosedCells closed, Walk walk) -> decltype(walk(RouteField{})) {
        const int goal_cell = grid_.index(goal);
        read_absent_ = false;
        auto result = walk(field(goal_cell, closed, from, goal, false));
        if (!read_absent_) return result;
        read_absent_ = false;
        return walk(field(goal_cell, closed, from, goal, true));
    }
    // Appends the walk from cell `from` on `steps` (start_cell's, then downhill to the goal's
    // cell) to `cells` while it holds fewer than max_cells: route_cells' route, and the route a
    // band field is made around.
    template <class Steps>
    void append_walk(const Steps& steps, int from, Vec2 goal, size_t max_cells, std::vector<int>& cells) {
        int k = start_cell(steps, from);
        while (k >= 0 && cells.size() < max_cells) {
            cells.push_back(k);
            k = steps[k] > 0 ? downhill(steps, k, goal) : -1;
        }
    }
    // steps[k], noting a read past a band field.
    int read(const RouteField& steps, int k) {
        const int v = steps[k];
        if (v == RouteField::kAbsent) read_absent_ = true;
        return v;
    }
    int read(const std::vector<int>& steps, int k) const { return steps[k]; }
    void check(ClosedCells closed) const {
        if (closed.label && closed.label->size() != (size_t)grid_.n * grid_.n)
            throw std::invalid_argument("ClosedCells.label: needs one entry per cell of the guide's grid (" + std::to_string(grid_.n * grid_.n) +
                                        "), got " + std::to_string(closed.label->size()));
        if (closed.cells && !closed.cells->empty() && (closed.cells->front() < 0 || closed.cells->back() >= grid_.n * grid_.n))
            throw std::invalid_argument("ClosedCells.cells: a cell is outside the guide's grid (" + std::to_string(grid_.n * grid_.n) + " cells)");
    }
    // Exact (every sample's distance to the map, so the same wherever the grid's lines fall), but
    // a sample whose cell keeps view_clear + half a cell diagonal needs none: clearance changes
    // no faster than position, so long views over open ground cost grid reads only.
    // `clearance`: view_clear, or the route's preferred clearance for the straight way.
    bool visible(Vec2 a, Vec2 b, ClosedCells closed = {}, double clearance = -1) {
        if (clearance < 0) clearance = view_clear;
        const int samples = 1 + (int)std::ceil(norm(b - a) / (0.5 * grid_.cell));
        const double sure = clearance + 0.71 * grid_.cell;
        bool near_made = false;  // the obstacles near the segment (obstacles_near), made at the first sample that needs them
        for (int i = 0; i <= samples; ++i) {
            const Vec2 q = a + (b - a) * ((double)i / samples);
            const int k = grid_.index(q);
            if (closed.closes(k)) return false;
            const bool inside = std::abs(q.x) < grid_.half && std::abs(q.y) < grid_.half;
            if (inside && grid_.clear[k] >= sure) continue;
            if (!near_made) {
                obstacles_near(map_, {std::min(a.x, b.x), std::min(a.y, b.y)}, {std::max(a.x, b.x), std::max(a.y, b.y)}, clearance, near_);
                near_made = true;
            }
            if (static_clearance(near_, q) < clearance) return false;
        }
        return true;
    }
    // Every half cell of a-b lies in a cell with the preferred clearance: the point is then within
    // half a cell diagonal (0.026) of that cell's centre, so it keeps clear - 0.026 >= view_clear.
    bool straight_way(Vec2 a, Vec2 b, ClosedCells closed) const {
        const int samples = 1 + (int)std::ceil(norm(b - a) / (0.5 * grid_.cell));
        for (int i = 0; i <= samples; ++i) {
            const int k = grid_.index(a + (b - a) * ((double)i / samples));
            if (grid_.clear[k] < clear || closed.closes(k)) return false;
        }
        return true;
    }
    // Where a walk on `steps` starts from cell k: k, or when k is too close to the map the
    // reachable cell within 2 cells nearest the goal; -1 when there is none.
    template <class Steps>
    int start_cell(const Steps& steps, int k) {
        if (read(steps, k) >= 0) return k;
        const int n = grid_.n;
        int best = -1;
        for (int dr = -2; dr <= 2; ++dr)
            for (int dc = -2; dc <= 2; ++dc) {
                const int r2 = k / n + dr, c2 = k % n + dc;
                if (r2 < 0 || r2 >= n || c2 < 0 || c2 >= n) continue;
                const int k2 = r2 * n + c2;
                if (read(steps, k2) >= 0 && (best < 0 || steps[k2] < steps[best])) best = k2;
            }
        return best;
    }
    // Downhill from cell k: among the neighbours on a cheapest way from k (their cost plus the
    // step into them is k's), the one nearest the goal (straighter paths); -1 when there is none.
    template <class Steps>
    int downhill(const Steps& steps, int k, Vec2 goal) {
        int next = -1;
        const RouteClearance r = route();
        const int here = read(steps, k);
        detail::for_each_neighbour(grid_.n, k, [&](int k2) {
            const int v = read(steps, k2);
            if (v >= 0 && v + r.step_cost(grid_.clear[k2]) == here &&
                (next < 0 || norm(grid_.centre(k2) - goal) < norm(grid_.centre(next) - goal)))
                next = k2;
        });
        return next;
    }
};

namespace detail {
// The states a space-time search has reached, (step, cell) -> cost and parent: a list of nodes
// and an open-addressing table over it (linear probing, at most half full), so memory follows
// the states reached (at most 8 per expansion plus the start), not steps x cells.
struct SpaceTimeStates {
    struct Node { int t, cell; float g; int parent; };
    std::vector<Node> nodes;
    std::vector<int> slots;  // node index, -1 empty; a power of 2 long
    void clear() {
        nodes.clear();
        std::vector<int>(1024, -1).swap(slots);  // also gives back a large table of the last search
    }
    // The node of (t, cell); a new one costs +infinity and has no parent.
    int find_or_add(int t, int cell) {
        if (2 * (nodes.size() + 1) > slots.size()) grow();
        const size_t mask = slots.size() - 1;
        for (size_t i = hash(t, cell) & mask;; i = (i + 1) & mask) {
            const int k = slots[i];
            if (k >= 0 && nodes[k].t == t && nodes[k].cell == cell) return k;
            if (k >= 0) continue;
            slots[i] = (int)nodes.size();
            nodes.push_back({t, cell, std::numeric_limits<float>::infinity(), -1});
            return slots[i];
        }
    }
    size_t bytes() const { return nodes.capacity() * sizeof(Node) + slots.capacity() * sizeof(int); }

private:
    static size_t hash(int t, int cell) {
        uint64_t x = ((uint64_t)(uint32_t)t << 32 | (uint32_t)cell) * 0x9E3779B97F4A7C15ull;
        return (size_t)(x ^ (x >> 29));
    }
    void grow() {
        std::vector<int>(slots.size() * 2, -1).swap(slots);
        const size_t mask = slots.size() - 1;
        for (size_t k = 0; k < nodes.size(); ++k) {
            size_t i = hash(nodes[k].t, nodes[k].cell) & mask;
            while (slots[i] >= 0) i = (i + 1) & mask;
            slots[i] = (int)k;
        }
    }
};

// The planned centres of higher-priority robots, by step and by square buckets of cells:
// count() is how many robots reserve a cell at a step (one of their centres there is within the
// reservation disc, or the wider one that robots giving way keep clear of). Memory follows the
// centres (robots x steps x (hold + 2)), not the grid.
struct Reservations {
    struct Centre { int robot, cell; };
    struct Disc {  // the cell offsets within a radius
        int R = 0;                 // radius, cells
        std::vector<char> inside;  // (2R + 1)^2: the offset is inside the disc
        bool holds(int dr, int dc) const { return std::abs(dr) <= R && std::abs(dc) <= R && inside[(size_t)(dr + R) * (2 * R + 1) + dc + R]; }
    };
    int n = 0, side = 1, buckets = 1;  // grid side; bucket side, cells (the wider disc's radius + 1); buckets a side
    Disc disc, wide;
    std::unordered_map<uint64_t, std::vector<Centre>> at;  // (step, bucket) -> centres
    size_t centres = 0;

    // Discs of radius `reach` and `wide_reach` >= reach (world units) on a grid of `grid_side` cells of `cell`.
    void reset(int grid_side, double cell, double reach, double wide_reach) {
        n = grid_side;
        make_disc(disc, cell, reach);
        make_disc(wide, cell, std::max(reach, wide_reach));
        side = wide.R + 1;
        buckets = (n + side - 1) / side;
        at.clear();
        centres = 0;
    }
    void add(int robot, int t, int cell) {
        at[key(t, cell / n / side, cell % n / side)].push_back({robot, cell});
        ++centres;
    }
    // The centres at step t whose wider disc may reach cell c or one of its neighbours, into `out`.
    void near(int t, int c, std::vector<Centre>& out) const {
        out.clear();
        if (at.empty()) return;
        const int row = c / n, col = c % n, R = wide.R;
        for (int br = std::max(0, (row - R - 1) / side); br <= std::min(buckets - 1, (row + R + 1) / side); ++br)
            for (int bc = std::max(0, (col - R - 1) / side); bc <= std::min(buckets - 1, (col + R + 1) / side); ++bc) {
                auto it = at.find(key(t, br, bc));
                if (it != at.end()) out.insert(out.end(), it->second.begin(), it->second.end());
            }
    }
    // How many robots of `near` reserve `cell` (with_wide: by the wider disc).
    int count(const std::vector<Centre>& near, int cell, bool with_wide = false) const {
        const Disc& d = with_wide ? wide : disc;
        int robots = 0, last = -1;
        const int row = cell / n, col = cell % n;
        for (size_t i = 0; i < near.size(); ++i) {
            const Centre& e = near[i];
            if (!d.holds(e.cell / n - row, e.cell % n - col) || e.robot == last) continue;
            bool counted = false;  // a robot's centres at one step may lie in several buckets
            for (size_t j = 0; j < i && !counted; ++j)
                counted = near[j].robot == e.robot && d.holds(near[j].cell / n - row, near[j].cell % n - col);
            if (!counted) ++robots;
            last = e.robot;
        }
        return robots;
    }
    size_t bytes() const { return centres * sizeof(Centre) + at.size() * (sizeof(uint64_t) + sizeof(std::vector<Centre>) + 2 * sizeof(void*)); }

private:
    uint64_t key(int t, int br, int bc) const { return ((uint64_t)t * buckets + br) * buckets + bc; }
    static void make_disc(Disc& d, double cell, double reach) {
        d.R = (int)std::ceil(reach / cell);
        d.inside.assign((size_t)(2 * d.R + 1) * (2 * d.R + 1), 0);
        for (int dr = -d.R; dr <= d.R; ++dr)
            for (int dc = -d.R; dc <= d.R; ++dc) d.inside[(size_t)(dr + d.R) * (2 * d.R + 1) + dc + d.R] = std::hypot(dr, dc) * cell < reach;
    }
};
}  // namespace detail

// The guided expert: a privileged classical planner that makes the training demonstrations
// and a strong classical row. Every `replan_every` steps it plans all agents one after the
// other in priority order (prioritized planning, a space-time A* per agent):
//   - space: the routing grid of a RouteGuide (cells of `cell`, one cell per step = 0.36
//     units/s along an axis, up to half-size 41.4: kRouteMaxGridSide; a larger world gets
//     coarser cells, each taking `stretch` world steps, with waypoints interpolated along the
//     path between them); cells closer than `min_clear` to an obstacle or wall are not
//     entered, and a step into one closer than `inflate` costs `narrow_cost` extra (RouteClearance);
//   - time: the agent's path is a cell per step; waiting is a move; plans look at most
//     kExpertMaxHorizon + extra_horizon world steps ahead; a search ends at its first state
//     on the horizon when no arrival is cheaper;
//   - heuristic: the guide's wavefront cost to the goal around the static map, exact when no
//     other agent is in the way (the Chebyshev distance when the straight way is clear: no field);
//   - conflicts: the planned centres of higher-priority agents reserve a disc of radius
//     2 r + buffer at every step; each step inside a reservation costs `conflict_cost` extra
//     steps (soft, so a plan always exists; the agent waits, detours or makes way when that
//     is cheaper), and arriving at the goal is charged for later reservations there;
//   - start: plans start from the robot's position: the first waypoints blend from it onto
//     the path's cell centres over replan_every steps (a robot is never told to go back to
//     its cell's centre first);
//   - memory, at any world size: the guide's grid and wavefront cache (RouteGuide), the
//     reached states of one search (at most 8 max_expansions + 1, detail::SpaceTimeStates)
//     and the reservations (robots x steps x (hold + 2) centres, detail::Reservations).
// Priorities: agents still travelling before agents that have arrived (those step aside and
// come back), then the longer route cost at the start first, then the id; robots that give way
// (ExpertHeading::gives_way) after all others. A robot whose route cost has not fallen for
// stall_steps goes before the rest, the stalled ones in an order drawn (from id and how many
// stall_steps it has waited) afresh every stall_steps: fixed priorities can hold robots nose
// to nose at a doorway for good (room-64-64-8, docs/design.md "Guided expert"). The plan is
// tracked with the SPEC 3.2 tracker and made safe by the safety filter, in which a
// higher-priority agent weighs more (deviates less; lower ones make way).
// Traffic: soft reservations do not settle two robots meeting head-on in a one-lane aisle (each
// plan sends both in, the filter holds them nose to nose). An ExpertTraffic rule may, before each
// plan, send a robot elsewhere than its goal: madbp.hpp's passage_traffic() gives the expert the
// planner's turns through one-lane passages (PassageControl). Without one, each heads for its goal.
struct ExpertHeading {
    Vec2 target;            // where the robot is planned to go this plan (its goal unless a rule says otherwise)
    ClosedCells closed;     // grid cells its route keeps out of (none by default)
    bool gives_way = false; // it waits or goes around for others: planned after every robot that does not,
                            // and so is a line it heads (`after`)
    int after = -1;         // the index of a robot it follows (through a one-lane aisle): planned right after it
};
// heading[i] comes filled for world.agents()[i] (its goal, nothing closed); `guide` is the expert's.
using ExpertTraffic = std::function<void(const World& world, RouteGuide& guide, std::vector<ExpertHeading>& heading)>;

struct ExpertParams {
    double cell = 0.036;          // planning cell, world units (distance per step at cruise)
    double inflate = 0.13;        // clearance preferred from obstacles and walls (radius + 0.03), world units
    double min_clear = kPassableClearance;  // clearance a planned centre keeps at least (radius + 0.002), world units
    int narrow_cost = 8;          // extra cost of a step into a cell closer than `inflate`, steps, [0, 1000]
    double buffer = 0.04;         // planned centres of two agents stay >= 2 r + buffer apart (the filter keeps 2 r + 0.03), world units
    double conflict_cost = 8;     // extra cost of a step inside another agent's reservation, steps
    double give_way_buffer = 0.2; // a robot that gives way (ExpertTraffic) keeps this much more clear of planned robots, world units
    int hold = 1;                 // a planned position stays reserved from one step before to `hold` steps after, for lag
    int replan_every = 5;         // steps between plans, >= 1
    double replan_error = 0.1;    // replan early when an agent is this far from its waypoint, world units
    int extra_horizon = 20;       // plans may run this many steps past the episode's step limit, [0, kExpertMaxHorizon]
    int max_expansions = 200000;  // A* budget per agent and plan, >= 1 (its memory: <= ~56 bytes per expansion)
    double priority_weight = 4;   // safety-filter weight of the highest-priority agent (the lowest has 1), >= 1
    int stall_steps = 150;        // a robot no nearer its goal for this many steps plans first (0: never), >= 0
    TrackerParams tracker;
    SafetyFilterParams filter;
    RouteClearance route() const { return {min_clear, inflate, narrow_cost}; }
};

class GuidedExpert : public Policy {
public:
    explicit GuidedExpert(const WorldMap& map, ExpertParams p = ExpertParams{}, ExpertTraffic traffic = nullptr)
        : prm_(p), traffic_(std::move(traffic)) {
        if (prm_.replan_every < 1) throw std::invalid_argument("ExpertParams.replan_every: must be >= 1");
        if (prm_.extra_horizon < 0 || prm_.extra_horizon > kExpertMaxHorizon)
            throw std::invalid_argument("ExpertParams.extra_horizon: must be in [0, kExpertMaxHorizon = " + std::to_string(kExpertMaxHorizon) + "]");
        if (prm_.max_expansions < 1) throw std::invalid_argument("ExpertParams.max_expansions: must be >= 1");
        if (prm_.hold < 0) throw std::invalid_argument("ExpertParams.hold: must be >= 0");
        if (prm_.stall_steps < 0) throw std::invalid_argument("ExpertParams.stall_steps: must be >= 0 (got " + std::to_string(prm_.stall_steps) + ")");
        if (!(prm_.give_way_buffer >= 0 && prm_.give_way_buffer <= 1))
            throw std::invalid_argument("ExpertParams.give_way_buffer: must be in [0, 1] world units (got " + number_text(prm_.give_way_buffer) + ")");
        prm_.route().check("ExpertParams");
        guide_.cell = prm_.cell;
        guide_.clear = prm_.inflate;
        guide_.min_clear = prm_.min_clear;
        guide_.narrow_cost = prm_.narrow_cost;
        guide_.band = 0;  // its A* heuristic reads the field anywhere: whole fields
        guide_.grid(map);
    }

    std::vector<Vec2> act(const World& world) override {
        if (needs_plan(world)) {
            auto t0 = std::chrono::steady_clock::now();
            make_plan(world);
            total_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
            plans_++;
        }
        const auto& ag = world.agents();
        const int n = (int)ag.size();
        StepModel model(world.config());
        int k = world.t() - plan_t0_;
        std::vector<Vec2> u(n);
        std::vector<double> weight(n);
        for (int i = 0; i < n; ++i) {
            int pi = plan_index(ag[i].id);
            u[i] = track_plan(ag[i], plan_.waypoints[pi], k, model, prm_.tracker, world.config().max_action);
            weight[i] = priority_weight_of(rank_[pi], n, prm_.priority_weight);
        }
        return safety_filter(world, u, prm_.filter, weight);
    }
    double decision_ms() const override { return plans_ ? total_ms_ / plans_ : 0; }
    // The current plan: waypoints of every agent from the step it was made.
    const Plan& plan() const { return plan_; }
    // The planning grid: the route guide's (its side n <= kRouteMaxGridSide).
    const ClearanceGrid& grid() const { return guide_.grid(); }
    // Bytes of the planning workspace: the guide's grid and fields, the last search's states and
    // the last plan's reservations (capacities).
    size_t workspace_bytes() const { return guide_.workspace_bytes() + states_.bytes() + reserved_.bytes(); }
    const RouteGuide& guide() const { return guide_; }

private:
    ExpertParams prm_;
    ExpertTraffic traffic_;                   // where robots head when not their goals (none: their goals)
    std::vector<ExpertHeading> heading_;      // per agent, this plan
    RouteGuide guide_;                        // grid and wavefronts (shared representation, Section 12)
    std::map<int, int> initial_steps_;        // agent id -> route cost from its start
    struct Progress { int best = 0, since = -1; };  // the least route cost yet, and the step it was reached
    std::map<int, Progress> progress_;        // agent id -> its progress (stall_steps)
    Plan plan_;
    std::vector<int> rank_;                   // per plan entry: 0 = highest priority
    int plan_t0_ = 0, plans_ = 0;
    double total_ms_ = 0;
    detail::SpaceTimeStates states_;          // one search's states, reused
    detail::Reservations reserved_;           // the plan's reservations so far
    std::vector<detail::Reservations::Centre> near_;
    std::vector<int> slot_, line_slot_, depth_;  // plan_lines' scratch: per robot, its slot, its line's, its place in the line

    int plan_index(int id) const {
        for (size_t i = 0; i < plan_.ids.size(); ++i) if (plan_.ids[i] == id) return (int)i;
        return -1;
    }
    bool needs_plan(const World& world) const {
        if (plans_ == 0 || world.t() < plan_t0_ || world.t() - plan_t0_ >= prm_.replan_every) return true;
        if ((int)plan_.ids.size() != world.size()) return true;
        int k = world.t() - plan_t0_;
        for (const Agent& a : world.agents()) {
            int pi = plan_index(a.id);
            if (pi < 0) return true;
            const auto& w = plan_.waypoints[pi];
            // Position now vs the waypoint planned for now (none yet when k = 0).
            if (k >= 1 && norm(a.pos - waypoint_now(w, k)) > prm_.replan_error) return true;
        }
        return false;
    }
    // Chebyshev distance between two cells (steps on an open grid).
    static int chebyshev(int n, int a, int b) { return std::max(std::abs(a / n - b / n), std::abs(a % n - b % n)); }
    // The route cost from p to goal: the Chebyshev steps when the straight way is clear, else the wavefront's.
    int route_cost(const WorldMap& map, Vec2 p, Vec2 goal) {
        const ClearanceGrid& g = guide_.grid(map);
        if (guide_.straight(map, p, goal)) return chebyshev(g.n, g.index(p), g.index(goal));
        return guide_.route_steps(map, p, goal);
    }

    void make_plan(const World& world) {
        const auto& ag = world.agents();
        const int n = (int)ag.size();
        const ClearanceGrid& grid = guide_.grid(world.map());
        const double r = world.config().radius;
        // World steps planned (waypoints), and grid steps searched: one per `stretch` world steps.
        const int T_world = std::min(std::max(1, world.config().max_steps - world.t()), kExpertMaxHorizon) + prm_.extra_horizon;
        const int T = grid.stretch > 1 ? std::max(1, (int)std::ceil(T_world / grid.stretch)) : T_world;
        // Priority order: the longest route from where the robot was first seen goes first.
        for (int i = 0; i < n; ++i)
            if (!initial_steps_.count(ag[i].id)) initial_steps_[ag[i].id] = route_cost(world.map(), ag[i].pos, ag[i].goal);
        std::vector<int> order;
        // Stalled robots first (stall_steps; see the class comment).
        for (int i = 0; i < n; ++i) {
            Progress& p = progress_[ag[i].id];
            const bool arrived = world.at_goal(ag[i]);
            const int cost = arrived ? 0 : route_cost(world.map(), ag[i].pos, ag[i].goal);
            if (p.since < 0 || arrived || cost < p.best) p.best = cost, p.since = world.t();
        }
        auto key = [&](const Agent& a) {
            const long stalls = prm_.stall_steps > 0 ? (world.t() - progress_[a.id].since) / prm_.stall_steps : 0;
            if (stalls == 0) return (double)initial_steps_[a.id];
            return 1e9 + (double)(Rng((uint64_t)a.id << 32 ^ (uint64_t)stalls).next_u64() >> 40);
        };
        priority_order(world, key, order);
        heading_.resize(n);
        for (int i = 0; i < n; ++i) heading_[i] = ExpertHeading{ag[i].goal, {}, false};
        if (traffic_) {
            traffic_(world, guide_, heading_);
            std::stable_partition(order.begin(), order.end(), [&](int i) { return !heading_[i].gives_way; });
            plan_lines(order);
        }
        // Robots that give way keep give_way_buffer more clear (a wider disc); no wider reach
        // unless one does, so plans without a traffic rule search as before.
        const bool any_gives_way = std::any_of(heading_.begin(), heading_.end(), [](const ExpertHeading& h) { return h.gives_way; });
        reserved_.reset(grid.n, grid.cell, 2 * r + prm_.buffer, 2 * r + prm_.buffer + (any_gives_way ? prm_.give_way_buffer : 0));
        plan_ = Plan{};
        rank_.assign(n, 0);
        plan_.ids.resize(n);
        plan_.waypoints.resize(n);
        // The first waypoints blend from the robot's position onto the path's cell centres.
        const double blend = std::max((double)prm_.replan_every, 2 * grid.stretch);
        std::vector<int> step_cells;
        for (int rank = 0; rank < n; ++rank) {
            int i = order[rank];
            std::vector<int> path = search(world.map(), ag[i].pos, heading_[i], T);
            // Reserve the path's discs at each step t: its centres from `hold` steps before to
            // one after (tracking lags the plan), each distinct centre once.
            for (int t = 1; t <= T; ++t) {
                step_cells.clear();
                for (int ts = std::max(1, t - prm_.hold); ts <= std::min(T, t + 1); ++ts) {
                    const int c = path[std::min(ts, (int)path.size() - 1)];
                    if (std::find(step_cells.begin(), step_cells.end(), c) == step_cells.end()) step_cells.push_back(c);
                }
                for (int c : step_cells) reserved_.add(rank, t, c);
            }
            // Waypoints: cell centres, the exact target in its cell; on a coarsened grid,
            // points along the path at 1 / stretch cells per world step.
            const Vec2 target = heading_[i].target;
            const int target_cell = grid.index(target);
            auto point = [&](int step) {
                int c = path[std::min(step, (int)path.size() - 1)];
                return c == target_cell ? target : grid.centre(c);
            };
            const Vec2 offset = ag[i].pos - point(0);
            std::vector<Vec2> w;
            for (int t = 1; t <= T_world; ++t) {
                Vec2 at_t;
                if (grid.stretch == 1) {
                    at_t = point(t);
                } else {
                    const double at = t / grid.stretch;
                    const int k0 = (int)std::floor(at);
                    const double frac = at - k0;
                    const Vec2 a = point(k0);
                    at_t = frac > 0 ? a + (point(k0 + 1) - a) * frac : a;
                }
                w.push_back(at_t + offset * std::max(0.0, 1 - t / blend));
            }
            plan_.ids[i] = ag[i].id;
            plan_.waypoints[i] = std::move(w);
            rank_[i] = rank;
        }
        plan_t0_ = world.t();
    }

    // Robots that follow another (ExpertHeading::after) are planned in a line at the slot of its
    // head (the robot no one is ahead of), then by how far down the line a robot is. Planned before
    // the robot ahead, a robot behind it in a one-lane aisle routes through it, and the one ahead,
    // planned around that, cannot go on (maze-32-32-4: the knot at the bottom aisle's left mouth;
    // docs/experiments.md, "The expert's line through an aisle").
    void plan_lines(std::vector<int>& order) {
        const int n = (int)order.size();
        if (std::none_of(heading_.begin(), heading_.end(), [n](const ExpertHeading& h) { return h.after >= 0 && h.after < n; })) return;
        slot_.resize(n), line_slot_.resize(n), depth_.resize(n);
        for (int r = 0; r < n; ++r) slot_[order[r]] = r;
        for (int i = 0; i < n; ++i) {
            int head = i, depth = 0;  // at most n links: a cycle (never made by PassageControl) ends there
            while (depth < n && heading_[head].after >= 0 && heading_[head].after < n) head = heading_[head].after, ++depth;
            line_slot_[i] = slot_[head], depth_[i] = depth;
        }
        std::sort(order.begin(), order.end(), [&](int a, int b) {
            return std::tie(line_slot_[a], depth_[a], slot_[a]) < std::tie(line_slot_[b], depth_[b], slot_[b]);
        });
    }

    // Space-time A* for one agent at `pos` to heading.target against the current reservations,
    // keeping out of heading.closed; returns cells for t = 0 .. arrival (the agent stays at the
    // last cell afterwards).
    std::vector<int> search(const WorldMap& map, Vec2 pos, const ExpertHeading& heading, int T) {
        const ClearanceGrid& grid = guide_.grid();
        const int n = grid.n;
        const int start = grid.index(pos), goal = grid.index(heading.target);
        const ClosedCells closed = heading.closed;
        const RouteClearance route = prm_.route();
        // The heuristic: the wavefront, or the Chebyshev steps when the straight way is open.
        const RouteField* field = guide_.straight(map, pos, heading.target, closed) ? nullptr : &guide_.steps_to(map, heading.target, closed);
        auto h = [&](int c) { return (float)std::max(field ? (*field)[c] : -1, chebyshev(n, c, goal)); };
        // A start pushed into the clearance band may move through cells no worse than its own.
        const float floor_clear = std::min((float)route.min, grid.clear[start]) - 1e-6f;
        auto allowed = [&](int c) { return (grid.clear[c] >= floor_clear || c == goal) && (c == start || !closed.closes(c)); };
        // Charge for staying at the goal from step t on while others pass through it.
        std::vector<float> stay(T + 2, 0.f);
        for (int t = T; t >= 1; --t) {
            reserved_.near(t, goal, near_);
            stay[t] = stay[t + 1] + (float)prm_.conflict_cost * reserved_.count(near_, goal, heading.gives_way);
        }
        stay[0] = stay[1];
        struct Node { float f, g; int state; };
        auto worse = [](const Node& x, const Node& y) { return x.f != y.f ? x.f > y.f : x.g < y.g; };
        std::priority_queue<Node, std::vector<Node>, decltype(worse)> open(worse);
        states_.clear();
        const int s0 = states_.find_or_add(0, start);
        states_.nodes[s0].g = 0;
        open.push({h(start), 0, s0});
        int best_end = -1, closest = s0;
        float best_total = std::numeric_limits<float>::infinity();
        for (int expansions = 0; !open.empty() && expansions < prm_.max_expansions; ++expansions) {
            Node node = open.top();
            open.pop();
            if (node.f >= best_total) break;
            const detail::SpaceTimeStates::Node st = states_.nodes[node.state];  // a copy: the list grows below
            if (node.g > st.g) continue;
            const int t = st.t, c = st.cell;
            if (c == goal) {
                float total = node.g + stay[t + 1];
                if (total < best_total) { best_total = total; best_end = node.state; }
            }
            const detail::SpaceTimeStates::Node& cl = states_.nodes[closest];
            if (h(c) < h(cl.cell) || (h(c) == h(cl.cell) && t < cl.t)) closest = node.state;
            if (t == T) {
                if (best_end < 0) { best_end = node.state; break; }  // the horizon, before any cheaper arrival
                continue;
            }
            reserved_.near(t + 1, c, near_);
            const int row = c / n, col = c % n;
            for (int dr = -1; dr <= 1; ++dr)
                for (int dc = -1; dc <= 1; ++dc) {
                    int r2 = row + dr, c2 = col + dc;
                    if (r2 < 0 || r2 >= n || c2 < 0 || c2 >= n) continue;
                    int k2 = r2 * n + c2;
                    if (!allowed(k2)) continue;
                    // One step (more into a narrow cell); a hair more for diagonals so straight runs win ties.
                    float g2 = node.g + (float)route.step_cost(grid.clear[k2]) + (dr && dc ? 1e-3f : 0.f) +
                               (float)prm_.conflict_cost * (near_.empty() ? 0 : reserved_.count(near_, k2, heading.gives_way));
                    const int s2 = states_.find_or_add(t + 1, k2);
                    if (states_.nodes[s2].g <= g2) continue;
                    states_.nodes[s2].g = g2;
                    states_.nodes[s2].parent = node.state;
                    open.push({g2 + h(k2), g2, s2});
                }
        }
        int end = best_end >= 0 ? best_end : closest;
        std::vector<int> path;
        for (int s = end; s >= 0; s = states_.nodes[s].parent) path.push_back(states_.nodes[s].cell);
        std::reverse(path.begin(), path.end());
        return path;
    }
};

// ---------------------------------------------------------------------------------------------
// The default step limit of a scene (eval and render --scene): twice the longest robot's
// shortest route at cruise speed, and never below default_max_steps(half-size), so that a maze
// does not time out by default. A route is a walk on a grid of kStepLimitCell cells (at most
// kStepLimitGridSide a side: a larger world gets coarser cells) through the cell centres a robot
// of `radius` fits at, one cell per move in 8 directions: at cruise a robot covers
// ExpertParams::cell (0.036) per step along each axis, so a move takes cell / 0.036 steps. Its
// own grid, coarser than the routing grid's and with a plain fit at the robot's radius: a
// 0.3-wide aisle leaves a 0.1-wide band for a robot's centre, which 0.05 cells always sample. A
// robot with no route on the grid counts its straight (Chebyshev) distance. Memory: 12 bytes a
// cell (12 MiB at most); time: one wavefront per robot.
constexpr double kStepLimitCell = 0.05;
constexpr int kStepLimitGridSide = 1024;
namespace detail {
// `cg.clear` on its layout: 1 where a robot centre of `radius` fits (clear of walls and
// obstacles), else 0. Each obstacle marks only the cells near it: thousands of boxes stay fast.
inline void fill_fits(ClearanceGrid& cg, const WorldMap& map, double radius) {
    const int n = cg.n;
    cg.clear.assign((size_t)n * n, 1.f);
    auto mark = [&](Vec2 lo, Vec2 hi, auto&& blocks) {  // cells with centres in [lo, hi] that blocks(centre)
        auto index = [&](double v) { return std::clamp((int)std::floor((v + cg.half) / cg.cell), 0, n - 1); };
        for (int row = index(lo.y); row <= index(hi.y); ++row)
            for (int col = index(lo.x); col <= index(hi.x); ++col)
                if (blocks(cg.centre(row * n + col))) cg.clear[(size_t)row * n + col] = 0;
    };
    const double h = map.half_size;
    mark({-h, -h}, {h, h}, [&](Vec2 p) { return std::max(std::fabs(p.x), std::fabs(p.y)) > h - radius; });
    for (const Disc& d : map.discs) {
        const double r = d.r + radius;
        mark(d.c - Vec2{r, r}, d.c + Vec2{r, r}, [&](Vec2 p) { return norm(p - d.c) < r; });
    }
    for (const Box& b : map.boxes)
        mark(b.lo - Vec2{radius, radius}, b.hi + Vec2{radius, radius}, [&](Vec2 p) { return box_distance(b, p) < radius; });
}
}  // namespace detail
inline int scene_step_limit(const Scene& scene, double radius = 0.1) {
    ClearanceGrid cg(scene.map, kStepLimitCell, kStepLimitGridSide, /*fill=*/false);
    detail::fill_fits(cg, scene.map, radius);
    const double steps_per_move = cg.cell / ExpertParams{}.cell;
    double longest = 0;
    for (size_t i = 0; i < scene.starts.size(); ++i) {
        const std::vector<int> steps = wavefront(cg, cg.index(scene.goals[i]), 0.5);
        const int k = cg.index(scene.starts[i]);
        int moves = steps[k];  // a start whose cell centre is too near the map: from a neighbour
        if (moves < 0)
            detail::for_each_neighbour(cg.n, k, [&](int k2) { if (steps[k2] >= 0 && (moves < 0 || steps[k2] + 1 < moves)) moves = steps[k2] + 1; });
        const Vec2 d = scene.goals[i] - scene.starts[i];
        const double cells = moves >= 0 ? moves : std::max(std::fabs(d.x), std::fabs(d.y)) / cg.cell;
        longest = std::max(longest, cells * steps_per_move);
    }
    return std::max(default_max_steps(scene.map.half_size), (int)std::ceil(2 * longest - 1e-9));
}

// =============================================================================================
// Section 13. SVG rendering (SPEC 2)
// =============================================================================================

// A static picture of an episode (map, goals, trajectories, start and end discs, collisions
// as red crosses) or, with `animate`, an SVG whose agents move in real time (SMIL
// <animate>, plays in browsers) over faint trajectories. `title` is written at the top.
struct SvgOptions {
    bool animate = false;
    double pixels_per_unit = 200;  // scale, > 0; lowered so that the picture is at most kMaxSvgPixels wide
    std::string title;
};
namespace detail {
inline const char* agent_colour(int id) {
    static const char* palette[] = {"#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b",
                                    "#e377c2", "#7f7f7f", "#bcbd22", "#17becf", "#393b79", "#ad494a"};
    return palette[((id % 12) + 12) % 12];
}
inline std::string fmt(double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%.1f", v);
    return b;
}
}  // namespace detail
inline std::string render_svg(const EpisodeLog& log, const SvgOptions& opt = SvgOptions{}) {
    MADBP_ASSERT(!log.frames.empty());
    if (!(log.map.half_size > 0) || !std::isfinite(log.map.half_size) || !(opt.pixels_per_unit > 0) || !std::isfinite(opt.pixels_per_unit))
        throw std::invalid_argument("render_svg: needs a finite half_size > 0 and pixels_per_unit > 0");
    double h = log.map.half_size, S = std::min(opt.pixels_per_unit, kMaxSvgPixels / (2 * h)), top = opt.title.empty() ? 0 : 24;
    auto X = [&](double x) { return detail::fmt((x + h) * S); };
    auto Y = [&](double y) { return detail::fmt((h - y) * S + top); };
    auto L = [&](double l) { return detail::fmt(l * S); };
    std::ostringstream o;
    double W = 2 * h * S;
    o << "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"" << detail::fmt(W) << "\" height=\"" << detail::fmt(W + top)
      << "\" viewBox=\"0 0 " << detail::fmt(W) << " " << detail::fmt(W + top) << "\">\n";
    o << "<rect x=\"0\" y=\"0\" width=\"" << detail::fmt(W) << "\" height=\"" << detail::fmt(W + top) << "\" fill=\"white\"/>\n";
    if (!opt.title.empty()) {
        std::string t;
        for (char c : opt.title) t += c == '<' ? std::string("&lt;") : c == '&' ? std::string("&amp;") : std::string(1, c);
        o << "<text x=\"6\" y=\"17\" font-family=\"sans-serif\" font-size=\"14\">" << t << "</text>\n";
    }
    o << "<rect x=\"0\" y=\"" << detail::fmt(top) << "\" width=\"" << detail::fmt(W) << "\" height=\"" << detail::fmt(W)
      << "\" fill=\"#fafafa\" stroke=\"black\" stroke-width=\"3\"/>\n";
    for (const Disc& d : log.map.discs)
        o << "<circle cx=\"" << X(d.c.x) << "\" cy=\"" << Y(d.c.y) << "\" r=\"" << L(d.r) << "\" fill=\"#555\"/>\n";
    for (const Box& b : log.map.boxes)
        o << "<rect x=\"" << X(b.lo.x) << "\" y=\"" << Y(b.hi.y) << "\" width=\"" << L(b.hi.x - b.lo.x) << "\" height=\""
          << L(b.hi.y - b.lo.y) << "\" fill=\"#555\"/>\n";
    // Per agent id: its track (frames where present) and goal.
    std::map<int, std::vector<std::pair<int, Vec2>>> tracks;
    std::map<int, Vec2> goals;
    for (size_t t = 0; t < log.frames.size(); ++t)
        for (size_t i = 0; i < log.frames[t].ids.size(); ++i) {
            tracks[log.frames[t].ids[i]].push_back({(int)t, log.frames[t].pos[i]});
            goals[log.frames[t].ids[i]] = log.frames[t].goal[i];
        }
    for (auto& kv : goals)
        o << "<circle cx=\"" << X(kv.second.x) << "\" cy=\"" << Y(kv.second.y) << "\" r=\"" << L(log.goal_tolerance)
          << "\" fill=\"none\" stroke=\"" << detail::agent_colour(kv.first) << "\" stroke-width=\"2\" stroke-dasharray=\"4 3\"/>\n";
    for (auto& kv : tracks) {
        const char* col = detail::agent_colour(kv.first);
        o << "<polyline fill=\"none\" stroke=\"" << col << "\" stroke-width=\"2\" stroke-opacity=\"" << (opt.animate ? "0.25" : "0.8")
          << "\" points=\"";
        for (auto& tp : kv.second) o << X(tp.second.x) << "," << Y(tp.second.y) << " ";
        o << "\"/>\n";
        Vec2 first = kv.second.front().second, last = kv.second.back().second;
        if (!opt.animate) {
            o << "<circle cx=\"" << X(first.x) << "\" cy=\"" << Y(first.y) << "\" r=\"" << L(log.radius) << "\" fill=\"" << col
              << "\" fill-opacity=\"0.25\"/>\n";
            o << "<circle cx=\"" << X(last.x) << "\" cy=\"" << Y(last.y) << "\" r=\"" << L(log.radius) << "\" fill=\"" << col
              << "\" fill-opacity=\"0.85\"/>\n";
            continue;
        }
        // Animated disc: positions per frame; hidden in frames where the agent is absent.
        size_t T = log.frames.size();
        std::string xs, ys, vis;
        size_t k = 0;
        Vec2 cur = first;
        for (size_t t = 0; t < T; ++t) {
            bool here = k < kv.second.size() && kv.second[k].first == (int)t;
            if (here) cur = kv.second[k++].second;
            xs += X(cur.x) + (t + 1 < T ? ";" : "");
            ys += Y(cur.y) + (t + 1 < T ? ";" : "");
            vis += std::string(here ? "1" : "0") + (t + 1 < T ? ";" : "");
        }
        std::string dur = detail::fmt(std::max<size_t>(T - 1, 1) * log.dt) + "s";
        o << "<circle r=\"" << L(log.radius) << "\" fill=\"" << col << "\" fill-opacity=\"0.85\" cx=\"" << X(first.x) << "\" cy=\""
          << Y(first.y) << "\">\n";
        o << "  <animate attributeName=\"cx\" dur=\"" << dur << "\" repeatCount=\"indefinite\" values=\"" << xs << "\"/>\n";
        o << "  <animate attributeName=\"cy\" dur=\"" << dur << "\" repeatCount=\"indefinite\" values=\"" << ys << "\"/>\n";
        o << "  <animate attributeName=\"opacity\" dur=\"" << dur << "\" repeatCount=\"indefinite\" calcMode=\"discrete\" values=\"" << vis << "\"/>\n";
        o << "</circle>\n";
    }
    for (const Frame& f : log.frames)
        for (Vec2 c : f.collisions) {
            double a = 0.04;
            o << "<path d=\"M" << X(c.x - a) << "," << Y(c.y - a) << " L" << X(c.x + a) << "," << Y(c.y + a) << " M" << X(c.x - a) << ","
              << Y(c.y + a) << " L" << X(c.x + a) << "," << Y(c.y - a) << "\" stroke=\"red\" stroke-width=\"2\"/>\n";
        }
    o << "</svg>\n";
    return o.str();
}
// Writes `text` to `path` (write_file_atomic).
inline void write_text_file(const std::string& path, const std::string& text) { write_file_atomic(path, text); }

}  // namespace madbp

#endif  // MADBP_SIM_HPP
