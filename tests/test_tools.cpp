// Tests of the tools at large teams (issue 47, item 5): eval, render and bench accept up to
// 1024 robots, random worlds keep a constant density (madbp::default_half_size), a world too
// small for its team fails naming the field, and a long episode reports its steps.
#include <doctest/doctest.h>

#include <chrono>

#include <fcntl.h>
#include <unistd.h>

#include <fstream>
#include <sstream>

#include "cli_common.hpp"
#include "madbp_sim.hpp"
#include "methods.hpp"     // read_planner_choice, for bench_plan
#include "bench_plan.hpp"

using namespace madbp;
using madbp_cli::Args;

TEST_CASE("tools: default_half_size keeps the density of 64 robots in half-size 3.4, 1.2 up to 8") {
    for (int n = 0; n <= 8; ++n) CHECK(default_half_size(n) == 1.2);  // exactly: the standard world is unchanged
    CHECK(default_half_size(9) == doctest::Approx(1.3));
    CHECK(default_half_size(16) == doctest::Approx(1.7));
    CHECK(default_half_size(32) == doctest::Approx(2.4));
    CHECK(default_half_size(64) == 3.4);
    CHECK(default_half_size(128) == doctest::Approx(4.8));
    CHECK(default_half_size(256) == doctest::Approx(6.8));
    CHECK(default_half_size(1024) == doctest::Approx(13.6));
    for (int n = 1; n < 1024; ++n) {
        CHECK(default_half_size(n + 1) >= default_half_size(n));
        // Robots per unit of area stay within rounding of 64 / 6.8^2 (about 1.4) beyond 8.
        const double side = 2 * default_half_size(n + 1);
        if (n + 1 > 8) CHECK((n + 1) / (side * side) == doctest::Approx(64 / (6.8 * 6.8)).epsilon(0.13));
    }
    // The tool: --half-size when given, else the density rule per team size.
    CHECK(madbp_cli::HalfSize{}.of(4) == 1.2);
    CHECK(madbp_cli::HalfSize{}.of(256) == doctest::Approx(6.8));
    CHECK(madbp_cli::HalfSize{2.0}.of(256) == 2.0);
    CHECK(madbp_cli::HalfSize{}.of(12, "circle") == 1.2);  // interaction scenes: drawn for the standard world
    CHECK(madbp_cli::HalfSize{2.4}.of(16, "circle") == 2.4);
    Args a(std::vector<std::string>{"--half-size", "2.5"});
    CHECK(madbp_cli::read_half_size(a).of(1024) == 2.5);
    Args none(std::vector<std::string>{});
    CHECK(madbp_cli::read_half_size(none).given == 0);
}

TEST_CASE("tools: --agents takes up to 1024 robots; 1025 is refused naming the flag and its range") {
    CHECK(madbp_cli::kMaxTeam == 1024);
    Args ok(std::vector<std::string>{"--agents", "2,256,1024"});
    CHECK(ok.integers("--agents", "2,4,6", 1, madbp_cli::kMaxTeam) == std::vector<long>{2, 256, 1024});
    Args over(std::vector<std::string>{"--agents", "4,1025"});
    CHECK_THROWS_WITH_AS(over.integers("--agents", "2,4,6", 1, madbp_cli::kMaxTeam),
                         "--agents: 1025 is out of range [1, 1024]", std::invalid_argument);
    Args one(std::vector<std::string>{"--agents", "1025"});
    CHECK_THROWS_WITH_AS(one.integer("--agents", 4, 1, madbp_cli::kMaxTeam), "--agents: 1025 is out of range [1, 1024]",
                         std::invalid_argument);
}

TEST_CASE("tools: 1024 robots spawn in the default world of every map, well under a second") {
    for (const std::string map : {"empty", "obstacles", "barrier"}) {
        const auto t0 = std::chrono::steady_clock::now();
        World w = make_random_world(map, 1024, 0, default_half_size(1024));
        const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        MESSAGE(map << ": 1024 robots spawned in " << 1000 * secs << " ms");
        CHECK(w.size() == 1024);
        CHECK(secs < 0.5);
        double closest = 1e9;
        for (int i = 0; i < w.size(); ++i)
            for (int j = i + 1; j < w.size(); ++j) closest = std::min(closest, norm(w.agents()[i].pos - w.agents()[j].pos));
        CHECK(closest >= 0.25);
    }
}

TEST_CASE("tools: a world too small for its team fails at once, naming the field and the size that fits") {
    const auto t0 = std::chrono::steady_clock::now();
    CHECK_THROWS_WITH_AS(make_random_world("empty", 1024, 0, 1.2),
                         doctest::Contains("half_size: 1.2 is too small for 1024 robots"), std::runtime_error);
    CHECK(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() < 1.0);
    CHECK_THROWS_WITH_AS(make_random_world("obstacles", 64, 0, 1.2), doctest::Contains("default_half_size(64) = 3.4"),
                         std::runtime_error);
    // The tool names its flag.
    CHECK_THROWS_WITH_AS(madbp_cli::check_random_world("empty", 256, 0, 1.2),
                         doctest::Contains("--half-size: 1.2 is too small for 256 robots"), std::invalid_argument);
    CHECK_NOTHROW(madbp_cli::check_random_world("barrier", 256, 0, default_half_size(256)));
    // Other failures pass through unchanged.
    CHECK_THROWS_WITH_AS(madbp_cli::check_random_world("nowhere", 4, 0, 1.2), doctest::Contains("unknown map name"),
                         std::invalid_argument);
}

namespace {
struct Still : Policy {
    std::vector<Vec2> act(const World& w) override { return std::vector<Vec2>(w.size()); }
};
}  // namespace

TEST_CASE("tools: evaluate reports the steps of a running episode as progress notes") {
    EvalConfig c;
    c.agents = 3;
    c.episodes = 2;
    c.world.max_steps = 5;
    std::vector<std::string> calls;
    c.progress = [&](long done, long total, const std::string& note) {
        calls.push_back(std::to_string(done) + "/" + std::to_string(total) + " " + note);
    };
    const EvalResult r = evaluate(c, [](const World&, uint64_t) { return std::make_unique<Still>(); });
    CHECK(r.success == 0);
    const std::vector<std::string> expected = {"0/2 step 0/5", "0/2 step 1/5", "0/2 step 2/5", "0/2 step 3/5", "0/2 step 4/5", "1/2 ",
                                               "1/2 step 0/5", "1/2 step 1/5", "1/2 step 2/5", "1/2 step 3/5", "1/2 step 4/5", "2/2 "};
    CHECK(calls == expected);
}

TEST_CASE("tools: bench --plan --episode-steps times the plans of an episode as eval makes them") {
    // Nine robots among obstacles (a scene batch: routes, goal fields, replans), 12 steps: the
    // follower plans at step 0 and at least every follower.replan_every (4) steps after.
    Args a(std::vector<std::string>{"--plan", "--agents", "9", "--plans", "1", "--no-expert", "--threads", "1", "--map", "obstacles",
                                    "--episode-steps", "12", "--json"});
    a.flag("--plan");
    char path[] = "/tmp/madbp-bench-episode-XXXXXX";
    const int fd = mkstemp(path);
    REQUIRE(fd >= 0);
    std::fflush(stdout);
    const int saved = dup(1);
    const bool redirected = saved >= 0 && dup2(fd, 1) >= 0;
    close(fd);
    int rc = -1;
    std::string error;
    if (redirected) {
        try { rc = madbp_cli::bench_plan(a); } catch (const std::exception& e) { error = e.what(); }
        std::fflush(stdout);
        dup2(saved, 1);  // stdout back before any check reports
    }
    if (saved >= 0) close(saved);
    set_num_threads(1);
    REQUIRE(redirected);
    CHECK_MESSAGE(error.empty(), error);
    CHECK(rc == 0);
    std::ifstream in(path);
    std::stringstream text;
    text << in.rdbuf();
    std::remove(path);
    const std::string out = text.str();
    auto field = [&](const std::string& name) {
        const size_t at = out.find("\"" + name + "\": ");
        REQUIRE_MESSAGE(at != std::string::npos, name << " missing in: " << out);
        return std::stod(out.substr(at + name.size() + 4));
    };
    CHECK(field("episode_steps") == 12);
    CHECK(field("episode_steps_run") == 12);  // no team of 9 finishes in 12 steps
    CHECK(field("episode_plans") >= 3);
    CHECK(field("episode_plans") <= 12);
    CHECK(field("episode_ms_per_plan") > 0);
    CHECK(field("episode_max_ms") >= field("episode_ms_per_plan"));  // the longest plan is at least the mean
}
