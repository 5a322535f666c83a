// madbp_train.hpp - demonstrations, datasets, the multi-term loss and training of MA-DBP.
// Part of madbp (Multi-Agent Diffusion Based Planner), header-only C++17. MIT licence.
//
// What it is
//   SPEC.md section 7: record demonstrations from a demonstrator (the guided expert, or any
//   Policy), cut them into moving windows, and train the MA-DBP denoiser with the paper's
//   curriculum over agent counts and its loss W . [L_noise, L_boundary, L_temporal,
//   L_collision], Adam, gradient clipping, weight EMA, atomic resumable checkpoints.
//
// Use
//   #include "madbp_train.hpp"
//   madbp::CollectConfig cc;                                   // maps, n = 1..4, episodes
//   madbp::DemoSet demos = madbp::collect_demonstrations(cc, madbp::expert_demonstrator(), "expert");
//   madbp::save_demos("demos.bin", demos);
//   madbp::TrainConfig tc;  tc.out = "model.safetensors";
//   madbp::train(demos, madbp::ModelConfig{}, tc);             // writes model + training state
//   madbp::DaggerConfig dg; dg.train.out = "dagger.safetensors";  // rounds of rollouts + expert labels
//   madbp::dagger(demos, model, dg, learner);                  // learner(model) -> PolicyFactory
//   madbp::MappoConfig mc; mc.map = "empty"; mc.agents = 4; madbp::train_mappo(mc);   // MAPPO
//   madbp::MadiffConfig dc; dc.agents = 2; madbp::MadiffTrainConfig dt; dt.out = "madiff.safetensors";
//   madbp::train_madiff(demos, dc, dt);                        // MADiff baseline (SPEC 3.4)
//
// Configuration macros: none beyond madbp.hpp's.
//
// Changelog
//   0.4  mappo_reward: one function for the MAPPO reward terms (the tool's --reward-* flags);
//        it takes the shaping distance before and after the step (straight or RouteDistance).
//        MappoObservation (lidar rays and range, the goal or the route goal) travels in MAPPO
//        and MADiff files; the constant kMappoObsLayout is gone (MappoObservation{}.layout()).
//   0.3  ModelConfig's velocity and priority contexts removed: DemoRoutes::first is gone.
//   0.2  TrainState: one resumable scaffold, with run identity, for train, MAPPO and MADiff.
//        Curve records (the tool draws the charts); ProgressFn; grad_clip names.
//        DAgger: dagger, expert_label, dagger_rollouts.
//        make_windows takes only the complete windows of unsuccessful recordings.
//        for_each_collect_episode.
//        DemoRoutes::first: the priority keys of ModelConfig::priority_context.
//   0.1  demonstrations, datasets, losses, training, MAPPO, MADiff.
//
// Contents (SPEC sections of docs/design.md in brackets)
//   1 demonstrations: Demonstration, DemoSet, CollectConfig, for_each_collect_episode,
//     collect_demonstrations                                                                [7]
//   2 datasets: demos_bytes, save_demos, load_demos, validate_demos                        [11]
//   3 losses: boundary_loss, temporal_loss, collision_loss                                  [7]
//   4 training batches: TrainConfig, WindowRef, DemoRoutes, route_demos, TrainBatch,
//     make_train_batch, make_windows                                                      [7]
//   5 the loss: LossTerms, diffusion_loss                                                   [7]
//   6 training scaffold: optimizer-state I/O (append/read_adam, _ema, _rng), Curve,
//     content_hash, TrainState (identity, resume, atomic state files)                      [11, 12]
//   7 training: TrainReport, curriculum_agents, train_identity, train                       [7]
//   7b DAgger: expert_label, dagger_rollouts, DaggerConfig, DaggerRound, dagger (issue 12)
//   8 MAPPO: observations (MappoObservation, mappo_observe), MappoNet, PPO loss, MappoRewards,
//     RouteDistance, mappo_reward, MappoConfig, train_mappo, MappoPolicy                  [3.3]
//   9 MADiff: MadiffConfig, InverseDynamics, MadiffModel, data, loss, train_madiff,
//     MadiffPolicy                                                                          [3.4]

#ifndef MADBP_TRAIN_HPP
#define MADBP_TRAIN_HPP

#include "madbp.hpp"
#if MADBP_VERSION_MAJOR != 0 || MADBP_VERSION_MINOR != 4
#error "madbp_train.hpp is release 0.4; the madbp.hpp it includes is another release"
#endif

#include <array>
#include <cstring>
#include <fstream>
#include <functional>
#include <mutex>

namespace madbp {

// =============================================================================================
// Section 1. Demonstrations (SPEC 7)
// =============================================================================================

// One recorded episode of a fixed team. Frame t = 0 is the start; frame t holds the state
// after t steps. Arrays are frame-major: pos[t * agents + i].
struct Demonstration {
    std::string map_name;
    WorldMap map;
    int agents = 0, steps = 0;  // frames = steps + 1
    bool success = false;
    std::vector<Vec2> goals;            // (agents)
    std::vector<Vec2> pos, vel, act;    // pos, vel: (steps + 1) * agents; act: steps * agents

    // Position of agent i at frame t; past the end the agent stays where it finished.
    Vec2 position(int t, int i) const { return pos[(size_t)std::min(t, steps) * agents + i]; }
};
struct DemoSet {
    std::string demonstrator;  // e.g. "expert" or "mappo:models/mappo/empty-4.safetensors"
    std::vector<Demonstration> episodes;
};

// Makes the demonstrator for one episode (its world and seed).
using DemonstratorFactory = PolicyFactory;
inline DemonstratorFactory expert_demonstrator(ExpertParams p = ExpertParams{}) {
    return [p](const World& w, uint64_t) { return std::unique_ptr<Policy>(new GuidedExpert(w.map(), p)); };
}

struct CollectConfig {
    std::vector<std::string> maps = {"empty", "obstacles", "barrier"};
    int n_train_max = 4;          // teams of n_train_min .. n_train_max agents
    int n_train_min = 1;          // (a cell's seeds do not depend on it: MADiff collects one team size)
    int episodes = 200;           // per (map, n) cell, >= 1
    uint64_t seed = 0;            // episode e of a cell uses seed + e + 100000 * (cell index)
    bool successful_only = true;  // keep only episodes the demonstrator solved
    int threads = 1;
    ProgressFn progress;          // called after each episode (optional)
    // Interaction scenes (madbp_sim.hpp Section 4b) mixed into every cell of n <= kMaxScenarioAgents:
    // {scenario, fraction of the cell's episodes}, fractions >= 0 summing to <= 1; the rest are
    // random spawns. Episode e of E takes the first scenario whose cumulative fraction exceeds
    // (e + 0.5) / E, with the same seed as a random spawn would; its map_name is "<map>/<scenario>".
    // Empty (default): random spawns only, as before.
    std::vector<std::pair<std::string, double>> scenarios;
};

// The scenario of episode e of a cell of `episodes` (CollectConfig::scenarios); "" = random spawns.
inline std::string collect_scenario(const CollectConfig& c, int n, int e) {
    if (n > kMaxScenarioAgents) return "";
    const double u = (e + 0.5) / c.episodes;
    double cum = 0;
    for (const auto& s : c.scenarios) {
        cum += s.second;
        if (u < cum) return s.first;
    }
    return "";
}

// Runs the demonstrator and records every step (positions, velocities, actions), until the
// episode is done or, with max_steps >= 0, that many steps are recorded.
inline Demonstration record_demonstration(World& world, Policy& policy, const std::string& map_name, int max_steps = -1) {
    Demonstration d;
    d.map_name = map_name;
    d.map = world.map();
    d.agents = world.size();
    for (const Agent& a : world.agents()) {
        d.goals.push_back(a.goal);
        d.pos.push_back(a.pos);
        d.vel.push_back(a.vel);
    }
    while (!world.done() && (max_steps < 0 || d.steps < max_steps)) {
        std::vector<Vec2> u = policy.act(world);
        for (Vec2& f : u) f = clamp_box(f, world.config().max_action);
        d.act.insert(d.act.end(), u.begin(), u.end());
        world.step(u);
        for (const Agent& a : world.agents()) {
            d.pos.push_back(a.pos);
            d.vel.push_back(a.vel);
        }
        d.steps++;
    }
    d.success = world.metrics().success;
    return d;
}

// Runs `episode(world, seed, map_name)` for every episode of c's cells (maps x teams of
// n_train_min .. n_train_max, c.episodes each; c.threads in parallel) and returns the results in
// cell, then episode, order, whatever the thread count. Episode e of a cell uses seed c.seed + e +
// 100000 * cell, cell = map * n_train_max + n - 1, and its scenario from collect_scenario;
// map_name is "<map>" or "<map>/<scenario>".
template <class Result>
std::vector<Result> for_each_collect_episode(const CollectConfig& c, const std::function<Result(World&, uint64_t, const std::string&)>& episode) {
    if (c.episodes < 1) throw std::invalid_argument("episodes: must be >= 1");
    if (c.n_train_max < 1 || c.n_train_max > 64) throw std::invalid_argument("n_train_max: must be in [1, 64]");
    if (c.n_train_min < 1 || c.n_train_min > c.n_train_max) throw std::invalid_argument("n_train_min: must be in [1, n_train_max]");
    double total = 0;
    for (const auto& s : c.scenarios) {
        const auto& names = interaction_scenarios();
        if (std::find(names.begin(), names.end(), s.first) == names.end())
            throw std::invalid_argument("scenarios: unknown scenario '" + printable(s.first) + "' (expected swap, cross, gap, corridor, parked or circle)");
        if (!(s.second >= 0) || !std::isfinite(s.second)) throw std::invalid_argument("scenarios: fraction of '" + s.first + "' must be >= 0");
        total += s.second;
    }
    if (total > 1 + 1e-9) throw std::invalid_argument("scenarios: fractions sum to " + std::to_string(total) + " > 1");
    const int sizes = c.n_train_max - c.n_train_min + 1, cells = (int)c.maps.size() * sizes;
    std::vector<Result> out((size_t)cells * c.episodes);
    long done = 0;
    std::string error;
    for (int m = 0; m < (int)c.maps.size(); ++m)
        for (int n = c.n_train_min; n <= c.n_train_max; ++n) {
            const int cell = m * c.n_train_max + (n - 1), slot = m * sizes + (n - c.n_train_min);
#pragma omp parallel for schedule(dynamic) num_threads(std::max(1, c.threads))
            for (int e = 0; e < c.episodes; ++e) {
                try {
                    const uint64_t seed = c.seed + e + 100000ull * cell;
                    const std::string scenario = collect_scenario(c, n, e);
                    World w = scenario.empty() ? make_random_world(c.maps[m], n, seed) : make_interaction_world(scenario, c.maps[m], n, seed);
                    out[(size_t)slot * c.episodes + e] = episode(w, seed, scenario.empty() ? c.maps[m] : c.maps[m] + "/" + scenario);
                } catch (const std::exception& ex) {
#pragma omp critical
                    if (error.empty()) error = ex.what();
                }
#pragma omp critical
                if (c.progress) c.progress(++done, (long)cells * c.episodes, "");
            }
            if (!error.empty()) throw std::runtime_error("collect: " + error);
        }
    return out;
}

inline DemoSet collect_demonstrations(const CollectConfig& c, const DemonstratorFactory& factory, const std::string& name) {
    std::vector<Demonstration> got = for_each_collect_episode<Demonstration>(c, [&](World& w, uint64_t seed, const std::string& map_name) {
        std::unique_ptr<Policy> policy = factory(w, seed);
        return record_demonstration(w, *policy, map_name);
    });
    DemoSet set;
    set.demonstrator = name;
    for (Demonstration& d : got)
        if (d.success || !c.successful_only) set.episodes.push_back(std::move(d));
    return set;
}

// =============================================================================================
// Section 2. Datasets (SPEC 11)
// =============================================================================================
// Dataset file (little-endian binary; documented in docs/formats.md):
//   "MADBPDS1", u32 version = 1, string demonstrator, u32 episode count, then per episode:
//   string map_name, f64 half_size, u32 discs + discs * (f64 cx, cy, r),
//   u32 boxes + boxes * (f64 x0, y0, x1, y1), u32 agents, u32 steps, u8 success,
//   goals agents*(f32 x, y), pos and vel (steps+1)*agents*(f32 x, y), act steps*agents*(f32 x, y).
//   A string is u32 length + bytes. Written by write_file_atomic.
// Limits (docs/limits.md), checked before allocating: the file <= kMaxDatasetBytes; per episode
// half_size <= kMaxHalfSize, discs + boxes <= kMaxObstacles, 1 <= agents <= kMaxDatasetAgents,
// 1 <= steps <= kMaxDatasetSteps; every count must also fit the bytes left in the file.
constexpr uint64_t kMaxDatasetBytes = 1ull << 30;  // 1 GiB (the shipped model's dataset is ~60 MB)
constexpr int kMaxDatasetAgents = 1024;
constexpr int kMaxDatasetSteps = 100000;
// Plausible motion: every velocity's speed <= kMaxDatasetSpeed world units per second (full
// force gives at most 0.57; contacts push harder for a step, far below this), every action
// component within the world's action bound kMaxDatasetAction (WorldConfig::max_action).
constexpr double kMaxDatasetSpeed = 10;
constexpr double kMaxDatasetAction = 1;
namespace detail {
struct ByteWriter {
    std::vector<uint8_t> bytes;
    template <class T> void put(T v) {
        const uint8_t* p = reinterpret_cast<const uint8_t*>(&v);  // x86-64 and ARM64 are little-endian
        bytes.insert(bytes.end(), p, p + sizeof(T));
    }
    void str(const std::string& s) { put<uint32_t>((uint32_t)s.size()); bytes.insert(bytes.end(), s.begin(), s.end()); }
    void vecs(const std::vector<Vec2>& v) { for (Vec2 a : v) { put<float>((float)a.x); put<float>((float)a.y); } }
};
struct ByteReader {
    const uint8_t* p;
    size_t left;
    std::string source;
    [[noreturn]] void fail(const std::string& what) const { throw std::runtime_error(source + ": " + what); }
    template <class T> T get(const char* field) {
        if (left < sizeof(T)) fail(std::string("file ends inside '") + field + "' (truncated)");
        T v;
        std::memcpy(&v, p, sizeof(T));
        p += sizeof(T);
        left -= sizeof(T);
        return v;
    }
    std::string str(const char* field, size_t max_len) {
        uint32_t n = get<uint32_t>(field);
        if (n > max_len || n > left) fail(std::string("'") + field + "' length " + std::to_string(n) + " is impossible");
        std::string s((const char*)p, n);
        p += n;
        left -= n;
        return s;
    }
    double finite(double v, const char* field) const {
        if (!std::isfinite(v)) fail(std::string("'") + field + "' is not finite");
        return v;
    }
    void vecs(std::vector<Vec2>& v, size_t count, const char* field) {
        if (count * 8 > left) fail(std::string("file ends inside '") + field + "' (truncated)");
        v.resize(count);
        for (Vec2& a : v) {
            a.x = finite(get<float>(field), field);
            a.y = finite(get<float>(field), field);
        }
    }
};
}  // namespace detail

// The dataset file's bytes (save_demos writes them; train hashes them into a run's identity).
inline std::vector<uint8_t> demos_bytes(const DemoSet& set) {
    detail::ByteWriter w;
    w.bytes.insert(w.bytes.end(), {'M', 'A', 'D', 'B', 'P', 'D', 'S', '1'});
    w.put<uint32_t>(1);
    w.str(set.demonstrator);
    w.put<uint32_t>((uint32_t)set.episodes.size());
    for (const Demonstration& d : set.episodes) {
        w.str(d.map_name);
        w.put<double>(d.map.half_size);
        w.put<uint32_t>((uint32_t)d.map.discs.size());
        for (const Disc& o : d.map.discs) { w.put<double>(o.c.x); w.put<double>(o.c.y); w.put<double>(o.r); }
        w.put<uint32_t>((uint32_t)d.map.boxes.size());
        for (const Box& b : d.map.boxes) { w.put<double>(b.lo.x); w.put<double>(b.lo.y); w.put<double>(b.hi.x); w.put<double>(b.hi.y); }
        w.put<uint32_t>((uint32_t)d.agents);
        w.put<uint32_t>((uint32_t)d.steps);
        w.put<uint8_t>(d.success ? 1 : 0);
        w.vecs(d.goals);
        w.vecs(d.pos);
        w.vecs(d.vel);
        w.vecs(d.act);
    }
    return std::move(w.bytes);
}
inline void save_demos(const std::string& path, const DemoSet& set) { write_file_atomic(path, demos_bytes(set)); }

// Semantic checks of a dataset (load_demos runs them with n_max = kMaxDatasetAgents; `madbp
// train` again with the model's n_max): per episode 1 <= agents <= n_max, 1 <= steps, array sizes
// that match, half_size in (0.2, kMaxHalfSize], discs with r > 0 and centres inside the world,
// boxes with x0 < x1, y0 < y1 inside the world, every value finite, every position and goal
// inside the world (|x|, |y| <= half_size). std::runtime_error naming `source`, the episode, the
// field, the index and the value.
inline void validate_demos(const DemoSet& set, int n_max = kMaxDatasetAgents, const std::string& source = "dataset") {
    auto num = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.6g", v); return std::string(b); };
    for (size_t e = 0; e < set.episodes.size(); ++e) {
        const Demonstration& d = set.episodes[e];
        const std::string ep = source + ": episode " + std::to_string(e) + ": ";
        auto fail = [&](const std::string& what) { throw std::runtime_error(ep + what); };
        const double h = d.map.half_size, tol = 1e-9 * (std::isfinite(h) ? std::fabs(h) : 1.0);
        if (!(h > 0.2 && h <= kMaxHalfSize)) fail("half_size " + num(h) + " outside (0.2, kMaxHalfSize = " + num(kMaxHalfSize) + "]");
        if (d.agents < 1 || d.agents > n_max) fail("agents = " + std::to_string(d.agents) + " outside [1, n_max = " + std::to_string(n_max) + "]");
        if (d.steps < 1) fail("steps = " + std::to_string(d.steps) + " (must be >= 1)");
        const size_t frames = (size_t)(d.steps + 1) * d.agents;
        if (d.goals.size() != (size_t)d.agents || d.pos.size() != frames || d.vel.size() != frames || d.act.size() != (size_t)d.steps * d.agents)
            fail("array sizes do not match agents = " + std::to_string(d.agents) + ", steps = " + std::to_string(d.steps));
        if (d.map.discs.size() + d.map.boxes.size() > (size_t)kMaxObstacles)
            fail(std::to_string(d.map.discs.size() + d.map.boxes.size()) + " obstacles exceed kMaxObstacles = " + std::to_string(kMaxObstacles));
        auto inside = [&](Vec2 p) { return std::fabs(p.x) <= h + tol && std::fabs(p.y) <= h + tol; };
        auto point = [&](Vec2 p) { return "(" + num(p.x) + ", " + num(p.y) + ")"; };
        for (size_t i = 0; i < d.map.discs.size(); ++i) {
            const Disc& o = d.map.discs[i];
            if (!std::isfinite(o.c.x) || !std::isfinite(o.c.y) || !(o.r > 0) || !std::isfinite(o.r))
                fail("disc " + std::to_string(i) + ": needs a finite centre and radius > 0 (r = " + num(o.r) + ")");
            if (!inside(o.c)) fail("disc " + std::to_string(i) + ": centre " + point(o.c) + " outside the world (half_size " + num(h) + ")");
        }
        for (size_t i = 0; i < d.map.boxes.size(); ++i) {
            const Box& b = d.map.boxes[i];
            if (!(b.lo.x < b.hi.x && b.lo.y < b.hi.y)) fail("box " + std::to_string(i) + ": needs x0 < x1 and y0 < y1");
            if (!inside(b.lo) || !inside(b.hi))
                fail("box " + std::to_string(i) + ": " + point(b.lo) + " - " + point(b.hi) + " outside the world (half_size " + num(h) + ")");
        }
        auto check_points = [&](const std::vector<Vec2>& v, const char* field) {
            for (size_t k = 0; k < v.size(); ++k)
                if (!inside(v[k]))
                    fail(std::string(field) + "[" + std::to_string(k) + "] = " + point(v[k]) + " outside the world (|x|, |y| <= half_size " + num(h) + ")");
        };
        check_points(d.goals, "goals");
        check_points(d.pos, "pos");
        for (size_t k = 0; k < d.vel.size(); ++k)
            if (!(norm(d.vel[k]) <= kMaxDatasetSpeed))
                fail("vel[" + std::to_string(k) + "] = " + point(d.vel[k]) + ": speed above kMaxDatasetSpeed = " + num(kMaxDatasetSpeed));
        const double act_lim = kMaxDatasetAction * (1 + 1e-6);  // stored as f32
        for (size_t k = 0; k < d.act.size(); ++k)
            if (!(std::fabs(d.act[k].x) <= act_lim && std::fabs(d.act[k].y) <= act_lim))
                fail("act[" + std::to_string(k) + "] = " + point(d.act[k]) + " outside the action bound kMaxDatasetAction = " + num(kMaxDatasetAction));
        const std::string base = d.map_name.substr(0, d.map_name.find('/'));
        const std::string scenario = base.size() < d.map_name.size() ? d.map_name.substr(base.size() + 1) : "";
        const auto& maps = map_names();
        const auto& scenarios = interaction_scenarios();
        if (std::find(maps.begin(), maps.end(), base) == maps.end() ||
            (base.size() < d.map_name.size() && std::find(scenarios.begin(), scenarios.end(), scenario) == scenarios.end()))
            fail("map name '" + printable(d.map_name) + "' is not MAP or MAP/SCENARIO (maps: empty, obstacles, barrier; case-sensitive)");
    }
}

// Parses and validates (validate_demos) a dataset held in memory; std::runtime_error naming
// `path` and the field on anything else.
inline DemoSet parse_demos(const uint8_t* data, size_t size, const std::string& path = "<memory>") {
    detail::ByteReader r{data, size, path};
    if (size > kMaxDatasetBytes) r.fail(std::to_string(size) + " bytes exceed the limit kMaxDatasetBytes = " + std::to_string(kMaxDatasetBytes));
    if (size < 8 || std::memcmp(data, "MADBPDS1", 8) != 0) r.fail("not a madbp dataset (magic 'MADBPDS1' missing)");
    r.p += 8;
    r.left -= 8;
    const uint32_t version = r.get<uint32_t>("version");
    if (version != 1) r.fail("dataset version " + std::to_string(version) + " is not supported (expected 1)");
    DemoSet set;
    set.demonstrator = r.str("demonstrator", 4096);
    const uint32_t count = r.get<uint32_t>("episode count");
    if (count > r.left / 77) r.fail("episode count " + std::to_string(count) + " does not fit the file");  // >= 77 bytes each
    for (uint32_t e = 0; e < count; ++e) {
        Demonstration& d = set.episodes.emplace_back();
        d.map_name = r.str("map_name", 256);
        d.map.half_size = r.finite(r.get<double>("half_size"), "half_size");
        if (!(d.map.half_size > 0.2 && d.map.half_size <= kMaxHalfSize))
            r.fail("episode " + std::to_string(e) + ": half_size " + number_text(d.map.half_size) + " outside (0.2, kMaxHalfSize = " +
                   number_text(kMaxHalfSize) + "]");
        const uint32_t discs = r.get<uint32_t>("discs");
        if (discs > (uint32_t)kMaxObstacles)
            r.fail("episode " + std::to_string(e) + ": discs = " + std::to_string(discs) + " exceed kMaxObstacles = " + std::to_string(kMaxObstacles));
        if (discs * 24ull > r.left) r.fail("episode " + std::to_string(e) + ": file ends inside 'discs' (truncated)");
        for (uint32_t i = 0; i < discs; ++i) {
            Disc o;
            o.c.x = r.finite(r.get<double>("disc"), "disc");
            o.c.y = r.finite(r.get<double>("disc"), "disc");
            o.r = r.finite(r.get<double>("disc"), "disc");
            d.map.discs.push_back(o);
        }
        const uint32_t boxes = r.get<uint32_t>("boxes");
        if (discs + (uint64_t)boxes > (uint64_t)kMaxObstacles)
            r.fail("episode " + std::to_string(e) + ": discs + boxes = " + std::to_string(discs + (uint64_t)boxes) + " exceed kMaxObstacles = " +
                   std::to_string(kMaxObstacles));
        if (boxes * 32ull > r.left) r.fail("episode " + std::to_string(e) + ": file ends inside 'boxes' (truncated)");
        for (uint32_t i = 0; i < boxes; ++i) {
            Box b;
            b.lo.x = r.finite(r.get<double>("box"), "box");
            b.lo.y = r.finite(r.get<double>("box"), "box");
            b.hi.x = r.finite(r.get<double>("box"), "box");
            b.hi.y = r.finite(r.get<double>("box"), "box");
            d.map.boxes.push_back(b);
        }
        const uint32_t agents = r.get<uint32_t>("agents"), steps = r.get<uint32_t>("steps");
        if (agents < 1 || agents > (uint32_t)kMaxDatasetAgents)
            r.fail("episode " + std::to_string(e) + ": agents = " + std::to_string(agents) + " outside [1, kMaxDatasetAgents = " +
                   std::to_string(kMaxDatasetAgents) + "]");
        if (steps < 1 || steps > (uint32_t)kMaxDatasetSteps)
            r.fail("episode " + std::to_string(e) + ": steps = " + std::to_string(steps) + " outside [1, kMaxDatasetSteps = " +
                   std::to_string(kMaxDatasetSteps) + "]");
        if (24ull * agents * (steps + 1ull) + 1 > r.left)  // success, goals, pos, vel, act
            r.fail("episode " + std::to_string(e) + ": file ends inside its " + std::to_string(steps) + " steps of " + std::to_string(agents) +
                   " agents (truncated)");
        d.agents = (int)agents;
        d.steps = (int)steps;
        const uint8_t success = r.get<uint8_t>("success");
        if (success > 1) r.fail("episode " + std::to_string(e) + ": success byte " + std::to_string(success) + " is not 0 or 1");
        d.success = success == 1;
        r.vecs(d.goals, agents, "goals");
        r.vecs(d.pos, (size_t)(steps + 1) * agents, "pos");
        r.vecs(d.vel, (size_t)(steps + 1) * agents, "vel");
        r.vecs(d.act, (size_t)steps * agents, "act");
    }
    if (r.left != 0) r.fail(std::to_string(r.left) + " trailing bytes after the last episode");
    validate_demos(set, kMaxDatasetAgents, path);
    return set;
}
// Reads a dataset file (at most kMaxDatasetBytes; a directory or device is refused; the
// signature is checked after the first bytes, so `yes | madbp train --data /dev/stdin` stops
// there instead of reading 1 GiB).
inline DemoSet load_demos(const std::string& path) {
    const std::vector<uint8_t> bytes = read_file(path, kMaxDatasetBytes, "kMaxDatasetBytes", "MADBPDS1", "madbp dataset");
    return parse_demos(bytes.data(), bytes.size(), path);
}

// =============================================================================================
// Section 3. Losses (SPEC 7, paper eqs. 3-8)
// =============================================================================================
// x0_hat is (2, H*A) in normalised units, columns a*H + t. Every auxiliary loss returns its
// value and ADDS weight * dL/dx0_hat into grad. scene_weight (B) scales each scene's terms
// (the trainer passes alpha_bar_k so that very noisy samples, whose x0_hat is mostly noise,
// do not dominate). mask (A): 1 = active agent.

// Smooth Euclidean norm (differentiable at 0) and its gradient factor.
namespace detail {
inline float smooth_norm(float x, float y) { return std::sqrt(x * x + y * y + 1e-8f); }
}  // namespace detail

// L_boundary = mean over active agents of |x0_hat[t=0] - start| + |x0_hat[t=H-1] - horizon_goal|.
inline double boundary_loss(const Mat& x0_hat, const Mat& start, const Mat& horizon_goal, const std::vector<float>& mask,
                            int H, int n, const float* scene_weight, float weight, Mat& grad) {
    const int A = (int)mask.size();
    double total = 0, active = 0;
    for (int a = 0; a < A; ++a) active += mask[a];
    if (active == 0) return 0;
    for (int a = 0; a < A; ++a) {
        if (!mask[a]) continue;
        const float w = scene_weight[a / n];
        const long c0 = (long)a * H, c1 = c0 + H - 1;
        for (int side = 0; side < 2; ++side) {
            const long col = side ? c1 : c0;
            const float dx = x0_hat(0, col) - (side ? horizon_goal(0, a) : start(0, a));
            const float dy = x0_hat(1, col) - (side ? horizon_goal(1, a) : start(1, a));
            const float len = detail::smooth_norm(dx, dy);
            total += w * len;
            const float g = (float)(weight * w / active) / len;
            grad(0, col) += g * dx;
            grad(1, col) += g * dy;
        }
    }
    return total / active;
}

// L_temporal = mean over active agents of mean_t |a_t| + jerk_weight * mean_t |j_t|, with
// v_t = x[t+1] - x[t], a_t = v[t+1] - v[t], j_t = a[t+1] - a[t] (finite differences per step).
inline double temporal_loss(const Mat& x0_hat, const std::vector<float>& mask, int H, int n, float jerk_weight,
                            const float* scene_weight, float weight, Mat& grad) {
    const int A = (int)mask.size();
    double total = 0, active = 0;
    for (int a = 0; a < A; ++a) active += mask[a];
    if (active == 0 || H < 4) return 0;
    // Second and third differences as stencils over x[t..t+3].
    const float acc_st[3] = {1, -2, 1}, jerk_st[4] = {-1, 3, -3, 1};
    for (int a = 0; a < A; ++a) {
        if (!mask[a]) continue;
        const float w = scene_weight[a / n];
        const long c = (long)a * H;
        for (int order = 0; order < 2; ++order) {
            const int len = order ? 4 : 3, terms = H - len + 1;
            const float* st = order ? jerk_st : acc_st;
            const float scale = (order ? jerk_weight : 1.0f) / terms;
            for (int t = 0; t < terms; ++t) {
                float dx = 0, dy = 0;
                for (int s = 0; s < len; ++s) {
                    dx += st[s] * x0_hat(0, c + t + s);
                    dy += st[s] * x0_hat(1, c + t + s);
                }
                const float l = detail::smooth_norm(dx, dy);
                total += w * scale * l;
                const float g = (float)(weight * w * scale / active) / l;
                for (int s = 0; s < len; ++s) {
                    grad(0, c + t + s) += g * st[s] * dx;
                    grad(1, c + t + s) += g * st[s] * dy;
                }
            }
        }
    }
    return total / active;
}

// L_collision = (1/B) sum_b sum_t [ sum_{i != j active} ReLU(d_min - |s_i - s_j|)
//                                   + sum_i ReLU(radius - clearance(s_i)) ]
// in world units, s = origin + x0_hat * scale (origin (2, A): each agent's current position);
// clearance is the distance to the nearest obstacle or wall surface of the scene's map.
// d_min = 2 * radius.
inline double collision_loss(const Mat& x0_hat, const Mat& origin, const std::vector<float>& mask, int B, int n, int H,
                             const std::vector<WorldMap>& maps, float scale, float radius, const float* scene_weight,
                             float weight, Mat& grad) {
    double total = 0;
    const float d_min = 2 * radius;
    auto world = [&](int a, int t) {
        return Vec2{origin(0, a) + x0_hat(0, (long)a * H + t) * (double)scale, origin(1, a) + x0_hat(1, (long)a * H + t) * (double)scale};
    };
    for (int b = 0; b < B; ++b) {
        const float w = scene_weight[b], g_scale = weight * w / B * scale;  // d(world)/d(normalised) = scale
        for (int t = 0; t < H; ++t)
            for (int i = 0; i < n; ++i) {
                const int ai = b * n + i;
                if (!mask[ai]) continue;
                const Vec2 si = world(ai, t);
                for (int j = 0; j < n; ++j) {
                    const int aj = b * n + j;
                    if (j == i || !mask[aj]) continue;
                    const Vec2 d = si - world(aj, t);
                    const double dist = norm(d);
                    if (dist >= d_min) continue;
                    total += w * (d_min - dist);
                    // Both orders (i, j) and (j, i) are in the sum; this one moves s_i and s_j.
                    const Vec2 u = dist > 1e-9 ? d / dist : Vec2{1, 0};
                    grad(0, (long)ai * H + t) -= (float)(g_scale * u.x);
                    grad(1, (long)ai * H + t) -= (float)(g_scale * u.y);
                    grad(0, (long)aj * H + t) += (float)(g_scale * u.x);
                    grad(1, (long)aj * H + t) += (float)(g_scale * u.y);
                }
                Vec2 away;
                const double clear = static_clearance(maps[b], si, &away);
                if (clear >= radius) continue;
                total += w * (radius - clear);
                grad(0, (long)ai * H + t) -= (float)(g_scale * away.x);
                grad(1, (long)ai * H + t) -= (float)(g_scale * away.y);
            }
    }
    return total / B;
}

// =============================================================================================
// Section 4. Training batches: windows, curriculum, augmentation
// =============================================================================================

struct TrainConfig {
    int n_train_max = 4;          // curriculum end: windows with up to this many agents
    long steps = 20000;           // optimizer steps
    int batch = 64;               // windows (scenes) per step
    float lr = 3e-4f;
    float grad_clip = 1.0f;       // global gradient-norm clip
    float ema_decay = 0.995f;
    long ema_start = 1000;        // EMA tracks the weights from this step (copied before)
    float curriculum_end = 0.5f;  // fraction of training at which n_curr reaches n_train_max
    std::array<float, 4> loss_weights = {0.85f, 0.025f, 0.025f, 0.1f};  // noise, boundary, temporal, collision
    float jerk_weight = 1.0f;     // lambda_jerk in L_temporal
    int stride = 1;               // window start stride in steps
    bool augment = true;          // random x / y mirror of whole scenes
    float goal_reach = -1;        // as SamplerConfig::goal_reach; < 0: default_goal_reach(model config)
    float val_fraction = 0.05f;   // episodes held out for the validation loss
    int val_batches = 4;
    long checkpoint_every = 1000;
    long log_every = 100;
    std::string out;              // model file; training state in out + ".train"; CSV in out + ".csv"
    bool resume = false;
    uint64_t seed = 0;
    int threads = 1;              // data-parallel replicas, each on its share of the batch (results depend on it)
    ProgressFn progress;          // called after every step with the smoothed loss (optional)
    // Called after every optimizer step; returning false stops training there (a time budget,
    // early stopping, or a test's simulated kill). Checkpoints already written stay valid.
    std::function<bool(long step)> keep_going;
};

// A window of one demonstration: frames t .. t+H-1 of episode `episode`.
struct WindowRef { int episode, t; };

// What every agent of every demonstration is told to head for at every frame (route_goal; only
// for a model with ModelConfig::subgoal_distance > 0): at[e][t * agents + i], t in [0, steps].
// Computed once before training, as the planner computes it, on the unmirrored map.
struct DemoRoutes {
    std::vector<std::vector<RouteGoal>> at;
    const RouteGoal& get(const Demonstration& d, int e, int t, int i) const { return at[e][(size_t)std::min(t, d.steps) * d.agents + i]; }
};
inline DemoRoutes route_demos(const DemoSet& demos, const ModelConfig& mc, int threads = 1) {
    DemoRoutes r;
    r.at.resize(demos.episodes.size());
    if (mc.subgoal_distance <= 0) return r;
#pragma omp parallel for num_threads(std::max(1, threads)) schedule(dynamic, 8)
    for (int e = 0; e < (int)demos.episodes.size(); ++e) {
        const Demonstration& d = demos.episodes[e];
        RouteGuide guide;
        r.at[e].resize((size_t)(d.steps + 1) * d.agents);
        for (int t = 0; t <= d.steps; ++t)
            for (int i = 0; i < d.agents; ++i) r.at[e][(size_t)t * d.agents + i] = route_goal(guide, mc, d.map, d.position(t, i), d.goals[i]);
    }
    return r;
}

// A batch ready for the model and the loss. x0 (2, H*A) normalised displacements from each
// agent's position at the window start; horizon_goal (2, A) the demonstrated displacement at
// t+H; origin (2, A) the start positions in world units; pinned (H*A) 1 where the sampler
// inpaints (t = 0, and the end when the goal is within reach): given to the model clean.
struct TrainBatch {
    SceneBatch scene;
    Mat x0, horizon_goal, origin;
    std::vector<float> pinned;
    std::vector<WorldMap> maps;  // per scene, in world units, mirrored like the scene
};

namespace detail {
// The map mirrored in x (fx = -1) and/or y (fy = -1): training augmentation.
inline WorldMap mirrored(const WorldMap& m, double fx, double fy) {
    WorldMap out = m;
    for (Disc& o : out.discs) o.c = Vec2{o.c.x * fx, o.c.y * fy};
    for (Box& b : out.boxes) {
        Vec2 a{b.lo.x * fx, b.lo.y * fy}, c{b.hi.x * fx, b.hi.y * fy};
        b.lo = Vec2{std::min(a.x, c.x), std::min(a.y, c.y)};
        b.hi = Vec2{std::max(a.x, c.x), std::max(a.y, c.y)};
    }
    return out;
}
}  // namespace detail

// Draws `batch` windows with at most n_curr agents. Agents go to random distinct PE_agent slots.
// With `routes` (route_demos) the goals are read from it; without, a model with subgoals
// computes them here (slowly: one RouteGuide per scene).
inline void make_train_batch(const DemoSet& demos, const std::vector<WindowRef>& windows, const ModelConfig& mc,
                             const TrainConfig& tc, int n_curr, Rng& rng, TrainBatch& tb, const DemoRoutes* routes = nullptr) {
    std::vector<int> picks;
    int n_slots = 1;
    for (int tries = 0; (int)picks.size() < tc.batch; ++tries) {
        if (tries > 1000 * tc.batch) throw std::runtime_error("train: no window with <= " + std::to_string(n_curr) + " agents in the dataset");
        int w = rng.uniform_int((int)windows.size());
        int agents = demos.episodes[windows[w].episode].agents;
        if (agents > n_curr) continue;
        picks.push_back(w);
        n_slots = std::max(n_slots, agents);
    }
    if (n_slots > mc.n_max) throw std::invalid_argument("train: windows with " + std::to_string(n_slots) + " agents exceed n_max");
    const int B = tc.batch, n = n_slots, H = mc.horizon, A = B * n;
    const float ws = mc.window_scale, reach = tc.goal_reach >= 0 ? tc.goal_reach : default_goal_reach(mc);
    const int stride = mc.waypoint_stride;
    tb.scene.resize(B, n, mc);
    tb.x0.setZero(2, (long)H * A);
    tb.horizon_goal.setZero(2, A);
    tb.origin.setZero(2, A);
    tb.pinned.assign((size_t)H * A, 0.0f);
    tb.maps.resize(B);
    std::vector<int> order(n), slots(mc.n_max);
    for (int b = 0; b < B; ++b) {
        const WindowRef ref = windows[picks[b]];
        const Demonstration& d = demos.episodes[ref.episode];
        const double fx = tc.augment && rng.uniform() < 0.5 ? -1 : 1, fy = tc.augment && rng.uniform() < 0.5 ? -1 : 1;
        auto mir = [&](Vec2 p) { return Vec2{p.x * fx, p.y * fy}; };
        tb.maps[b] = detail::mirrored(d.map, fx, fy);
        tb.scene.origin[b] = scene_origin(mc, d.agents, [&](int i) { return mir(d.position(ref.t, i)); });
        encode_map(tb.scene, b, tb.maps[b], mc);
        std::iota(order.begin(), order.end(), 0);
        for (int i = d.agents - 1; i > 0; --i) std::swap(order[i], order[rng.uniform_int(i + 1)]);
        std::iota(slots.begin(), slots.end(), 0);
        for (int i = 0; i < d.agents; ++i) std::swap(slots[i], slots[i + rng.uniform_int(mc.n_max - i)]);
        tb.scene.count[b] = d.agents;
        RouteGuide guide;  // only without `routes`
        for (int i = 0; i < d.agents; ++i) {
            const int a = b * n + i, src = order[i];
            const Vec2 start = mir(d.position(ref.t, src));
            const RouteGoal rg = routes && mc.subgoal_distance > 0 ? routes->get(d, ref.episode, ref.t, src)
                                                                   : route_goal(guide, mc, d.map, d.position(ref.t, src), d.goals[src]);
            encode_agent(tb.scene, a, slots[i], start, mir(rg.goal), tb.maps[b], mc, rg.final);
            tb.origin.col(a) << (float)start.x, (float)start.y;
            for (int t = 0; t < H; ++t) {
                const Vec2 p = mir(d.position(ref.t + t * stride, src)) - start;
                tb.x0.col((long)a * H + t) << (float)(p.x / ws), (float)(p.y / ws);
            }
            const Vec2 hg = mir(d.position(ref.t + H * stride, src)) - start;
            tb.horizon_goal.col(a) << (float)(hg.x / ws), (float)(hg.y / ws);
            tb.pinned[(size_t)a * H] = 1;
            // The end is pinned as the sampler pins it (to the demonstrated end, which is where
            // the demonstrator took the agent toward its goal).
            if (end_pinned(tb.scene, a, mc, reach)) tb.pinned[(size_t)a * H + H - 1] = 1;
        }
        for (int i = d.agents; i < n; ++i) tb.scene.slot[b * n + i] = slots[i];  // unused, distinct
    }
}

inline std::vector<WindowRef> make_windows(const DemoSet& demos, const std::vector<int>& episodes, const ModelConfig& mc, int stride) {
    std::vector<WindowRef> out;
    for (int e : episodes) {
        const Demonstration& d = demos.episodes[e];
        if (mc.window == WindowMode::CT) { out.push_back({e, 0}); continue; }
        // A successful episode ends with every robot at its goal, so frames past its end (held
        // positions) are true. An unsuccessful one was cut short (a timeout, or a DAgger label of
        // a few steps): only its windows that lie wholly inside the recording are taken.
        const int last = d.success ? std::max(1, d.steps) - 1 : d.steps - mc.horizon * mc.waypoint_stride;
        for (int t = 0; t <= std::max(0, last); t += std::max(1, stride)) out.push_back({e, t});
    }
    return out;
}

// =============================================================================================
// Section 5. The loss: noise the batch, run the model, combine the four terms (SPEC 7)
// =============================================================================================

struct LossTerms {
    double noise = 0, boundary = 0, temporal = 0, collision = 0, total = 0;
};

struct LossWorkspace {
    Mat eps, x_k, out, x0_hat, d_x0, d_out, zero_start;
    std::vector<int> k;
    std::vector<float> alpha_bar;
};

// Forward (and, when `backward`, the model's backward) of the training loss on one batch.
inline LossTerms diffusion_loss(MadbpModel& model, const NoiseSchedule& schedule, const TrainBatch& tb, const TrainConfig& tc,
                                Rng& rng, bool backward, LossWorkspace& ws) {
    const ModelConfig& mc = model.config;
    const SceneBatch& sc = tb.scene;
    const int B = sc.B, n = sc.n, A = B * n, H = mc.horizon;
    const auto& W = tc.loss_weights;
    ws.k.resize(B);
    ws.alpha_bar.resize(B);
    for (int b = 0; b < B; ++b) {
        ws.k[b] = 1 + rng.uniform_int(schedule.K);
        ws.alpha_bar[b] = (float)schedule.alpha_bar[ws.k[b]];
    }
    ws.zero_start.setZero(2, A);  // windows are displacements: every start is 0
    ws.eps.resize(2, (long)H * A);
    for (long j = 0; j < ws.eps.size(); ++j) ws.eps.data()[j] = (float)rng.normal();
    ws.x_k.resize(2, (long)H * A);
    for (int a = 0; a < A; ++a) {
        const int b = a / n;
        const float sa = std::sqrt(ws.alpha_bar[b]), s1a = std::sqrt(1 - ws.alpha_bar[b]);
        for (int t = 0; t < H; ++t) {
            const long c = (long)a * H + t;
            if (!sc.agent_mask[a]) ws.x_k.col(c).setZero();
            else if (tb.pinned[c]) ws.x_k.col(c) = tb.x0.col(c);
            else ws.x_k.col(c) = sa * tb.x0.col(c) + s1a * ws.eps.col(c);
        }
    }
    model.encode_context(sc);
    model.denoise(ws.x_k, ws.k.data(), ws.out);
    const bool eps_mode = mc.prediction == Prediction::Eps;
    // The denoising target: the noise (paper eq. 3) or the clean window (x0 prediction).
    const Mat& target = eps_mode ? ws.eps : tb.x0;

    LossTerms L;
    ws.d_out.setZero(2, (long)H * A);
    // L_noise: mean squared error over the active, not pinned, elements.
    double count = 0;
    for (long c = 0; c < (long)H * A; ++c) count += sc.agent_mask[c / H] && !tb.pinned[c] ? 2 : 0;
    for (long c = 0; c < (long)H * A; ++c) {
        if (!sc.agent_mask[c / H] || tb.pinned[c]) continue;
        for (int r = 0; r < 2; ++r) {
            const float e = ws.out(r, c) - target(r, c);
            L.noise += e * e;
            ws.d_out(r, c) = (float)(2 * W[0] * e / count);
        }
    }
    L.noise /= std::max(1.0, count);
    // x0_hat (pinned columns are known exactly and pass no gradient).
    ws.x0_hat.resize(2, (long)H * A);
    for (long c = 0; c < (long)H * A; ++c) {
        const float ab = ws.alpha_bar[c / H / n];
        if (tb.pinned[c] || !sc.agent_mask[c / H]) ws.x0_hat.col(c) = ws.x_k.col(c);
        else if (!eps_mode) ws.x0_hat.col(c) = ws.out.col(c);
        else
            for (int r = 0; r < 2; ++r) ws.x0_hat(r, c) = predict_x0(ws.x_k(r, c), ws.out(r, c), ab);
    }
    ws.d_x0.setZero(2, (long)H * A);
    L.boundary = boundary_loss(ws.x0_hat, ws.zero_start, tb.horizon_goal, sc.agent_mask, H, n, ws.alpha_bar.data(), W[1], ws.d_x0);
    L.temporal = temporal_loss(ws.x0_hat, sc.agent_mask, H, n, tc.jerk_weight, ws.alpha_bar.data(), W[2], ws.d_x0);
    L.collision = collision_loss(ws.x0_hat, tb.origin, sc.agent_mask, B, n, H, tb.maps, mc.window_scale, 0.1f, ws.alpha_bar.data(),
                                 W[3], ws.d_x0);
    L.total = W[0] * L.noise + W[1] * L.boundary + W[2] * L.temporal + W[3] * L.collision;
    if (!backward) return L;
    // Chain the auxiliary gradients to the network output: d x0_hat / d eps = -sqrt(1-ab)/sqrt(ab)
    // (eps prediction) or 1 (x0 prediction), on the free columns.
    for (long c = 0; c < (long)H * A; ++c) {
        if (tb.pinned[c] || !sc.agent_mask[c / H]) continue;
        const float ab = ws.alpha_bar[c / H / n];
        ws.d_out.col(c) += ws.d_x0.col(c) * (eps_mode ? -std::sqrt(1 - ab) / std::sqrt(ab) : 1.0f);
    }
    model.backward(ws.d_out);
    return L;
}

// =============================================================================================
// Section 6. Training scaffold: optimizer state, run identity, resumable state files, loss curves
// =============================================================================================
// One piece for train, train_mappo and train_madiff. A run writes <out> (the model, by the
// trainer), <out>.train (what --resume reads: weights, state, Adam, EMA, RNG streams and the
// run's identity) and <out>.csv (the loss curve), each atomically. A resumed run continues
// exactly as an uninterrupted one, and refuses a state file written by another run, naming
// the field that differs.

// Reads a flat tensor of exactly n values into out (used for optimizer state).
inline void read_flat(const SafeTensors& st, const std::string& name, int n, Vec& out) {
    const NamedTensor& t = st.at(name);
    if (t.shape != std::vector<int>{n})
        throw std::runtime_error(st.source + ": tensor '" + name + "' has shape " + detail::shape_string(t.shape) + " but [" +
                                 std::to_string(n) + "] is expected");
    out = Eigen::Map<const Vec>(t.data.data(), n);
}

// Adam state: tensors optim.adam.m / optim.adam.v (P) and metadata "optim.adam.step".
// Only the moments and step are saved; hyper-parameters belong to the training config.
inline void append_adam(const Adam& adam, std::vector<NamedTensor>& tensors, std::map<std::string, std::string>& metadata) {
    tensors.push_back(make_tensor("optim.adam.m", {(int)adam.m.size()}, adam.m.data()));
    tensors.push_back(make_tensor("optim.adam.v", {(int)adam.v.size()}, adam.v.data()));
    metadata["optim.adam.step"] = std::to_string(adam.step);
}
inline void read_adam(const SafeTensors& st, int param_count, Adam& adam) {
    const std::string& s = st.meta("optim.adam.step");
    if (s.empty() || s.size() > 18 || s.find_first_not_of("0123456789") != std::string::npos)
        throw std::runtime_error(st.source + ": __metadata__['optim.adam.step'] = '" + s + "' is not a step count");
    read_flat(st, "optim.adam.m", param_count, adam.m);
    read_flat(st, "optim.adam.v", param_count, adam.v);
    adam.step = std::stol(s);
}

// EMA state: tensor optim.ema.shadow (P) and metadata "optim.ema.decay".
inline void append_ema(const Ema& ema, std::vector<NamedTensor>& tensors, std::map<std::string, std::string>& metadata) {
    tensors.push_back(make_tensor("optim.ema.shadow", {(int)ema.shadow.size()}, ema.shadow.data()));
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.9g", ema.decay);
    metadata["optim.ema.decay"] = buf;
}
inline void read_ema(const SafeTensors& st, int param_count, Ema& ema) {
    read_flat(st, "optim.ema.shadow", param_count, ema.shadow);
    const std::string& s = st.meta("optim.ema.decay");
    char* endp = nullptr;
    const float d = std::strtof(s.c_str(), &endp);
    if (s.empty() || *endp != '\0' || !(d >= 0 && d <= 1))
        throw std::runtime_error(st.source + ": __metadata__['optim.ema.decay'] = '" + s + "' is not a decay in [0, 1]");
    ema.decay = d;
}

// RNG state as metadata "<key>" = four decimal words (float tensors cannot hold u64 exactly).
inline void append_rng(const Rng& rng, const std::string& key, std::map<std::string, std::string>& metadata) {
    std::string s;
    for (int i = 0; i < 4; ++i) s += (i ? " " : "") + std::to_string(rng.s[i]);
    metadata[key] = s;
}
inline void read_rng(const SafeTensors& st, const std::string& key, Rng& rng) {
    const std::string& s = st.meta(key);
    uint64_t w[4];
    const char* p = s.c_str();
    for (int i = 0; i < 4; ++i) {
        char* endp = nullptr;
        errno = 0;
        if (*p < '0' || *p > '9') endp = const_cast<char*>(p);
        else w[i] = std::strtoull(p, &endp, 10);
        if (endp == p || errno == ERANGE || (i < 3 ? *endp != ' ' : *endp != '\0'))
            throw std::runtime_error(st.source + ": __metadata__['" + key + "'] = '" + s.substr(0, 80) + "' is not four 64-bit words");
        p = endp + (i < 3 ? 1 : 0);
    }
    if ((w[0] | w[1] | w[2] | w[3]) == 0) throw std::runtime_error(st.source + ": __metadata__['" + key + "'] is the all-zero state");
    for (int i = 0; i < 4; ++i) rng.s[i] = w[i];
}

// A training curve: named columns, one row per logged step; column 0 is the step (or
// iteration). Written as <out>.csv; the madbp tool draws it as <out>.svg.
struct Curve {
    std::vector<std::string> columns;
    std::vector<std::vector<double>> rows;

    void add(std::vector<double> row) {
        MADBP_ASSERT(row.size() == columns.size());
        rows.push_back(std::move(row));
    }
    // Index of a column (std::invalid_argument when there is none).
    int column(const std::string& name) const {
        for (size_t i = 0; i < columns.size(); ++i)
            if (columns[i] == name) return (int)i;
        throw std::invalid_argument("curve: no column '" + name + "'");
    }
    std::string csv() const {
        std::string out;
        for (size_t i = 0; i < columns.size(); ++i) out += (i ? "," : "") + columns[i];
        out += '\n';
        for (const auto& row : rows) {
            for (size_t i = 0; i < row.size(); ++i) {
                char b[32];
                std::snprintf(b, sizeof b, i == 0 ? "%.0f" : "%.7g", row[i]);
                out += (i ? "," : "") + std::string(b);
            }
            out += '\n';
        }
        return out;
    }
    // The rows of a CSV with these columns up to step `last` (a resumed run's history); a
    // missing file gives none; another header or a malformed row is an error naming the file.
    void read_csv(const std::string& path, long last) {
        rows.clear();
        std::ifstream in(path);
        if (!in) return;
        std::string line, header = csv();
        header = header.substr(0, header.find('\n'));
        if (!std::getline(in, line) || line != header)
            throw std::runtime_error(path + ": the loss curve's header is not '" + header + "'");
        for (int lineno = 2; std::getline(in, line); ++lineno) {
            std::vector<double> row;
            std::stringstream ss(line);
            for (std::string cell; std::getline(ss, cell, ',');) {
                char* end = nullptr;
                row.push_back(std::strtod(cell.c_str(), &end));
                if (cell.empty() || *end != '\0') row.clear();
                if (row.empty()) break;
            }
            if (row.size() != columns.size()) throw std::runtime_error(path + ":" + std::to_string(lineno) + ": malformed curve row");
            if (row[0] <= (double)last) rows.push_back(std::move(row));
        }
    }
};

// FNV-1a 64 of bytes, as 16 hex digits: the content hash in a run's identity.
inline std::string content_hash(const std::vector<uint8_t>& bytes) {
    uint64_t h = 1469598103934665603ull;
    for (uint8_t b : bytes) h = (h ^ b) * 1099511628211ull;
    char out[17];
    std::snprintf(out, sizeof out, "%016llx", (unsigned long long)h);
    return out;
}

// The resumable state of one run. The trainer owns the model, optimizer and RNGs; TrainState
// knows where they are and what makes the run this run:
//   TrainState state(out, *model.params, adam, &ema, {{"train.rng", &rng}}, identity, curve columns);
//   if (resume) step = state.resume();           // checks identity, restores everything
//   ... state.curve.add({step, loss, ...}); state.save(step, extra metadata);
class TrainState {
public:
    Curve curve;

    TrainState(std::string out, ParamStore& params, Adam& adam, Ema* ema, std::vector<std::pair<std::string, Rng*>> rngs,
               std::map<std::string, std::string> identity, std::vector<std::string> curve_columns)
        : out_(std::move(out)), params_(params), adam_(adam), ema_(ema), rngs_(std::move(rngs)), identity_(std::move(identity)) {
        curve.columns = std::move(curve_columns);
    }
    std::string state_path() const { return out_ + ".train"; }
    std::string csv_path() const { return out_ + ".csv"; }

    // Restores the run from <out>.train and returns its step: every identity field must equal
    // this run's (the error names the first that differs), then the weights, state, Adam, EMA,
    // RNG streams and the curve rows up to that step come back. The file's metadata stays in
    // `resumed` for a trainer's own fields (resumed_numbers). A state past this run's
    // `last_step` (a summary and no model, before) or whose Adam step is not `adam_per_step`
    // updates per step is refused (std::invalid_argument, std::runtime_error).
    std::map<std::string, std::string> resumed;
    long resume(long last_step, long adam_per_step = 1) {
        const SafeTensors st = load_safetensors(state_path());
        resumed = st.metadata;
        for (auto& kv : identity_) {
            auto it = st.metadata.find(kv.first);
            if (it == st.metadata.end() || it->second != kv.second)
                throw std::runtime_error(state_path() + ": was written by a run with another " + kv.first + " (" +
                                         (it == st.metadata.end() ? std::string("none") : it->second.substr(0, 80)) +
                                         ", this run: " + kv.second.substr(0, 80) + ")");
        }
        read_param_tensors(st, params_);
        read_adam(st, params_.size(), adam_);
        if (ema_) read_ema(st, params_.size(), *ema_);
        for (auto& r : rngs_) read_rng(st, r.first, *r.second);
        const std::string& s = st.meta("train.step");
        if (s.empty() || s.size() > 18 || s.find_first_not_of("0123456789") != std::string::npos)
            throw std::runtime_error(state_path() + ": __metadata__['train.step'] = '" + s + "' is not a step count");
        const long step = std::stol(s);
        if (step > last_step)
            throw std::invalid_argument(state_path() + ": the training state is at step " + s + ", past this run's last step " +
                                        std::to_string(last_step) + " (--steps / --iterations): ask for at least " + s +
                                        " to continue it, or write another --out");
        if (adam_.step != step * adam_per_step)
            throw std::runtime_error(state_path() + ": __metadata__['optim.adam.step'] = " + std::to_string(adam_.step) +
                                     " does not match train.step = " + s + " (" + std::to_string(adam_per_step) +
                                     " optimizer updates per step): the file is inconsistent");
        curve.read_csv(csv_path(), step);
        return step;
    }
    // `count` finite numbers from the resumed metadata's `key` (a trainer's smoothed losses);
    // std::runtime_error naming the file and the key otherwise.
    std::vector<double> resumed_numbers(const std::string& key, int count) const {
        auto it = resumed.find(key);
        std::stringstream ss(it == resumed.end() ? std::string() : it->second);
        std::vector<double> v((size_t)count);
        for (double& x : v)
            if (!(ss >> x) || !std::isfinite(x)) ss.setstate(std::ios::failbit);
        std::string rest;
        if (!ss || (ss >> rest))
            throw std::runtime_error(state_path() + ": __metadata__['" + key + "'] is not " + std::to_string(count) + " finite numbers");
        return v;
    }
    // Writes <out>.train (identity, step and `metadata` in its header) and <out>.csv.
    void save(long step, std::map<std::string, std::string> metadata) const {
        std::vector<NamedTensor> tensors = param_tensors(params_);
        for (auto& kv : identity_) metadata[kv.first] = kv.second;
        metadata["train.step"] = std::to_string(step);
        append_adam(adam_, tensors, metadata);
        if (ema_) append_ema(*ema_, tensors, metadata);
        for (auto& r : rngs_) append_rng(*r.second, r.first, metadata);
        save_safetensors(state_path(), tensors, metadata);
        const std::string text = curve.csv();
        write_file_atomic(csv_path(), std::vector<uint8_t>(text.begin(), text.end()));
    }
    // Runs write_model with the EMA weights in the store when `use_ema` (the model file a
    // planner loads), then puts the raw training weights back.
    template <class F>
    void with_model_weights(bool use_ema, const F& write_model) {
        if (!use_ema || !ema_) { write_model(); return; }
        raw_ = params_.value;
        ema_->copy_to(params_);
        write_model();
        params_.value = raw_;
    }

private:
    std::string out_;
    ParamStore& params_;
    Adam& adam_;
    Ema* ema_;
    std::vector<std::pair<std::string, Rng*>> rngs_;
    std::map<std::string, std::string> identity_;
    Vec raw_;
};

// =============================================================================================
// Section 7. Training loop (paper Alg. 1)
// =============================================================================================

struct TrainReport {
    long steps = 0;
    double seconds = 0;
    LossTerms last_train, last_val;
    Curve curve;  // step, n_curr, smoothed train losses, validation total (as <out>.csv)
};

// The curriculum (SPEC 7): n_curr rises linearly from 1 to n_train_max, reaching it at
// curriculum_end of training.
inline int curriculum_agents(long step, const TrainConfig& tc) {
    const double ramp = std::max(1.0, (double)tc.curriculum_end * tc.steps);
    return std::min(tc.n_train_max, 1 + (int)(step / ramp * tc.n_train_max));
}

// What makes a training run this run (checked on --resume): the model, the data's content,
// every hyper-parameter that changes the result, the seed and the replica count.
inline std::map<std::string, std::string> train_identity(const DemoSet& demos, const ModelConfig& mc, const TrainConfig& tc) {
    auto f = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.9g", v); return std::string(b); };
    std::map<std::string, std::string> id = mc.to_metadata();
    std::string w;
    for (float x : tc.loss_weights) w += (w.empty() ? "" : ",") + f(x);
    id.insert({{"train.data", content_hash(demos_bytes(demos))}, {"train.seed", std::to_string(tc.seed)},
               {"train.steps", std::to_string(tc.steps)}, {"train.batch", std::to_string(tc.batch)},
               {"train.threads", std::to_string(std::max(1, std::min(tc.threads, tc.batch)))}, {"train.lr", f(tc.lr)},
               {"train.grad_clip", f(tc.grad_clip)}, {"train.loss_weights", w}, {"train.jerk_weight", f(tc.jerk_weight)},
               {"train.n_train_max", std::to_string(tc.n_train_max)}, {"train.curriculum_end", f(tc.curriculum_end)},
               {"train.ema", f(tc.ema_decay) + " from " + std::to_string(tc.ema_start)}, {"train.stride", std::to_string(tc.stride)},
               {"train.augment", tc.augment ? "1" : "0"}, {"train.goal_reach", f(tc.goal_reach)},
               {"train.validation", f(tc.val_fraction) + " x " + std::to_string(tc.val_batches)}});
    return id;
}

// Trains `model` on `demos`; writes tc.out (the EMA weights, ready for DiffusionPlanner),
// tc.out + ".train" (raw weights, Adam, EMA, RNG: what --resume reads), tc.out + ".csv"
// and tc.out + ".svg" (loss curves). Deterministic for a seed on one machine.
inline TrainReport train(const DemoSet& demos, MadbpModel& model, const TrainConfig& tc) {
    const ModelConfig& mc = model.config;
    if (demos.episodes.empty()) throw std::invalid_argument("train: the dataset has no episodes");
    float weight_sum = 0;
    for (float w : tc.loss_weights) {
        if (!(w >= 0 && std::isfinite(w))) throw std::invalid_argument("train: loss_weights must be finite and >= 0");
        weight_sum += w;
    }
    if (!(weight_sum > 0)) throw std::invalid_argument("train: loss_weights are all 0: there is nothing to train");
    if (tc.batch < 1 || tc.steps < 1) throw std::invalid_argument("train: batch and steps must be >= 1");
    if (tc.log_every < 1 || tc.checkpoint_every < 1 || tc.val_batches < 1)
        throw std::invalid_argument("train: log_every, checkpoint_every and val_batches must be >= 1");
    if (tc.n_train_max > mc.n_max) throw std::invalid_argument("train: n_train_max exceeds the model's n_max");
    if (mc.window == WindowMode::CT)
        for (const Demonstration& d : demos.episodes)
            if (d.steps + 1 > mc.horizon) throw std::invalid_argument("train: CT mode needs horizon >= episode frames (" + std::to_string(d.steps + 1) + ")");
    // Split episodes into training and validation deterministically from the seed.
    Rng split_rng(tc.seed ^ 0x5eed5eedull);
    std::vector<int> train_eps, val_eps;
    for (int e = 0; e < (int)demos.episodes.size(); ++e) (split_rng.uniform() < tc.val_fraction ? val_eps : train_eps).push_back(e);
    if (train_eps.empty()) train_eps.swap(val_eps);
    if (val_eps.empty()) val_eps = train_eps;
    const std::vector<WindowRef> train_windows = make_windows(demos, train_eps, mc, tc.stride);
    const std::vector<WindowRef> val_windows = make_windows(demos, val_eps, mc, tc.stride);
    const DemoRoutes routes = route_demos(demos, mc, tc.threads);

    NoiseSchedule schedule(mc.diffusion_steps);
    Adam adam;
    adam.lr = tc.lr;
    Ema ema;
    ema.decay = tc.ema_decay;
    // The curriculum starts at the smallest team the data has.
    int smallest_team = 1 << 30;
    for (const WindowRef& w : train_windows) smallest_team = std::min(smallest_team, demos.episodes[w.episode].agents);
    // Data parallelism: replica r trains on its share of the batch with its own random stream;
    // gradients and BatchNorm running statistics are averaged weighted by the shares.
    const int R = std::max(1, std::min(tc.threads, tc.batch));
    std::vector<Rng> rngs;
    for (int r = 0; r < R; ++r) rngs.emplace_back(tc.seed + 0x9E3779B97F4A7C15ull * r);
    std::vector<std::pair<std::string, Rng*>> rng_names;
    for (int r = 0; r < R; ++r) rng_names.push_back({r == 0 ? "train.rng" : "train.rng." + std::to_string(r), &rngs[r]});
    TrainState state(tc.out, *model.params, adam, &ema, rng_names, train_identity(demos, mc, tc),
                     {"step", "n_curr", "train_total", "train_noise", "train_boundary", "train_temporal", "train_collision", "val_total"});
    long step = 0;
    LossTerms smooth;  // exponentially smoothed training losses (in the state file: the curve continues exactly)
    if (tc.resume) {
        step = state.resume(tc.steps);
        const std::vector<double> sm = state.resumed_numbers("train.smooth", 5);
        smooth.total = sm[0], smooth.noise = sm[1], smooth.boundary = sm[2], smooth.temporal = sm[3], smooth.collision = sm[4];
    }
    if (ema.shadow.size() != model.params->size()) ema.shadow = model.params->value;

    model.set_training(true);
    TrainBatch vb;
    LossWorkspace ws;
    TrainReport rep;
    auto t_start = std::chrono::steady_clock::now();
    auto validate = [&]() {
        // Fixed seeds: the same validation windows and noise every time.
        Rng vrng(tc.seed + 777);
        LossTerms sum;
        for (int v = 0; v < tc.val_batches; ++v) {
            make_train_batch(demos, val_windows, mc, tc, tc.n_train_max, vrng, vb, &routes);
            LossTerms l = diffusion_loss(model, schedule, vb, tc, vrng, false, ws);
            sum.noise += l.noise / tc.val_batches;
            sum.boundary += l.boundary / tc.val_batches;
            sum.temporal += l.temporal / tc.val_batches;
            sum.collision += l.collision / tc.val_batches;
            sum.total += l.total / tc.val_batches;
        }
        return sum;
    };
    auto save = [&]() {
        // Model file: EMA weights (or raw weights before the EMA starts), eval-ready.
        state.with_model_weights(step >= tc.ema_start, [&] {
            save_model(tc.out, model, {{"demonstrator", demos.demonstrator}, {"train.step", std::to_string(step)},
                                       {"train.n_train_max", std::to_string(tc.n_train_max)}});
        });
        char sm[160];
        std::snprintf(sm, sizeof sm, "%.17g %.17g %.17g %.17g %.17g", smooth.total, smooth.noise, smooth.boundary, smooth.temporal,
                      smooth.collision);
        state.save(step, {{"train.smooth", sm}});
    };
    std::vector<MadbpModel> clones;
    std::vector<MadbpModel*> replica = {&model};
    std::vector<TrainConfig> share(R, tc);
    std::vector<TrainBatch> batches(R);
    std::vector<LossWorkspace> spaces(R);
    std::vector<LossTerms> losses(R);
    for (int r = 1; r < R; ++r) clones.push_back(model.clone());
    for (int r = 1; r < R; ++r) replica.push_back(&clones[r - 1]);
    for (int r = 0; r < R; ++r) share[r].batch = tc.batch / R + (r < tc.batch % R ? 1 : 0);
    while (step < tc.steps) {
        const int n_curr = std::max(smallest_team, curriculum_agents(step, tc));
        std::string error;
        // Every replica starts the step from the main model's weights and running statistics.
        for (int r = 1; r < R; ++r) {
            replica[r]->params->value = model.params->value;
            replica[r]->params->state = model.params->state;
        }
#pragma omp parallel for num_threads(R) schedule(static, 1)
        for (int r = 0; r < R; ++r) {
            try {
                replica[r]->set_training(true);
                make_train_batch(demos, train_windows, mc, share[r], n_curr, rngs[r], batches[r], &routes);
                replica[r]->params->zero_grad();
                losses[r] = diffusion_loss(*replica[r], schedule, batches[r], share[r], rngs[r], true, spaces[r]);
            } catch (const std::exception& e) {
#pragma omp critical
                error = e.what();
            }
        }
        if (!error.empty()) throw std::runtime_error("train: " + error);
        LossTerms l = losses[0];
        if (R > 1) {
            l = LossTerms{};
            for (int r = 0; r < R; ++r) {
                const double w = (double)share[r].batch / tc.batch;
                l.noise += w * losses[r].noise, l.boundary += w * losses[r].boundary, l.temporal += w * losses[r].temporal;
                l.collision += w * losses[r].collision, l.total += w * losses[r].total;
            }
            ParamStore& main = *model.params;
            main.grad *= (float)share[0].batch / tc.batch;
            main.state *= (float)share[0].batch / tc.batch;
            for (int r = 1; r < R; ++r) {
                const float w = (float)share[r].batch / tc.batch;
                main.grad += w * replica[r]->params->grad;
                main.state += w * replica[r]->params->state;
            }
        }
        if (!std::isfinite(l.total)) throw std::runtime_error("train: loss became non-finite at step " + std::to_string(step));
        clip_grad_norm(*model.params, tc.grad_clip);
        adam.update(*model.params);
        step++;
        if (step == tc.ema_start) ema.shadow = model.params->value;
        else if (step > tc.ema_start) ema.update(*model.params);
        const double keep = step == 1 ? 0.0 : 0.98;
        smooth.noise = keep * smooth.noise + (1 - keep) * l.noise;
        smooth.boundary = keep * smooth.boundary + (1 - keep) * l.boundary;
        smooth.temporal = keep * smooth.temporal + (1 - keep) * l.temporal;
        smooth.collision = keep * smooth.collision + (1 - keep) * l.collision;
        smooth.total = keep * smooth.total + (1 - keep) * l.total;
        rep.last_train = l;
        if (step % tc.log_every == 0 || step == tc.steps) {
            model.set_training(false);  // validation uses the running BatchNorm statistics
            rep.last_val = validate();
            model.set_training(true);
            state.curve.add({(double)step, (double)n_curr, smooth.total, smooth.noise, smooth.boundary, smooth.temporal,
                             smooth.collision, rep.last_val.total});
        }
        if (step % tc.checkpoint_every == 0 || step == tc.steps) save();
        if (tc.progress) {
            char note[96];
            std::snprintf(note, sizeof note, "n_curr %d  loss %.4f", n_curr, smooth.total);
            tc.progress(step, tc.steps, note);
        }
        if (tc.keep_going && !tc.keep_going(step)) break;
    }
    rep.steps = step;
    rep.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();
    rep.curve = state.curve;
    if (step >= tc.ema_start) ema.copy_to(*model.params);
    model.set_training(false);
    return rep;
}

// =============================================================================================
// Section 7b. DAgger: on-policy data aggregation (issue 12)
// =============================================================================================
// The learner drives, the expert labels. Expert demonstrations only show states the expert
// visits; a learned planner drifts into others (two robots nose to nose, neither yielding)
// and has never seen a way out of them. Each round rolls the current model out, labels every
// label_every-th visited state with what the guided expert does from that exact state, adds
// the labels to those of earlier rounds and fine-tunes the model on them plus expert windows.

// What the expert does from `state`: the first `steps` steps of a fresh episode (the world's
// configuration, its full step budget) that starts from the robots' positions, velocities and
// goals, solved by a fresh GuidedExpert, so its plan and priorities come from this state. A
// label is successful only if every robot reached its goal within it; otherwise make_windows
// takes only its complete windows.
inline Demonstration expert_label(const World& state, int steps, const ExpertParams& expert, const std::string& map_name) {
    if (steps < 1) throw std::invalid_argument("expert_label: steps must be >= 1");
    World w(state.map(), state.config());
    for (const Agent& a : state.agents()) {
        w.add_agent(a.goal, a.goal, a.id);  // then moved: a state pressed into a wall is valid
        w.set_state(a.id, a.pos, a.vel);
    }
    GuidedExpert policy(w.map(), expert);
    return record_demonstration(w, policy, map_name, steps);
}

// Labels a window needs: H * waypoint_stride steps (frames t .. t + H stride; make_train_batch
// reads the frame after the window as the horizon goal).
inline int label_steps(const ModelConfig& mc) { return mc.horizon * mc.waypoint_stride; }

struct DaggerRollouts {
    int episodes = 0, successes = 0;
    long collisions = 0;
    DemoSet labels;  // one Demonstration per labelled state, in episode order
    double success() const { return episodes ? (double)successes / episodes : 0; }
    double success_se() const { const double p = success(); return episodes ? std::sqrt(p * (1 - p) / episodes) : 0; }
};

// Rolls `learner` out on the episodes of `scenes` (as collect_demonstrations would, the same
// seeds and scenes) and labels every label_every-th state it visits (0: none, an evaluation).
inline DaggerRollouts dagger_rollouts(const CollectConfig& scenes, const PolicyFactory& learner, const ModelConfig& mc, int label_every,
                                      const ExpertParams& expert = ExpertParams{}) {
    if (label_every < 0) throw std::invalid_argument("label_every: must be >= 0");
    struct Episode { bool success = false; long collisions = 0; std::vector<Demonstration> labels; };
    std::vector<Episode> got = for_each_collect_episode<Episode>(scenes, [&](World& w, uint64_t seed, const std::string& map_name) {
        std::unique_ptr<Policy> policy = learner(w, seed);
        Episode ep;
        const EpisodeResult result = run_episode(w, *policy, /*record*/ false, [&](World& now) {
            if (label_every > 0 && now.t() % label_every == 0) ep.labels.push_back(expert_label(now, label_steps(mc), expert, map_name));
        });
        ep.success = result.success;
        ep.collisions = result.collisions();
        return ep;
    });
    DaggerRollouts r;
    r.labels.demonstrator = "expert:dagger";
    for (Episode& ep : got) {
        r.episodes++;
        r.successes += ep.success;
        r.collisions += ep.collisions;
        for (Demonstration& d : ep.labels) r.labels.episodes.push_back(std::move(d));
    }
    return r;
}

struct DaggerConfig {
    int rounds = 3;               // >= 1
    // The episodes each round rolls out (maps, teams of 1 .. n_train_max, episodes per cell,
    // scenario mix, threads). Round r uses seed rollouts.seed + r * kDaggerRoundSeeds, so no
    // two rounds (and, with the default seed, no training demonstration or reported evaluation
    // seed) share an episode.
    CollectConfig rollouts;
    int label_every = 2;          // label every k-th visited state, >= 1
    ExpertParams expert;
    // Expert-demonstration windows per label window in each fine-tune (drawn afresh each round
    // from the base set): the labels teach the way out of the learner's own states, the expert
    // windows keep what the model already knew.
    double base_ratio = 1.0;
    TrainConfig train;            // each round's fine-tune; train.out = the final model
    std::function<void(const struct DaggerRound&)> on_round;  // after each round (the tool logs it)
};
static constexpr uint64_t kDaggerRoundSeeds = 10000000;
static constexpr uint64_t kDaggerDefaultSeed = 50000000;

// One round: the success of the model it started from (on its own rollouts), the labels it
// made, and the fine-tune. Round `rounds + 1` is the final model's evaluation (no labels).
struct DaggerRound {
    int round = 0;
    double success = 0, success_se = 0, collisions = 0;  // collisions per episode
    int episodes = 0;
    long labels = 0, train_episodes = 0;
    double seconds = 0;
};

// A round's files: the labels (<out>.round-R.labels.bin) and the fine-tuned model
// (<out>.round-R.safetensors, with train's .train state and .csv curve).
inline std::string dagger_file(const TrainConfig& tc, int round, const char* what) { return tc.out + ".round-" + std::to_string(round) + what; }

// The DAgger log <out>.dagger.csv, one row per finished round (read back on resume).
inline std::string dagger_csv(const std::vector<DaggerRound>& rounds) {
    std::string s = "round,success,success_se,collisions,episodes,labels,train_episodes,seconds\n";
    char line[256];
    for (const DaggerRound& r : rounds) {
        std::snprintf(line, sizeof line, "%d,%.17g,%.17g,%.17g,%d,%ld,%ld,%.3f\n", r.round, r.success, r.success_se, r.collisions, r.episodes,
                      r.labels, r.train_episodes, r.seconds);
        s += line;
    }
    return s;
}
inline std::vector<DaggerRound> read_dagger_csv(const std::string& path) {
    std::vector<DaggerRound> rounds;
    const std::vector<uint8_t> bytes = read_file(path, 1 << 20, "1 MiB");
    std::stringstream ss(std::string(bytes.begin(), bytes.end()));
    std::string line;
    std::getline(ss, line);  // header
    while (std::getline(ss, line)) {
        DaggerRound r;
        if (std::sscanf(line.c_str(), "%d,%lf,%lf,%lf,%d,%ld,%ld,%lf", &r.round, &r.success, &r.success_se, &r.collisions, &r.episodes, &r.labels,
                        &r.train_episodes, &r.seconds) != 8 || r.round != (int)rounds.size() + 1)
            throw std::runtime_error(path + ": row " + std::to_string(rounds.size() + 1) + " is not a DAgger round ('" + printable(line) + "')");
        rounds.push_back(r);
    }
    return rounds;
}

// Runs the rounds from `model` (trained on `base`), fine-tuning it in place; writes every
// round's files, the log and finally train.out. `learner(model)` makes the rollout policy
// (the planner with the sampler settings it will be used with). With train.resume, finished
// rounds are read back (their labels from their files) and an interrupted fine-tune continues
// from its state file, so a resumed run ends with the same files as an uninterrupted one. A
// fine-tune stopped by train.keep_going ends the run there (fewer than rounds + 1 rows).
using LearnerFactory = std::function<PolicyFactory(const MadbpModel&)>;
inline std::vector<DaggerRound> dagger(const DemoSet& base, MadbpModel& model, const DaggerConfig& c, const LearnerFactory& learner) {
    auto file_exists = [](const std::string& path) { return std::ifstream(path).good(); };
    if (c.rounds < 1) throw std::invalid_argument("rounds: must be >= 1");
    if (c.label_every < 1) throw std::invalid_argument("label_every: must be >= 1");
    if (!(c.base_ratio >= 0) || !std::isfinite(c.base_ratio)) throw std::invalid_argument("base_ratio: must be finite and >= 0");
    if (c.train.out.empty()) throw std::invalid_argument("train.out: DAgger needs an output file");
    if (base.episodes.empty()) throw std::invalid_argument("dagger: the base dataset has no episodes");
    const ModelConfig mc = model.config;
    const std::string log_path = c.train.out + ".dagger.csv";
    std::vector<DaggerRound> done;
    if (c.train.resume && file_exists(log_path)) done = read_dagger_csv(log_path);
    DemoSet labels;  // every round's so far
    labels.demonstrator = "expert:dagger";
    for (const DaggerRound& r : done) {
        if (r.round > c.rounds) break;  // the final evaluation's row
        DemoSet l = load_demos(dagger_file(c.train, r.round, ".labels.bin"));
        for (Demonstration& d : l.episodes) labels.episodes.push_back(std::move(d));
        model = load_model(dagger_file(c.train, r.round, ".safetensors"));
    }
    for (int round = (int)done.size() + 1; round <= c.rounds + 1; ++round) {
        const auto t0 = std::chrono::steady_clock::now();
        CollectConfig scenes = c.rollouts;
        scenes.seed = c.rollouts.seed + (uint64_t)round * kDaggerRoundSeeds;
        const bool last = round == c.rounds + 1;
        const std::string labels_path = dagger_file(c.train, round, ".labels.bin");
        DaggerRollouts ro;
        if (!last && c.train.resume && file_exists(labels_path)) {
            ro.labels = load_demos(labels_path);  // rolled out before the interruption; only its success is recomputed
            DaggerRollouts eval = dagger_rollouts(scenes, learner(model), mc, 0, c.expert);
            ro.episodes = eval.episodes, ro.successes = eval.successes, ro.collisions = eval.collisions;
        } else {
            ro = dagger_rollouts(scenes, learner(model), mc, last ? 0 : c.label_every, c.expert);
            if (!last) {
                save_demos(labels_path, ro.labels);
                ro.labels = load_demos(labels_path);  // as stored (f32), so a resumed run trains on the same values
            }
        }
        DaggerRound r;
        r.round = round;
        r.episodes = ro.episodes;
        r.success = ro.success();
        r.success_se = ro.success_se();
        r.collisions = (double)ro.collisions / std::max(1, ro.episodes);
        r.labels = (long)ro.labels.episodes.size();
        if (!last) {
            for (Demonstration& d : ro.labels.episodes) labels.episodes.push_back(std::move(d));
            // This round's fine-tune set: every label so far, then base episodes in an order
            // drawn from the round's seed until their windows reach base_ratio x the labels'.
            DemoSet mix;
            mix.demonstrator = base.demonstrator + "+dagger";
            mix.episodes = labels.episodes;
            double label_windows = 0;
            for (int e = 0; e < (int)labels.episodes.size(); ++e) label_windows += make_windows(labels, {e}, mc, 1).size();
            std::vector<int> order(base.episodes.size());
            std::iota(order.begin(), order.end(), 0);
            Rng shuffle(c.train.seed + 0xda66e7ull * round);
            for (int i = (int)order.size() - 1; i > 0; --i) std::swap(order[i], order[shuffle.uniform_int(i + 1)]);
            double base_windows = 0;
            for (int e : order) {
                if (base_windows >= c.base_ratio * label_windows) break;
                mix.episodes.push_back(base.episodes[e]);
                base_windows += make_windows(base, {e}, mc, 1).size();
            }
            r.train_episodes = (long)mix.episodes.size();
            TrainConfig tc = c.train;
            tc.out = dagger_file(c.train, round, ".safetensors");
            tc.resume = c.train.resume && file_exists(tc.out + ".train");
            tc.seed = c.train.seed + round;
            if (train(mix, model, tc).steps < tc.steps) return done;  // stopped by train.keep_going: resume later
        }
        r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        done.push_back(r);
        const std::string csv = dagger_csv(done);
        write_file_atomic(log_path, std::vector<uint8_t>(csv.begin(), csv.end()));
        if (c.on_round) c.on_round(r);
    }
    save_model(c.train.out, model, {{"demonstrator", base.demonstrator + "+dagger"}, {"train.n_train_max", std::to_string(c.train.n_train_max)},
                                    {"train.dagger_rounds", std::to_string(c.rounds)}});
    return done;
}

}  // namespace madbp

// =============================================================================================
// Section 8. MAPPO (SPEC 3.3): the paper's demonstrator and baseline
// =============================================================================================

namespace madbp {

// ---------------------------------------------------------------------------------------------
// MAPPO observations (SPEC 3.3; VMAS navigation)

// Per agent, 6 + R numbers in this order (VMAS navigation's layout, lidar extended to the map):
//   [0, 2)      position p (x, y)
//   [2, 4)      velocity v
//   [4, 6)      p - goal (the relative goal, pointing from the goal to the agent); with a route
//               goal D > 0, p - route_goal(D) instead: the point D ahead on the agent's route
//               around the map, as MA-DBP's model is told (madbp.hpp route_goal; the goal itself
//               when it is within D and in view)
//   [6, 6 + R)  R lidar readings (default 12). Ray k leaves the agent's centre at angle
//               2 pi k / R from +x, counter-clockwise (R = 12: k = 0 +x, k = 3 +y, k = 6 -x,
//               k = 9 -y). It stops at the first surface of another agent's disc, a static disc,
//               a box or a border wall within the range (default 0.35). The reading is range -
//               distance, as VMAS feeds its lidar (max_range - measure): 0 when the ray hits
//               nothing, larger when closer, the range when the ray starts inside a surface.
// A policy's observation is part of its file (the layout string in "mappo.obs"). The defaults
// are VMAS navigation's; the barrier's policies see a route goal (docs/design.md "MAPPO").
constexpr int kLidarRays = 12;
constexpr double kLidarRange = 0.35;
constexpr int kMappoObs = 6 + kLidarRays;  // observation size with the default lidar (MADiff's)
constexpr int kMaxLidarRays = 360;

struct MappoObservation {
    int rays = kLidarRays;       // lidar rays, in [1, kMaxLidarRays]
    double range = kLidarRange;  // lidar range, world units, in (0, 10]
    double route_goal = 0;       // D: 0 the goal itself, else the route goal D ahead, in (0, 10]
    int size() const { return 6 + rays; }
    // "pos2,vel2,pos-goal2,lidar12@0.35(range-distance)" (the defaults), or with a route goal
    // "pos2,vel2,pos-routegoal2@1.5,lidar12@0.35(range-distance)": the observation, as files record it.
    std::string layout() const {
        return std::string("pos2,vel2,") + (route_goal > 0 ? "pos-routegoal2@" + number_text(route_goal) : std::string("pos-goal2")) +
               ",lidar" + std::to_string(rays) + "@" + number_text(range) + "(range-distance)";
    }
    // Lengths must survive the layout string (6 significant digits): a file then gives back the
    // observation it was trained on, and a resumed run's identity tells two runs apart.
    void check(const std::string& owner) const {
        auto exact = [](double v) { return std::strtod(number_text(v).c_str(), nullptr) == v; };
        if (rays < 1 || rays > kMaxLidarRays)
            throw std::invalid_argument(owner + ".rays: must be in [1, " + std::to_string(kMaxLidarRays) + "] (got " + std::to_string(rays) + ")");
        if (!(range > 0 && range <= 10) || !exact(range))
            throw std::invalid_argument(owner + ".range: must be in (0, 10] world units, at most 6 significant digits (got " +
                                        number_text(range) + ")");
        if (!(route_goal >= 0 && route_goal <= 10) || !exact(route_goal))
            throw std::invalid_argument(owner + ".route_goal: must be 0 (off) or in (0, 10] world units, at most 6 significant digits (got " +
                                        number_text(route_goal) + ")");
    }
    // The observation the layout string `layout` (metadata entry `key` of file `source`) names;
    // std::runtime_error naming both for any other string.
    static MappoObservation from_layout(const std::string& layout, const std::string& source, const std::string& key) {
        auto refuse = [&](const std::string& why) {
            return std::runtime_error(source + ": __metadata__['" + key + "'] = '" + layout.substr(0, 80) + "' is not an observation layout this build reads (" +
                                      why + "; e.g. '" + MappoObservation{}.layout() + "')");
        };
        MappoObservation o;
        const char* rest = layout.c_str();
        int used = 0;
        if (std::sscanf(rest, "pos2,vel2,pos-routegoal2@%lf,%n", &o.route_goal, &used) == 1 && used > 0) rest += used;
        else if (layout.compare(0, 20, "pos2,vel2,pos-goal2,") == 0) rest += 20;
        else throw refuse("it starts with neither pos2,vel2,pos-goal2 nor pos2,vel2,pos-routegoal2@D");
        if (std::strncmp(rest, "lidar", 5) != 0 || std::strspn(rest + 5, "0123456789") > 3 || std::sscanf(rest, "lidar%d@%lf", &o.rays, &o.range) != 2)
            throw refuse("no lidarR@range after the goal");
        try {
            o.check("obs");
        } catch (const std::invalid_argument& e) {
            throw refuse(e.what());
        }
        if (o.layout() != layout) throw refuse("not written as this build writes it");
        return o;
    }
};

namespace detail {
constexpr double kNoHit = std::numeric_limits<double>::infinity();

// Distance along the ray p + t d (t >= 0, |d| = 1) to the disc (c, r); 0 from inside.
inline double ray_disc(Vec2 p, Vec2 d, Vec2 c, double r) {
    const Vec2 m = p - c;
    const double b = dot(m, d), q = dot(m, m) - r * r;
    if (q <= 0) return 0;
    const double disc = b * b - q;
    if (b > 0 || disc < 0) return kNoHit;  // pointing away, or passing by
    return -b - std::sqrt(disc);
}
// Distance along the ray to the box (slab method); 0 from inside.
inline double ray_box(Vec2 p, Vec2 d, const Box& box) {
    double t0 = 0, t1 = kNoHit;
    const double pp[2] = {p.x, p.y}, dd[2] = {d.x, d.y}, lo[2] = {box.lo.x, box.lo.y}, hi[2] = {box.hi.x, box.hi.y};
    for (int a = 0; a < 2; ++a) {
        if (std::fabs(dd[a]) < 1e-12) {
            if (pp[a] < lo[a] || pp[a] > hi[a]) return kNoHit;
            continue;
        }
        double ta = (lo[a] - pp[a]) / dd[a], tb = (hi[a] - pp[a]) / dd[a];
        if (ta > tb) std::swap(ta, tb);
        t0 = std::max(t0, ta);
        t1 = std::min(t1, tb);
        if (t0 > t1) return kNoHit;
    }
    return t0;
}
// Distance along the ray to the border walls of [-h, h]^2 from a point inside (0 outside).
inline double ray_border(Vec2 p, Vec2 d, double h) {
    double t = kNoHit;
    if (d.x > 1e-12) t = std::min(t, (h - p.x) / d.x);
    if (d.x < -1e-12) t = std::min(t, (-h - p.x) / d.x);
    if (d.y > 1e-12) t = std::min(t, (h - p.y) / d.y);
    if (d.y < -1e-12) t = std::min(t, (-h - p.y) / d.y);
    return std::max(0.0, t);
}
}  // namespace detail

// Distance from agent index `i` of `world` along the unit direction `dir` to the first surface
// (other agents, static discs, boxes, border walls), capped at `range`.
inline double lidar_distance(const World& world, int i, Vec2 dir, double range = kLidarRange) {
    const WorldMap& map = world.map();
    const Vec2 p = world.agents()[i].pos;
    double t = std::min(range, detail::ray_border(p, dir, map.half_size));
    for (const Disc& o : map.discs) t = std::min(t, detail::ray_disc(p, dir, o.c, o.r));
    for (const Box& b : map.boxes) t = std::min(t, detail::ray_box(p, dir, b));
    const std::vector<Agent>& agents = world.agents();
    for (int j = 0; j < (int)agents.size(); ++j)
        if (j != i) t = std::min(t, detail::ray_disc(p, dir, agents[j].pos, world.config().radius));
    return t;
}

// Writes agent index `i`'s observation (layout above) to out[0, ob.size()). `guide` finds the
// route goal (required when ob.route_goal > 0; it keeps the map's grid and fields between calls).
inline void mappo_observe(const World& world, int i, float* out, const MappoObservation& ob = {}, RouteGuide* guide = nullptr) {
    const Agent& a = world.agents()[i];
    if (ob.route_goal > 0 && !guide) throw std::invalid_argument("mappo_observe: an observation with a route goal needs a RouteGuide");
    const Vec2 rel = a.pos - (ob.route_goal > 0 ? route_goal(*guide, ob.route_goal, world.map(), a.pos, a.goal).goal : a.goal);
    const float head[6] = {(float)a.pos.x, (float)a.pos.y, (float)a.vel.x, (float)a.vel.y, (float)rel.x, (float)rel.y};
    std::copy(head, head + 6, out);
    for (int k = 0; k < ob.rays; ++k) {
        const double angle = 2 * M_PI * k / ob.rays;
        out[6 + k] = (float)(ob.range - lidar_distance(world, i, {std::cos(angle), std::sin(angle)}, ob.range));
    }
}

// Fixed input scaling of the networks (our observation normalisation): each feature divided by
// its natural range (world half-size 1.2 for positions, top speed 0.4, the lidar's range), so
// inputs are O(1) without running statistics that a checkpoint would have to carry.
inline float mappo_obs_scale(int feature, const MappoObservation& ob = {}) {
    if (feature < 2 || (feature >= 4 && feature < 6)) return 1.0f / 1.2f;
    if (feature < 4) return 1.0f / 0.4f;
    return (float)(1.0 / ob.range);
}

// Scaled observations of every agent of `world`, one column each, into columns
// [col, col + n) of `obs` (ob.size() rows); `guide` as for mappo_observe.
inline void mappo_observe_all(const World& world, Mat& obs, long col, const MappoObservation& ob = {}, RouteGuide* guide = nullptr) {
    MADBP_ASSERT(obs.rows() == ob.size() && ob.rays <= kMaxLidarRays);
    float raw[6 + kMaxLidarRays];  // on the stack: this runs every step of every world
    for (int i = 0; i < world.size(); ++i) {
        mappo_observe(world, i, raw, ob, guide);
        for (int f = 0; f < ob.size(); ++f) obs(f, col + i) = raw[f] * mappo_obs_scale(f, ob);
    }
}

// Critic input of a team of n agents whose actor inputs are columns [col, col + n) of `obs`:
// for agent i, its own observation followed by the others' in index order (n * O rows). The
// critic is centralised (it sees every agent) yet per agent, so agents keep their own rewards.
inline void mappo_critic_input(const Mat& obs, long col, int n, Mat& critic, long out_col) {
    const long O = obs.rows();
    for (int i = 0; i < n; ++i) {
        critic.block(0, out_col + i, O, 1) = obs.col(col + i);
        int slot = 1;
        for (int j = 0; j < n; ++j)
            if (j != i) critic.block(O * slot++, out_col + i, O, 1) = obs.col(col + j);
    }
}

// ---------------------------------------------------------------------------------------------
// MAPPO networks (SPEC 3.3)

// x (in, N) -> Linear -> Tanh -> Linear -> Tanh -> Linear -> y (out, N). Keeps the
// activations of its last forward for backward.
struct Mlp {
    Linear l1, l2, l3;
    Tanh t1, t2;
    Mat h1, a1, h2, a2, da2, dh2, da1, dh1, dx;

    Mlp() = default;
    // `out_gain` scales the last layer's initial weights (0.01 for the policy mean, as PPO
    // implementations do, so the first actions are near zero and training starts unbiased).
    Mlp(ParamStore& ps, const std::string& name, int in, int hidden, int out, Rng& rng, float out_gain = 1.0f)
        : l1(ps, name + ".fc1", in, hidden, rng), l2(ps, name + ".fc2", hidden, hidden, rng), l3(ps, name + ".fc3", hidden, out, rng) {
        ps.value.segment(l3.w, hidden * out) *= out_gain;
    }
    void forward(const Mat& x, Mat& y) {
        l1.forward(x, h1);
        t1.forward(h1, a1);
        l2.forward(a1, h2);
        t2.forward(h2, a2);
        l3.forward(a2, y);
    }
    // Adds the parameter gradients of the loss whose gradient at y is dy (x as in forward).
    void backward(const Mat& x, const Mat& dy) {
        l3.backward(a2, dy, da2);
        t2.backward(h2, da2, dh2);
        l2.backward(a1, dh2, da1);
        t1.backward(h1, da1, dh1);
        l1.backward(x, dh1, dx);
    }
};

// Architecture of a MAPPO policy; stored in the checkpoint.
struct MappoNetConfig {
    int agents = 2;            // team size n the policy is built for (>= 1)
    int hidden = 64;           // width of both hidden layers of actor and critic
    float init_log_std = -0.5f;
    MappoObservation obs;      // what the actor observes
};

// The shared actor (scaled observation -> mean force (2), plus a state-independent learned
// log-std (2)) and the centralised critic (n * O critic input -> value). One parameter store:
// entries "actor.fc{1,2,3}.{weight,bias}", "actor.log_std", "critic.fc{1,2,3}.{weight,bias}".
class MappoNet {
public:
    MappoNetConfig config;
    std::unique_ptr<ParamStore> params;  // heap-held: the layers keep pointers to it
    Mlp actor, critic;
    int log_std = -1;                    // offset of actor.log_std (2)

    explicit MappoNet(MappoNetConfig c, uint64_t seed = 0) : config(c), params(new ParamStore) {
        if (c.agents < 1 || c.agents > 64) throw std::invalid_argument("agents: must be in [1, 64] (got " + std::to_string(c.agents) + ")");
        if (c.hidden < 1 || c.hidden > 4096) throw std::invalid_argument("hidden: must be in [1, 4096] (got " + std::to_string(c.hidden) + ")");
        c.obs.check("obs");
        Rng rng(seed);
        actor = Mlp(*params, "actor", c.obs.size(), c.hidden, 2, rng, 0.01f);
        log_std = params->add("actor.log_std", {2}, Init::zeros(), rng);
        params->vec(log_std, 2).setConstant(c.init_log_std);
        critic = Mlp(*params, "critic", c.obs.size() * c.agents, c.hidden, 1, rng);
    }
    MappoNet(MappoNet&&) = default;
    MappoNet& operator=(MappoNet&&) = default;
    MappoNet clone() const {
        MappoNet m(config);
        m.params->value = params->value;
        return m;
    }
    Eigen::Vector2f log_std_value() const { return params->vec(log_std, 2); }
    std::map<std::string, std::string> metadata() const {
        return {{"format", "madbp-mappo"}, {"mappo.agents", std::to_string(config.agents)},
                {"mappo.hidden", std::to_string(config.hidden)}, {"mappo.obs", config.obs.layout()}};
    }
};

// ---------------------------------------------------------------------------------------------
// Gaussian policy and the PPO objective (SPEC 3.3)

// Diagonal Gaussian over the 2 force components. log N(a; mu, sigma) =
// sum_k -(a_k - mu_k)^2 / (2 sigma_k^2) - log sigma_k - log(2 pi) / 2. The gradients are
// d/dmu_k = (a_k - mu_k) / sigma_k^2 and d/dlog sigma_k = (a_k - mu_k)^2 / sigma_k^2 - 1.
// The sample is clipped to the action box only when stepping the world; log-probabilities
// are of the unclipped sample (as BenchMARL's Gaussian policy).
inline float gaussian_log_prob(const float* a, const float* mu, const float* log_sigma, float* dmu = nullptr,
                               float* dlog_sigma = nullptr) {
    float lp = 0;
    for (int k = 0; k < 2; ++k) {
        const float inv_var = std::exp(-2 * log_sigma[k]), diff = a[k] - mu[k];
        lp += -0.5f * diff * diff * inv_var - log_sigma[k] - 0.9189385332f;
        if (dmu) dmu[k] = diff * inv_var;
        if (dlog_sigma) dlog_sigma[k] = diff * diff * inv_var - 1;
    }
    return lp;
}
// Entropy sum_k (1/2 + log(2 pi)/2 + log sigma_k); its gradient is 1 per log sigma_k.
inline float gaussian_entropy(const float* log_sigma) { return 2 * (0.5f + 0.9189385332f) + log_sigma[0] + log_sigma[1]; }

// The clipped surrogate (PPO): mean over samples of -min(r A, clip(r, 1-eps, 1+eps) A), with
// r = exp(logp - logp_old). Writes dloss/dlogp per sample: -r A / N where the unclipped term
// is the minimum or r lies inside the clip range, else 0. Also the fraction of clipped samples.
inline double clipped_surrogate(const Vec& logp, const Vec& logp_old, const Vec& adv, float eps, Vec& dlogp,
                                double* clip_fraction = nullptr) {
    const long N = logp.size();
    MADBP_ASSERT(logp_old.size() == N && adv.size() == N && N > 0);
    dlogp.resize(N);
    double loss = 0;
    long clipped = 0;
    for (long s = 0; s < N; ++s) {
        const float r = std::exp(logp[s] - logp_old[s]), rc = std::clamp(r, 1 - eps, 1 + eps);
        const bool use_unclipped = r * adv[s] <= rc * adv[s] || r == rc;
        loss -= std::min(r * adv[s], rc * adv[s]);
        dlogp[s] = use_unclipped ? -r * adv[s] / N : 0.0f;
        clipped += !use_unclipped;
    }
    if (clip_fraction) *clip_fraction = (double)clipped / N;
    return loss / N;
}

// Generalised advantage estimation over one stream of T steps (entries `stride` apart):
// delta_t = r_t + gamma V_{t+1} (1 - term_t) - V_t, A_t = delta_t + gamma lambda (1 - term_t)
// A_{t+1}, returns R_t = A_t + V_t. V_T = `last_value` (the bootstrap of a stream cut by the
// iteration, or of a time-out, which our observations cannot tell from any other step).
// `terminal` marks steps that ended an episode by success: nothing follows them; the next
// entry starts a fresh episode.
inline void gae(const float* reward, const float* value, const uint8_t* terminal, float last_value, int T, long stride,
                float gamma, float lambda, float* adv, float* ret) {
    float next_value = last_value, next_adv = 0;
    for (int t = T - 1; t >= 0; --t) {
        const long s = t * stride;
        const float keep = terminal[s] ? 0.0f : 1.0f;
        const float delta = reward[s] + gamma * next_value * keep - value[s];
        adv[s] = delta + gamma * lambda * keep * next_adv;
        ret[s] = adv[s] + value[s];
        next_value = value[s];
        next_adv = adv[s];
    }
}

// One PPO minibatch's losses.
struct PpoTerms {
    double policy = 0, value = 0, entropy = 0, approx_kl = 0, clip_fraction = 0;
};

// Minibatch of samples (columns) and the coefficients of the loss
// policy + vf_coef * value - ent_coef * entropy, value = mean (V - R)^2 / 2.
struct PpoBatch {
    Mat obs, critic_in, act;   // (O, N), (n O, N), (2, N)
    Vec logp_old, adv, ret;    // (N)
};
struct PpoCoefficients {
    float ratio_clip = 0.2f, vf_coef = 0.5f, ent_coef = 1e-3f;
};

// Forward and backward of the full PPO loss on one minibatch: adds the gradients to
// net.params->grad (the caller zeroes them) and returns the terms. Workspaces in `ws`.
struct PpoWorkspace {
    Mat mean, value, dmean, dvalue;
    Vec logp, dlogp;
};
inline PpoTerms ppo_loss(MappoNet& net, const PpoBatch& b, const PpoCoefficients& k, PpoWorkspace& ws) {
    const long N = b.obs.cols();
    PpoTerms terms;
    net.actor.forward(b.obs, ws.mean);
    const Eigen::Vector2f ls = net.log_std_value();
    ws.logp.resize(N);
    for (long s = 0; s < N; ++s) ws.logp[s] = gaussian_log_prob(&b.act(0, s), &ws.mean(0, s), ls.data());
    terms.policy = clipped_surrogate(ws.logp, b.logp_old, b.adv, k.ratio_clip, ws.dlogp, &terms.clip_fraction);
    terms.approx_kl = (b.logp_old - ws.logp).mean();
    terms.entropy = gaussian_entropy(ls.data());
    // Chain rule through the log-probability: d/dmu and d/dlog sigma per sample.
    ws.dmean.resize(2, N);
    float dls[2] = {-k.ent_coef, -k.ent_coef};  // - ent_coef * dH/dlog sigma
    for (long s = 0; s < N; ++s) {
        float dmu[2], dsig[2];
        gaussian_log_prob(&b.act(0, s), &ws.mean(0, s), ls.data(), dmu, dsig);
        for (int c = 0; c < 2; ++c) {
            ws.dmean(c, s) = ws.dlogp[s] * dmu[c];
            dls[c] += ws.dlogp[s] * dsig[c];
        }
    }
    net.actor.backward(b.obs, ws.dmean);
    for (int c = 0; c < 2; ++c) net.params->grad[net.log_std + c] += dls[c];
    net.critic.forward(b.critic_in, ws.value);
    ws.dvalue = (ws.value.row(0) - b.ret.transpose()) * (k.vf_coef / N);
    terms.value = 0.5 * (ws.value.row(0) - b.ret.transpose()).squaredNorm() / N;
    net.critic.backward(b.critic_in, ws.dvalue);
    return terms;
}

// ---------------------------------------------------------------------------------------------
// MAPPO training (SPEC 3.3)

// Rewards per agent and step (VMAS navigation's terms; our constants):
//   shaping * (distance to goal before the step - after it)     VMAS pos_shaping_factor 1
//   + success_bonus to every agent on the step the team succeeds (all at goal together)
//   + collision per contact the agent is in (agent-agent pair or agent-static)
//   + time per step (a small push toward finishing early)
// VMAS's collision penalty is -1, but with obstacles that is a whole episode's shaping for one
// step of contact and the policy grew timid: obstacles n = 2 reached .52 with (-1, bonus 1),
// .88 with (-0.1, 1) and .94 with (-0.1, 5) (200 iterations, 100 evaluation episodes; docs/experiments.md).
// With `route` set the shaping distance is the length of the shortest way around the map
// (RouteDistance) rather than the straight one: on the barrier the straight distance rewards
// pressing against the wall in front of the goal, a trap the policy must unlearn, while the way
// through the gap rewards every step toward it. (Either is a difference of potentials, as VMAS
// shapes, undiscounted: close to, not exactly, a shaping that leaves the best policy unchanged.)
struct MappoRewards {
    float shaping = 1.0f, success_bonus = 5.0f, collision = -0.1f, time = -0.01f;
    float at_goal = 0.0f;  // per step while within the goal tolerance
    bool route = false;    // shaping on the route distance (RouteDistance), not the straight one
};

// Length of the shortest way from any point to one goal around a map's obstacles, for reward
// shaping: Dijkstra over the cells of a ClearanceGrid (cells of about 0.04) a robot's centre
// fits in, 8-connected with steps of 1 and sqrt 2 cells (in open space at most 8 % longer than
// the straight distance, the octile metric); at p, the least of (cell's distance + straight
// distance from p to the cell's centre) over p's 3 x 3 cells, so it changes smoothly as a robot
// moves. Where none of those cells is reachable (inside an obstacle), the straight distance.
// Not RouteGuide's wavefront: that counts grid steps, with an extra cost for narrow cells, to
// choose a route; shaping needs the route's length. Memory: 8 bytes a cell (its ClearanceGrid
// and the distances; 3600 cells in the standard world).
class RouteDistance {
public:
    RouteDistance() = default;
    RouteDistance(const WorldMap& map, Vec2 goal, double cell = 0.04) : grid_(map, cell), goal_(goal) {
        const int n = grid_.n;
        dist_.assign((size_t)n * n, kFar);
        using Item = std::pair<float, int>;
        std::priority_queue<Item, std::vector<Item>, std::greater<Item>> open;
        const int g = grid_.index(goal);
        dist_[g] = (float)norm(grid_.centre(g) - goal);
        open.push({dist_[g], g});
        while (!open.empty()) {
            const auto [d, k] = open.top();
            open.pop();
            if (d > dist_[k]) continue;
            detail::for_each_neighbour(n, k, [&](int k2) {
                if (grid_.clear[k2] < kPassableClearance) return;
                const bool diagonal = k2 % n != k % n && k2 / n != k / n;
                const float d2 = d + (float)(grid_.cell * (diagonal ? M_SQRT2 : 1.0));
                if (d2 < dist_[k2]) dist_[k2] = d2, open.push({d2, k2});
            });
        }
    }
    double operator()(Vec2 p) const {
        const int n = grid_.n, k = grid_.index(p), row = k / n, col = k % n;
        double best = kFar;
        for (int r = std::max(0, row - 1); r <= std::min(n - 1, row + 1); ++r)
            for (int c = std::max(0, col - 1); c <= std::min(n - 1, col + 1); ++c) {
                const int k2 = r * n + c;
                if (dist_[k2] < kFar) best = std::min(best, dist_[k2] + norm(p - grid_.centre(k2)));
            }
        return best < kFar ? best : norm(p - goal_);
    }
    Vec2 goal() const { return goal_; }

private:
    static constexpr float kFar = std::numeric_limits<float>::infinity();
    ClearanceGrid grid_;
    Vec2 goal_;
    std::vector<float> dist_;
};

// The reward of agent index i of `world` for the step just taken: `before` and `after` are its
// shaping distances to its goal (straight or RouteDistance) before and after the step,
// `contacts` the contacts it was in during the step.
inline float mappo_reward(const MappoRewards& r, const World& world, int i, double before, double after, int contacts) {
    const Agent& a = world.agents()[i];
    return r.shaping * (float)(before - after) + r.collision * contacts + r.time +
           (world.metrics().success ? r.success_bonus : 0.0f) + (world.at_goal(a) ? r.at_goal : 0.0f);
}

struct MappoConfig {
    std::string map = "empty";     // map name (SPEC 2)
    int agents = 2;                // team size n, in [1, 64]
    double half_size = 1.2;        // world half-size
    int hidden = 64;               // actor and critic width (2 hidden layers, Tanh)
    float init_log_std = -0.5f;
    MappoObservation obs;          // what the actor observes (lidar, goal or route goal)
    int worlds = 32;               // worlds stepping together; each iteration plays max_steps (100) steps on each
    long iterations = 300;         // rollout + update rounds
    int epochs = 4;                // passes over each rollout
    int minibatches = 4;           // per epoch
    float lr = 3e-4f, gamma = 0.99f, lambda = 0.9f, max_grad_norm = 1.0f;
    PpoCoefficients ppo;
    MappoRewards rewards;
    uint64_t seed = 0;
    std::string out;               // policy file ("" = no files); + ".train" (resumable state), ".csv", ".svg"
    bool resume = false;           // continue from out + ".train"
    long checkpoint_every = 10;    // iterations
    int threads = 1;               // OpenMP threads (worlds, observations, products); results do not depend on it
    ProgressFn progress;           // called after every iteration (optional)
    // Called after every iteration; false stops there, after a checkpoint (time budgets).
    std::function<bool(long iteration)> keep_going;

    void validate() const {
        Rng probe(0);
        make_map(map, probe, half_size);  // throws on an unknown name
        obs.check("obs");
        if (agents < 1 || agents > 64) throw std::invalid_argument("agents: must be in [1, 64] (got " + std::to_string(agents) + ")");
        if (worlds < 1 || iterations < 1 || epochs < 1 || minibatches < 1 || checkpoint_every < 1)
            throw std::invalid_argument("MappoConfig: worlds, iterations, epochs, minibatches, checkpoint_every must be >= 1");
        if (!(lr > 0 && gamma > 0 && gamma <= 1 && lambda >= 0 && lambda <= 1 && max_grad_norm > 0 && ppo.ratio_clip > 0))
            throw std::invalid_argument("MappoConfig: lr, gamma, lambda, max_grad_norm or clip out of range");
        if (resume && out.empty()) throw std::invalid_argument("resume: needs an output file");
    }
    // The hyper-parameters as checkpoint metadata (the record of how a policy was trained).
    std::map<std::string, std::string> metadata() const {
        auto f = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.6g", v); return std::string(b); };
        return {{"mappo.map", map}, {"mappo.half_size", f(half_size)}, {"mappo.worlds", std::to_string(worlds)},
                {"mappo.epochs", std::to_string(epochs)}, {"mappo.minibatches", std::to_string(minibatches)},
                {"mappo.lr", f(lr)}, {"mappo.gamma", f(gamma)}, {"mappo.lambda", f(lambda)}, {"mappo.clip", f(ppo.ratio_clip)},
                {"mappo.vf_coef", f(ppo.vf_coef)}, {"mappo.ent_coef", f(ppo.ent_coef)},
                {"mappo.max_grad_norm", f(max_grad_norm)}, {"mappo.seed", std::to_string(seed)},
                {"mappo.rewards", "shaping " + f(rewards.shaping) + ", success " + f(rewards.success_bonus) +
                                      ", collision " + f(rewards.collision) + ", time " + f(rewards.time) + ", at_goal " + f(rewards.at_goal) +
                                      (rewards.route ? ", route distance" : "")}};
    }
};

// The training curve (<out>.csv): per iteration, statistics of each world's first episode
// (exactly `worlds` complete, unbiased episodes; later ones are cut by the iteration): success
// rate, mean per-agent undiscounted return, and the mean PPO terms over the minibatches.
struct MappoReport {
    long iterations = 0, env_steps = 0;
    double seconds = 0;
    Curve curve;  // iteration, env_steps, seconds, success, episode_return, policy_loss, value_loss, entropy, approx_kl, clip_fraction
};

namespace detail {

// Everything one iteration collects: columns s = (t * W + w) * n + i.
struct Rollout {
    Mat obs, critic_in, act;
    Vec logp, value, reward, adv, ret;
    std::vector<uint8_t> terminal;
    void resize(int O, int n, long S) {
        obs.resize(O, S);
        critic_in.resize((long)O * n, S);
        act.resize(2, S);
        logp.resize(S), value.resize(S), reward.resize(S), adv.resize(S), ret.resize(S);
        terminal.assign(S, 0);
    }
};

}  // namespace detail

// Saves a policy file: the parameters and the metadata of net and training (no optimizer).
inline void save_mappo(const std::string& path, const MappoNet& net, std::map<std::string, std::string> extra = {}) {
    auto md = net.metadata();
    for (auto& kv : extra) md[kv.first] = kv.second;
    save_params(path, *net.params, md);
}

namespace detail {
inline int meta_int(const SafeTensors& st, const std::string& key, int lo, int hi) {
    const std::string& s = st.meta(key);
    char* end = nullptr;
    const long v = std::strtol(s.c_str(), &end, 10);
    if (s.empty() || *end != '\0' || v < lo || v > hi)
        throw std::runtime_error(st.source + ": __metadata__['" + key + "'] = '" + s + "' is not an integer in [" +
                                 std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return (int)v;
}
inline MappoNet mappo_from(const SafeTensors& st) {
    auto it = st.metadata.find("format");
    if (it == st.metadata.end() || it->second != "madbp-mappo")
        throw std::runtime_error(st.source + ": not a MAPPO policy (__metadata__['format'] is '" +
                                 (it == st.metadata.end() ? std::string("missing") : it->second) + "', expected 'madbp-mappo')");
    MappoNetConfig c;
    c.obs = MappoObservation::from_layout(st.meta("mappo.obs"), st.source, "mappo.obs");
    c.agents = meta_int(st, "mappo.agents", 1, 64);
    c.hidden = meta_int(st, "mappo.hidden", 1, 4096);
    const ParamBudget budget(st.values(), st.source);  // the declared net may need no more values than the file holds
    MappoNet net(c);
    read_param_tensors(st, *net.params);
    for (long k = 0; k < net.params->size(); ++k)
        if (!std::isfinite(net.params->value[k])) throw std::runtime_error(st.source + ": a parameter is not finite");
    return net;
}
}  // namespace detail

// Loads a policy file (or a .train state file); a file that is not a MAPPO policy, or whose
// tensors do not match the architecture its metadata declares, throws std::runtime_error
// naming the file and the field.
inline MappoNet load_mappo(const std::string& path) { return detail::mappo_from(load_safetensors(path)); }

// Trains a MAPPO policy. Each iteration: `worlds` fresh random worlds (seeds from the run's
// RNG), max_steps (100) steps on each with the sampled actions, a world that succeeds is
// replaced at once by a fresh one; GAE; `epochs` passes of `minibatches` PPO steps (Adam,
// global-norm clip). Because every iteration starts from fresh worlds, the state at an
// iteration boundary is just (parameters, Adam, RNG): a resumed run continues exactly as an
// uninterrupted one. Deterministic for a seed, whatever the thread count.
inline MappoReport train_mappo(const MappoConfig& c, MappoNet* result = nullptr) {
    c.validate();
    set_num_threads(std::max(1, c.threads));
    MappoNetConfig nc;
    nc.agents = c.agents;
    nc.hidden = c.hidden;
    nc.init_log_std = c.init_log_std;
    nc.obs = c.obs;
    MappoNet net(nc, c.seed);
    Adam adam;
    adam.lr = c.lr;
    Rng rng(c.seed ^ 0x3a990f00ull);
    MappoReport rep;
    long iteration = 0;
    double seconds_before = 0;
    // Identity: every hyper-parameter and the seed (c.metadata()) and the network's shape; a
    // resumed run may ask for more iterations.
    std::map<std::string, std::string> identity = c.metadata();
    for (auto& kv : net.metadata()) identity[kv.first] = kv.second;
    TrainState state(c.out, *net.params, adam, nullptr, {{"mappo.rng", &rng}}, identity,
                     {"iteration", "env_steps", "seconds", "success", "episode_return", "policy_loss", "value_loss", "entropy",
                      "approx_kl", "clip_fraction"});
    if (c.resume) {
        // Adam updates per iteration: one per non-empty minibatch (the rollout's S samples in
        // c.minibatches parts) of each epoch.
        const long samples = (long)WorldConfig{}.max_steps * c.worlds * c.agents;
        iteration = state.resume(c.iterations, (long)c.epochs * std::min<long>(c.minibatches, samples));
        seconds_before = state.resumed_numbers("mappo.seconds", 1)[0];
    }
    const int n = c.agents, W = c.worlds, O = c.obs.size();
    WorldConfig wc;
    const int T = wc.max_steps;
    const long S = (long)T * W * n, per_step = (long)W * n;
    detail::Rollout ro;
    ro.resize(O, n, S);
    WorldBatch batch;
    std::vector<std::vector<Vec2>> actions(W, std::vector<Vec2>(n));
    Mat step_obs(O, per_step), step_critic((long)O * n, per_step), mean, values;
    std::vector<double> dist_before(per_step);
    std::vector<std::vector<RouteDistance>> routes(W);  // per world, per agent (rewards.route)
    std::vector<RouteGuide> guides(W);                  // per world (route goals in observations)
    PpoWorkspace ws;
    PpoBatch mb;
    const auto t_start = std::chrono::steady_clock::now();
    auto elapsed = [&] { return seconds_before + std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count(); };
    auto save = [&] {
        if (c.out.empty()) return;
        std::map<std::string, std::string> md = c.metadata();
        md["mappo.iteration"] = std::to_string(iteration);
        md["mappo.env_steps"] = std::to_string(iteration * (long)T * W);
        char secs[32];
        std::snprintf(secs, sizeof secs, "%.3f", elapsed());
        md["mappo.seconds"] = secs;
        save_mappo(c.out, net, md);
        state.save(iteration, md);
    };
    auto fresh_world = [&](uint64_t seed) { return make_random_world(c.map, n, seed, c.half_size, wc); };
    // A world's shaping distances: fields made when the world is, read every step.
    auto make_routes = [&](int w) {
        routes[w].clear();
        if (c.rewards.route)
            for (const Agent& ag : batch.worlds[w].agents()) routes[w].emplace_back(batch.worlds[w].map(), ag.goal);
    };
    auto shaping_distance = [&](int w, int i) {
        const Agent& ag = batch.worlds[w].agents()[i];
        if (!c.rewards.route) return norm(ag.pos - ag.goal);
        MADBP_ASSERT(routes[w][i].goal() == ag.goal);  // made for this world
        return routes[w][i](ag.pos);
    };
    auto observe_world = [&](int w) {
        mappo_observe_all(batch.worlds[w], step_obs, (long)w * n, c.obs, &guides[w]);
        mappo_critic_input(step_obs, (long)w * n, n, step_critic, (long)w * n);
    };
    while (iteration < c.iterations) {
        // ---- Rollout: T steps on W worlds.
        batch.worlds.clear();
        for (int w = 0; w < W; ++w) batch.worlds.push_back(fresh_world(rng.next_u64()));
        std::vector<uint8_t> first_done(W, 0), first_success(W, 0);
        std::vector<double> first_return(W, 0);
#pragma omp parallel for schedule(static)
        for (int w = 0; w < W; ++w) {
            make_routes(w);
            observe_world(w);
        }
        for (int t = 0; t < T; ++t) {
            const long col = t * per_step;
            net.actor.forward(step_obs, mean);
            net.critic.forward(step_critic, values);
            const Eigen::Vector2f ls = net.log_std_value();
            for (long k = 0; k < per_step; ++k) {
                float a[2];
                for (int d = 0; d < 2; ++d) a[d] = mean(d, k) + std::exp(ls[d]) * (float)rng.normal();
                ro.act(0, col + k) = a[0], ro.act(1, col + k) = a[1];
                ro.logp[col + k] = gaussian_log_prob(a, &mean(0, k), ls.data());
                actions[k / n][k % n] = clamp_box(Vec2{a[0], a[1]}, wc.max_action);
                dist_before[k] = shaping_distance((int)(k / n), (int)(k % n));
            }
            ro.obs.middleCols(col, per_step) = step_obs;
            ro.critic_in.middleCols(col, per_step) = step_critic;
            ro.value.segment(col, per_step) = values.row(0).transpose();
            batch.step(actions);
            // Rewards, episode ends (success: terminal, then a fresh world), next observations.
            std::vector<uint64_t> reseed(W);
            for (int w = 0; w < W; ++w) reseed[w] = batch.worlds[w].done() ? rng.next_u64() : 0;
#pragma omp parallel for schedule(static)
            for (int w = 0; w < W; ++w) {
                World& world = batch.worlds[w];
                std::vector<int> contacts(n, 0);
                for (auto pr : world.last_agent_contacts()) contacts[world.index_of(pr.first)]++, contacts[world.index_of(pr.second)]++;
                for (int id : world.last_static_contacts()) contacts[world.index_of(id)]++;
                const bool success = world.metrics().success;
                for (int i = 0; i < n; ++i) {
                    const long s = col + (long)w * n + i;
                    ro.reward[s] = mappo_reward(c.rewards, world, i, dist_before[(long)w * n + i], shaping_distance(w, i), contacts[i]);
                    ro.terminal[s] = success;
                    if (!first_done[w]) first_return[w] += ro.reward[s] / n;
                }
                if (world.done()) {
                    if (!first_done[w]) first_done[w] = 1, first_success[w] = success;
                    if (t + 1 < T) {
                        world = fresh_world(reseed[w]);
                        make_routes(w);
                    }
                }
                observe_world(w);
            }
        }
        // ---- Advantages: bootstrap every stream with V(state after the last step).
        net.critic.forward(step_critic, values);
        for (long k = 0; k < per_step; ++k)
            gae(ro.reward.data() + k, ro.value.data() + k, ro.terminal.data() + k, values(0, k), T, per_step, c.gamma, c.lambda,
                ro.adv.data() + k, ro.ret.data() + k);
        const float adv_mean = ro.adv.mean();
        const float adv_std = std::sqrt((ro.adv.array() - adv_mean).square().mean()) + 1e-8f;
        ro.adv = (ro.adv.array() - adv_mean) / adv_std;  // normalised over the whole rollout
        // ---- PPO epochs over shuffled minibatches.
        std::vector<long> order(S);
        for (long s = 0; s < S; ++s) order[s] = s;
        PpoTerms sum;
        int updates = 0;
        for (int e = 0; e < c.epochs; ++e) {
            for (long s = S - 1; s > 0; --s) std::swap(order[s], order[(long)(rng.uniform() * (s + 1))]);
            for (int m = 0; m < c.minibatches; ++m) {
                const long b0 = S * m / c.minibatches, B = S * (m + 1) / c.minibatches - b0;
                if (B == 0) continue;
                mb.obs.resize(O, B), mb.critic_in.resize((long)O * n, B), mb.act.resize(2, B);
                mb.logp_old.resize(B), mb.adv.resize(B), mb.ret.resize(B);
                for (long j = 0; j < B; ++j) {
                    const long s = order[b0 + j];
                    mb.obs.col(j) = ro.obs.col(s);
                    mb.critic_in.col(j) = ro.critic_in.col(s);
                    mb.act.col(j) = ro.act.col(s);
                    mb.logp_old[j] = ro.logp[s], mb.adv[j] = ro.adv[s], mb.ret[j] = ro.ret[s];
                }
                net.params->zero_grad();
                PpoTerms l = ppo_loss(net, mb, c.ppo, ws);
                if (!std::isfinite(l.policy) || !std::isfinite(l.value))
                    throw std::runtime_error("mappo: loss became non-finite at iteration " + std::to_string(iteration));
                clip_grad_norm(*net.params, c.max_grad_norm);
                adam.update(*net.params);
                sum.policy += l.policy, sum.value += l.value, sum.entropy += l.entropy;
                sum.approx_kl += l.approx_kl, sum.clip_fraction += l.clip_fraction;
                ++updates;
            }
        }
        ++iteration;
        double success = 0, episode_return = 0;
        for (int w = 0; w < W; ++w) success += first_success[w], episode_return += first_return[w];
        success /= W, episode_return /= W;
        const double u = std::max(1, updates);
        state.curve.add({(double)iteration, (double)(iteration * (long)T * W), elapsed(), success, episode_return, sum.policy / u,
                         sum.value / u, sum.entropy / u, sum.approx_kl / u, sum.clip_fraction / u});
        const bool stop = c.keep_going && !c.keep_going(iteration);
        if (iteration % c.checkpoint_every == 0 || iteration == c.iterations || stop) save();
        if (c.progress) {
            char note[96];
            std::snprintf(note, sizeof note, "success %.2f  return %.3f", success, episode_return);
            c.progress(iteration, c.iterations, note);
        }
        if (stop) break;
    }
    rep.curve = state.curve;
    rep.iterations = iteration;
    rep.env_steps = iteration * (long)T * W;
    rep.seconds = elapsed();
    if (result) *result = std::move(net);
    return rep;
}

// ---------------------------------------------------------------------------------------------
// Running a trained policy (SPEC 3.3, 9)

// Drives a team with the actor's mean action (deterministic, no safety filter: MAPPO runs raw,
// as in the paper), clipped to the action box. The team must have exactly the policy's n
// agents (std::invalid_argument otherwise): MAPPO is built per team size. decision_ms() is the
// mean wall time of one act() call (the per-step decision time of Fig. 3b).
class MappoPolicy : public Policy {
public:
    explicit MappoPolicy(MappoNet net) : net_(std::move(net)) {}
    std::vector<Vec2> act(const World& world) override {
        const auto t0 = std::chrono::steady_clock::now();
        const int n = net_.config.agents;
        if (world.size() != n)
            throw std::invalid_argument("mappo: the policy was trained for " + std::to_string(n) + " agents, the world has " +
                                        std::to_string(world.size()) + " (MAPPO is trained per team size)");
        obs_.resize(net_.config.obs.size(), n);
        mappo_observe_all(world, obs_, 0, net_.config.obs, &guide_);
        net_.actor.forward(obs_, mean_);
        std::vector<Vec2> u(n);
        for (int i = 0; i < n; ++i) u[i] = clamp_box(Vec2{mean_(0, i), mean_(1, i)}, world.config().max_action);
        total_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        ++calls_;
        return u;
    }
    double decision_ms() const override { return calls_ ? total_ms_ / calls_ : 0; }
    int agents() const { return net_.config.agents; }

private:
    MappoNet net_;
    Mat obs_, mean_;
    RouteGuide guide_;  // route goals (a policy whose observation has one)
    double total_ms_ = 0;
    long calls_ = 0;
};

// Per-episode MAPPO policies from policy files, loaded once each (every episode gets its own
// copy, so episodes can run in parallel). Usable for evaluation and as the demonstrator of
// `collect` (SPEC 7: the paper's source of demonstrations). Since a policy drives one team
// size and collect records teams of 1..n_train_max, `path` may contain "{n}", replaced by the
// episode's team size (e.g. "models/mappo/empty-{n}.safetensors"); without it every episode
// must have the policy's n. A missing file or a wrong n throws when the episode starts.
inline DemonstratorFactory mappo_demonstrator(const std::string& path) {
    struct Cache {
        std::mutex mutex;
        std::map<int, std::shared_ptr<const MappoNet>> nets;
    };
    const size_t slot = path.find("{n}");
    auto cache = std::make_shared<Cache>();
    if (slot == std::string::npos) {
        auto net = std::make_shared<const MappoNet>(load_mappo(path));  // fail early on a bad file
        cache->nets[net->config.agents] = net;
    }
    return [path, slot, cache](const World& world, uint64_t) {
        std::shared_ptr<const MappoNet> net;
        {
            std::lock_guard<std::mutex> lock(cache->mutex);
            if (slot == std::string::npos) net = cache->nets.begin()->second;
            else {
                auto& entry = cache->nets[world.size()];
                if (!entry) {
                    std::string file = path;
                    file.replace(slot, 3, std::to_string(world.size()));
                    entry = std::make_shared<const MappoNet>(load_mappo(file));
                    if (entry->config.agents != world.size()) {
                        const int trained = entry->config.agents;
                        entry.reset();
                        throw std::invalid_argument(file + ": trained for " + std::to_string(trained) + " agents, not " +
                                                    std::to_string(world.size()));
                    }
                }
                net = entry;
            }
        }
        return std::unique_ptr<Policy>(new MappoPolicy(net->clone()));
    };
}

}  // namespace madbp

// =============================================================================================
// Section 9. MADiff (SPEC 3.4): a return-conditioned diffusion baseline over observation sequences
// =============================================================================================
//
// After zbzhu99/madiff (Zhu et al., "MADiff", 2023), written from its description on the NN
// core: one 1-D temporal U-Net shared by every agent (agents folded into the batch) with
// self-attention over the agents at every time step, on each skip connection and at the
// bottleneck; it diffuses each agent's window of H observations (the MAPPO observation,
// scaled), the first frame inpainted with the current observation; classifier-free guidance
// on the window's return; an inverse-dynamics MLP turns (o_t, o_t+1) into the action a_t. One
// model per map and team size n; the policy replans at every step and executes the first
// action, raw (no safety filter), as the paper runs it.
//
// Normalisation and target (ours where the paper is silent; Diffuser's choices): every
// observation feature is mapped to [-1, 1] by its minimum and maximum over the training data
// (stored in the model as the non-trainable tensors norm.lo / norm.hi), and the network
// predicts the clean window x0 (Diffuser's maze setting; eps prediction left x0_hat far off at
// high noise here, measured in docs/experiments.md). Guidance is applied to the noise implied by each
// branch's x0, eps = (x_k - sqrt(ab) x0) / sqrt(1 - ab), which is affine in x0, so it equals
// x0_u + w (x0_c - x0_u).
//
// Shapes: B windows (scenes), n agents, A = B*n agent columns, H window length, O = 18
// observation features (kMappoObs), D embedding width, C_l U-Net widths. A window tensor is
// (O, H*A) with column a*H + t, a = b*n + i (agent-major, time fastest), as MA-DBP's.
//
// Reward and return (ours; the paper's navigation task has no MADiff reward): per step the
// team reward is the mean over agents of MAPPO's shaping and contact terms,
//   r_t = mean_i [ (|p_t^i - g^i| - |p_t+1^i - g^i|) - 0.1 * contacts_t+1^i ],
// (contacts: other agents closer than 2 r_a, static surfaces closer than r_a), without the
// constant time term and the success bonus (a one-off +5 would squash every other window
// into the bottom of [0, 1]). A window's return is the undiscounted sum of its H - 1
// transitions' rewards, normalised to [0, 1] by the minimum and maximum over the training
// windows; sampling conditions on the 90th percentile of those normalised returns.

namespace madbp {

constexpr const char* kMadiffFormat = "madiff";

// Architecture and sampling defaults of a MADiff model; stored in the checkpoint.
// |norm.lo|, |norm.hi| of a MADiff checkpoint: its observations are scaled to about +-1.7.
constexpr double kMaxMadiffLimit = 1e3;

// MADiff's observation: MAPPO's default lidar, the goal or (route_goal > 0) the route goal.
inline MappoObservation madiff_observation(double route_goal) { return {kLidarRays, kLidarRange, route_goal}; }

struct MadiffConfig {
    std::string map = "empty";           // map the model was trained on (recorded, not enforced)
    int agents = 2;                      // n, the fixed team size, in [1, 64]
    int horizon = 8;                     // H, frames per window incl. the current one; multiple of 2^levels
    int dim = 32;                        // D, width of the step and return embeddings (cond is 2D)
    std::vector<int> channels = {32, 64};  // U-Net widths per level
    int kernel = 3;                      // Conv1d kernel, odd
    int heads = 4;                       // heads of the agent attention, divides every width
    int inv_hidden = 128;                // inverse dynamics: 2 Tanh layers of this width
    int diffusion_steps = 100;           // K
    int sample_steps = 10;               // S (DDIM, eta = 0), default of the policy
    float guidance = 1.2f;               // w of classifier-free guidance
    float condition_dropout = 0.25f;     // training: probability a window's return is dropped
    float x0_clip = 1.0f;                // sampling: x0_hat clipped to [-x0_clip, x0_clip] (normalised observations)
    double route_goal = 0;               // observed goal: 0 the goal, else the route goal this far ahead (MappoObservation)
    // Data-derived (set by train_madiff): raw return range and the normalised sampling target.
    float return_min = 0, return_max = 1, return_target = 0.9f;

    int levels() const { return (int)channels.size(); }
    MappoObservation observation() const { return madiff_observation(route_goal); }
    void validate() const {
        auto bad = [](const std::string& f, const std::string& why) { throw std::invalid_argument("madiff config " + f + ": " + why); };
        if (agents < 1 || agents > 64) bad("agents", std::to_string(agents) + " must be in [1, 64]");
        if (channels.empty() || channels.size() > 3) bad("channels", "needs 1 to 3 levels");
        if (heads < 1 || heads > 16) bad("heads", "must be in [1, 16]");
        for (int c : channels)
            if (c < 1 || c > 512 || c % heads) bad("channels", "each width must be in [1, 512] and divisible by heads");
        if (horizon < 2 || horizon > 256 || horizon % (1 << levels()) != 0)
            bad("horizon", std::to_string(horizon) + " must be in [2, 256] and a multiple of 2^levels");
        if (dim < 4 || dim > 1024 || dim % 2) bad("dim", "must be even, in [4, 1024]");
        if (kernel < 1 || kernel > 15 || kernel % 2 == 0) bad("kernel", "must be odd, at most 15");
        if (inv_hidden < 1 || inv_hidden > 4096) bad("inv_hidden", "must be in [1, 4096]");
        if (diffusion_steps < 2 || diffusion_steps > 100000) bad("diffusion_steps", "must be in [2, 100000]");
        if (sample_steps < 1 || sample_steps > diffusion_steps) bad("sample_steps", "must be in [1, diffusion_steps]");
        if (!(guidance >= 0 && guidance <= 100)) bad("guidance", "must be in [0, 100]");
        if (!(condition_dropout >= 0 && condition_dropout <= 1)) bad("condition_dropout", "must be in [0, 1]");
        if (!(x0_clip > 0 && x0_clip < 1e6)) bad("x0_clip", "must be positive");
        if (!std::isfinite(return_min) || !std::isfinite(return_max) || !(return_max > return_min))
            bad("return_min/return_max", "need finite values with max > min");
        if (!(return_target >= -10 && return_target <= 10)) bad("return_target", "must be in [-10, 10]");
        observation().check("madiff config obs");
    }
    std::map<std::string, std::string> to_metadata() const {
        auto f = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.9g", v); return std::string(b); };
        std::string ch;
        for (size_t i = 0; i < channels.size(); ++i) ch += (i ? "," : "") + std::to_string(channels[i]);
        return {{"model", kMadiffFormat}, {"madiff.map", map}, {"madiff.agents", std::to_string(agents)},
                {"madiff.horizon", std::to_string(horizon)}, {"madiff.dim", std::to_string(dim)}, {"madiff.channels", ch},
                {"madiff.kernel", std::to_string(kernel)}, {"madiff.heads", std::to_string(heads)},
                {"madiff.inv_hidden", std::to_string(inv_hidden)}, {"madiff.diffusion_steps", std::to_string(diffusion_steps)},
                {"madiff.sample_steps", std::to_string(sample_steps)}, {"madiff.guidance", f(guidance)},
                {"madiff.condition_dropout", f(condition_dropout)}, {"madiff.clip", f(x0_clip)},
                {"madiff.return_min", f(return_min)}, {"madiff.return_max", f(return_max)},
                {"madiff.return_target", f(return_target)}, {"madiff.obs", observation().layout()},
                {"madiff.prediction", "x0"}, {"madiff.normalizer", "limits"}};
    }
    static MadiffConfig from_metadata(const SafeTensors& st) {
        auto it = st.metadata.find("model");
        if (it == st.metadata.end() || it->second != kMadiffFormat)
            throw std::runtime_error(st.source + ": not a MADiff model (__metadata__['model'] is '" +
                                     (it == st.metadata.end() ? std::string("missing") : it->second) + "', expected 'madiff')");
        if (st.meta("madiff.prediction") != "x0" || st.meta("madiff.normalizer") != "limits")
            throw std::runtime_error(st.source + ": prediction '" + st.meta("madiff.prediction") + "' / normalizer '" +
                                     st.meta("madiff.normalizer") + "' are not this build's 'x0' / 'limits'");
        const MappoObservation ob = MappoObservation::from_layout(st.meta("madiff.obs"), st.source, "madiff.obs");
        if (ob.layout() != madiff_observation(ob.route_goal).layout())
            throw std::runtime_error(st.source + ": observation layout '" + st.meta("madiff.obs") + "': MADiff observes with the default lidar (" +
                                     std::to_string(kLidarRays) + " rays of " + number_text(kLidarRange) + ")");
        auto real = [&](const std::string& k) {
            const std::string& s = st.meta(k);
            char* end = nullptr;
            const float v = std::strtof(s.c_str(), &end);
            if (s.empty() || s.size() > 40 || *end != '\0' || !std::isfinite(v))
                throw std::runtime_error(st.source + ": __metadata__['" + k + "'] = '" + s.substr(0, 40) + "' is not a number");
            return v;
        };
        MadiffConfig c;
        c.route_goal = ob.route_goal;
        c.map = st.meta("madiff.map");
        c.agents = detail::meta_int(st, "madiff.agents", 1, 64);
        c.horizon = detail::meta_int(st, "madiff.horizon", 2, 256);
        c.dim = detail::meta_int(st, "madiff.dim", 4, 1024);
        c.kernel = detail::meta_int(st, "madiff.kernel", 1, 15);
        c.heads = detail::meta_int(st, "madiff.heads", 1, 16);
        c.inv_hidden = detail::meta_int(st, "madiff.inv_hidden", 1, 4096);
        c.diffusion_steps = detail::meta_int(st, "madiff.diffusion_steps", 2, 100000);
        c.sample_steps = detail::meta_int(st, "madiff.sample_steps", 1, 100000);
        c.channels.clear();
        const std::string& ch = st.meta("madiff.channels");
        if (ch.size() > 64) throw std::runtime_error(st.source + ": __metadata__['madiff.channels'] is malformed");
        std::stringstream ss(ch);
        for (std::string item; std::getline(ss, item, ',');) {
            size_t pos = 0;
            int v = 0;
            try { v = std::stoi(item, &pos); } catch (...) { pos = 0; }
            if (pos == 0 || pos != item.size()) throw std::runtime_error(st.source + ": __metadata__['madiff.channels'] is malformed");
            c.channels.push_back(v);
        }
        c.guidance = real("madiff.guidance");
        c.condition_dropout = real("madiff.condition_dropout");
        c.x0_clip = real("madiff.clip");
        c.return_min = real("madiff.return_min");
        c.return_max = real("madiff.return_max");
        c.return_target = real("madiff.return_target");
        try { c.validate(); } catch (const std::invalid_argument& e) { throw std::runtime_error(st.source + ": " + e.what()); }
        return c;
    }
};

// ---------------------------------------------------------------------------------------------
// Layers of MADiff

// Classifier-free guidance: out = eps_uncond + w (eps_cond - eps_uncond), element-wise.
// w = 0 gives the unconditional prediction, w = 1 the conditional one.
inline void classifier_free_guidance(const Mat& eps_cond, const Mat& eps_uncond, float w, Mat& out) {
    MADBP_ASSERT(eps_cond.rows() == eps_uncond.rows() && eps_cond.cols() == eps_uncond.cols());
    out = eps_uncond + w * (eps_cond - eps_uncond);
}

// Which windows keep their return condition in training: keep[b] = 1 with probability
// 1 - dropout, else 0 (the condition is dropped: the unconditional model is trained).
inline void condition_keep_mask(int B, float dropout, Rng& rng, std::vector<float>& keep) {
    keep.resize(B);
    for (int b = 0; b < B; ++b) keep[b] = rng.uniform() < dropout ? 0.0f : 1.0f;
}

// Inverse dynamics: (o_t, o_t+1) (O, N) each -> a_t (2, N), an MLP [o_t; o_t+1] (2O) ->
// hidden -> hidden -> 2 with Tanh (Mlp). backward(da) adds the parameter gradients.
struct InverseDynamics {
    Mlp mlp;
    int obs = 0;
    Mat in;  // (2O, N) the last input

    InverseDynamics() = default;
    InverseDynamics(ParamStore& ps, const std::string& name, int obs_dim, int hidden, Rng& rng)
        : mlp(ps, name, 2 * obs_dim, hidden, 2, rng), obs(obs_dim) {}
    void forward(const Mat& o_t, const Mat& o_next, Mat& a) {
        MADBP_ASSERT(o_t.rows() == obs && o_next.rows() == obs && o_t.cols() == o_next.cols());
        in.resize(2 * obs, o_t.cols());
        in.topRows(obs) = o_t;
        in.bottomRows(obs) = o_next;
        mlp.forward(in, a);
    }
    void backward(const Mat& da) { mlp.backward(in, da); }
};

// ---------------------------------------------------------------------------------------------
// The MADiff denoiser and its inverse dynamics, one parameter store. Tensor names: "step.*",
// "ret.*" (embeddings), "unet.*" (U-Net), "attn.skip<l>.*", "attn.mid.*", "inv.*".
class MadiffModel {
public:
    MadiffConfig config;
    std::unique_ptr<ParamStore> params;
    InverseDynamics inv;

    explicit MadiffModel(const MadiffConfig& c, uint64_t seed = 0) : config(c), params(new ParamStore) {
        config.validate();
        build(seed);
    }
    MadiffModel(MadiffModel&&) = default;
    MadiffModel& operator=(MadiffModel&&) = default;
    MadiffModel clone() const {
        MadiffModel m(config);
        m.params->value = params->value;
        m.params->state = params->state;
        m.set_training(training_);
        return m;
    }
    long parameter_count() const { return params->trainable_count(); }
    void set_training(bool on) {
        training_ = on;
        unet_.set_training(on);
    }
    bool training() const { return training_; }

    // Per-feature limits of the observations (norm.lo, norm.hi (O), state).
    void set_limits(const Vec& lo, const Vec& hi) {
        MADBP_ASSERT(lo.size() == kMappoObs && hi.size() == kMappoObs);
        params->state_vec(lo_, kMappoObs) = lo;
        params->state_vec(hi_, kMappoObs) = hi.array().max(lo.array() + 1e-3f).matrix();
    }
    // Refuses limits a checkpoint holds that no training data gives: lo < hi per feature, both
    // finite within +-kMaxMadiffLimit (swapped limits flip every observation: 413 collisions).
    void check_limits(const std::string& source) const {
        const auto lo = params->state_vec(lo_, kMappoObs), hi = params->state_vec(hi_, kMappoObs);
        for (int i = 0; i < kMappoObs; ++i)
            if (!(lo[i] < hi[i] && std::fabs(lo[i]) <= kMaxMadiffLimit && std::fabs(hi[i]) <= kMaxMadiffLimit))
                throw std::runtime_error(source + ": norm.lo[" + std::to_string(i) + "] = " + number_text(lo[i]) + ", norm.hi[" +
                                         std::to_string(i) + "] = " + number_text(hi[i]) + ": needs lo < hi within +-kMaxMadiffLimit = " +
                                         number_text(kMaxMadiffLimit));
    }
    // Scaled observations (O, N) -> [-1, 1] per feature, in place (values beyond the training
    // data's limits map beyond +-1).
    void normalize(Mat& obs) const {
        const auto lo = params->state_vec(lo_, kMappoObs).array(), hi = params->state_vec(hi_, kMappoObs).array();
        obs = ((obs.array().colwise() - lo).colwise() * (2.0f / (hi - lo))) - 1.0f;
    }

    // out (O, H*A) = the predicted clean window x0 from x (O, H*A), k (B) step per window,
    // ret (B) normalised returns, keep (B) 1 = conditioned on ret, 0 = unconditional. B
    // windows of n agents; normalised observations.
    void denoise(const Mat& x, int B, int n, const int* k, const float* ret, const float* keep, Mat& out) {
        const MadiffConfig& c = config;
        const int A = B * n, D = c.dim;
        MADBP_ASSERT(B >= 1 && n >= 1 && x.rows() == kMappoObs && x.cols() == (long)c.horizon * A);
        B_ = B, n_ = n;
        x_ = &x;
        auto& e = emb_;
        e.ret_in.resize(1, B);
        e.keep.assign(keep, keep + B);
        for (int b = 0; b < B; ++b) e.ret_in(0, b) = ret[b];
        step_.forward(k, B, e.t_tok);
        e.r1.forward(e.ret_in, e.rh);
        e.r_act.forward(e.rh, e.rha);
        e.r2.forward(e.rha, e.r_tok);
        e.pre.resize(2 * D, B);
        e.pre.topRows(D) = e.t_tok;
        for (int b = 0; b < B; ++b) e.pre.col(b).tail(D) = e.keep[b] * e.r_tok.col(b);
        e.c_act.forward(e.pre, e.cond_b);
        cond_.resize(2 * D, A);
        for (int a = 0; a < A; ++a) cond_.col(a) = e.cond_b.col(a / n);
        unet_.forward(x, cond_, B, n, out);
    }

    // Backward of the last denoise: ADDS the parameter gradients of the loss whose gradient
    // at out is d_out.
    void backward(const Mat& d_out) {
        const int D = config.dim, A = B_ * n_;
        d_cond_.setZero(2 * D, A);
        unet_.backward(*x_, cond_, B_, n_, d_out, d_x_, d_cond_);
        auto& e = emb_;
        e.d_cond_b.setZero(2 * D, B_);
        for (int a = 0; a < A; ++a) e.d_cond_b.col(a / n_) += d_cond_.col(a);
        e.c_act.backward(e.pre, e.d_cond_b, e.d_pre);
        e.d_t = e.d_pre.topRows(D);
        e.d_r.resize(D, B_);
        for (int b = 0; b < B_; ++b) e.d_r.col(b) = e.keep[b] * e.d_pre.col(b).tail(D);
        step_.backward(e.d_t);
        e.r2.backward(e.rha, e.d_r, e.d_rha);
        e.r_act.backward(e.rh, e.d_rha, e.d_rh);
        e.r1.backward(e.ret_in, e.d_rh, e.d_ret);
    }

private:
    bool training_ = true;
    int B_ = 0, n_ = 0, lo_ = -1, hi_ = -1;
    const Mat* x_ = nullptr;       // the input of the last denoise (kept for backward)
    Mat cond_, d_cond_;            // (2D, A) each agent's condition: [step token; return token]
    Mat d_x_;                      // (O, H*A) unused input gradient
    StepEmbedding step_;
    FilmUNet unet_;
    struct ReturnEmbed {           // return (1, B) -> r_tok (D, B); keep (B) drops it (CFG)
        Linear r1, r2;
        Mish r_act, c_act;
        std::vector<float> keep;
        Mat t_tok, ret_in, rh, rha, r_tok;   // (D, B), (1, B), (D, B) x3
        Mat pre, cond_b;                     // (2D, B)
        Mat d_cond_b, d_pre, d_t, d_r, d_rha, d_rh, d_ret;
    } emb_;

    // Parameters are created in this order (it fixes the initial weights for a seed).
    void build(uint64_t seed) {
        Rng rng(seed);
        ParamStore& ps = *params;
        const MadiffConfig& c = config;
        const int D = c.dim;
        step_ = StepEmbedding(ps, "step", D, rng);
        emb_.r1 = Linear(ps, "ret.l1", 1, D, rng);
        emb_.r2 = Linear(ps, "ret.l2", D, D, rng);
        unet_ = FilmUNet(ps, "unet", "attn", kMappoObs, kMappoObs, c.channels, c.kernel, 2 * D, c.horizon, c.heads, rng);
        inv = InverseDynamics(ps, "inv", kMappoObs, c.inv_hidden, rng);
        lo_ = ps.add("norm.lo", {kMappoObs}, Init::zeros(), rng, false);
        hi_ = ps.add("norm.hi", {kMappoObs}, Init::ones(), rng, false);
        params->state_vec(lo_, kMappoObs).setConstant(-1.0f);
    }
};

// Model files (SPEC 11): parameters as safetensors, MadiffConfig in __metadata__ (model =
// madiff) plus `extra` fields. load_madiff validates the file, the metadata and that every
// tensor matches the declared architecture, and that every value is finite.
inline void save_madiff(const std::string& path, const MadiffModel& m, std::map<std::string, std::string> extra = {}) {
    auto md = m.config.to_metadata();
    for (auto& kv : extra) md[kv.first] = kv.second;
    save_params(path, *m.params, md);
}
namespace detail {
inline MadiffModel madiff_from(const SafeTensors& st) {
    const ParamBudget budget(st.values(), st.source);  // the declared config may need no more values than the file holds
    MadiffModel m(MadiffConfig::from_metadata(st));
    read_param_tensors(st, *m.params);
    if (!m.params->value.allFinite() || !m.params->state.allFinite()) throw std::runtime_error(st.source + ": a parameter is not finite");
    m.check_limits(st.source);
    m.set_training(false);
    return m;
}
}  // namespace detail
inline MadiffModel load_madiff(const std::string& path) { return detail::madiff_from(load_safetensors(path)); }

// ---------------------------------------------------------------------------------------------
// MADiff data: the demonstrations of one map and team size as observation sequences

// Episodes of exactly n agents on one map, with every frame's scaled observations, actions,
// team rewards, and the windows (episode, first frame) that fit inside their episode.
struct MadiffData {
    int n = 0, H = 0;
    std::vector<Mat> obs;              // per episode (O, frames*n), column f*n + i
    std::vector<Mat> act;              // per episode (2, steps*n), column t*n + i
    std::vector<std::vector<float>> reward;  // per episode (steps) team reward of step t -> t+1
    std::vector<std::pair<int, int>> windows;
    std::vector<float> window_return;  // raw return of each window
};

// Team reward of the step from frame t to t+1 of demonstration d (see the section comment).
inline float madiff_step_reward(const Demonstration& d, int t, double radius = WorldConfig{}.radius) {
    const int n = d.agents;
    double sum = 0;
    for (int i = 0; i < n; ++i) {
        const Vec2 p0 = d.position(t, i), p1 = d.position(t + 1, i);
        int contacts = static_clearance(d.map, p1) < radius ? 1 : 0;
        for (int j = 0; j < n; ++j)
            if (j != i && norm(p1 - d.position(t + 1, j)) < 2 * radius) contacts++;
        sum += norm(p0 - d.goals[i]) - norm(p1 - d.goals[i]) - 0.1 * contacts;
    }
    return (float)(sum / n);
}

// Scaled observations `ob` (as mappo_observe_all) of every frame of d, (O, frames*n).
inline Mat madiff_episode_observations(const Demonstration& d, const MappoObservation& ob) {
    const int n = d.agents, frames = d.steps + 1;
    World w(d.map);
    for (int i = 0; i < n; ++i) w.add_agent(d.pos[i], d.goals[i]);
    Mat obs(ob.size(), (long)frames * n);
    RouteGuide guide;
    for (int f = 0; f < frames; ++f) {
        for (int i = 0; i < n; ++i) w.set_state(w.agents()[i].id, d.pos[(size_t)f * n + i], d.vel[(size_t)f * n + i]);
        mappo_observe_all(w, obs, (long)f * n, ob, &guide);
    }
    return obs;
}

// Selects the episodes of `demos` on `map` with exactly n agents and at least H frames, observed
// as MADiff does (MadiffConfig::observation: the default lidar; the goal, or the route goal
// `route_goal` ahead when > 0).
inline MadiffData madiff_data(const DemoSet& demos, const std::string& map, int n, int H, double route_goal = 0) {
    const MappoObservation ob = madiff_observation(route_goal);
    MadiffData out;
    out.n = n, out.H = H;
    for (size_t e = 0; e < demos.episodes.size(); ++e) {
        const Demonstration& d = demos.episodes[e];
        if (d.map_name != map || d.agents != n || d.steps + 1 < H) continue;
        if ((long)d.act.size() != (long)d.steps * n) throw std::invalid_argument("madiff: episode " + std::to_string(e) + " has no actions");
        Mat obs;
        try {
            obs = madiff_episode_observations(d, ob);
        } catch (const std::exception& ex) {
            throw std::invalid_argument("madiff: episode " + std::to_string(e) + " of the dataset: " + ex.what());
        }
        const int k = (int)out.obs.size();
        out.obs.push_back(std::move(obs));
        Mat act(2, (long)d.steps * n);
        for (long j = 0; j < act.cols(); ++j) act.col(j) << (float)d.act[j].x, (float)d.act[j].y;
        out.act.push_back(std::move(act));
        std::vector<float> r(d.steps);
        for (int t = 0; t < d.steps; ++t) r[t] = madiff_step_reward(d, t);
        for (int t = 0; t + H - 1 <= d.steps; ++t) {
            double R = 0;
            for (int s = t; s < t + H - 1; ++s) R += r[s];
            out.windows.push_back({k, t});
            out.window_return.push_back((float)R);
        }
        out.reward.push_back(std::move(r));
    }
    if (out.windows.empty())
        throw std::invalid_argument("madiff: the dataset has no episode on map '" + map + "' with " + std::to_string(n) +
                                    " agents and at least " + std::to_string(H) + " frames (collect with --maps " + map +
                                    " --n-train-max >= " + std::to_string(n) + ")");
    return out;
}

// One training batch: B windows, their clean observations, returns and actions.
struct MadiffBatch {
    int B = 0, n = 0;
    Mat x0;                    // (O, H*A) clean windows
    std::vector<float> ret;    // (B) normalised returns
    Mat o_t, o_next, act;      // (O, (H-1)*A), (O, (H-1)*A), (2, (H-1)*A): the windows' transitions
};

inline void make_madiff_batch(const MadiffData& data, const MadiffConfig& c, int B, Rng& rng, MadiffBatch& mb) {
    const int n = data.n, H = c.horizon, A = B * n;
    MADBP_ASSERT(H == data.H);
    mb.B = B, mb.n = n;
    mb.x0.resize(kMappoObs, (long)H * A);
    mb.ret.resize(B);
    mb.o_t.resize(kMappoObs, (long)(H - 1) * A);
    mb.o_next.resize(kMappoObs, (long)(H - 1) * A);
    mb.act.resize(2, (long)(H - 1) * A);
    for (int b = 0; b < B; ++b) {
        const int w = rng.uniform_int((int)data.windows.size());
        const int e = data.windows[w].first, t0 = data.windows[w].second;
        mb.ret[b] = (data.window_return[w] - c.return_min) / (c.return_max - c.return_min);
        for (int i = 0; i < n; ++i) {
            const long a = (long)b * n + i;
            for (int t = 0; t < H; ++t) mb.x0.col(a * H + t) = data.obs[e].col((long)(t0 + t) * n + i);
            for (int t = 0; t + 1 < H; ++t) {
                const long j = a * (H - 1) + t;
                mb.o_t.col(j) = data.obs[e].col((long)(t0 + t) * n + i);
                mb.o_next.col(j) = data.obs[e].col((long)(t0 + t + 1) * n + i);
                mb.act.col(j) = data.act[e].col((long)(t0 + t) * n + i);
            }
        }
    }
}

struct MadiffLoss {
    double diffusion = 0, inverse = 0, total = 0;
};
struct MadiffWorkspace {
    std::vector<int> k;
    std::vector<float> keep;
    Mat eps, x_k, out, d_out, a_hat, d_a;
};

// The training loss of one batch: total = (L_diffusion + L_inverse) / 2 (as Decision Diffuser).
// L_diffusion is the mean squared error of the predicted clean window over frames 1..H-1
// (frame 0 is given clean, as the sampler inpaints it); windows keep their return condition with
// probability 1 - condition_dropout. L_inverse is the mean squared error of the inverse
// dynamics' actions on the windows' clean transitions. With `backward`, ADDS the gradients.
inline MadiffLoss madiff_loss(MadiffModel& m, const NoiseSchedule& schedule, const MadiffBatch& mb, Rng& rng, bool backward,
                              MadiffWorkspace& ws) {
    const int B = mb.B, n = mb.n, A = B * n, H = m.config.horizon, O = kMappoObs;
    ws.k.resize(B);
    for (int b = 0; b < B; ++b) ws.k[b] = 1 + rng.uniform_int(schedule.K);
    condition_keep_mask(B, m.config.condition_dropout, rng, ws.keep);
    ws.eps.resize(O, (long)H * A);
    for (long j = 0; j < ws.eps.size(); ++j) ws.eps.data()[j] = (float)rng.normal();
    ws.x_k.resize(O, (long)H * A);
    for (long a = 0; a < A; ++a) {
        const double ab = schedule.alpha_bar[ws.k[a / n]];
        const float sa = (float)std::sqrt(ab), s1a = (float)std::sqrt(1 - ab);
        ws.x_k.col(a * H) = mb.x0.col(a * H);
        ws.x_k.middleCols(a * H + 1, H - 1) = sa * mb.x0.middleCols(a * H + 1, H - 1) + s1a * ws.eps.middleCols(a * H + 1, H - 1);
    }
    m.denoise(ws.x_k, B, n, ws.k.data(), mb.ret.data(), ws.keep.data(), ws.out);
    MadiffLoss L;
    const double count = (double)O * (H - 1) * A;
    ws.d_out.setZero(O, (long)H * A);
    for (long a = 0; a < A; ++a)
        for (int t = 1; t < H; ++t) {
            const long c = a * H + t;
            for (int r = 0; r < O; ++r) {
                const float e = ws.out(r, c) - mb.x0(r, c);
                L.diffusion += (double)e * e;
                ws.d_out(r, c) = (float)(e / count);  // d(0.5 * mean e^2)/d out = e / count
            }
        }
    L.diffusion /= count;
    m.inv.forward(mb.o_t, mb.o_next, ws.a_hat);
    ws.d_a = ws.a_hat - mb.act;
    L.inverse = ws.d_a.squaredNorm() / (double)ws.d_a.size();
    L.total = 0.5 * (L.diffusion + L.inverse);
    if (!backward) return L;
    ws.d_a *= 1.0f / (float)ws.d_a.size();  // d(0.5 * mean)/d a_hat = (a_hat - a) / N
    m.backward(ws.d_out);
    m.inv.backward(ws.d_a);
    return L;
}

// ---------------------------------------------------------------------------------------------
// MADiff training

struct MadiffTrainConfig {
    long steps = 3000;             // optimizer steps
    int batch = 32;                // windows per step (each with n agents)
    float lr = 3e-4f;
    float grad_clip = 1.0f;        // global gradient-norm clip
    float ema_decay = 0.995f;
    long ema_start = 500;          // the EMA tracks the weights from this step (the file holds raw weights before)
    float return_quantile = 1.0f;  // sampling target: this quantile of the normalised window returns (1: the best window)
    long log_every = 50;           // loss CSV rows
    long checkpoint_every = 500;
    std::string out;               // model file ("" = no files); + ".train" (resumable), ".csv" (loss curve)
    bool resume = false;
    uint64_t seed = 0;
    int threads = 1;               // OpenMP threads of the layers; the result does not depend on it
    ProgressFn progress;           // called after every step with the smoothed loss (optional)
    std::function<bool(long step)> keep_going;  // false stops after that step (a checkpoint is written)

    void validate() const {
        if (steps < 1 || batch < 1 || log_every < 1 || checkpoint_every < 1 || ema_start < 0)
            throw std::invalid_argument("madiff: steps, batch, log_every and checkpoint_every must be >= 1, ema_start >= 0");
        if (!(lr > 0 && lr < 1) || !(grad_clip > 0)) throw std::invalid_argument("madiff: lr must be in (0, 1) and grad_clip > 0");
        if (!(ema_decay >= 0 && ema_decay < 1)) throw std::invalid_argument("madiff: ema_decay must be in [0, 1)");
        if (!(return_quantile >= 0 && return_quantile <= 1)) throw std::invalid_argument("madiff: return_quantile must be in [0, 1]");
        if (resume && out.empty()) throw std::invalid_argument("resume: needs an output file");
    }
};

struct MadiffReport {
    long steps = 0;
    double seconds = 0;
    int episodes = 0;
    long windows = 0;
    Curve curve;  // step, seconds, smoothed losses (as <out>.csv)
};

// Trains a MADiff model for `model_config.map` and `.agents` on the matching episodes of
// `demos` (return range and target are set from the data). Writes tc.out (EMA weights),
// tc.out + ".train" (raw weights, Adam, EMA, RNG: what resume reads) and tc.out + ".csv",
// atomically, every checkpoint_every steps and at the end. Deterministic for a seed, whatever
// the thread count. Returns the report; the trained model (EMA weights) in *result if given.
inline MadiffReport train_madiff(const DemoSet& demos, MadiffConfig mc, const MadiffTrainConfig& tc, MadiffModel* result = nullptr) {
    tc.validate();
    {
        Rng probe(0);
        make_map(mc.map, probe);  // an unknown map name fails here
    }
    mc.validate();
    set_num_threads(std::max(1, tc.threads));
    MadiffData data = madiff_data(demos, mc.map, mc.agents, mc.horizon, mc.route_goal);
    std::vector<float> sorted = data.window_return;
    std::sort(sorted.begin(), sorted.end());
    mc.return_min = sorted.front();
    mc.return_max = std::max(sorted.back(), sorted.front() + 1e-6f);
    const float q = sorted[(size_t)std::lround(tc.return_quantile * (sorted.size() - 1))];
    mc.return_target = (q - mc.return_min) / (mc.return_max - mc.return_min);
    MadiffModel model(mc, tc.seed);
    Vec lo = Vec::Constant(kMappoObs, 1e30f), hi = Vec::Constant(kMappoObs, -1e30f);
    for (const Mat& o : data.obs) lo = lo.cwiseMin(o.rowwise().minCoeff()), hi = hi.cwiseMax(o.rowwise().maxCoeff());
    model.set_limits(lo, hi);
    for (Mat& o : data.obs) model.normalize(o);
    NoiseSchedule schedule(mc.diffusion_steps);
    Adam adam;
    adam.lr = tc.lr;
    Ema ema;
    ema.decay = tc.ema_decay;
    Rng rng(tc.seed ^ 0x3ad1ff00ull);
    long step = 0;
    double seconds_before = 0;
    MadiffReport rep;
    rep.episodes = (int)data.obs.size();
    rep.windows = (long)data.windows.size();
    auto f = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.9g", v); return std::string(b); };
    std::map<std::string, std::string> identity = mc.to_metadata();  // includes the data's return range
    identity.insert({{"madiff.train.data", content_hash(demos_bytes(demos))}, {"madiff.train.seed", std::to_string(tc.seed)},
                     {"madiff.train.steps", std::to_string(tc.steps)}, {"madiff.train.batch", std::to_string(tc.batch)},
                     {"madiff.train.lr", f(tc.lr)}, {"madiff.train.grad_clip", f(tc.grad_clip)},
                     {"madiff.train.ema", f(tc.ema_decay) + " from " + std::to_string(tc.ema_start)}});
    TrainState state(tc.out, *model.params, adam, &ema, {{"madiff.rng", &rng}}, identity,
                     {"step", "seconds", "loss", "diffusion", "inverse"});
    MadiffLoss smooth;  // exponentially smoothed (in the state file: the curve continues exactly)
    if (tc.resume) {
        step = state.resume(tc.steps);
        seconds_before = state.resumed_numbers("madiff.seconds", 1)[0];
        const std::vector<double> sm = state.resumed_numbers("madiff.smooth", 3);
        smooth.total = sm[0], smooth.diffusion = sm[1], smooth.inverse = sm[2];
    }
    if (ema.shadow.size() != model.params->size()) ema.shadow = model.params->value;
    const auto t_start = std::chrono::steady_clock::now();
    auto elapsed = [&] { return seconds_before + std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count(); };
    auto save = [&] {
        if (tc.out.empty()) return;
        char secs[32], sm[96];
        std::snprintf(secs, sizeof secs, "%.3f", elapsed());
        std::snprintf(sm, sizeof sm, "%.17g %.17g %.17g", smooth.total, smooth.diffusion, smooth.inverse);
        const std::map<std::string, std::string> info = {{"demonstrator", demos.demonstrator}, {"train.step", std::to_string(step)},
            {"madiff.seconds", secs}, {"madiff.episodes", std::to_string(rep.episodes)}, {"madiff.windows", std::to_string(rep.windows)}};
        state.with_model_weights(step >= tc.ema_start, [&] { save_madiff(tc.out, model, info); });
        auto md = info;
        md["madiff.smooth"] = sm;
        state.save(step, md);
    };
    model.set_training(true);
    MadiffBatch mb;
    MadiffWorkspace ws;
    while (step < tc.steps) {
        make_madiff_batch(data, model.config, tc.batch, rng, mb);
        model.params->zero_grad();
        const MadiffLoss l = madiff_loss(model, schedule, mb, rng, true, ws);
        if (!std::isfinite(l.total)) throw std::runtime_error("madiff: loss became non-finite at step " + std::to_string(step));
        clip_grad_norm(*model.params, tc.grad_clip);
        adam.update(*model.params);
        ++step;
        if (step == tc.ema_start) ema.shadow = model.params->value;
        else if (step > tc.ema_start) ema.update(*model.params);
        const double keep = step == 1 ? 0.0 : 0.98;
        smooth.total = keep * smooth.total + (1 - keep) * l.total;
        smooth.diffusion = keep * smooth.diffusion + (1 - keep) * l.diffusion;
        smooth.inverse = keep * smooth.inverse + (1 - keep) * l.inverse;
        if (step % tc.log_every == 0 || step == tc.steps)
            state.curve.add({(double)step, elapsed(), smooth.total, smooth.diffusion, smooth.inverse});
        const bool stop = tc.keep_going && !tc.keep_going(step);
        if (step % tc.checkpoint_every == 0 || step == tc.steps || stop) save();
        if (tc.progress) {
            char note[96];
            std::snprintf(note, sizeof note, "loss %.4f (diffusion %.4f, inverse %.4f)", smooth.total, smooth.diffusion, smooth.inverse);
            tc.progress(step, tc.steps, note);
        }
        if (stop) break;
    }
    rep.curve = state.curve;
    rep.steps = step;
    rep.seconds = elapsed();
    if (step >= tc.ema_start) ema.copy_to(*model.params);
    model.set_training(false);
    if (result) *result = std::move(model);
    return rep;
}

// ---------------------------------------------------------------------------------------------
// Running a MADiff model (SPEC 3.4, 9)

// At every step: the team's normalised observations; a window of H observations per agent
// drawn with DDIM in S steps from N(0, I), frame 0 inpainted with the current observation
// after every step, the noise estimate guided by eps_u + w (eps_c - eps_u) towards the return
// target; then a_i = inverse dynamics (o_0, o_1) of agent i, clamped to the action box. Raw
// actions, no safety filter. The team must have exactly the model's n agents
// (std::invalid_argument otherwise). Seeded: the same seed and world give the same actions.
// decision_ms() is the mean wall time of one act().
class MadiffPolicy : public Policy {
public:
    int sample_steps;       // S, in [1, K]
    float guidance;         // w
    float return_target;    // normalised return to condition on

    explicit MadiffPolicy(MadiffModel model, uint64_t seed = 0)
        : sample_steps(model.config.sample_steps), guidance(model.config.guidance), return_target(model.config.return_target),
          model_(std::move(model)), schedule_(model_.config.diffusion_steps), rng_(seed) {
        model_.set_training(false);
    }
    const MadiffConfig& config() const { return model_.config; }
    void reseed(uint64_t seed) { rng_.reseed(seed); }

    std::vector<Vec2> act(const World& world) override {
        const auto t0 = std::chrono::steady_clock::now();
        const MadiffConfig& c = model_.config;
        const int n = c.agents, H = c.horizon, O = kMappoObs, S = sample_steps;
        if (world.size() != n)
            throw std::invalid_argument("madiff: the model was trained for " + std::to_string(n) + " agents, the world has " +
                                        std::to_string(world.size()) + " (MADiff is built for a fixed team size)");
        if (S < 1 || S > schedule_.K)
            throw std::invalid_argument("sample_steps: " + std::to_string(S) + " must be in [1, " + std::to_string(schedule_.K) + "]");
        for (const Agent& a : world.agents())
            if (!std::isfinite(a.pos.x + a.pos.y + a.vel.x + a.vel.y + a.goal.x + a.goal.y))
                throw std::invalid_argument("madiff: agent " + std::to_string(a.id) + " has a non-finite state or goal");
        obs_.resize(O, n);
        mappo_observe_all(world, obs_, 0, c.observation(), &guide_);
        model_.normalize(obs_);
        x_.resize(O, (long)H * n);
        for (long j = 0; j < x_.size(); ++j) x_.data()[j] = (float)rng_.normal();
        auto inpaint = [&] { for (int i = 0; i < n; ++i) x_.col((long)i * H) = obs_.col(i); };
        inpaint();
        // One denoiser call evaluates both branches: scenes 0 (conditioned) and 1 (unconditional).
        const float ret[2] = {return_target, return_target}, keep[2] = {1, 0};
        int k2[2];
        xx_.resize(O, 2L * H * n);
        // The planner's DDIM loop (madbp.hpp detail::ddim_loop), steered by classifier-free guidance.
        auto guided_x0 = [&](const detail::DdimLevels& l, Mat& x0) {
            k2[0] = k2[1] = l.k;
            xx_.leftCols((long)H * n) = x_;
            xx_.rightCols((long)H * n) = x_;
            model_.denoise(xx_, 2, n, k2, ret, keep, out_);
            // The noise each branch's x0 implies, then guidance (the formula on eps).
            eps_c_ = (x_ - l.sa * out_.leftCols((long)H * n)) / l.s1a;
            eps_u_ = (x_ - l.sa * out_.rightCols((long)H * n)) / l.s1a;
            classifier_free_guidance(eps_c_, eps_u_, guidance, eps_);
            x0.resize(O, (long)H * n);
            for (long j = 0; j < x_.size(); ++j) x0.data()[j] = std::clamp(predict_x0(x_.data()[j], eps_.data()[j], l.alpha_bar), -c.x0_clip, c.x0_clip);
        };
        detail::ddim_loop(schedule_, S, S, x_, x0_, guided_x0, [&](Mat&) { inpaint(); });
        o_next_.resize(O, n);
        for (int i = 0; i < n; ++i) o_next_.col(i) = x_.col((long)i * H + 1);
        model_.inv.forward(obs_, o_next_, a_);
        std::vector<Vec2> u(n);
        for (int i = 0; i < n; ++i) u[i] = clamp_box(Vec2{a_(0, i), a_(1, i)}, world.config().max_action);
        total_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        ++calls_;
        return u;
    }
    double decision_ms() const override { return calls_ ? total_ms_ / calls_ : 0; }
    // The window sampled by the last act(): (O, H*n), column i*H + t, normalised observations.
    const Mat& last_window() const { return x_; }

private:
    MadiffModel model_;
    NoiseSchedule schedule_;
    Rng rng_;
    Mat obs_, x_, xx_, out_, eps_c_, eps_u_, eps_, x0_, o_next_, a_;
    RouteGuide guide_;  // route goals (a model whose observation has one)
    double total_ms_ = 0;
    long calls_ = 0;
};

}  // namespace madbp

#endif  // MADBP_TRAIN_HPP
