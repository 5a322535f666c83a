// Tests of the MADiff baseline (madbp_train.hpp, SPEC 3.4): classifier-free guidance and the
// condition dropout, the inverse dynamics (shapes, and learning a linear relation), central
// differences for the agent attention, the inverse dynamics and the whole training loss, the
// step reward on a hand-built episode, training (deterministic, resumable, loss falls),
// checkpoints (round trip, truncated / foreign files) and the policy (finite, in-range,
// seeded actions; a team of another size is refused).
#include <doctest/doctest.h>

#include <cstdio>

#include "madbp_train.hpp"

using namespace madbp;

namespace {

std::string temp_path(const std::string& name) { return "/tmp/madbp_test_madiff_" + std::to_string(::getpid()) + "_" + name; }

void remove_outputs(const std::string& out) {
    for (const char* ext : {"", ".train", ".csv"}) std::remove((out + ext).c_str());
}

MadiffConfig tiny_config(int agents = 2) {
    MadiffConfig c;
    c.agents = agents;
    c.horizon = 8;
    c.dim = 8;
    c.channels = {8, 16};
    c.heads = 2;
    c.inv_hidden = 8;
    c.diffusion_steps = 20;
    c.sample_steps = 4;
    return c;
}

Mat randn(int r, int c, Rng& rng, double scale = 1) {
    Mat m(r, c);
    for (long j = 0; j < m.size(); ++j) m.data()[j] = (float)(scale * rng.normal());
    return m;
}

// A batch of B windows built by hand (no demonstrations needed).
MadiffBatch random_batch(const MadiffConfig& c, int B, Rng& rng) {
    MadiffBatch mb;
    const int A = B * c.agents, H = c.horizon;
    mb.B = B, mb.n = c.agents;
    mb.x0 = randn(kMappoObs, H * A, rng, 0.5);
    mb.ret.resize(B);
    for (float& r : mb.ret) r = (float)rng.uniform();
    mb.o_t = randn(kMappoObs, (H - 1) * A, rng, 0.5);
    mb.o_next = randn(kMappoObs, (H - 1) * A, rng, 0.5);
    mb.act = randn(2, (H - 1) * A, rng, 0.5);
    return mb;
}

// Relative error of central differences of f against the analytic gradient at a few entries
// of every trainable tensor; returns (tensors checked, tensors within 5%, worst error).
struct FdSummary { int tensors = 0, close = 0; double worst = 0; };
FdSummary check_params(ParamStore& ps, const Vec& analytic, const std::function<double()>& f, Rng& rng, int probes, float h) {
    FdSummary s;
    for (const auto& e : ps.entries) {
        if (!e.trainable) continue;
        double diff2 = 0, mag2 = 0;
        for (int p = 0; p < probes; ++p) {
            const int idx = e.offset + (int)(rng.uniform() * e.numel());
            const float keep = ps.value[idx];
            ps.value[idx] = keep + h;
            const double up = f();
            ps.value[idx] = keep - h;
            const double down = f();
            ps.value[idx] = keep;
            const double fd = (up - down) / (2 * h), an = analytic[idx];
            diff2 += (fd - an) * (fd - an);
            mag2 += fd * fd + an * an;
        }
        // Floor: tensors whose true gradient is ~0 (a bias before BatchNorm) show float32 noise.
        const double err = std::sqrt(diff2) / std::max(std::sqrt(mag2), 0.05);
        if (err > 0.05) MESSAGE(e.name << " relative error " << err);
        s.tensors++;
        s.close += err < 0.05;
        s.worst = std::max(s.worst, err);
    }
    return s;
}

// A small expert dataset on the empty map: teams of 1 and 2, a few episodes each.
const DemoSet& tiny_demos() {
    static DemoSet set = [] {
        CollectConfig c;
        c.maps = {"empty"};
        c.n_train_max = 2;
        c.episodes = 8;
        return collect_demonstrations(c, expert_demonstrator(), "expert");
    }();
    return set;
}

MadiffTrainConfig tiny_train(const std::string& out, long steps) {
    MadiffTrainConfig tc;
    tc.steps = steps;
    tc.batch = 4;
    tc.log_every = 10;
    tc.checkpoint_every = 20;
    tc.ema_start = 10;
    tc.out = out;
    return tc;
}

}  // namespace

TEST_CASE("madiff: classifier-free guidance on hand-built eps tensors") {
    Mat c(2, 2), u(2, 2), out;
    c << 1, 2, 3, -1;
    u << 0.5f, 0, 1, 1;
    classifier_free_guidance(c, u, 1.2f, out);
    // u + 1.2 (c - u): 0.5 + 1.2*0.5, 0 + 1.2*2, 1 + 1.2*2, 1 + 1.2*(-2).
    CHECK(out(0, 0) == doctest::Approx(1.1));
    CHECK(out(0, 1) == doctest::Approx(2.4));
    CHECK(out(1, 0) == doctest::Approx(3.4));
    CHECK(out(1, 1) == doctest::Approx(-1.4));
    classifier_free_guidance(c, u, 0.0f, out);
    CHECK((out - u).cwiseAbs().maxCoeff() == 0.0f);
    classifier_free_guidance(c, u, 1.0f, out);
    CHECK((out - c).cwiseAbs().maxCoeff() < 1e-6f);
    // The sampler combines the noise each branch's x0 implies; since eps is affine in x0 this
    // equals guiding x0 directly: eps(x0_u + w (x0_c - x0_u)).
    const float sa = 0.6f, s1a = 0.8f, w = 1.2f;
    Mat x(2, 2), x0c(2, 2), x0u(2, 2), ec, eu, guided;
    x << 0.3f, -0.2f, 1.0f, 0.1f;
    x0c << 0.5f, 0.1f, -0.4f, 0.9f;
    x0u << -0.2f, 0.3f, 0.2f, 0.4f;
    ec = (x - sa * x0c) / s1a;
    eu = (x - sa * x0u) / s1a;
    classifier_free_guidance(ec, eu, w, guided);
    const Mat direct = (x - sa * (x0u + w * (x0c - x0u))) / s1a;
    CHECK((guided - direct).cwiseAbs().maxCoeff() < 1e-5f);
}

TEST_CASE("madiff: condition dropout drops about a quarter of a seeded batch") {
    Rng rng(42);
    std::vector<float> keep;
    condition_keep_mask(4000, 0.25f, rng, keep);
    REQUIRE(keep.size() == 4000);
    double dropped = 0;
    for (float k : keep) {
        CHECK((k == 0.0f || k == 1.0f));
        dropped += k == 0.0f;
    }
    // sd of the fraction: sqrt(0.25 * 0.75 / 4000) = 0.0068; +-0.03 is 4.4 sd.
    CHECK(dropped / 4000 == doctest::Approx(0.25).epsilon(0.12));
    condition_keep_mask(100, 0.0f, rng, keep);
    CHECK(std::count(keep.begin(), keep.end(), 1.0f) == 100);
    condition_keep_mask(100, 1.0f, rng, keep);
    CHECK(std::count(keep.begin(), keep.end(), 0.0f) == 100);
    // The training loss draws the same mask from the model's dropout (0.25 by default).
    MadiffModel m(tiny_config(), 1);
    NoiseSchedule schedule(m.config.diffusion_steps);
    Rng brng(3);
    MadiffBatch mb = random_batch(m.config, 400, brng);
    MadiffWorkspace ws;
    Rng lrng(9);
    madiff_loss(m, schedule, mb, lrng, false, ws);
    REQUIRE(ws.keep.size() == 400);
    CHECK(std::count(ws.keep.begin(), ws.keep.end(), 0.0f) / 400.0 == doctest::Approx(0.25).epsilon(0.3));
}

TEST_CASE("madiff: inverse dynamics shapes, and it learns a = k (o_t+1 - o_t)") {
    Rng rng(7);
    ParamStore ps;
    InverseDynamics inv(ps, "inv", 2, 16, rng);
    Mat a;
    inv.forward(randn(2, 5, rng), randn(2, 5, rng), a);
    CHECK(a.rows() == 2);
    CHECK(a.cols() == 5);
    CHECK(a.allFinite());
    // Train on a = 0.8 (o_next - o_t), o_t and the step uniform in [-1, 1]^2.
    const float k = 0.8f;
    auto draw = [&](int N, Mat& o0, Mat& o1, Mat& target) {
        o0.resize(2, N), o1.resize(2, N);
        for (int j = 0; j < N; ++j)
            for (int r = 0; r < 2; ++r) {
                o0(r, j) = (float)rng.uniform(-1, 1);
                o1(r, j) = o0(r, j) + (float)rng.uniform(-1, 1);
            }
        target = k * (o1 - o0);
    };
    Adam adam;
    adam.lr = 1e-2f;
    Mat o0, o1, target, da;
    for (int step = 0; step < 400; ++step) {
        draw(64, o0, o1, target);
        inv.forward(o0, o1, a);
        da = (a - target) / 64.0f;
        ps.zero_grad();
        inv.backward(da);
        adam.update(ps);
    }
    draw(200, o0, o1, target);
    inv.forward(o0, o1, a);
    const double rms = std::sqrt((a - target).squaredNorm() / a.size());
    MESSAGE("inverse dynamics held-out RMS error " << rms << " (targets within +-0.8)");
    CHECK(rms < 0.05);
}

TEST_CASE("madiff: agent attention and inverse dynamics backward match central differences") {
    Rng rng(11);
    ParamStore ps;
    const int C = 8, T = 4, B = 2, n = 3;
    AgentAttention att(ps, "att", C, 2, rng);
    InverseDynamics inv(ps, "inv", 3, 6, rng);
    for (long j = 0; j < ps.size(); ++j) ps.value[j] += (float)(0.1 * rng.normal());  // LayerNorm gain/bias off 1/0
    Mat x = randn(C, T * B * n, rng), R = randn(C, T * B * n, rng);
    Mat o0 = randn(3, 7, rng), o1 = randn(3, 7, rng), Ra = randn(2, 7, rng);
    Mat y, a, dx;
    auto loss = [&]() {
        att.forward(x, T, B, n, y);
        inv.forward(o0, o1, a);
        return (double)y.cwiseProduct(R).sum() + (double)a.cwiseProduct(Ra).sum();
    };
    loss();
    ps.zero_grad();
    att.backward(x, T, B, n, R, dx);
    inv.backward(Ra);
    const Vec analytic = ps.grad;
    FdSummary s = check_params(ps, analytic, loss, rng, 6, 1e-2f);
    CHECK(s.tensors == 16);  // LayerNorm (2), attention (8), inverse dynamics (3 Linear layers: 6)
    CHECK(s.worst < 0.05);
    // The input gradient of the attention block, every element.
    double diff2 = 0, mag2 = 0;
    for (long j = 0; j < x.size(); ++j) {
        const float keep = x.data()[j];
        x.data()[j] = keep + 1e-2f;
        const double up = loss();
        x.data()[j] = keep - 1e-2f;
        const double down = loss();
        x.data()[j] = keep;
        const double fd = (up - down) / 2e-2;
        diff2 += (fd - dx.data()[j]) * (fd - dx.data()[j]);
        mag2 += fd * fd;
    }
    CHECK(std::sqrt(diff2 / mag2) < 0.01);
    // The agents of one scene at one time step interact; other scenes and time steps do not.
    att.forward(x, T, B, n, y);
    const Mat y0 = y;
    x(0, 1 * T + 2) += 1.0f;  // scene 0, agent 1, t = 2
    att.forward(x, T, B, n, y);
    CHECK((y.col(0 * T + 2) - y0.col(0 * T + 2)).norm() > 1e-4);  // agent 0 at t = 2 sees it
    CHECK((y.col(0 * T + 1) - y0.col(0 * T + 1)).norm() == 0.0);  // agent 0 at t = 1 does not
    CHECK((y.middleCols(n * T, n * T) - y0.middleCols(n * T, n * T)).norm() == 0.0);  // scene 1 does not
}

TEST_CASE("madiff: the whole training loss (U-Net, attention, embeddings, inverse dynamics) matches central differences") {
    MadiffModel m(tiny_config(3), 5);
    Rng rng(6);
    MadiffBatch mb = random_batch(m.config, 3, rng);
    NoiseSchedule schedule(m.config.diffusion_steps);
    MadiffWorkspace ws;
    m.set_training(true);
    auto loss = [&]() {
        Rng lrng(21);  // the same steps, noise and dropout every call
        return madiff_loss(m, schedule, mb, lrng, false, ws).total;
    };
    {
        Rng lrng(21);
        m.params->zero_grad();
        madiff_loss(m, schedule, mb, lrng, true, ws);
    }
    REQUIRE(std::count(ws.keep.begin(), ws.keep.end(), 1.0f) >= 1);  // the return embedding gets gradient
    const Vec analytic = m.params->grad;
    FdSummary s = check_params(*m.params, analytic, loss, rng, 4, 1e-3f);
    // BatchNorm over a small batch and ReLU / max-pool kinks make single probes noisy: nearly
    // every tensor within 5%, none beyond 30% (a wrong backward is off by O(1) on many).
    CHECK(s.tensors > 60);
    CHECK(s.close >= 0.9 * s.tensors);
    CHECK(s.worst < 0.3);
}

TEST_CASE("madiff: step reward and window returns on a hand-built episode") {
    Demonstration d;
    d.map_name = "empty";
    d.agents = 2;
    d.steps = 2;
    d.goals = {{1, 0}, {-1, 0}};
    // Agent 0 moves 0.1 toward its goal each step; agent 1 stays, 0.15 from agent 0 at frame 2.
    d.pos = {{0, 0}, {-0.15, 0.5}, {0.1, 0}, {-0.15, 0.5}, {0.2, 0}, {0.2, 0.15}};
    d.vel.assign(6, Vec2{0, 0});
    d.act.assign(4, Vec2{0, 0});
    CHECK(madiff_step_reward(d, 0) == doctest::Approx(0.05));
    // Step 1: agent 0 progresses 0.1 and touches agent 1 (0.15 < 0.2): 0.1 - 0.1; agent 1
    // moves from (-0.15, 0.5) to (0.2, 0.15), away from (-1, 0), and touches agent 0.
    const double d1 = norm(Vec2{-0.15, 0.5} - Vec2{-1, 0}) - norm(Vec2{0.2, 0.15} - Vec2{-1, 0});
    CHECK(madiff_step_reward(d, 1) == doctest::Approx((0.0 + d1 - 0.1) / 2));
    DemoSet set;
    set.episodes = {d};
    MadiffData data = madiff_data(set, "empty", 2, 2);
    REQUIRE(data.windows.size() == 2);
    CHECK(data.window_return[0] == doctest::Approx(madiff_step_reward(d, 0)));
    CHECK(data.obs[0].cols() == 6);
    // Nothing to learn from: a clear error naming the map and team size.
    CHECK_THROWS_WITH_AS(madiff_data(set, "barrier", 2, 2), doctest::Contains("'barrier' with 2 agents"), std::invalid_argument);
    CHECK_THROWS_AS(madiff_data(set, "empty", 3, 2), std::invalid_argument);
    CHECK_THROWS_AS(madiff_data(set, "empty", 2, 8), std::invalid_argument);  // 3 frames < H
}

TEST_CASE("madiff: training is deterministic, resumable, and lowers the loss") {
    const std::string out = temp_path("train.safetensors"), out2 = temp_path("train2.safetensors");
    MadiffModel a(tiny_config()), b(tiny_config()), c(tiny_config());
    const MadiffReport ra = train_madiff(tiny_demos(), tiny_config(), tiny_train(out, 60), &a);
    CHECK(ra.steps == 60);
    CHECK(ra.episodes == 8);
    REQUIRE(ra.curve.rows.size() == 6);
    const int loss = ra.curve.column("loss");
    CHECK(ra.curve.rows.back()[loss] < ra.curve.rows.front()[loss]);
    // The data set the normalisation and the return range.
    CHECK(a.config.return_max > a.config.return_min);
    CHECK(a.config.return_target >= 0.0f);
    CHECK(a.config.return_target <= 1.0f);
    // Same seed, same result.
    train_madiff(tiny_demos(), tiny_config(), tiny_train(out2, 60), &b);
    CHECK(a.params->value == b.params->value);
    // Stopped at step 30 and resumed: identical to the straight run.
    MadiffTrainConfig tc = tiny_train(out2, 60);
    tc.keep_going = [](long step) { return step < 30; };
    CHECK(train_madiff(tiny_demos(), tiny_config(), tc, &c).steps == 30);
    tc.keep_going = nullptr;
    tc.resume = true;
    CHECK(train_madiff(tiny_demos(), tiny_config(), tc, &c).steps == 60);
    CHECK(a.params->value == c.params->value);
    // The files: the model, its state and the loss curve.
    MadiffModel loaded = load_madiff(out);
    CHECK(loaded.params->value == a.params->value);
    std::FILE* f = std::fopen((out + ".csv").c_str(), "r");
    REQUIRE(f != nullptr);
    char header[64] = {0};
    CHECK(std::fgets(header, sizeof header, f) != nullptr);
    std::fclose(f);
    CHECK(std::string(header) == "step,seconds,loss,diffusion,inverse\n");
    // Bad input: an unknown map, a team size the data lacks, a resume without state.
    MadiffConfig bad = tiny_config();
    bad.map = "nowhere";
    CHECK_THROWS_AS(train_madiff(tiny_demos(), bad, tiny_train("", 1)), std::invalid_argument);
    CHECK_THROWS_AS(train_madiff(tiny_demos(), tiny_config(3), tiny_train("", 1)), std::invalid_argument);
    MadiffTrainConfig no_state = tiny_train(temp_path("none.safetensors"), 10);
    no_state.resume = true;
    CHECK_THROWS_AS(train_madiff(tiny_demos(), tiny_config(), no_state), std::runtime_error);
    remove_outputs(out);
    remove_outputs(out2);
}

TEST_CASE("madiff: checkpoint round trip; truncated and foreign files are clear errors") {
    const std::string path = temp_path("model.safetensors");
    MadiffConfig cfg = tiny_config();
    cfg.return_target = 0.7f;
    cfg.route_goal = 1.5;  // the observed goal: the route goal 1.5 ahead (MappoObservation)
    MadiffModel m(cfg, 3);
    Rng rng(4);
    Vec lo(kMappoObs), hi(kMappoObs);
    for (int r = 0; r < kMappoObs; ++r) lo[r] = (float)rng.uniform(-2, -1), hi[r] = (float)rng.uniform(1, 2);
    m.set_limits(lo, hi);
    save_madiff(path, m, {{"demonstrator", "expert"}});
    MadiffModel back = load_madiff(path);
    CHECK(back.config.to_metadata() == m.config.to_metadata());
    CHECK(back.config.route_goal == 1.5);
    CHECK(back.params->value == m.params->value);
    CHECK(!back.training());
    // Same seed and world: the same actions from the original and the loaded model.
    World w = make_random_world("empty", 2, 5);
    MadiffPolicy p1(m.clone(), 9), p2(std::move(back), 9);
    const auto u1 = p1.act(w), u2 = p2.act(w);
    CHECK(u1[0].x == u2[0].x);
    CHECK(u1[1].y == u2[1].y);
    // Truncated.
    std::vector<uint8_t> bytes = read_file(path);
    write_file_atomic(path + ".cut", std::vector<uint8_t>(bytes.begin(), bytes.begin() + bytes.size() / 2));
    CHECK_THROWS_AS(load_madiff(path + ".cut"), std::runtime_error);
    // Foreign: a MAPPO policy, and a file whose metadata declares another architecture.
    MappoNetConfig mc;
    save_mappo(path + ".mappo", MappoNet(mc));
    CHECK_THROWS_WITH_AS(load_madiff(path + ".mappo"), doctest::Contains("not a MADiff model"), std::runtime_error);
    auto md = m.config.to_metadata();
    md["madiff.channels"] = "8,8";
    save_params(path + ".other", *m.params, md);
    CHECK_THROWS_WITH_AS(load_madiff(path + ".other"), doctest::Contains("shape"), std::runtime_error);
    md = m.config.to_metadata();
    md["madiff.agents"] = "many";
    save_params(path + ".other", *m.params, md);
    CHECK_THROWS_WITH_AS(load_madiff(path + ".other"), doctest::Contains("madiff.agents"), std::runtime_error);
    md = m.config.to_metadata();
    md["madiff.obs"] = "pos2,vel2,pos-goal2,lidar24@1(range-distance)";  // MAPPO may have another lidar; MADiff may not
    save_params(path + ".other", *m.params, md);
    CHECK_THROWS_WITH_AS(load_madiff(path + ".other"), doctest::Contains("default lidar"), std::runtime_error);
    md["madiff.obs"] = "pos2,vel2,pos-goal2";
    save_params(path + ".other", *m.params, md);
    CHECK_THROWS_WITH_AS(load_madiff(path + ".other"), doctest::Contains("observation layout"), std::runtime_error);
    CHECK_THROWS_AS(load_madiff(path + ".missing"), std::runtime_error);
    for (const char* ext : {"", ".cut", ".mappo", ".other"}) std::remove((path + ext).c_str());
}

TEST_CASE("madiff: the policy gives finite, in-range, seeded actions and refuses another team size") {
    MadiffModel m(tiny_config(), 8);
    MadiffPolicy policy(m.clone(), 1);
    World w = make_random_world("empty", 2, 3);
    for (int step = 0; step < 5; ++step) {
        const std::vector<Vec2> u = policy.act(w);
        REQUIRE(u.size() == 2);
        for (Vec2 f : u) {
            CHECK(std::isfinite(f.x));
            CHECK(std::isfinite(f.y));
            CHECK(std::fabs(f.x) <= 1.0);
            CHECK(std::fabs(f.y) <= 1.0);
        }
        CHECK(policy.last_window().cols() == 2 * m.config.horizon);
        w.step(u);
    }
    CHECK(policy.decision_ms() > 0);
    // Seeded: a fresh policy with the same seed repeats the first action; another seed differs.
    World w0 = make_random_world("empty", 2, 3);
    MadiffPolicy again(m.clone(), 1), other(m.clone(), 2), first(m.clone(), 1);
    const auto ua = again.act(w0), ub = first.act(w0), uc = other.act(w0);
    CHECK(ua[0].x == ub[0].x);
    CHECK(ua[1].y == ub[1].y);
    CHECK((ua[0].x != uc[0].x || ua[0].y != uc[0].y || ua[1].x != uc[1].x));
    // Another team size.
    World w3 = make_random_world("empty", 3, 3);
    CHECK_THROWS_WITH_AS(policy.act(w3), doctest::Contains("trained for 2 agents"), std::invalid_argument);
    policy.sample_steps = 0;
    CHECK_THROWS_AS(policy.act(w), std::invalid_argument);
}
