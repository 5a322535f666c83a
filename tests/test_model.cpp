// MA-DBP model, diffusion sampler and planner (SPEC 5, 6, 8, 12).
#include <doctest/doctest.h>

#include "madbp_train.hpp"
#include "tiny_model.hpp"

using namespace madbp;

namespace {


// B scenes, n slots; agent (b, i) is active when i < counts[b]. Random poses, one disc map.
SceneBatch random_batch(const ModelConfig& c, int B, int n, const std::vector<int>& counts, Rng& rng) {
    SceneBatch s;
    s.resize(B, n, c);
    WorldMap map;
    map.discs.push_back({Vec2{0.3, -0.2}, 0.3});
    Grid g = occupancy_grid(map, c.grid);
    for (int b = 0; b < B; ++b) {
        s.count[b] = counts[b];
        for (int j = 0; j < c.grid * c.grid; ++j) s.grid(0, (long)b * c.grid * c.grid + j) = g.cells[j];
        for (int i = 0; i < n; ++i) {
            const int a = b * n + i;
            s.agent_mask[a] = i < counts[b] ? 1.0f : 0.0f;
            s.slot[a] = (i + 2 * b) % c.n_max;
            for (int r = 0; r < 4; ++r) s.pose(r, a) = (float)rng.uniform(-0.8, 0.8);
            if (c.local_grid > 0)
                local_crop(map, Vec2{s.pose(0, a) * c.position_scale, s.pose(1, a) * c.position_scale}, c.local_grid, c.local_extent,
                           s.local.data() + (long)a * c.local_grid * c.local_grid);
        }
    }
    return s;
}

Mat random_window(const ModelConfig& c, const SceneBatch& s, Rng& rng) {
    Mat x(2, (long)c.horizon * s.agents());
    for (long j = 0; j < x.size(); ++j) x.data()[j] = (float)rng.normal();
    return x;
}

// Columns of the window tensor that belong to agent a.
Mat agent_cols(const Mat& m, int a, int H) { return m.middleCols((long)a * H, H); }

}  // namespace

TEST_CASE("model: parameter count and config validation") {
    ModelConfig c;
    MadbpModel m(c, 0);
    CHECK(m.parameter_count() > 10000);
    ModelConfig bad = c;
    bad.horizon = 10;  // not a multiple of 4 with two levels
    CHECK_THROWS_AS(MadbpModel(bad, 0), std::invalid_argument);
    bad = c;
    bad.heads = 3;
    CHECK_THROWS_AS(MadbpModel(bad, 0), std::invalid_argument);
}

TEST_CASE("model: masked slots never change active agents' outputs") {
    for (Processor p : {Processor::AAP, Processor::LE})
        for (bool training : {true, false}) {
            const ModelConfig c = tiny_config(p);
            MadbpModel m(c, 3);
            m.set_training(training);
            Rng rng(5);
            SceneBatch s = random_batch(c, 2, 4, {2, 3}, rng);
            Mat x = random_window(c, s, rng), eps1, eps2;
            const int k[2] = {3, 17};
            m.encode_context(s);
            m.denoise(x, k, eps1);
            // Garbage in every masked slot: window, pose and slot.
            for (int b = 0; b < 2; ++b)
                for (int i = s.count[b]; i < 4; ++i) {
                    const int a = b * 4 + i;
                    x.middleCols((long)a * c.horizon, c.horizon).setConstant(37.0f);
                    s.pose.col(a).setConstant(-5.0f);
                    s.local.middleCols((long)a * 64, 64).setConstant(1.0f);
                    s.slot[a] = c.n_max - 1;
                }
            m.encode_context(s);
            m.denoise(x, k, eps2);
            for (int b = 0; b < 2; ++b)
                for (int i = 0; i < s.count[b]; ++i) {
                    const int a = b * 4 + i;
                    CHECK((agent_cols(eps1, a, c.horizon) - agent_cols(eps2, a, c.horizon)).cwiseAbs().maxCoeff() < 1e-5f);
                }
        }
}

TEST_CASE("model: a padded batch gives the same outputs as an unpadded one") {
    const ModelConfig c = tiny_config();
    for (bool training : {true, false}) {
        MadbpModel m(c, 4);
        m.set_training(training);
        Rng rng(6);
        SceneBatch tight = random_batch(c, 1, 3, {3}, rng);
        Mat x_tight = random_window(c, tight, rng);
        SceneBatch padded;
        padded.resize(1, 5, c);
        padded.grid = tight.grid;
        padded.count[0] = 3;
        Mat x_padded = Mat::Zero(2, (long)c.horizon * 5);
        for (int i = 0; i < 5; ++i) padded.slot[i] = i;
        for (int i = 0; i < 3; ++i) {
            padded.agent_mask[i] = 1;
            padded.slot[i] = tight.slot[i];
            padded.pose.col(i) = tight.pose.col(i);
            const long L = (long)c.local_grid * c.local_grid;
            padded.local.middleCols(i * L, L) = tight.local.middleCols(i * L, L);
            x_padded.middleCols((long)i * c.horizon, c.horizon) = agent_cols(x_tight, i, c.horizon);
        }
        padded.slot[3] = 4, padded.slot[4] = 5;
        const int k[1] = {9};
        Mat e1, e2;
        m.encode_context(tight);
        m.denoise(x_tight, k, e1);
        m.encode_context(padded);
        m.denoise(x_padded, k, e2);
        CHECK((e1 - e2.leftCols(e1.cols())).cwiseAbs().maxCoeff() < 1e-5f);
    }
}

TEST_CASE("model: whole-model backward matches finite differences") {
    // Per tensor, the relative error of a few central differences. BatchNorm over a small
    // batch and ReLU / max-pool kinks make single probes noisy, so the check is: nearly every
    // tensor within 5%, none beyond 30%. A wrong backward is off by O(1) on many tensors.
    for (Processor p : {Processor::AAP, Processor::LE}) {
        const ModelConfig c = tiny_config(p);
        MadbpModel m(c, 11);
        m.set_training(true);
        Rng rng(12);
        SceneBatch s = random_batch(c, 3, 3, {3, 2, 3}, rng);
        const Mat x = random_window(c, s, rng);
        const int k[3] = {4, 15, 9};
        Mat R(2, x.cols());
        for (long j = 0; j < R.size(); ++j) R.data()[j] = (float)rng.normal();
        for (int a = 0; a < s.agents(); ++a)
            if (!s.agent_mask[a]) R.middleCols((long)a * c.horizon, c.horizon).setZero();
        Mat eps;
        auto loss = [&]() {
            m.encode_context(s);
            m.denoise(x, k, eps);
            double sum = 0;
            for (long j = 0; j < eps.size(); ++j) sum += (double)eps.data()[j] * R.data()[j];
            return sum;
        };
        loss();
        m.params->zero_grad();
        m.backward(R);
        const Vec analytic = m.params->grad;
        int tensors = 0, close = 0;
        double worst = 0;
        for (const auto& e : m.params->entries) {
            if (!e.trainable) continue;
            double diff2 = 0, mag2 = 0;
            for (int probe = 0; probe < 4; ++probe) {
                const int idx = e.offset + (int)(rng.uniform() * e.numel());
                const float keep = m.params->value[idx], h = 1e-3f;
                m.params->value[idx] = keep + h;
                const double up = loss();
                m.params->value[idx] = keep - h;
                const double down = loss();
                m.params->value[idx] = keep;
                const double fd = (up - down) / (2 * h), an = analytic[idx];
                diff2 += (fd - an) * (fd - an);
                mag2 += fd * fd + an * an;
            }
            // Floor 0.1: tensors whose true gradient is zero (a bias before BatchNorm, attention
            // key biases) show only float32 noise of the differences (~1e-2), and must stay near 0.
            const double err = std::sqrt(diff2) / std::max(std::sqrt(mag2), 0.1);
            if (err > 0.05) MESSAGE(e.name << " relative error " << err);
            tensors++;
            close += err < 0.05;
            worst = std::max(worst, err);
        }
        CHECK(tensors > 30);
        CHECK(close >= 0.9 * tensors);
        CHECK(worst < 0.3);
    }
}

namespace {
// A denoiser that knows the answer for a fixed x0: eps = (x - sqrt(ab) x0) / sqrt(1 - ab), or
// x0 itself, as config.prediction says.
struct OracleDenoiser {
    ModelConfig config;
    const NoiseSchedule* schedule;
    Mat x0;
    void encode_context(const SceneBatch&) {}
    void denoise(const Mat& x, const int* k, Mat& out) {
        const double ab = schedule->alpha_bar[k[0]];
        if (config.prediction == Prediction::X0) out = x0;
        else out = (x - (float)std::sqrt(ab) * x0) / (float)std::sqrt(1 - ab);
    }
};
}  // namespace

TEST_CASE("sampler: DDIM with an oracle recovers x0; inpainted starts are exact") {
  for (Prediction pred : {Prediction::Eps, Prediction::X0}) {
    ModelConfig c = tiny_config();
    c.prediction = pred;
    NoiseSchedule sched(c.diffusion_steps);
    Rng rng(21);
    SceneBatch s = random_batch(c, 1, 3, {3}, rng);
    OracleDenoiser oracle{c, &sched, Mat()};
    oracle.x0 = Mat(2, (long)c.horizon * 3);
    for (long j = 0; j < oracle.x0.size(); ++j) oracle.x0.data()[j] = (float)rng.uniform(-0.9, 0.9);
    // The oracle's x0 starts at zero displacement, as a trained model's would.
    for (int a = 0; a < 3; ++a) oracle.x0.col((long)a * c.horizon).setZero();
    SamplerConfig sc;
    sc.sample_steps = 5;
    sc.goal_inpaint = false;
    Mat x, eps;
    std::vector<int> buf;
    sample_windows(oracle, sched, s, sc, rng, x, eps, buf);
    CHECK((x - oracle.x0).cwiseAbs().maxCoeff() < 1e-4f);
    // An oracle that disagrees about the start: the start is still imposed exactly.
    for (int a = 0; a < 3; ++a) oracle.x0.col((long)a * c.horizon).setConstant(0.5f);
    sample_windows(oracle, sched, s, sc, rng, x, eps, buf);
    for (int a = 0; a < 3; ++a) {
        CHECK(x(0, (long)a * c.horizon) == 0.0f);
        CHECK(x(1, (long)a * c.horizon) == 0.0f);
    }
    // Goal inpainting: a goal within reach pins the last waypoint to it.
    sc.goal_inpaint = true;
    s.pose.col(0).tail<2>() = s.pose.col(0).head<2>() + Eigen::Vector2f(0.2f, -0.1f) / c.position_scale;
    sample_windows(oracle, sched, s, sc, rng, x, eps, buf);
    CHECK(x(0, c.horizon - 1) == doctest::Approx(0.2 / c.window_scale));
    CHECK(x(1, c.horizon - 1) == doctest::Approx(-0.1 / c.window_scale));
  }
}

TEST_CASE("noise schedule: cosine, monotone, DDIM steps") {
    NoiseSchedule s(100);
    CHECK(s.alpha_bar[0] == 1.0);
    for (int k = 1; k <= 100; ++k) CHECK(s.alpha_bar[k] < s.alpha_bar[k - 1]);
    CHECK(s.alpha_bar[100] < 1e-3);
    CHECK(s.alpha_bar[1] > 0.999);
    auto ks = s.ddim_steps(10);
    CHECK(ks.size() == 11);
    CHECK(ks.front() == 100);
    CHECK(ks.back() == 0);
    CHECK_THROWS_AS(s.ddim_steps(0), std::invalid_argument);
}

TEST_CASE("planner: plans every agent, rejects bad input") {
    ModelConfig c = tiny_config();
    c.n_max = 4;
    DiffusionPlanner planner(MadbpModel(c, 1), 7);
    World w = make_random_world("obstacles", 3, 2);
    Plan p = planner.plan(w);
    REQUIRE(p.ids.size() == 3);
    for (auto& wp : p.waypoints) {
        CHECK((int)wp.size() == c.horizon - 1);
        for (Vec2 q : wp) CHECK((std::isfinite(q.x) && std::isfinite(q.y)));
    }
    // Same seed, same plan.
    DiffusionPlanner again(MadbpModel(c, 1), 7);
    Plan p2 = again.plan(w);
    CHECK(p2.waypoints[2][3].x == p.waypoints[2][3].x);
    // More agents than n_max: neighbourhoods of n_max by default; one scene of them all is refused.
    World crowded = make_random_world("empty", 5, 3);
    CHECK(planner.plan(crowded).ids.size() == 5);
    CHECK(planner.last_scene_batch().B > 1);  // scenes that cover the team
    CHECK(planner.last_scene_batch().B < 5);
    planner.settings.neighbourhood.neighbours = 0;
    CHECK_THROWS_WITH_AS(planner.plan(crowded), doctest::Contains("n_max"), std::invalid_argument);
    planner.settings.neighbourhood.neighbours = -1;
    // A team of zero plans nothing.
    World none;
    CHECK(planner.plan(none).ids.empty());
}

TEST_CASE("checkpoint: model round trip; a mismatching config is a clear error") {
    const ModelConfig c = tiny_config();
    MadbpModel m(c, 9);
    const std::string path = "build/test-model.safetensors";
    save_model(path, m, {{"demonstrator", "test"}});
    MadbpModel back = load_model(path);
    CHECK(back.config.to_metadata() == c.to_metadata());
    CHECK(back.params->value == m.params->value);
    // Rewrite with a different dim in the metadata: shapes no longer match.
    auto tensors = param_tensors(*m.params);
    auto md = c.to_metadata();
    md["dim"] = "16";
    save_safetensors(path, tensors, md);
    CHECK_THROWS_AS(load_model(path), std::runtime_error);
    md = c.to_metadata();
    md["model"] = "mappo";
    save_safetensors(path, tensors, md);
    CHECK_THROWS_WITH_AS(load_model(path), doctest::Contains("not an MA-DBP checkpoint"), std::runtime_error);
    md = c.to_metadata();
    md["channels"] = "4,x";
    save_safetensors(path, tensors, md);
    CHECK_THROWS_WITH_AS(load_model(path), doctest::Contains("channels"), std::runtime_error);
    std::remove(path.c_str());
}

#include "alloc_counter_api.hpp"

TEST_CASE("planner: a steady-state plan allocates nothing") {
    ModelConfig c;  // the default configuration
    set_num_threads(1);  // Eigen's own threaded GEMM allocates per call
    DiffusionPlanner planner(MadbpModel(c, 1), 3);
    World w = make_random_world("barrier", 6, 4);
    Plan plan;
    for (int i = 0; i < 3; ++i) planner.plan_into(w, plan);  // warm-up: workspaces take their sizes
    [[maybe_unused]] const long allocs = count_allocs([&] { for (int i = 0; i < 3; ++i) planner.plan_into(w, plan); });
#if MADBP_TEST_COUNT_ALLOCS
    CHECK(allocs == 0);
#endif
    CHECK(plan.ids.size() == 6);
}

TEST_CASE("planner: with a waypoint stride the steps between sampled waypoints are interpolated") {
    ModelConfig c = tiny_config();
    c.waypoint_stride = 2;
    DiffusionPlanner planner(MadbpModel(c, 2), 1);
    World w = make_random_world("empty", 2, 9);
    Plan p = planner.plan(w);
    REQUIRE(p.waypoints[0].size() == (size_t)(c.horizon - 1) * 2);
    const Vec2 start = w.agents()[0].pos;
    // Step 1 lies halfway between the start and sampled waypoint 1 (step 2), and so on.
    CHECK(norm(p.waypoints[0][0] - (start + p.waypoints[0][1]) * 0.5) < 1e-9);
    CHECK(norm(p.waypoints[0][2] - (p.waypoints[0][1] + p.waypoints[0][3]) * 0.5) < 1e-9);
    // Reach scales with the window's span: 0.55 units per 15 steps; 7 waypoints x 2 steps here.
    CHECK(default_goal_reach(c) == doctest::Approx(0.55 * 14 / 15).epsilon(1e-6));
}

TEST_CASE("planner: a team that changes size on the same map plans like a fresh planner") {
    ModelConfig c = tiny_config();
    WorldMap map;
    map.discs.push_back({Vec2{0.0, 0.0}, 0.5});  // large enough to show on the tiny 8x8 grid
    World w(map);
    w.add_agent({-0.9, -0.9}, {0.9, 0.9});
    w.add_agent({0.9, -0.9}, {-0.9, 0.9});
    w.add_agent({-0.9, 0.9}, {0.9, -0.9});
    DiffusionPlanner reused(MadbpModel(c, 4), 8);
    reused.plan(w);
    w.remove_agent(w.agents()[1].id);
    reused.reseed(99);
    Plan a = reused.plan(w);
    DiffusionPlanner fresh(MadbpModel(c, 4), 99);
    Plan b = fresh.plan(w);
    REQUIRE(a.ids == b.ids);
    // The context encodes the map (random weights saturate the sampler's clip, so compare it).
    CHECK((reused.model().context() - fresh.model().context()).cwiseAbs().maxCoeff() == 0.0f);
}

TEST_CASE("checkpoint: oversized or malformed numbers in the metadata are clear errors") {
    const ModelConfig c = tiny_config();
    MadbpModel m(c, 9);
    const std::string path = "build/test-model-meta.safetensors";
    for (auto bad : std::vector<std::pair<std::string, std::string>>{
             {"dim", "46342"}, {"grid", "536870912"}, {"position_scale", "1.2junk"}, {"diffusion_steps", "999999999"}}) {
        auto md = c.to_metadata();
        md[bad.first] = bad.second;
        save_safetensors(path, param_tensors(*m.params), md);
        CHECK_THROWS_WITH_AS(load_model(path), doctest::Contains(bad.first.c_str()), std::runtime_error);
    }
    std::remove(path.c_str());
}

TEST_CASE("planner: neighbourhood planning gives each agent the context of itself and its nearest agents") {
    ModelConfig c = tiny_config();
    WorldMap map;
    map.discs.push_back({Vec2{0.0, 0.0}, 0.5});
    World w(map);
    const Vec2 starts[5] = {{-0.9, -0.9}, {-0.6, -0.9}, {0.9, 0.9}, {0.9, 0.6}, {-0.9, 0.9}};
    for (int i = 0; i < 5; ++i) w.add_agent(starts[i], -starts[i]);
    // K >= n: the whole team in one scene, exactly the paper's planner.
    DiffusionPlanner whole(MadbpModel(c, 5), 11), wide(MadbpModel(c, 5), 11);
    whole.settings.neighbourhood.neighbours = 0;
    wide.settings.neighbourhood.neighbours = 5;
    Plan a = whole.plan(w), b = wide.plan(w);
    CHECK(a.waypoints[3][2].x == b.waypoints[3][2].x);
    // K = 2: agent i is planned in a scene of itself (slot 0) and its nearest agent (slot 1).
    DiffusionPlanner local(MadbpModel(c, 5), 11);
    local.settings.neighbourhood.neighbours = 2;
    local.settings.neighbourhood.cover = 0;  // a scene per robot
    local.settings.workspace.chunk_scenes = 8;  // one chunk: model().context() is every scene's
    local.settings.neighbourhood.sensing_radius = 10;  // every nearest agent counts, however far (agent 4's is 1.8 away)
    Plan p = local.plan(w);
    REQUIRE(p.ids.size() == 5);
    for (size_t i = 0; i < 5; ++i) {
        CHECK(p.ids[i] == w.agents()[i].id);
        for (Vec2 q : p.waypoints[i]) CHECK((std::isfinite(q.x) && std::isfinite(q.y)));
    }
    const int nearest[5] = {1, 0, 3, 2, 0};  // by construction of the starts
    const Mat ctx = local.model().context();
    REQUIRE(ctx.cols() == 10);
    for (int i = 0; i < 5; ++i) {
        World pair(map);
        pair.add_agent(starts[i], -starts[i]);
        pair.add_agent(starts[nearest[i]], -starts[nearest[i]]);
        DiffusionPlanner alone(MadbpModel(c, 5), 11);
        alone.plan(pair);
        CHECK((alone.model().context().col(0) - ctx.col(2 * i)).cwiseAbs().maxCoeff() < 1e-5f);
        CHECK((alone.model().context().col(1) - ctx.col(2 * i + 1)).cwiseAbs().maxCoeff() < 1e-5f);
    }
    // A team larger than n_max (6 here) plans in neighbourhoods, and only then.
    World crowd = make_random_world("empty", 8, 4);
    CHECK(local.plan(crowd).ids.size() == 8);
    CHECK_THROWS_AS(whole.plan(crowd), std::invalid_argument);
    // Within a sensing radius of 1.5 agent 4 (1.8 from its nearest) has no neighbour: a scene of
    // one; the default radius (2 position_scale = 2.4) includes its nearest.
    local.settings.neighbourhood.sensing_radius = 1.5;
    local.plan(w);
    CHECK(local.last_scene_batch().count[4] == 1);
    CHECK(local.last_scene_batch().count[0] == 2);
    local.settings.neighbourhood.sensing_radius = 0;
    local.plan(w);
    CHECK(local.last_scene_batch().count[4] == 2);
    local.settings.neighbourhood.neighbours = -2;
    CHECK_THROWS_AS(local.plan(w), std::invalid_argument);
}
