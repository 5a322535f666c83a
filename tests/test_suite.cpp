// The evaluation suite (`madbp eval --suite paper`, tool/suite.hpp): cells, store, resume,
// shards, missing models and reports, on a shrunken suite with tiny models built here.
#include <doctest/doctest.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <sstream>

#include "suite.hpp"
#include "tiny_model.hpp"

using namespace madbp_cli;

namespace {

std::string read_text(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}
void copy_file(const std::string& from, const std::string& to) {
    std::ofstream(to, std::ios::binary) << read_text(from);
}
std::string make_temp_dir() {
    char tmpl[] = "/tmp/madbp-suite-XXXXXX";
    REQUIRE(::mkdtemp(tmpl) != nullptr);
    return tmpl;
}
long count_lines(const std::string& text, const std::string& prefix) {
    long k = 0;
    std::istringstream in(text);
    for (std::string line; std::getline(in, line);) k += line.rfind(prefix, 0) == 0;
    return k;
}

// The shared tiny model, with room for the suite's teams of 8 and a shorter sampler.
madbp::ModelConfig tiny_model_config() {
    madbp::ModelConfig c = tiny_config();
    c.n_max = 8;
    c.sample_steps = 3;
    return c;
}

// A models/ directory with tiny files at every path the shrunken suite reads, except
// mappo/barrier-2 (left out to check missing models) and madiff/* (never built here).
std::string make_tiny_models(const std::string& root) {
    const std::string dir = root + "/models";
    make_dirs(dir + "/mappo");
    make_dirs(dir + "/paper");
    madbp::CollectConfig cc;
    cc.maps = {"empty"};
    cc.n_train_max = 2;
    cc.episodes = 3;
    madbp::DemoSet demos = madbp::collect_demonstrations(cc, madbp::expert_demonstrator(), "expert");
    madbp::TrainConfig tc;
    tc.n_train_max = 2;
    tc.steps = 10;
    tc.batch = 4;
    tc.val_batches = 1;
    tc.out = dir + "/madbp-default.safetensors";
    madbp::MadbpModel model(tiny_model_config(), 0);
    madbp::train(demos, model, tc);
    // One tiny model under every MA-DBP name: the suite reads each file's own window H.
    for (const char* name : {"paper/madbp-n2", "paper/ablation-CT-LE-n2", "paper/ablation-CT-AAP-n2", "paper/ablation-MW-LE-n2",
                             "paper/ablation-MW-AAP-n2", "paper/ablation-MW-AAP-n4", "paper/ablation-MW-AAP-n4-h8"})
        copy_file(tc.out, dir + "/" + name + ".safetensors");
    madbp::MappoConfig m;
    m.map = "empty";
    m.agents = 2;
    m.iterations = 1;
    m.worlds = 2;
    m.hidden = 8;
    m.out = dir + "/mappo/empty-2.safetensors";
    madbp::train_mappo(m);
    return dir;
}

// The suite shrunk to one or two cells per list, tiny budgets, one thread.
SuiteConfig tiny_suite(const std::string& models, const std::string& out) {
    SuiteConfig c;
    c.models = models;
    c.out = out;
    c.episodes = 2;
    c.threads = 1;
    c.table1_cells = {{"empty", {2}}, {"barrier", {2}}};
    c.fig4_maps = {"empty"};
    c.fig4_train = {2};
    c.fig4_counts = {1, 3};
    c.table2_train = {2};
    c.table2_counts = {3};
    c.horizon_lengths = {8, 16};
    c.horizon_counts = {2};
    c.dynamic_maps = {"empty"};
    c.dynamic_start = 2, c.dynamic_join = 1, c.dynamic_join_step = 5, c.dynamic_leave_step = 10, c.dynamic_max_steps = 30;
    c.large_maps = {"empty"};
    c.large_counts = {3};
    c.large_methods = {"madbp", "line"};
    c.large_max_steps = 30;
    c.fig3b_counts = {1, 2};
    c.fig3b_steps = 20;
    c.fig3a_counts = {2, 4};  // MAPPO k = 1, 2, 4: k = 1 shared by both pipelines, 2 and 4 trained once each
    c.fig3a_madbp_steps = 3;
    c.fig3a_collect_episodes = 2;
    c.fig3a_mappo_scale = 0.001;  // one iteration
    c.fig3a_mappo_worlds = 2;
    c.fig3a_batch = 4;
    c.fig3a_successful_only = false;  // one-iteration MAPPO rarely succeeds
    c.fig3a_model = tiny_model_config();
    c.picture_barrier_agents = 3;
    c.picture_large_agents = 3;
    return c;
}

}  // namespace

TEST_CASE("suite: options are validated with clear messages") {
    auto read = [](std::vector<std::string> v) {
        Args a(v);
        SuiteConfig c = read_suite_options(a);
        a.finish();
        return c;
    };
    SuiteConfig c = read({"--suite", "paper", "--only", "table1,fig4", "--shard", "1/3", "--episodes", "7", "--fig3a-mappo-scale", "0.5"});
    CHECK(c.only == std::vector<std::string>{"table1", "fig4"});
    CHECK(c.shard_index == 1);
    CHECK(c.shard_count == 3);
    CHECK(c.episodes == 7);
    CHECK(c.fig3a_mappo_scale == 0.5);
    CHECK_THROWS_WITH_AS(read({"--suite", "mine"}), doctest::Contains("only one is 'paper'"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(read({"--suite", "paper", "--only", "table9"}), doctest::Contains("unknown group 'table9'"), std::invalid_argument);
    for (const char* bad : {"2/2", "1", "-1/2", "0/0", "a/b", "0/2x"})
        CHECK_THROWS_WITH_AS(read({"--suite", "paper", "--shard", bad}), doctest::Contains("--shard"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(read({"--suite", "paper", "--episodes", "0"}), doctest::Contains("--episodes"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(read({"--suite", "paper", "--shards", "0/2"}), doctest::Contains("unknown option --shards"), std::invalid_argument);
}

TEST_CASE("suite: the paper's cell list; shards partition it; fig3a's stages stay in one shard") {
    SuiteConfig cfg;
    std::vector<SuiteCell> cells = suite_cells(cfg);
    std::set<std::string> ids;
    std::map<std::string, int> per_group;
    for (const SuiteCell& c : cells) {
        CHECK(ids.insert(c.id).second);  // ids are unique
        per_group[c.group]++;
    }
    CHECK(per_group["table1"] == 63);   // 9 (map, n) x 7 methods (MA-DBP tuned and the paper's planner)
    CHECK(per_group["fig4"] == 216);    // 3 maps x 3 k x 8 n x (MA-DBP tuned, the paper's planner, MAPPO)
    CHECK(per_group["table2"] == 24);
    CHECK(per_group["horizon"] == 9);
    CHECK(per_group["dynamic"] == 9);
    CHECK(per_group["large"] == 20);    // 2 maps x 2 n x (MA-DBP, the paper's planner, neighbourhoods of 4, expert, line)
    CHECK(ids.count("large/empty/n=16/madbp-k4"));
    CHECK(per_group["interaction"] == 144);  // 6 scenes x 3 maps x 2 n x (MA-DBP, the paper's planner, expert, line)
    CHECK(ids.count("interaction/corridor/barrier/n=4/madbp-paper"));
    CHECK(ids.count("fig4/empty/k=3/n=6/madbp-paper"));
    CHECK(per_group["fig3b"] == 1);
    CHECK(per_group["fig3a"] == 13);    // MAPPO 1, 2, 3, 4, 8; 2 collect; 2 train; 4 evals
    CHECK(per_group["pictures"] == 3);
    CHECK(ids.count("table1/barrier/n=3/madbp"));
    CHECK(ids.count("fig4/obstacles/k=2/n=8/mappo"));
    CHECK(ids.count("table2/CT-LE/k=4/n=7"));
    for (int N : {2, 3}) {
        std::set<int> fig3a_shards;
        for (const SuiteCell& c : cells) {
            int owners = 0;
            for (int i = 0; i < N; ++i) {
                SuiteConfig s = cfg;
                s.shard_index = i;
                s.shard_count = N;
                if (suite_selected(s, c)) {
                    owners++;
                    if (c.group == "fig3a") fig3a_shards.insert(i);
                }
            }
            CHECK(owners == 1);
        }
        CHECK(fig3a_shards.size() == 1);
    }
}

TEST_CASE("suite: the store ignores a torn last line and appends after it on a fresh line") {
    const std::string dir = make_temp_dir(), path = dir + "/cells.tsv";
    SuiteRecord r;
    r.id = "table1/empty/n=2/line";
    r.status = "ok";
    r.set("success", 0.5).set("why", "tab\there");
    append_suite_record(path, r);
    { std::ofstream(path, std::ios::app) << "table1/empty/n=4/line\tok\tsucc"; }  // killed mid-line
    SuiteStore st = load_suite_store(path);
    REQUIRE(st.size() == 1);
    CHECK(st.at(r.id).num("success") == 0.5);
    CHECK(st.at(r.id).get("why") == "tab here");
    r.set("success", 0.75);
    append_suite_record(path, r);
    st = load_suite_store(path);
    CHECK(st.size() == 1);  // the torn line stays unreadable, the new one counts
    CHECK(st.at(r.id).num("success") == 0.75);
    std::remove(path.c_str());
    ::rmdir(dir.c_str());
}

TEST_CASE("suite: a MAPPO policy trained on k agents drives a team of n with the same actor") {
    madbp::MappoNetConfig nc;
    nc.agents = 2;
    nc.hidden = 8;
    madbp::MappoNet trained(nc, 5);
    madbp::MappoPolicy team(mappo_for_team(trained, 5));
    madbp::World w = madbp::make_random_world("obstacles", 5, 3);
    const std::vector<madbp::Vec2> u = team.act(w);
    REQUIRE(u.size() == 5);
    // Each agent's action is the trained actor's mean on that agent's own observation.
    madbp::Mat obs(madbp::kMappoObs, 5), mean;
    madbp::mappo_observe_all(w, obs, 0);
    trained.actor.forward(obs, mean);
    for (int i = 0; i < 5; ++i) {
        const madbp::Vec2 want = madbp::clamp_box(madbp::Vec2{mean(0, i), mean(1, i)}, 1.0);
        CHECK(u[i].x == want.x);
        CHECK(u[i].y == want.y);
    }
    CHECK(mappo_for_team(trained, 2).params->value == trained.params->value);
}

TEST_CASE("suite: a whole shrunken suite runs, writes every report, resumes, retries missing models, and shards") {
    const std::string root = make_temp_dir();
    const std::string models = make_tiny_models(root);
    const std::string out = root + "/results";
    SuiteConfig cfg = tiny_suite(models, out);
    const size_t n_cells = suite_cells(cfg).size();

    // First run: every cell runs, except MADiff's and the MAPPO barrier cell (no files).
    SuiteSummary s1;
    CHECK(run_suite(cfg, &s1) == 0);
    CHECK(s1.errors == 0);
    CHECK(s1.missing == 3);  // madiff empty-2 and barrier-2, mappo barrier-2
    CHECK(s1.run + s1.missing == (int)n_cells);
    for (const char* f : {"cells.tsv", "index.md", "table1.md", "table1.csv", "fig4.md", "fig4.csv", "fig4.svg", "table2.md", "table2.csv",
                          "horizon.md", "horizon.csv", "horizon.svg", "dynamic.md", "dynamic.csv", "large.md", "large.csv", "fig3b.md",
                          "fig3b.csv", "fig3b.svg", "fig3a.md", "fig3a.csv", "fig3a.svg", "episode-barrier-n3.svg",
                          "episode-large-empty-n3.svg", "episode-dynamic-empty.svg", "fig3a/madbp-4.safetensors"}) {
        INFO(f);
        CHECK(read_text(out + "/" + f).size() > 0);
    }
    const std::string table1 = read_text(out + "/table1.md");
    CHECK(count_lines(table1, "| empty | 2 |") == 1);
    CHECK(count_lines(table1, "| barrier* | 2 |") == 1);
    CHECK(table1.find("n/a (missing " + models + "/mappo/barrier-2.safetensors)") != std::string::npos);
    CHECK(table1.find("n/a (missing " + models + "/madiff/empty-2.safetensors)") != std::string::npos);
    CHECK(table1.find(".96 ± .024") != std::string::npos);  // the paper's MAPPO, empty n = 2
    CHECK(count_lines(read_text(out + "/table2.md"), "| CT+LE | 2 |") == 1);
    CHECK(count_lines(read_text(out + "/horizon.md"), "| 8 | 2 | 8 | 2 |") == 1);  // the file's H = 8: the tuned planner replans every H/4 = 2
    CHECK(count_lines(read_text(out + "/fig3b.md"), "| 2 |") == 1);
    {  // Steps per plan with the tiny models' 8-step window: the paper's planner H/2, the tuned H/4, the line 8.
        const SuiteStore st = load_suite_store(out + "/cells.tsv");
        CHECK(st.at("table1/empty/n=2/madbp-paper").get("replan") == "4");
        CHECK(st.at("table1/empty/n=2/madbp").get("replan") == "2");
        CHECK(st.at("table1/empty/n=2/line").get("replan") == "8");
    }
    const std::string fig3a = read_text(out + "/fig3a.md");
    CHECK(count_lines(fig3a, "| 4 |") == 1);
    CHECK(count_lines(fig3a, "| fig3a/mappo/k=") == 3);  // 1, 2, 4: each trained once
    CHECK(read_text(out + "/index.md").find("episode-dynamic-empty.svg") != std::string::npos);

    // Second run: nothing to do; the still-missing cells add no lines.
    const std::string store_before = read_text(out + "/cells.tsv");
    SuiteSummary s2;
    run_suite(cfg, &s2);
    CHECK(s2.run == 0);
    CHECK(s2.missing == 3);
    CHECK(s2.skipped == (int)n_cells - 3);
    CHECK(read_text(out + "/cells.tsv") == store_before);

    // The missing policy appears: the next run runs exactly that cell.
    copy_file(models + "/mappo/empty-2.safetensors", models + "/mappo/barrier-2.safetensors");
    SuiteSummary s3;
    run_suite(cfg, &s3);
    CHECK(s3.run == 1);
    CHECK(read_text(out + "/table1.md").find("n/a (missing " + models + "/mappo/barrier-2") == std::string::npos);

    // Two shards into a fresh store cover every cell exactly once; a full run then has nothing to do.
    cfg.out = root + "/sharded";
    cfg.only = {"table1", "fig4", "table2", "dynamic", "pictures"};  // the cheap groups keep the test short
    int total = 0;
    for (int i = 0; i < 2; ++i) {
        SuiteConfig s = cfg;
        s.shard_index = i;
        s.shard_count = 2;
        SuiteSummary sum;
        run_suite(s, &sum);
        total += sum.run + sum.missing;
    }
    const std::string store = read_text(cfg.out + "/cells.tsv");
    int selected = 0;
    for (const SuiteCell& c : suite_cells(cfg)) {
        if (!suite_selected(cfg, c)) continue;
        selected++;
        INFO(c.id);
        CHECK(count_lines(store, c.id + "\t") == 1);
    }
    CHECK(total == selected);
    SuiteSummary again;
    run_suite(cfg, &again);
    CHECK(again.run == 0);
    CHECK(again.skipped + again.missing == selected);
    std::system(("rm -rf '" + root + "'").c_str());
}
