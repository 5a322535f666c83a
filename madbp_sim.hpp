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
//   0.1  world, maps, controllers.

#ifndef MADBP_SIM_HPP
#define MADBP_SIM_HPP

#define MADBP_VERSION_MAJOR 0
#define MADBP_VERSION_MINOR 1
#define MADBP_VERSION_PATCH 0

#ifndef MADBP_ASSERT
#include <cassert>
#define MADBP_ASSERT(cond) assert(cond)
#endif

#include <chrono>
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
// Progress line for long work: "label  120/1000  37.2/s  ETA 24s" rewritten in place on a
// terminal (stderr), silent when stderr is not a terminal (CI logs) or when quiet.
struct ProgressLine {
    std::string label;
    long total = 0, done = 0;
    bool enabled = false;
    std::chrono::steady_clock::time_point start, last_print;

    ProgressLine(std::string label_, long total_, bool quiet = false)
        : label(std::move(label_)), total(total_), enabled(!quiet && isatty(2)),
          start(std::chrono::steady_clock::now()), last_print(start) {}
    // Advance by `k` units; `extra` is appended (e.g. the current loss).
    void tick(long k = 1, const std::string& extra = "") {
        done += k;
        if (!enabled) return;
        auto now = std::chrono::steady_clock::now();
        if (done < total && now - last_print < std::chrono::milliseconds(200)) return;
        last_print = now;
        double secs = std::chrono::duration<double>(now - start).count();
        double rate = secs > 0 ? done / secs : 0;
        double eta = rate > 0 ? (total - done) / rate : 0;
        std::fprintf(stderr, "\r%s  %ld/%ld  %.1f/s  ETA %.0fs  %s\033[K", label.c_str(), done,
                     total, rate, eta, extra.c_str());
        if (done >= total) std::fprintf(stderr, "\n");
        std::fflush(stderr);
    }
    ~ProgressLine() {
        if (enabled && done < total) std::fprintf(stderr, "\n");
    }
};

// Throws std::invalid_argument("<field>: <why>") when a value is not finite.
inline void require_finite(double v, const std::string& field) {
    if (!std::isfinite(v)) throw std::invalid_argument(field + ": value is not finite (" + std::to_string(v) + ")");
}

}  // namespace madbp

// ============================ WORLD AND CONTROLLERS BELOW ===================================

#include <algorithm>
#include <array>
#include <fstream>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <queue>
#include <sstream>
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
struct Map {
    double half_size = 1.2;
    std::vector<Disc> discs;
    std::vector<Box> boxes;
};

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

// Distance from `p` to the nearest static surface of `map` (obstacle or border wall), and the
// unit direction pointing away from it. Negative when `p` is inside an obstacle.
inline double static_clearance(const Map& map, Vec2 p, Vec2* away = nullptr) {
    double h = map.half_size;
    double best = h - p.x;
    Vec2 dir{-1, 0};
    auto consider = [&](double d, Vec2 a) { if (d < best) { best = d; dir = a; } };
    consider(p.x + h, {1, 0});
    consider(h - p.y, {0, -1});
    consider(p.y + h, {0, 1});
    for (const Disc& o : map.discs) {
        Vec2 d = p - o.c;
        double n = norm(d);
        consider(n - o.r, n > 0 ? d / n : Vec2{1, 0});
    }
    for (const Box& b : map.boxes) {
        Vec2 a;
        double d = box_distance(b, p, &a);
        consider(d, a);
    }
    if (away) *away = dir;
    return best;
}

// True when `p` lies inside an obstacle (not the border walls), or outside the world.
inline bool inside_obstacle(const Map& map, Vec2 p) {
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
// world with one gap of width 0.5. Throws std::invalid_argument on an unknown name.
inline Map make_map(const std::string& name, Rng& rng, double half_size = 1.2) {
    if (!(half_size > 0.5) || !std::isfinite(half_size))
        throw std::invalid_argument("half_size: must be a finite number > 0.5 (got " + std::to_string(half_size) + ")");
    double scale = half_size / 1.2;
    Map map;
    map.half_size = half_size;
    if (name == "empty") return map;
    if (name == "obstacles") {
        // 5 discs of radius 0.1 (VMAS "flocking"), >= 0.15 apart surface to surface.
        int count = (int)std::lround(5 * scale * scale);
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
    explicit World(Map map = Map{}, WorldConfig cfg = WorldConfig{}) : map_(std::move(map)), cfg_(cfg) {
        require_finite(map_.half_size, "map.half_size");
        if (!(map_.half_size > 0)) throw std::invalid_argument("map.half_size: must be > 0");
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
    // id must not be in use (std::invalid_argument otherwise).
    int add_agent(Vec2 start, Vec2 goal, int id = -1) {
        check_point(start, "start", cfg_.radius);
        check_point(goal, "goal", cfg_.radius);
        if (id >= 0 && index_of(id) >= 0) throw std::invalid_argument("add_agent: duplicate agent id " + std::to_string(id));
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
    const Map& map() const { return map_; }
    const WorldConfig& config() const { return cfg_; }
    const Metrics& metrics() const { return metrics_; }
    int t() const { return metrics_.steps; }
    // The episode is over: success, or max_steps taken.
    bool done() const { return metrics_.success || metrics_.steps >= cfg_.max_steps; }
    bool at_goal(const Agent& a) const { return norm(a.pos - a.goal) < cfg_.goal_tolerance; }
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

    // Contact force on a disc of this world's radius at `p` from obstacles and walls.
    Vec2 static_contact_force(Vec2 p) const {
        Vec2 f{0, 0};
        double r = cfg_.radius, reach = r + kContactCutoff * cfg_.contact_k, h = map_.half_size;
        if (h - p.x < reach) f.x -= penetration_force(h - p.x, r);
        if (p.x + h < reach) f.x += penetration_force(p.x + h, r);
        if (h - p.y < reach) f.y -= penetration_force(h - p.y, r);
        if (p.y + h < reach) f.y += penetration_force(p.y + h, r);
        for (const Disc& o : map_.discs) {
            Vec2 d = p - o.c;
            double dist = norm(d);
            if (dist > 0 && dist < o.r + reach) f += d / dist * penetration_force(dist, o.r + r);
        }
        for (const Box& b : map_.boxes) {
            Vec2 away;
            double dist = box_distance(b, p, &away);
            if (dist < reach) f += away * penetration_force(dist, r);
        }
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

    Map map_;
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
        double r = cfg_.radius, h = map_.half_size;
        for (size_t i = 0; i < agents_.size(); ++i) {
            Vec2 p = agents_[i].pos;
            for (size_t j = i + 1; j < agents_.size(); ++j)
                if (norm(p - agents_[j].pos) < 2 * r) last_agent_contacts_.push_back({agents_[i].id, agents_[j].id});
            int hits = (h - p.x < r) + (p.x + h < r) + (h - p.y < r) + (p.y + h < r);
            for (const Disc& o : map_.discs) hits += norm(p - o.c) < o.r + r;
            for (const Box& b : map_.boxes) hits += box_distance(b, p) < r;
            for (int k = 0; k < hits; ++k) last_static_contacts_.push_back(agents_[i].id);
        }
        metrics_.agent_collisions += (long)last_agent_contacts_.size();
        metrics_.obstacle_collisions += (long)last_static_contacts_.size();
    }
};

// =============================================================================================
// Section 4. Spawning (SPEC 2)
// =============================================================================================

// Draws `n` starts and then `n` goals by rejection sampling: uniform in [-1, 1]^2 scaled by
// half_size/1.2; every centre >= `min_separation` (0.25) from every earlier centre (starts and
// goals alike) and >= radius + 0.05 from any obstacle or wall surface. Each point gets at most
// `max_tries` draws; a layout that cannot be placed throws std::runtime_error (never hangs).
struct SpawnConfig {
    double min_separation = 0.25;  // between centres, world units
    double clearance = 0.05;       // extra gap to obstacle and wall surfaces beyond the radius
    int max_tries = 20000;         // draws per point before giving up
};
inline void spawn_agents(World& world, int n, Rng& rng, const SpawnConfig& sc = SpawnConfig{}) {
    if (n < 0) throw std::invalid_argument("agents: must be >= 0 (got " + std::to_string(n) + ")");
    const Map& map = world.map();
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
        throw std::runtime_error(std::string("spawn: could not place ") + what + " " + std::to_string(k) + " of " +
                                 std::to_string(n) + " after " + std::to_string(sc.max_tries) + " tries (world too crowded)");
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
#pragma omp parallel for schedule(static)
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
inline Grid occupancy_grid(const Map& map, int size = 32) {
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

// =============================================================================================
// Section 6. Scene files (SPEC 2)
// =============================================================================================

// A whole problem given by hand: a map plus agents' starts and goals.
struct Scene {
    Map map;
    std::vector<Vec2> starts, goals;
};

// Parses the line-based scene format:
//   madbp-scene 1               header, first non-comment line
//   world H                     half-size of the square world (optional, default 1.2, once)
//   disc X Y R                  static disc obstacle
//   box X0 Y0 X1 Y1             static axis-aligned box, X0 < X1, Y0 < Y1
//   agent SX SY GX GY           one robot: start, goal
// '#' starts a comment. Errors are std::invalid_argument("<source>:<line>: <why>"). Checks:
// numbers finite, radii > 0, starts and goals inside the walls (|x|,|y| <= H - 0.1), starts
// >= 0.2 apart (no overlap), goals >= 0.2 apart, starts and goals >= 0.1 clear of every
// obstacle surface. A start may coincide with another agent's goal (swaps).
inline Scene parse_scene(const std::string& text, const std::string& source = "scene", double radius = 0.1) {
    Scene scene;
    std::vector<int> agent_lines;
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
            if (tok[1] != "1") fail(line_no, "unsupported scene version '" + tok[1] + "' (this reader knows 1)");
            header = true;
            continue;
        }
        const std::string& kw = tok[0];
        size_t want = kw == "world" ? 1 : kw == "disc" ? 3 : kw == "box" ? 4 : kw == "agent" ? 4 : 0;
        if (want == 0) fail(line_no, "unknown keyword '" + kw + "' (expected world, disc, box or agent)");
        if (tok.size() != want + 1)
            fail(line_no, "'" + kw + "' takes " + std::to_string(want) + " numbers, got " + std::to_string(tok.size() - 1));
        double v[4];
        for (size_t k = 0; k < want; ++k) {
            size_t pos = 0;
            try { v[k] = std::stod(tok[k + 1], &pos); } catch (...) { pos = 0; }
            if (pos != tok[k + 1].size()) fail(line_no, "'" + tok[k + 1] + "' is not a number");
            if (!std::isfinite(v[k])) fail(line_no, "'" + tok[k + 1] + "' is not finite");
        }
        if (kw == "world") {
            if (world_seen) fail(line_no, "'world' given twice");
            if (!scene.starts.empty() || !scene.map.discs.empty() || !scene.map.boxes.empty())
                fail(line_no, "'world' must come before obstacles and agents");
            if (!(v[0] > 2 * radius)) fail(line_no, "world half-size must be > " + std::to_string(2 * radius));
            scene.map.half_size = v[0];
            world_seen = true;
        } else if (kw == "disc") {
            if (!(v[2] > 0)) fail(line_no, "disc radius must be > 0");
            scene.map.discs.push_back({{v[0], v[1]}, v[2]});
        } else if (kw == "box") {
            if (!(v[0] < v[2] && v[1] < v[3])) fail(line_no, "box needs x0 < x1 and y0 < y1");
            scene.map.boxes.push_back({{v[0], v[1]}, {v[2], v[3]}});
        } else {
            scene.starts.push_back({v[0], v[1]});
            scene.goals.push_back({v[2], v[3]});
            agent_lines.push_back(line_no);
        }
    }
    if (!header) fail(line_no, "empty scene: expected the header 'madbp-scene 1'");
    if (scene.starts.empty()) fail(line_no, "no 'agent' line");
    // Validation needs the whole map, so it runs after parsing; errors name the agent's line.
    double lim = scene.map.half_size - radius;
    for (size_t i = 0; i < scene.starts.size(); ++i) {
        for (int which = 0; which < 2; ++which) {
            Vec2 p = which == 0 ? scene.starts[i] : scene.goals[i];
            const char* name = which == 0 ? "start" : "goal";
            if (std::fabs(p.x) > lim || std::fabs(p.y) > lim)
                fail(agent_lines[i], std::string(name) + " is outside the world (|x|, |y| must be <= " + std::to_string(lim) + ")");
            Map obstacles_only = scene.map;
            obstacles_only.half_size = 1e9;  // walls were checked just above
            if (static_clearance(obstacles_only, p) < radius) fail(agent_lines[i], std::string(name) + " overlaps an obstacle");
            const std::vector<Vec2>& same = which == 0 ? scene.starts : scene.goals;
            for (size_t j = 0; j < i; ++j)
                if (norm(same[j] - p) < 2 * radius)
                    fail(agent_lines[i], std::string(name) + " overlaps the " + name + " of the agent on line " + std::to_string(agent_lines[j]));
        }
    }
    return scene;
}
inline Scene load_scene(const std::string& path) {
    std::ifstream f(path);
    if (!f) throw std::runtime_error(path + ": cannot open scene file");
    std::stringstream ss;
    ss << f.rdbuf();
    return parse_scene(ss.str(), path);
}
// The scene format of a world's current problem (agents at their current positions).
inline std::string scene_text(const World& world) {
    std::ostringstream o;
    o.precision(17);
    o << "madbp-scene 1\nworld " << world.map().half_size << "\n";
    for (const Disc& d : world.map().discs) o << "disc " << d.c.x << " " << d.c.y << " " << d.r << "\n";
    for (const Box& b : world.map().boxes) o << "box " << b.lo.x << " " << b.lo.y << " " << b.hi.x << " " << b.hi.y << "\n";
    for (const Agent& a : world.agents()) o << "agent " << a.pos.x << " " << a.pos.y << " " << a.goal.x << " " << a.goal.y << "\n";
    return o.str();
}
inline World make_world(const Scene& scene, WorldConfig cfg = WorldConfig{}) {
    World world(scene.map, cfg);
    for (size_t i = 0; i < scene.starts.size(); ++i) world.add_agent(scene.starts[i], scene.goals[i]);
    return world;
}

}  // namespace madbp

#endif  // MADBP_SIM_HPP
