// DAgger (issue 12): expert labels of visited states, their training windows, rollouts, and
// resumable rounds.
#include <doctest/doctest.h>

#include <cstdio>
#include <fstream>

#include "madbp_train.hpp"
#include "tiny_model.hpp"

using namespace madbp;

namespace {

// The MA-DBP planner of one rollout episode, on a copy of `model`.
PolicyFactory tiny_learner(const MadbpModel& model) {
    auto shared = std::make_shared<const MadbpModel>(model.clone());
    return [shared](const World&, uint64_t seed) -> std::unique_ptr<Policy> {
        auto planner = std::make_shared<DiffusionPlanner>(shared->clone(), seed);
        return std::make_unique<PlanFollower>([planner](const World& w) { return planner->plan(w); }, FollowerConfig{});
    };
}

std::string file_text(const std::string& path) {
    std::ifstream f(path, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
}

// The log without its last column (seconds).
std::string log_rows(const std::string& path) {
    std::string out, line;
    std::stringstream ss(file_text(path));
    while (std::getline(ss, line)) out += line.substr(0, line.rfind(',')) + "\n";
    return out;
}

}  // namespace

TEST_CASE("dagger: a label is what the expert does from that exact state") {
    // From an episode's start, the label is the first steps of the expert's own demonstration.
    for (const char* map : {"empty", "barrier"})
        for (uint64_t seed : {3, 4, 5}) {
            World w = make_random_world(map, 3, seed);
            World copy = w;
            GuidedExpert expert(copy.map());
            const Demonstration full = record_demonstration(copy, expert, map);
            const Demonstration label = expert_label(w, 16, ExpertParams{}, map);
            REQUIRE(label.steps == std::min(16, full.steps));
            REQUIRE(label.agents == 3);
            for (size_t k = 0; k < label.pos.size(); ++k) {
                CHECK(label.pos[k].x == full.pos[k].x);
                CHECK(label.pos[k].y == full.pos[k].y);
                CHECK(label.vel[k].x == full.vel[k].x);
            }
            CHECK(label.success == (full.steps <= 16));
        }
    // From a mid-episode state reached by another policy, robots moving: the label starts at
    // that state, velocities included, and the velocities change what the expert does.
    World w = make_interaction_world("swap", "empty", 2, 7);
    ClfQp line;
    for (int t = 0; t < 12; ++t) w.step(line.act(w));
    const Demonstration label = expert_label(w, 16, ExpertParams{}, "empty");
    REQUIRE(label.steps == 16);
    CHECK_FALSE(label.success);
    for (int i = 0; i < 2; ++i) {
        CHECK(label.pos[i].x == w.agents()[i].pos.x);
        CHECK(label.pos[i].y == w.agents()[i].pos.y);
        CHECK(label.vel[i].x == w.agents()[i].vel.x);
        CHECK(label.goals[i].x == w.agents()[i].goal.x);
        CHECK(norm(w.agents()[i].vel) > 0.05);
    }
    World still = w;
    for (const Agent& a : w.agents()) still.set_state(a.id, a.pos, {0, 0});
    const Demonstration from_rest = expert_label(still, 16, ExpertParams{}, "empty");
    CHECK(norm(from_rest.pos[2] - label.pos[2]) > 1e-3);
    CHECK_THROWS_WITH_AS(expert_label(w, 0, ExpertParams{}, "empty"), doctest::Contains("steps"), std::invalid_argument);
}

TEST_CASE("dagger: a truncated recording gives only complete windows") {
    ModelConfig mc = tiny_config();  // H = 8, stride 1: a window needs frames t .. t + 8
    REQUIRE(label_steps(mc) == 8);
    DemoSet set;
    auto episode = [](int steps, bool success) {
        Demonstration d;
        d.agents = 1, d.steps = steps, d.success = success;
        return d;
    };
    set.episodes = {episode(8, false), episode(20, false), episode(8, true), episode(3, false)};
    auto windows = [&](int e) { return make_windows(set, {e}, mc, 1); };
    CHECK(windows(0).size() == 1);   // a label: its one window, at t = 0
    CHECK(windows(1).size() == 13);  // t = 0 .. 12
    CHECK(windows(1).back().t == 12);
    CHECK(windows(2).size() == 8);   // a successful episode: every start (robots hold their goals after)
    CHECK(windows(3).size() == 1);   // shorter than a window: its start only, as before
}

TEST_CASE("dagger: rollouts label every k-th visited state") {
    CollectConfig scenes;
    scenes.maps = {"empty", "barrier"};
    scenes.n_train_max = 2;
    scenes.episodes = 2;
    scenes.scenarios = {{"swap", 0.5}};
    scenes.seed = 11;
    const ModelConfig mc = tiny_config();
    // The expert as the learner: every rollout is its own demonstration, so the labels at its
    // states are the demonstration's own windows.
    const DaggerRollouts r = dagger_rollouts(scenes, expert_demonstrator(), mc, 5);
    const DemoSet demos = collect_demonstrations(scenes, expert_demonstrator(), "expert");
    REQUIRE(r.episodes == 8);
    CHECK(r.success() == 1.0);
    CHECK(r.collisions == 0);
    size_t expected = 0, k = 0;
    for (const Demonstration& d : demos.episodes) {
        expected += (d.steps + 4) / 5;
        for (int t = 0; t < d.steps; t += 5, ++k) {
            REQUIRE(k < r.labels.episodes.size());
            const Demonstration& l = r.labels.episodes[k];
            CHECK(l.map_name == d.map_name);
            for (int i = 0; i < d.agents; ++i) {
                CHECK(l.pos[i].x == d.position(t, i).x);
                CHECK(l.pos[i].y == d.position(t, i).y);
            }
        }
    }
    CHECK(r.labels.episodes.size() == expected);
    // label_every 0: an evaluation, no labels, the same success.
    CHECK(dagger_rollouts(scenes, expert_demonstrator(), mc, 0).labels.episodes.empty());
}

TEST_CASE("dagger: rounds are logged, and a killed run resumes to the same files") {
    CollectConfig base_cells;
    base_cells.maps = {"empty"};
    base_cells.n_train_max = 2;
    base_cells.episodes = 3;
    const DemoSet base = collect_demonstrations(base_cells, expert_demonstrator(), "expert");
    DaggerConfig c;
    c.rounds = 2;
    c.rollouts.maps = {"empty"};
    c.rollouts.n_train_max = 2;
    c.rollouts.episodes = 1;
    c.rollouts.seed = 5;
    c.label_every = 25;
    c.train.n_train_max = 2;
    c.train.steps = 6;
    c.train.batch = 4;
    c.train.curriculum_end = 0;
    c.train.ema_start = 0;
    c.train.checkpoint_every = 2;
    c.train.val_batches = 1;
    auto clean = [&](const std::string& out) {
        for (const char* f : {"", ".dagger.csv", ".round-1.labels.bin", ".round-2.labels.bin", ".round-1.safetensors", ".round-2.safetensors",
                              ".round-1.safetensors.train", ".round-2.safetensors.train", ".round-1.safetensors.csv", ".round-2.safetensors.csv"})
            std::remove((out + f).c_str());
    };
    const std::string a = "build/test-dagger-a.safetensors", b = "build/test-dagger-b.safetensors";
    clean(a);
    clean(b);
    MadbpModel straight(tiny_config(), 1);
    c.train.out = a;
    std::vector<int> logged;
    c.on_round = [&](const DaggerRound& r) { logged.push_back(r.round); };
    const std::vector<DaggerRound> rounds = dagger(base, straight, c, tiny_learner);
    c.on_round = nullptr;
    REQUIRE(rounds.size() == 3);  // two rounds, then the final model's evaluation
    CHECK(logged == std::vector<int>{1, 2, 3});
    long so_far = 0;
    for (int r = 0; r < 2; ++r) {
        CHECK(rounds[r].episodes == 2);
        CHECK(rounds[r].labels >= 2);  // at t = 0 of each episode, then every 25 steps
        CHECK(load_demos(a + ".round-" + std::to_string(r + 1) + ".labels.bin").episodes.size() == (size_t)rounds[r].labels);
        so_far += rounds[r].labels;
        CHECK(rounds[r].train_episodes > so_far);  // every label so far, and expert episodes
    }
    CHECK(rounds[2].labels == 0);
    // The final model is the last round's fine-tune.
    CHECK(load_model(a).params->value == load_model(a + ".round-2.safetensors").params->value);
    CHECK(load_model(a).params->value != MadbpModel(tiny_config(), 1).params->value);

    // The same run killed in round 2's fine-tune (its last checkpoint at step 2), then resumed.
    MadbpModel killed(tiny_config(), 1);
    c.train.out = b;
    long calls = 0;
    c.train.keep_going = [&](long) { return ++calls < 6 + 3; };
    CHECK(dagger(base, killed, c, tiny_learner).size() == 1);
    c.train.keep_going = nullptr;
    c.train.resume = true;
    MadbpModel resumed(tiny_config(), 42);  // other weights: every round's must come from the files
    CHECK(dagger(base, resumed, c, tiny_learner).size() == 3);
    CHECK(file_text(b) == file_text(a));
    CHECK(file_text(b + ".round-2.labels.bin") == file_text(a + ".round-2.labels.bin"));
    CHECK(log_rows(b + ".dagger.csv") == log_rows(a + ".dagger.csv"));
    // Resuming a finished run changes nothing.
    CHECK(dagger(base, resumed, c, tiny_learner).size() == 3);
    CHECK(file_text(b) == file_text(a));

    c.rounds = 0;
    CHECK_THROWS_WITH_AS(dagger(base, resumed, c, tiny_learner), doctest::Contains("rounds"), std::invalid_argument);
    c.rounds = 2;
    c.label_every = 0;
    CHECK_THROWS_WITH_AS(dagger(base, resumed, c, tiny_learner), doctest::Contains("label_every"), std::invalid_argument);
    c.label_every = 25;
    c.base_ratio = std::nan("");
    CHECK_THROWS_WITH_AS(dagger(base, resumed, c, tiny_learner), doctest::Contains("base_ratio"), std::invalid_argument);
    clean(a);
    clean(b);
}
