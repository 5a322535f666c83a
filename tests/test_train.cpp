// Demonstrations, datasets, losses and training (SPEC 7, 11, 12).
#include <doctest/doctest.h>

#include <cstdio>
#include <fstream>

#include "madbp_train.hpp"
#include "tiny_model.hpp"

using namespace madbp;

namespace {

// A small expert dataset: empty and barrier maps, 1-2 agents, a few episodes each.
const DemoSet& tiny_demos() {
    static DemoSet set = [] {
        CollectConfig c;
        c.maps = {"empty", "barrier"};
        c.n_train_max = 2;
        c.episodes = 6;
        return collect_demonstrations(c, expert_demonstrator(), "expert");
    }();
    return set;
}

TrainConfig tiny_train(const std::string& out) {
    TrainConfig t;
    t.n_train_max = 2;
    t.steps = 30;
    t.batch = 8;
    t.ema_start = 10;
    t.checkpoint_every = 10;
    t.log_every = 10;
    t.val_batches = 2;
    t.out = out;
    t.seed = 3;
    return t;
}

void remove_run(const std::string& out) {
    for (const char* ext : {"", ".train", ".csv", ".svg"}) std::remove((out + ext).c_str());
}

}  // namespace

TEST_CASE("demonstrations: recorded consistently; dataset file round trip") {
    const DemoSet& set = tiny_demos();
    REQUIRE(set.episodes.size() >= 20);  // the expert solves nearly all of 24
    for (const Demonstration& d : set.episodes) {
        CHECK(d.success);
        CHECK(d.pos.size() == (size_t)(d.steps + 1) * d.agents);
        CHECK(d.act.size() == (size_t)d.steps * d.agents);
        for (int i = 0; i < d.agents; ++i) CHECK(norm(d.position(d.steps, i) - d.goals[i]) < 0.1);
        CHECK(d.position(d.steps + 50, 0) == d.position(d.steps, 0));
    }
    const std::string path = "build/test-demos.bin";
    save_demos(path, set);
    DemoSet back = load_demos(path);
    REQUIRE(back.episodes.size() == set.episodes.size());
    CHECK(back.demonstrator == "expert");
    const Demonstration &a = set.episodes[3], &b = back.episodes[3];
    CHECK(a.map_name == b.map_name);
    CHECK(a.map.boxes.size() == b.map.boxes.size());
    CHECK(b.pos[5].x == (double)(float)a.pos[5].x);
    CHECK(b.act.back().y == (double)(float)a.act.back().y);
    std::remove(path.c_str());
}

TEST_CASE("dataset file: foreign, truncated and corrupt files are clear errors") {
    const std::string path = "build/test-demos-bad.bin";
    save_demos(path, tiny_demos());
    std::vector<uint8_t> bytes = read_file(path);
    auto write = [&](const std::vector<uint8_t>& b) { std::ofstream(path, std::ios::binary).write((const char*)b.data(), b.size()); };
    auto truncated = bytes;
    truncated.resize(bytes.size() / 2);
    write(truncated);
    CHECK_THROWS_WITH_AS(load_demos(path), doctest::Contains("truncated"), std::runtime_error);
    auto foreign = bytes;
    foreign[0] = 'X';
    write(foreign);
    CHECK_THROWS_WITH_AS(load_demos(path), doctest::Contains("magic"), std::runtime_error);
    auto trailing = bytes;
    trailing.push_back(0);
    write(trailing);
    CHECK_THROWS_WITH_AS(load_demos(path), doctest::Contains("trailing"), std::runtime_error);
    auto nan = bytes;
    const float bad = std::nanf("");
    std::memcpy(nan.data() + nan.size() - 4, &bad, 4);  // the last action component
    write(nan);
    CHECK_THROWS_WITH_AS(load_demos(path), doctest::Contains("not finite"), std::runtime_error);
    CHECK_THROWS_AS(load_demos("build/no-such-file.bin"), std::runtime_error);
    std::remove(path.c_str());
}

TEST_CASE("collision loss: two overlapping agents and an agent in a wall") {
    // Two agents 0.1 apart (world units) for all H steps, in one scene; scale 1.
    const int H = 4, n = 2, B = 1;
    Mat x(2, H * n), grad = Mat::Zero(2, H * n);
    for (int t = 0; t < H; ++t) {
        x.col(t) << 0.0f, 0.0f;
        x.col(H + t) << 0.1f, 0.0f;
    }
    std::vector<float> mask = {1, 1}, weight = {1};
    std::vector<WorldMap> maps(1);
    const Mat origin = Mat::Zero(2, n);
    const double L = collision_loss(x, origin, mask, B, n, H, maps, 1.0f, 0.1f, weight.data(), 1.0f, grad);
    // Per step both orders of the pair: 2 * (0.2 - 0.1).
    CHECK(L == doctest::Approx(H * 0.2).epsilon(1e-5));
    for (int t = 0; t < H; ++t) {
        CHECK(grad(0, t) == doctest::Approx(2.0));       // moving agent 0 left lowers the loss
        CHECK(grad(0, H + t) == doctest::Approx(-2.0));  // agent 1 right
        CHECK(grad(1, t) == doctest::Approx(0.0));
    }
    // A masked agent costs nothing.
    grad.setZero();
    mask[1] = 0;
    CHECK(collision_loss(x, origin, mask, B, n, H, maps, 1.0f, 0.1f, weight.data(), 1.0f, grad) == 0.0);
    // An agent 0.04 from the wall at x = 1.2 (scale 1.2: normalised 1.16 / 1.2).
    mask = {1, 0};
    for (int t = 0; t < H; ++t) x.col(t) << 1.16f / 1.2f, 0.0f;
    grad.setZero();
    const double Lw = collision_loss(x, origin, mask, B, n, H, maps, 1.2f, 0.1f, weight.data(), 1.0f, grad);
    CHECK(Lw == doctest::Approx(H * 0.06).epsilon(1e-4));
    CHECK(grad(0, 0) > 0);  // moving right (into the wall) raises the loss
}

TEST_CASE("boundary and temporal losses: hand-built values and finite differences") {
    const int H = 6, n = 1;
    Mat x(2, H), start(2, 1), goal(2, 1);
    for (int t = 0; t < H; ++t) x.col(t) << 0.1f * t, 0.0f;  // constant velocity
    start << 0.0f, 0.0f;
    goal << 0.5f, 0.3f;
    std::vector<float> mask = {1}, weight = {1};
    Mat grad = Mat::Zero(2, H);
    // |x[0] - start| = 0, |x[5] - goal| = 0.3.
    CHECK(boundary_loss(x, start, goal, mask, H, n, weight.data(), 1.0f, grad) == doctest::Approx(0.3).epsilon(1e-3));
    grad.setZero();
    CHECK(temporal_loss(x, mask, H, n, 1.0f, weight.data(), 1.0f, grad) < 1e-3);  // no acceleration, no jerk
    // A zig-zag: accelerations of size 0.2 and 0.4-size jerks.
    for (int t = 0; t < H; ++t) x.col(t) << 0.0f, (t % 2) ? 0.1f : 0.0f;
    grad.setZero();
    // |a_t| = 0.2 for every t; |j_t| = 0.4.
    CHECK(temporal_loss(x, mask, H, n, 1.0f, weight.data(), 1.0f, grad) == doctest::Approx(0.2 + 0.4).epsilon(1e-3));
    // Gradients of both against central differences at a random trajectory.
    Rng rng(4);
    for (int t = 0; t < H; ++t) x.col(t) << (float)rng.uniform(-1, 1), (float)rng.uniform(-1, 1);
    for (int which = 0; which < 2; ++which) {
        auto eval = [&](Mat& g) {
            return which ? temporal_loss(x, mask, H, n, 0.7f, weight.data(), 1.0f, g)
                         : boundary_loss(x, start, goal, mask, H, n, weight.data(), 1.0f, g);
        };
        Mat g = Mat::Zero(2, H), scratch = Mat::Zero(2, H);
        eval(g);
        for (int j = 0; j < 2 * H; ++j) {
            const float keep = x.data()[j], h = 1e-3f;
            x.data()[j] = keep + h;
            const double up = eval(scratch);
            x.data()[j] = keep - h;
            const double down = eval(scratch);
            x.data()[j] = keep;
            CHECK(g.data()[j] == doctest::Approx((up - down) / (2 * h)).epsilon(2e-2).scale(1e-2));
        }
    }
}

TEST_CASE("training: a tiny model overfits one batch") {
    const ModelConfig mc = tiny_config();
    MadbpModel model(mc, 1);
    model.set_training(true);
    TrainConfig tc = tiny_train("");
    const DemoSet& demos = tiny_demos();
    std::vector<int> eps(demos.episodes.size());
    std::iota(eps.begin(), eps.end(), 0);
    auto windows = make_windows(demos, eps, mc, 1);
    Rng rng(2);
    TrainBatch tb;
    make_train_batch(demos, windows, mc, tc, 2, rng, tb);
    NoiseSchedule sched(mc.diffusion_steps);
    LossWorkspace ws;
    Adam adam;
    adam.lr = 3e-3f;
    // The same batch, noise and steps every time: the loss must collapse.
    auto loss_once = [&](bool update) {
        Rng fixed(9);
        model.params->zero_grad();
        LossTerms l = diffusion_loss(model, sched, tb, tc, fixed, update, ws);
        if (update) {
            clip_grad_norm(*model.params, 1.0f);
            adam.update(*model.params);
        }
        return l.total;
    };
    const double first = loss_once(false);
    for (int s = 0; s < 150; ++s) loss_once(true);
    const double last = loss_once(false);
    MESSAGE("overfit: loss " << first << " -> " << last);
    CHECK(last < 0.25 * first);
}

TEST_CASE("training: lowers the validation loss and is bit-identical for a seed") {
    const std::string a = "build/test-train-a.safetensors", b = "build/test-train-b.safetensors";
    const DemoSet& demos = tiny_demos();
    MadbpModel m1(tiny_config(), 1), m2(tiny_config(), 1);
    TrainConfig t1 = tiny_train(a), t2 = tiny_train(b);
    t1.steps = t2.steps = 200;
    t1.lr = t2.lr = 2e-3f;
    t1.log_every = t2.log_every = 20;
    TrainReport r1 = train(demos, m1, t1);
    TrainReport r2 = train(demos, m2, t2);
    CHECK(m1.params->value == m2.params->value);
    CHECK(r1.last_val.total == r2.last_val.total);
    // The CSV's first validation loss (step 20) against the last (step 200).
    std::ifstream csv(a + ".csv");
    std::string header, first, line, last;
    std::getline(csv, header);
    std::getline(csv, first);
    while (std::getline(csv, line)) last = line;
    auto val = [](const std::string& row) { return std::stod(row.substr(row.rfind(',') + 1)); };
    MESSAGE("validation loss " << val(first) << " -> " << val(last));
    CHECK(val(last) < 0.8 * val(first));
    // The written model loads and is the trained (EMA) one.
    MadbpModel back = load_model(a);
    CHECK(back.params->value == m1.params->value);
    remove_run(a);
    remove_run(b);
}

TEST_CASE("training: killed after a checkpoint, resumed, ends where an uninterrupted run ends") {
    const std::string a = "build/test-resume-a.safetensors", b = "build/test-resume-b.safetensors";
    const DemoSet& demos = tiny_demos();
    MadbpModel straight(tiny_config(), 1);
    train(demos, straight, tiny_train(a));
    // The same run, "killed" at step 17 (last checkpoint at 10), then resumed.
    MadbpModel killed(tiny_config(), 1);
    TrainConfig tk = tiny_train(b);
    tk.keep_going = [](long step) { return step < 17; };
    train(demos, killed, tk);
    MadbpModel resumed(tiny_config(), 99);  // other initial weights: all must come from the file
    TrainConfig tr = tiny_train(b);
    tr.resume = true;
    TrainReport rep = train(demos, resumed, tr);
    CHECK(rep.steps == 30);
    CHECK(resumed.params->value == straight.params->value);
    CHECK(resumed.params->state == straight.params->state);  // BatchNorm running statistics too
    // The loss curve continues seamlessly: the same file as the uninterrupted run's.
    auto text = [](const std::string& path) { std::ifstream f(path); return std::string(std::istreambuf_iterator<char>(f), {}); };
    CHECK(text(b + ".csv") == text(a + ".csv"));
    CHECK(rep.curve.rows.size() == 3);
    // A resume by another run is refused, naming what differs: seed, learning rate, loss
    // weights, curriculum, data.
    auto refused = [&](TrainConfig t, const DemoSet& data, const char* field) {
        MadbpModel m(tiny_config(), 1);
        CHECK_THROWS_WITH_AS(train(data, m, t), doctest::Contains(field), std::runtime_error);
    };
    TrainConfig other = tr;
    other.seed = 4;
    refused(other, demos, "train.seed");
    other = tr;
    other.lr = 1e-3f;
    refused(other, demos, "train.lr");
    other = tr;
    other.loss_weights[3] = 0.5f;
    refused(other, demos, "train.loss_weights");
    other = tr;
    other.curriculum_end = 0.9f;
    refused(other, demos, "train.curriculum_end");
    other = tr;
    other.n_train_max = 1;
    refused(other, demos, "train.n_train_max");
    DemoSet fewer = demos;
    fewer.episodes.pop_back();
    refused(tr, fewer, "train.data");
    // A state file of another configuration is refused.
    ModelConfig other_config = tiny_config();
    other_config.dim = 16;
    MadbpModel wrong(other_config, 1);
    CHECK_THROWS_AS(train(demos, wrong, tr), std::runtime_error);
    remove_run(a);
    remove_run(b);
}

TEST_CASE("curriculum: n_curr rises from 1 to n_train_max") {
    TrainConfig t;
    t.steps = 1000;
    t.n_train_max = 4;
    t.curriculum_end = 0.5f;
    CHECK(curriculum_agents(0, t) == 1);
    CHECK(curriculum_agents(130, t) == 2);
    CHECK(curriculum_agents(499, t) == 4);
    CHECK(curriculum_agents(900, t) == 4);
    for (long s = 1; s < 1000; ++s) CHECK(curriculum_agents(s, t) >= curriculum_agents(s - 1, t));
}

TEST_CASE("training: two data-parallel replicas are deterministic and resume exactly") {
    const std::string a = "build/test-par-a.safetensors", b = "build/test-par-b.safetensors";
    const DemoSet& demos = tiny_demos();
    MadbpModel straight(tiny_config(), 1), again(tiny_config(), 1);
    TrainConfig ta = tiny_train(a);
    ta.threads = 2;
    train(demos, straight, ta);
    TrainConfig tb = tiny_train(b);
    tb.threads = 2;
    tb.keep_going = [](long step) { return step < 13; };
    train(demos, again, tb);
    tb.keep_going = nullptr;
    tb.resume = true;
    MadbpModel resumed(tiny_config(), 5);
    train(demos, resumed, tb);
    CHECK(resumed.params->value == straight.params->value);
    // A different split of the same batch is a (slightly) different run.
    MadbpModel single(tiny_config(), 1);
    train(demos, single, tiny_train(a));
    CHECK(single.params->value != straight.params->value);
    remove_run(a);
    remove_run(b);
}

TEST_CASE("train: training and planning encode the same state identically (one encoder)") {
  for (SceneFrame frame : {SceneFrame::World, SceneFrame::Local}) {
    CAPTURE((int)frame);
    // One scene: three robots on the barrier map, planned once with a small random model; in
    // the Local frame with route subgoals (the barrier is in the way of most goals).
    ModelConfig c = tiny_config();
    c.frame = frame;
    c.subgoal_distance = frame == SceneFrame::Local ? 0.8f : 0.0f;
    World world = make_random_world("barrier", 3, 5);
    DiffusionPlanner planner(MadbpModel(c, 1));
    planner.plan(world);
    const SceneBatch& planned = planner.last_scene_batch();
    // The same state as a one-frame-per-step demonstration that stays put for a window.
    Demonstration d;
    d.map = world.map();
    d.agents = world.size();
    d.steps = c.horizon + 1;
    for (const Agent& a : world.agents()) d.goals.push_back(a.goal);
    for (int t = 0; t <= d.steps; ++t)
        for (const Agent& a : world.agents()) d.pos.push_back(a.pos);
    DemoSet demos;
    demos.episodes.push_back(d);
    TrainConfig tc = tiny_train("unused");
    tc.batch = 1;
    tc.augment = false;  // no mirroring: the same world
    Rng rng(2);
    TrainBatch tb;
    make_train_batch(demos, {{0, 0}}, c, tc, 3, rng, tb);
    const SceneBatch& trained = tb.scene;
    REQUIRE(trained.n == planned.n);
    CHECK(trained.origin == planned.origin);
    CHECK(trained.grid == planned.grid);
    const long Gl2 = (long)c.local_grid * c.local_grid;
    const float reach = default_goal_reach(c);
    int matched = 0;
    for (int a = 0; a < trained.n; ++a)      // training shuffles the agents: match them by pose
        for (int b = 0; b < planned.n; ++b) {
            if (trained.pose.col(a) != planned.pose.col(b)) continue;
            ++matched;
            CHECK(trained.agent_mask[a] == planned.agent_mask[b]);
            CHECK(trained.goal_final[a] == planned.goal_final[b]);
            CHECK(trained.local.middleCols(a * Gl2, Gl2) == planned.local.middleCols(b * Gl2, Gl2));
            const bool pinned = tb.pinned[(size_t)a * c.horizon + c.horizon - 1] != 0;
            CHECK(pinned == end_pinned(planned, b, c, reach));
        }
    CHECK(matched == 3);
    // Training draws PE_agent slots at random (distinct); planning numbers them in order.
    CHECK(trained.slot[0] != trained.slot[1]);
    if (frame == SceneFrame::Local) CHECK(std::count(trained.goal_final.begin(), trained.goal_final.end(), 0.0f) > 0);  // subgoals were used
  }
}
