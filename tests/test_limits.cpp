// Tests of bounded memory and strict inputs (issue 15, docs/limits.md): one test case per row
// of the table of hostile and careless inputs, named after the row. Where a regression
// would allocate without bound, the code runs in a forked child under an address-space cap
// (setrlimit RLIMIT_AS: the process's current size plus a few hundred MiB), so that it fails
// with bad_alloc instead of swapping. The cap is skipped under AddressSanitizer, which reserves
// terabytes of virtual memory. The whole file runs in a few seconds.
#include "madbp_train.hpp"
#include "methods.hpp"  // the tool's Args, read_planner_choice, refuse_scene_overrides
#include "tiny_model.hpp"

#include <doctest/doctest.h>

#include <chrono>
#include <climits>
#include <csignal>
#include <cstdlib>
#include <dirent.h>
#include <fcntl.h>
#include <functional>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "limits_helpers.hpp"

using madbp_cli::Args;

TEST_CASE("limits: eval --method expert --half-size 100: the expert's grid is bounded at any world size") {
    // Before: a 5556 x 5556 grid and 121 steps of reservations, 21 GB. Now at most
    // kRouteMaxGridSide cells a side (coarser cells beyond half-size ~41.4) and a sparse search.
    const std::string r = capped(512, [] {
        World w = make_random_world("empty", 4, 0, 100.0);
        GuidedExpert expert(w.map());
        for (int t = 0; t < 20; ++t) w.step(expert.act(w));
        return std::to_string(expert.grid().n);
    });
    CHECK(r == "ok: " + std::to_string(kRouteMaxGridSide));
    // A step limit of 10^6 plans at most kExpertMaxHorizon steps ahead (was 10^6 x 133^2 states).
    const std::string r2 = capped(512, [] {
        WorldConfig wc;
        wc.max_steps = 1000000;
        World w = make_random_world("empty", 4, 0, 2.4, wc);
        GuidedExpert expert(w.map());
        for (int t = 0; t < 3; ++t) w.step(expert.act(w));
        return std::string();
    });
    CHECK(r2 == "ok");
    // Up to half-size 41.4 the cells are the expert's 0.036 (189 a side at 3.4, 333 at 6) ...
    Rng rng(0);
    const ClearanceGrid at34(make_map("empty", rng, 3.4), ExpertParams{}.cell);
    CHECK(at34.n == 189);
    CHECK(at34.stretch == 1);
    const ClearanceGrid at6(make_map("empty", rng, 6.0), ExpertParams{}.cell);
    CHECK(at6.n == 333);
    CHECK(at6.stretch == 1);
    // ... and beyond it the coarsened expert still solves a problem (half-size 50, 1.2x cells).
    WorldConfig wc;
    wc.max_steps = 300;
    World w(WorldMap{50, {}, {}}, wc);
    w.add_agent({1.01, 2.02}, {-0.5, 1.1});
    w.add_agent({-0.4, 2.5}, {1.2, 1.3});
    GuidedExpert expert(w.map());
    CHECK(expert.grid().n == kRouteMaxGridSide);
    CHECK(expert.grid().stretch > 1.15);
    EpisodeResult res = run_episode(w, expert);
    CHECK(res.success);
    CHECK(res.collisions() == 0);
}

TEST_CASE("limits: a checkpoint whose metadata says kernel 100001 fails with a message, not bad_alloc") {
    TempDir dir;
    const std::string path = model_with(dir, "k100001.safetensors", {{"kernel", "100001"}});
    const std::string r = capped(256, [&] { load_model(path); return std::string(); });
    CHECK(contains(r, "threw: "));
    CHECK(contains(r, "kernel"));
    CHECK(contains(r, "kMaxKernel"));
    // Fields within their ranges that together imply far more parameters than the file holds:
    // the model is built inside a budget of the file's values and refused before allocating.
    const std::string big = model_with(dir, "big.safetensors", {{"kernel", "255"}, {"channels", "1024,1024"}, {"dim", "4096"}, {"heads", "64"}});
    const std::string r2 = capped(256, [&] { load_model(big); return std::string(); });
    CHECK(contains(r2, "threw: "));
    CHECK(contains(r2, "big.safetensors: the architecture its metadata declares needs more values than"));
    // The same budget guards the baselines' loaders: a MAPPO policy claiming 4096-wide layers.
    const std::string mappo = dir.file("mappo.safetensors");
    save_mappo(mappo, MappoNet(MappoNetConfig{}));
    SafeTensors st = load_safetensors(mappo);
    st.metadata["mappo.hidden"] = "4096";
    save_safetensors(mappo, st.tensors, st.metadata);
    CHECK(contains(error_of([&] { load_mappo(mappo); }), "mappo.safetensors: the architecture its metadata declares needs more values than"));
    // The temporal attention's workspace per agent is bounded too.
    ModelConfig c = tiny_config();
    c.horizon = 4096;
    c.heads = 4;
    CHECK(contains(error_of([&] { c.validate(); }), "kMaxAttentionScores"));
    // The unchanged file still loads.
    CHECK(load_model(model_with(dir, "ok.safetensors", {})).config.kernel == 3);
}

TEST_CASE("limits: kernel 1073741823 is refused without signed overflow in Conv1d") {
    TempDir dir;
    const std::string path = model_with(dir, "khuge.safetensors", {{"kernel", "1073741823"}});
    const std::string e = error_of([&] { load_model(path); });
    CHECK(contains(e, "khuge.safetensors"));
    CHECK(contains(e, "kernel"));
    // The layers themselves: sizes are multiplied without int overflow (UBSan checks this in
    // make test-sanitize) and a tensor beyond the store's int offsets is refused, not allocated.
    ParamStore ps;
    Rng rng(0);
    CHECK_THROWS_WITH_AS(Conv1d(ps, "c", 2, 32, 1073741823, rng), doctest::Contains("kMaxStoreValues"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(Conv2d(ps, "c2", 64, 64, 46341, 1, 0, rng), doctest::Contains("kMaxStoreValues"), std::invalid_argument);
    CHECK(ps.size() == 0);
    Conv1d ok(ps, "ok", 2, 4, 3, rng);  // normal sizes still work
    CHECK(ps.size() == 3 * 2 * 4 + 4);
}

TEST_CASE("limits: --model /dev/zero or an 8 GB sparse file fails fast with a clear message") {
    TempDir dir;
    const auto t0 = std::chrono::steady_clock::now();
    CHECK(contains(error_of([] { load_model("/dev/zero"); }), "/dev/zero: is a device"));
    CHECK(contains(error_of([] { load_demos("/dev/zero"); }), "/dev/zero: is a device"));
    CHECK(contains(error_of([&] { load_model(dir.path); }), "is a directory"));
    // A sparse 8 GB file, empty, and one that begins with a valid checkpoint.
    const std::string empty = dir.file("sparse.bin"), valid = model_with(dir, "sparse-valid.safetensors", {});
    for (const std::string& path : {empty, valid}) {
        const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT, 0644);
        REQUIRE(fd >= 0);
        REQUIRE(::ftruncate(fd, 8ll << 30) == 0);
        ::close(fd);
        const std::string r = capped(256, [&] { load_model(path); return std::string(); });
        CHECK(contains(r, "threw: " + path + ": 8589934592 bytes exceed the limit kMaxCheckpointBytes"));
        const std::string d = capped(256, [&] { load_demos(path); return std::string(); });
        CHECK(contains(d, "threw: " + path + ": 8589934592 bytes exceed the limit kMaxDatasetBytes"));
    }
    // A pipe is read by its declared header: a valid checkpoint followed by an endless stream
    // of zeros is refused once the declared payload has been read.
    const std::string good = model_with(dir, "good.safetensors", {});
    const std::vector<uint8_t> bytes = read_file(good);
    const std::string fifo = dir.file("pipe");
    REQUIRE(::mkfifo(fifo.c_str(), 0600) == 0);
    const pid_t writer = ::fork();
    REQUIRE(writer >= 0);
    if (writer == 0) {
        std::signal(SIGPIPE, SIG_IGN);
        const int fd = ::open(fifo.c_str(), O_WRONLY);
        if (fd < 0) ::_exit(1);
        for (size_t done = 0; done < bytes.size();) {
            const ssize_t w = ::write(fd, bytes.data() + done, bytes.size() - done);
            if (w <= 0) ::_exit(0);
            done += (size_t)w;
        }
        const std::vector<uint8_t> zeros(1 << 16, 0);
        while (::write(fd, zeros.data(), zeros.size()) > 0) {}
        ::_exit(0);
    }
    const std::string e = error_of([&] { load_safetensors(fifo); });
    int status = 0;
    ::waitpid(writer, &status, 0);
    CHECK(contains(e, "more bytes follow the"));
    CHECK(std::chrono::steady_clock::now() - t0 < std::chrono::seconds(10));
}

TEST_CASE("limits: a dataset whose positions lie 1e6 outside its world is refused") {
    TempDir dir;
    const std::string path = dir.file("demos.bin");
    auto error_after = [&](const std::function<void(Demonstration&)>& edit) {
        DemoSet set = one_episode();
        set.episodes.push_back(set.episodes[0]);  // a valid second episode
        edit(set.episodes[0]);
        save_demos(path, set);
        return error_of([&] { load_demos(path); });
    };
    CHECK(error_after([](Demonstration&) {}) == "");
    CHECK(contains(error_after([](Demonstration& d) { d.pos[1].x = 1e6; }), "episode 0: pos[1] = (1e+06, 0.02) outside the world"));
    CHECK(contains(error_after([](Demonstration& d) { d.goals[0].y = -3; }), "goals[0] = (0.5, -3) outside the world"));
    CHECK(contains(error_after([](Demonstration& d) { d.map.discs.push_back({{0, 0}, -0.1}); }), "disc 0: needs a finite centre and radius > 0"));
    CHECK(contains(error_after([](Demonstration& d) { d.map.discs.push_back({{9, 0}, 0.1}); }), "disc 0: centre (9, 0) outside the world"));
    CHECK(contains(error_after([](Demonstration& d) { d.map.boxes.push_back({{0.5, 0}, {0.1, 0.1}}); }), "box 0: needs x0 < x1 and y0 < y1"));
    CHECK(contains(error_after([](Demonstration& d) { d.map.boxes.push_back({{-5, 0}, {0.1, 0.1}}); }), "box 0: (-5, 0) - (0.1, 0.1) outside the world"));
    CHECK(contains(error_after([](Demonstration& d) { d.map.half_size = 1e9; }), "kMaxHalfSize"));
    CHECK(contains(error_after([](Demonstration& d) {
        d.steps = 0;
        d.pos.resize(1);
        d.vel.resize(1);
        d.act.clear();
    }), "steps = 0 outside [1, kMaxDatasetSteps"));
    // Team sizes against the model's n_max (madbp train checks its dataset this way).
    DemoSet two = one_episode();
    Demonstration& d = two.episodes[0];
    d.agents = 2;
    d.goals.push_back({-0.5, -0.5});
    for (auto* v : {&d.pos, &d.vel, &d.act}) {
        const std::vector<Vec2> copy = *v;
        v->insert(v->end(), copy.begin(), copy.end());
    }
    CHECK_NOTHROW(validate_demos(two, 2));
    CHECK_THROWS_WITH_AS(validate_demos(two, 1, "d.bin"), doctest::Contains("d.bin: episode 0: agents = 2 outside [1, n_max = 1]"), std::runtime_error);
    // Counts that do not fit the file are refused before anything is allocated.
    DemoSet set = one_episode();
    save_demos(path, set);
    std::vector<uint8_t> bytes = read_file(path);
    const uint32_t huge = 0xffffffffu;
    std::memcpy(bytes.data() + 8 + 4 + 4 + 4, &huge, 4);  // after magic, version, "test": the episode count
    CHECK(contains(error_of([&] { parse_demos(bytes.data(), bytes.size(), "x"); }), "episode count 4294967295 does not fit the file"));
}

TEST_CASE("limits: --episodes= (an empty value) is an error, not the default") {
    Args a(std::vector<std::string>{"--episodes="});
    CHECK_THROWS_WITH_AS(a.integer("--episodes", 100, 1, 1000000), doctest::Contains("--episodes: empty value"), std::invalid_argument);
    Args b(std::vector<std::string>{"--out", ""});
    CHECK_THROWS_WITH_AS(b.str("--out", "x.svg"), doctest::Contains("--out: empty value"), std::invalid_argument);
    Args c(std::vector<std::string>{"--half-size="});
    CHECK_THROWS_WITH_AS(c.real("--half-size", 1.2, 0.6, 100), doctest::Contains("empty value"), std::invalid_argument);
    Args d(std::vector<std::string>{"--json="});
    CHECK_THROWS_WITH_AS(d.flag("--json"), doctest::Contains("takes no value"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(madbp_cli::split("empty,", "--map"), doctest::Contains("--map: empty item in 'empty,'"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(madbp_cli::split("empty,,barrier", "--map"), doctest::Contains("--map: empty item"), std::invalid_argument);
    Args ok(std::vector<std::string>{"--episodes", "7"});
    CHECK(ok.integer("--episodes", 100, 1, 1000000) == 7);
    Args absent(std::vector<std::string>{});
    CHECK(absent.integer("--episodes", 100, 1, 1000000) == 100);
}

TEST_CASE("limits: add_agent(..., id = INT_MAX) is refused, ids stay in range") {
    World w;
    CHECK_THROWS_WITH_AS(w.add_agent({0, 0}, {0.5, 0.5}, INT_MAX), doctest::Contains("kMaxAgentId"), std::invalid_argument);
    CHECK(w.size() == 0);
    CHECK(w.add_agent({0, 0}, {0.5, 0.5}, kMaxAgentId) == kMaxAgentId);
    // The next automatic id would pass the limit.
    CHECK_THROWS_WITH_AS(w.add_agent({0.5, 0}, {-0.5, 0.5}), doctest::Contains("no free id"), std::invalid_argument);
    CHECK(w.add_agent({0.5, 0}, {-0.5, 0.5}, 3) == 3);
}

TEST_CASE("limits: --scene naming a directory says so") {
    TempDir dir;
    CHECK_THROWS_WITH_AS(load_scene(dir.path), doctest::Contains((dir.path + ": is a directory").c_str()), std::runtime_error);
    CHECK_THROWS_WITH_AS(load_scene("/dev/zero"), doctest::Contains("is a device"), std::runtime_error);
    // A scene file over kMaxSceneBytes is refused before it is read.
    const std::string big = dir.file("big.scene");
    {
        std::ofstream f(big);
        f << "madbp-scene 1\n" << std::string(kMaxSceneBytes, '#') << "\nagent 0 0 0.5 0.5\n";
    }
    CHECK_THROWS_WITH_AS(load_scene(big), doctest::Contains("kMaxSceneBytes"), std::runtime_error);
}

TEST_CASE("limits: --scene together with --agents, --map or --half-size is an error") {
    for (const char* k : {"--agents", "--map", "--half-size"}) {
        Args a(std::vector<std::string>{"--scene", "x.scene", k, "4"});
        CHECK_THROWS_WITH_AS(madbp_cli::refuse_scene_overrides(a, "x.scene"), doctest::Contains((std::string(k) + ": --scene x.scene fixes").c_str()),
                             std::invalid_argument);
        CHECK_NOTHROW(madbp_cli::refuse_scene_overrides(a, ""));  // without a scene they are fine
    }
    Args plain(std::vector<std::string>{"--scene", "x.scene", "--episodes", "4"});
    CHECK_NOTHROW(madbp_cli::refuse_scene_overrides(plain, "x.scene"));
}

TEST_CASE("limits: a NUL byte inside a scene number gives the whole message") {
    std::string text = "madbp-scene 1\nagent 0 0 0.5 1";
    text += '\0';
    text += "7\n";
    const std::string e = error_of([&] { parse_scene(text, "t.scene"); });
    CHECK(e == "t.scene:2: '1\\x007' is not a number");
    std::string kw = "madbp-scene 1\nag";
    kw += '\0';
    kw += "ent 0 0 0.5 0.5\n";
    CHECK(contains(error_of([&] { parse_scene(kw, "t.scene"); }), "unknown keyword 'ag\\x00ent' (expected"));
    CHECK(printable(std::string(100, 'a'), 8) == "aaaaaaaa...");
}

TEST_CASE("limits: planner flags: --set and --neighbours are checked against the settings table; no silent sentinels") {
    auto choice = [](std::vector<std::string> v) { Args a(v); return madbp_cli::read_planner_choice(a); };
    CHECK_THROWS_WITH_AS(choice({"--set", "sampler.goal_reach=-0.5"}),
                         doctest::Contains("planner setting sampler.goal_reach: must be [0, 100] or auto (got -0.5)"), std::invalid_argument);
    CHECK(choice({"--set", "sampler.goal_reach=0.3"}).settings.sampler.goal_reach == doctest::Approx(0.3));
    CHECK(choice({}).settings.sampler.goal_reach < 0);  // absent: automatic, the model's default_goal_reach
    CHECK(choice({"--set", "sampler.goal_reach=auto"}).settings.sampler.goal_reach < 0);
    CHECK_THROWS_WITH_AS(choice({"--set", "guidance.wieght=1"}), doctest::Contains("'guidance.wieght': no such setting"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(choice({"--set", "guidance.weight"}), doctest::Contains("--set: expected GROUP.NAME=VALUE"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(choice({"--set", "sampler.candidates=2.5"}), doctest::Contains("expected a whole number"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(choice({"--set", "sampler.candidates=65"}), doctest::Contains("must be [1, 64]"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(choice({"--neighbours", "-2"}), doctest::Contains("neighbourhood.neighbours: must be [0, 1024] or auto"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(choice({"--preset", "fast"}), doctest::Contains("--preset: expected tuned or paper"), std::invalid_argument);
    // --set may be given many times, in order; it goes after the preset and the daily flags.
    const auto c = choice({"--preset", "paper", "--neighbours", "4", "--set", "guidance.weight=0.01", "--set=guidance.weight=0.02",
                           "--set", "traffic.take_turns=true"});
    CHECK(c.settings.neighbourhood.neighbours == 4);
    CHECK(c.settings.guidance.weight == 0.02f);
    CHECK(c.settings.traffic.take_turns);
    CHECK(c.settings.sampler.warm_start == 0);  // the rest is the paper's
    Args d(std::vector<std::string>{"--seed", "-1"});
    CHECK_THROWS_WITH_AS(d.integer("--seed", 0, 0), doctest::Contains("out of range"), std::invalid_argument);
}

TEST_CASE("limits: world 1e9 in a scene is refused; grids and pictures stay bounded") {
    CHECK_THROWS_WITH_AS(parse_scene("madbp-scene 1\nworld 1e9\nagent 0 0 1 1\n", "w.scene"),
                         doctest::Contains("w.scene:2: world half-size 1e9 exceeds the limit kMaxHalfSize"), std::invalid_argument);
    CHECK_NOTHROW(parse_scene("madbp-scene 1\nworld 100\nagent 0 0 1 1\n"));
    WorldMap huge;
    huge.half_size = 1e9;
    CHECK_THROWS_WITH_AS(World{huge}, doctest::Contains("kMaxHalfSize"), std::invalid_argument);
    Rng rng(0);
    CHECK_THROWS_WITH_AS(make_map("empty", rng, 1e9), doctest::Contains("kMaxHalfSize"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(make_map("obstacles", rng, 60), doctest::Contains("kMaxObstacles"), std::invalid_argument);
    // The expert's grid no longer wraps to 2 x 2 on a huge map handed to it directly.
    const ClearanceGrid g(huge, ExpertParams{}.cell);
    CHECK(g.n == kRouteMaxGridSide);
    // Scene counts are bounded.
    std::string many = "madbp-scene 1\nworld 50\n";
    for (int i = 0; i <= kMaxObstacles; ++i) many += "disc 0 0 0.01\n";
    many += "agent 10 10 11 11\n";
    CHECK_THROWS_WITH_AS(parse_scene(many), doctest::Contains("kMaxObstacles"), std::invalid_argument);
    // Pictures of a large world are at most kMaxSvgPixels wide; a small world's are unchanged.
    auto width = [](double half) {
        WorldConfig wc;
        wc.max_steps = 2;
        World w = make_random_world("empty", 1, 0, half, wc);
        GuidedExpert expert(w.map());
        const std::string svg = render_svg(run_episode(w, expert, true).log);
        const size_t at = svg.find("width=\"") + 7;
        return std::stod(svg.substr(at, svg.find('"', at) - at));
    };
    CHECK(width(1.2) == doctest::Approx(480));
    CHECK(width(100) <= kMaxSvgPixels);
}
