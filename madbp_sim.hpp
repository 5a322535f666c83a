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

#endif  // MADBP_SIM_HPP
