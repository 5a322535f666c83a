// suite.hpp - `madbp eval --suite paper`: every table and figure of the paper, plus ours, from
// one resumable, shardable command (SPEC 9, 10; docs/evaluation.md). `make results`.
//
// The suite is a fixed, ordered list of cells. A cell is one measurement, usually an eval of
// one method on one (map, n), with a stable id such as "table1/barrier/n=3/madbp". Every
// finished cell appends one line to OUT/cells.tsv (the store); a later run skips the cells the
// store has as done (resume). `--shard i/N` runs the cells whose unit index satisfies
// index % N == i; a unit is one cell, except that fig3a's stages form one unit because each
// stage reads the files the previous one wrote. After running, every report (OUT/<group>.md,
// .csv, the SVG charts and OUT/index.md) is regenerated from the whole store, so shards that
// share the store see each other's cells.
//
// Store format, one line per record, fields separated by tabs:
//   <id> <status> key=value key=value ... end     status: ok | missing | error
// Later lines override earlier ones of the same id; '#' lines are comments. A line without its
// final "end" (a run killed while writing it) is ignored, even once a later append ends it.
#pragma once
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <functional>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "cli_common.hpp"
#include "madbp_train.hpp"
#include "methods.hpp"

namespace madbp_cli {

// =============================================================================================
// Configuration: every budget, list and path, so a test can shrink the suite.
// =============================================================================================

inline const std::vector<std::string>& suite_groups() {
    static const std::vector<std::string> g = {"table1", "fig4", "table2", "horizon", "dynamic", "large", "interaction", "fig3b", "fig3a", "pictures"};
    return g;
}

struct SuiteConfig {
    std::string suite = "paper";
    std::vector<std::string> only;   // groups to run (empty: all); reports always cover the whole store
    int episodes = 100;              // per cell; episode i has seed i
    int threads = 2;                 // episodes in parallel (results do not depend on it)
    std::string models = "models";   // model directory, laid out as models/ (README "Shipped models")
    std::string out = "results";     // store, reports, charts, pictures, fig3a's trained files
    int shard_index = 0, shard_count = 1;
    bool list = false;               // print the cells and their state, run nothing
    bool json = false;               // one JSON line per finished cell on stdout

    // table1 (paper Table I): methods, and the team sizes of each map.
    // "madbp" is the tuned planner, "madbp-paper" the paper's (--preset paper), both with the default model.
    std::vector<std::string> table1_methods = {"line", "clfqp", "expert", "mappo", "madiff", "madbp-paper", "madbp"};
    std::vector<std::pair<std::string, std::vector<int>>> table1_cells = {
        {"empty", {2, 4, 6}}, {"obstacles", {2, 3, 4}}, {"barrier", {2, 3, 4}}};
    // fig4 (upscaling): models trained on k agents, deployed on each n.
    std::vector<std::string> fig4_maps = {"empty", "obstacles", "barrier"};
    std::vector<int> fig4_train = {2, 3, 4};
    std::vector<int> fig4_counts = {1, 2, 3, 4, 5, 6, 7, 8};
    std::vector<std::string> fig4_planners = {"madbp", "madbp-paper"};
    // table2 (paper Table II, ablation on the empty map).
    std::vector<int> table2_train = {2, 3, 4};
    std::vector<int> table2_counts = {6, 7};
    // horizon sweep (empty map, n_train 4): window lengths H and team sizes.
    std::vector<int> horizon_lengths = {8, 16, 32};
    std::vector<int> horizon_counts = {4, 6, 8};
    // dynamic teams: `start` agents, `join` more at join_step, the lowest id leaves at leave_step.
    std::vector<std::string> dynamic_maps = {"empty", "obstacles", "barrier"};
    std::vector<std::string> dynamic_methods = {"madbp", "expert", "line"};
    int dynamic_start = 4, dynamic_join = 2, dynamic_join_step = 10, dynamic_leave_step = 20, dynamic_max_steps = 150;
    // large world (twice the side).
    std::vector<std::string> large_maps = {"empty", "obstacles"};
    std::vector<int> large_counts = {16, 32};
    std::vector<std::string> large_methods = {"madbp", "madbp-paper", "madbp-k4", "expert", "line"};
    double large_half_size = 2.4;
    int large_max_steps = 200;
    // interaction scenes (madbp_sim.hpp Section 4b) on every map with 2 and 4 robots.
    std::vector<std::string> interaction_scenarios = {"swap", "cross", "gap", "corridor", "parked", "circle"};
    std::vector<std::string> interaction_maps = {"empty", "obstacles", "barrier"};
    std::vector<int> interaction_counts = {2, 4};
    std::vector<std::string> interaction_methods = {"madbp", "madbp-paper", "expert", "line"};
    // fig3b (decision time per step).
    std::vector<long> fig3b_counts = {1, 2, 4, 8, 16};
    int fig3b_steps = 5000;
    // fig3a (training time): team sizes n (even); MA-DBP trains on n/2.
    std::vector<int> fig3a_counts = {4, 8};
    long fig3a_madbp_steps = 3000;
    int fig3a_collect_episodes = 300;
    double fig3a_mappo_scale = 1.0;   // multiplies the MAPPO iterations (tests)
    int fig3a_mappo_worlds = 32;      // MappoConfig default
    int fig3a_batch = 64;
    bool fig3a_successful_only = true;  // keep only solved demonstrations (as `madbp collect`)
    madbp::ModelConfig fig3a_model;     // the default MA-DBP
    // pictures.
    int picture_barrier_agents = 8, picture_large_agents = 16;
};

inline const char* kSuiteHelp =
    "madbp eval --suite paper - every table and figure of the paper plus ours (docs/evaluation.md)\n"
    "  --only GROUPS          comma list of table1, fig4, table2, horizon, dynamic, large, interaction, fig3b,\n"
    "                         fig3a, pictures (default all)\n"
    "  --episodes E           episodes per cell, seeds 0..E-1 (default 100)\n"
    "  --threads T            episodes in parallel; results do not depend on it (default 2)\n"
    "  --models DIR           model files (default models)\n"
    "  --out DIR              store (DIR/cells.tsv), reports and charts (default results)\n"
    "  --shard i/N            run only the cells with unit index % N == i (0-based)\n"
    "  --list                 print the cells, their ids and state; run nothing\n"
    "  --fig3a-madbp-steps N  MA-DBP training steps in fig3a (default 3000)\n"
    "  --fig3a-collect-episodes E  demonstrations per team size in fig3a (default 300)\n"
    "  --fig3a-mappo-scale F  multiplies fig3a's MAPPO iterations (default 1)\n"
    "  --json                 one JSON object per finished cell\n"
    "A run skips the cells the store has as done; a missing model file is recorded as missing\n"
    "(retried next run) and every other cell still runs.\n";

// Reads the suite's options (everything but --help); bad values throw std::invalid_argument.
inline SuiteConfig read_suite_options(Args& a) {
    SuiteConfig c;
    c.suite = a.str("--suite", "paper");
    if (c.suite != "paper") throw std::invalid_argument("--suite: unknown suite '" + c.suite + "' (the only one is 'paper')");
    std::string only = a.str("--only", "");
    if (!only.empty()) {
        c.only = split(only);
        for (auto& g : c.only)
            if (std::find(suite_groups().begin(), suite_groups().end(), g) == suite_groups().end())
                throw std::invalid_argument("--only: unknown group '" + g +
                                            "' (expected table1, fig4, table2, horizon, dynamic, large, interaction, fig3b, fig3a, pictures)");
    }
    c.episodes = (int)a.integer("--episodes", c.episodes, 1, 1000000);
    c.threads = (int)a.integer("--threads", c.threads, 1, 256);
    c.models = a.str("--models", c.models);
    c.out = a.str("--out", c.out);
    if (c.out.empty() || c.models.empty()) throw std::invalid_argument("--out/--models: must not be empty");
    std::string shard = a.str("--shard", "");
    if (!shard.empty()) {
        int i = -1, n = -1;
        char tail = 0;
        if (std::sscanf(shard.c_str(), "%d/%d%c", &i, &n, &tail) != 2 || n < 1 || i < 0 || i >= n)
            throw std::invalid_argument("--shard: expected i/N with 0 <= i < N, e.g. 0/2, got '" + shard + "'");
        c.shard_index = i;
        c.shard_count = n;
    }
    c.list = a.flag("--list");
    c.json = a.flag("--json");
    c.fig3a_madbp_steps = a.integer("--fig3a-madbp-steps", c.fig3a_madbp_steps, 1, 100000000);
    c.fig3a_collect_episodes = (int)a.integer("--fig3a-collect-episodes", c.fig3a_collect_episodes, 1, 10000000);
    c.fig3a_mappo_scale = a.real("--fig3a-mappo-scale", c.fig3a_mappo_scale, 1e-6, 1000);
    return c;
}

// =============================================================================================
// The store: one record per line, appended as each cell finishes.
// =============================================================================================

struct SuiteRecord {
    std::string id, status;  // ok | missing | error
    std::vector<std::pair<std::string, std::string>> fields;

    std::string get(const std::string& key) const {
        for (auto& kv : fields) if (kv.first == key) return kv.second;
        return "";
    }
    // The field as a number; NaN when absent or not a number.
    double num(const std::string& key) const {
        const std::string s = get(key);
        char* end = nullptr;
        const double v = std::strtod(s.c_str(), &end);
        return s.empty() || *end ? NAN : v;
    }
    SuiteRecord& set(const std::string& key, std::string value) {
        for (char& ch : value) if (ch == '\t' || ch == '\n' || ch == '\r') ch = ' ';  // keeps the line format intact
        for (auto& kv : fields) if (kv.first == key) { kv.second = value; return *this; }
        fields.push_back({key, value});
        return *this;
    }
    SuiteRecord& set(const std::string& key, const char* value) { return set(key, std::string(value)); }
    SuiteRecord& set(const std::string& key, double value) {
        char b[32];
        std::snprintf(b, sizeof b, "%.6g", value);
        return set(key, std::string(b));
    }
    SuiteRecord& set(const std::string& key, long value) { return set(key, std::to_string(value)); }
    SuiteRecord& set(const std::string& key, int value) { return set(key, std::to_string(value)); }
    bool ok() const { return status == "ok"; }
    // Why a cell has no numbers, as the tables print it.
    std::string why() const { return get("why"); }

    std::string line() const {
        std::string s = id + "\t" + status;
        for (auto& kv : fields) s += "\t" + kv.first + "=" + kv.second;
        return s + "\tend\n";
    }
    std::string json() const {
        Json j;
        j.add("id", id).add("status", status);
        for (auto& kv : fields) {
            char* end = nullptr;
            const double v = std::strtod(kv.second.c_str(), &end);
            if (!kv.second.empty() && !*end) j.add(kv.first, v);
            else j.add(kv.first, kv.second);
        }
        return j.line();
    }
};

// The latest record of every id in the store file (empty when the file does not exist).
using SuiteStore = std::map<std::string, SuiteRecord>;
inline SuiteStore load_suite_store(const std::string& path) {
    SuiteStore store;
    std::ifstream in(path, std::ios::binary);
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    size_t start = 0;
    for (size_t nl; (nl = text.find('\n', start)) != std::string::npos; start = nl + 1) {  // a torn last line has no '\n'
        const std::string line = text.substr(start, nl - start);
        if (line.empty() || line[0] == '#') continue;
        std::vector<std::string> parts;
        for (size_t pos = 0;;) {
            const size_t tab = line.find('\t', pos);
            parts.push_back(line.substr(pos, tab == std::string::npos ? std::string::npos : tab - pos));
            if (tab == std::string::npos) break;
            pos = tab + 1;
        }
        if (parts.size() < 3 || parts.back() != "end" || parts[0].empty() || parts[1].empty()) continue;  // torn
        SuiteRecord r;
        r.id = parts[0];
        r.status = parts[1];
        for (size_t k = 2; k + 1 < parts.size(); ++k) {
            const size_t eq = parts[k].find('=');
            if (eq != std::string::npos) r.fields.push_back({parts[k].substr(0, eq), parts[k].substr(eq + 1)});
        }
        store[r.id] = r;
    }
    return store;
}

// Appends one line with a single write() on an O_APPEND descriptor (shards sharing the file do
// not interleave within a line), then fsync: a killed run loses at most the cell in progress.
inline void append_suite_record(const std::string& path, const SuiteRecord& r) {
    std::string line = r.line();
    struct stat st {};
    if (::stat(path.c_str(), &st) == 0 && st.st_size > 0) {  // after a torn line, start a fresh one
        std::ifstream in(path, std::ios::binary);
        in.seekg(st.st_size - 1);
        if (in.get() != '\n') line = "\n" + line;
    }
    const int fd = ::open(path.c_str(), O_WRONLY | O_APPEND | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) throw std::runtime_error(path + ": cannot open for appending");
    const bool ok = ::write(fd, line.data(), line.size()) == (ssize_t)line.size() && ::fsync(fd) == 0;
    ::close(fd);
    if (!ok) throw std::runtime_error(path + ": append failed");
}

inline bool file_exists(const std::string& path) {
    struct stat st {};
    return ::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode);
}
inline void make_dirs(const std::string& path) {
    for (size_t slash = path.find('/', 1);; slash = path.find('/', slash + 1)) {
        const std::string part = path.substr(0, slash);
        if (::mkdir(part.c_str(), 0755) != 0 && errno != EEXIST) throw std::runtime_error(part + ": cannot create directory");
        if (slash == std::string::npos) break;
    }
}
inline void write_report(const std::string& path, const std::string& text) {
    madbp::write_file_atomic(path, std::vector<uint8_t>(text.begin(), text.end()));
}

// =============================================================================================
// Model files (paths relative to --models) and the paper's published numbers.
// =============================================================================================

struct SuiteModels {
    std::string dir;
    std::string madbp_default() const { return dir + "/madbp-default.safetensors"; }
    std::string mappo(const std::string& map, int n) const { return dir + "/mappo/" + map + "-" + std::to_string(n) + ".safetensors"; }
    std::string madiff(const std::string& map, int n) const { return dir + "/madiff/" + map + "-" + std::to_string(n) + ".safetensors"; }
    // MA-DBP trained on n_train_max = k on all maps; k = 4 is the shipped default model.
    std::string madbp_trained_on(int k) const {
        return k == 4 ? madbp_default() : dir + "/paper/madbp-n" + std::to_string(k) + ".safetensors";
    }
    // Table II variants on the empty map: window CT|MW, processor LE|AAP.
    std::string ablation(const std::string& window, const std::string& processor, int k) const {
        return dir + "/paper/ablation-" + window + "-" + processor + "-n" + std::to_string(k) + ".safetensors";
    }
    // The horizon sweep: MW + AAP, n_train 4; H = 16 is the ablation's MA-DBP model.
    std::string horizon(int H) const {
        return H == 16 ? ablation("MW", "AAP", 4) : dir + "/paper/ablation-MW-AAP-n4-h" + std::to_string(H) + ".safetensors";
    }
};

// The paper's Table I (mean ± standard error over its 20 episodes).
struct PaperTable1 { const char* method; const char* map; int n; double success, se; };
inline const std::vector<PaperTable1>& paper_table1() {
    static const std::vector<PaperTable1> t = {
        {"mappo", "empty", 2, .96, .024}, {"mappo", "empty", 4, .94, .033}, {"mappo", "empty", 6, .94, .021},
        {"mappo", "obstacles", 2, .94, .021}, {"mappo", "obstacles", 3, .95, .037}, {"mappo", "obstacles", 4, .94, .014},
        {"mappo", "barrier", 2, .92, .035}, {"mappo", "barrier", 3, .88, .021}, {"mappo", "barrier", 4, .84, .034},
        {"clfqp", "empty", 2, .97, .020}, {"clfqp", "empty", 4, .96, .021}, {"clfqp", "empty", 6, .94, .036},
        {"clfqp", "obstacles", 2, .80, .01}, {"clfqp", "obstacles", 3, .68, .02}, {"clfqp", "obstacles", 4, .65, .02},
        {"clfqp", "barrier", 2, .78, .021}, {"clfqp", "barrier", 3, .65, .016}, {"clfqp", "barrier", 4, .67, .014},
        {"madiff", "empty", 2, .55, .081}, {"madiff", "empty", 4, .47, .011}, {"madiff", "empty", 6, .42, .031},
        {"madiff", "obstacles", 2, .12, .021}, {"madiff", "obstacles", 3, .15, .018}, {"madiff", "obstacles", 4, .18, .010},
        {"madiff", "barrier", 2, .37, .026}, {"madiff", "barrier", 3, .32, .034}, {"madiff", "barrier", 4, .30, .041},
        {"madbp", "empty", 2, .94, .027}, {"madbp", "empty", 4, .96, .034}, {"madbp", "empty", 6, .95, .021},
        {"madbp", "obstacles", 2, .72, .100}, {"madbp", "obstacles", 3, .70, .080}, {"madbp", "obstacles", 4, .78, .065},
        {"madbp", "barrier", 2, .81, .048}, {"madbp", "barrier", 3, .73, .096}, {"madbp", "barrier", 4, .65, .047}};
    return t;
}
// The paper's Table II: success on the empty map at n = 6 and 7 of models trained on k agents.
// Its MA-DBP (MW + AAP) row is also the paper's upscaling on the empty map (Fig. 4's values
// are not in the paper's text).
struct PaperTable2 { const char* variant; int k; double n6, n7; };
inline const std::vector<PaperTable2>& paper_table2() {
    static const std::vector<PaperTable2> t = {
        {"CT-LE", 2, .18, .10}, {"CT-LE", 3, .28, .22}, {"CT-LE", 4, .34, .31},
        {"CT-AAP", 2, .32, .34}, {"CT-AAP", 3, .68, .59}, {"CT-AAP", 4, .71, .69},
        {"MW-LE", 2, .46, .42}, {"MW-LE", 3, .65, .61}, {"MW-LE", 4, .72, .67},
        {"MW-AAP", 2, .60, .58}, {"MW-AAP", 3, .83, .82}, {"MW-AAP", 4, .95, .87}};
    return t;
}
inline double paper_table2_value(const std::string& variant, int k, int n) {
    for (auto& p : paper_table2())
        if (variant == p.variant && k == p.k && (n == 6 || n == 7)) return n == 6 ? p.n6 : p.n7;
    return NAN;
}
inline const char* variant_title(const std::string& v) {
    return v == "CT-LE" ? "CT+LE" : v == "CT-AAP" ? "CT+AAP" : v == "MW-LE" ? "MW+LE" : "MA-DBP (MW+AAP)";
}
inline std::string method_title(const std::string& m) {
    static const std::map<std::string, std::string> t = {{"line", "straight line"}, {"clfqp", "CLF-QP"}, {"expert", "guided expert"},
                                                         {"mappo", "MAPPO"}, {"madiff", "MADiff"}, {"madbp", "MA-DBP"},
                                                         {"madbp-k4", "MA-DBP, neighbourhoods of 4"},
                                                         {"madbp-paper", "MA-DBP, paper's planner"}};
    auto it = t.find(m);
    return it == t.end() ? m : it->second;
}

// MAPPO iterations for an empty-map team of k agents: the Makefile's MAPPO_CELLS.
inline long fig3a_mappo_iterations(int k) {
    static const std::map<int, long> it = {{1, 100}, {2, 200}, {3, 250}, {4, 300}, {6, 400}, {8, 500}};
    auto f = it.find(k);
    if (f == it.end()) throw std::invalid_argument("fig3a: no MAPPO iteration budget for " + std::to_string(k) + " agents (1, 2, 3, 4, 6, 8)");
    return f->second;
}

// =============================================================================================
// Running cells
// =============================================================================================

// One measurement. `base` holds what the cell is (group, method, map, n, ...), copied into its
// record whatever the outcome; `run` fills the record with numbers and may return sub-records
// (fig3b's rows), stored before the cell's own.
struct SuiteCell {
    std::string id, group;
    int unit = 0;                      // shard unit (see the file comment)
    std::vector<std::string> needs;    // model files; a missing one makes the cell "missing"
    std::string output;                // a file the cell writes: done only while it exists
    SuiteRecord base;
    std::function<std::vector<SuiteRecord>(SuiteRecord&)> run;
};

inline void put_eval_result(SuiteRecord& r, const madbp::EvalResult& e) {
    r.set("episodes", e.episodes).set("success", e.success).set("success_se", e.success_se).set("collisions", e.collisions)
        .set("agent_collisions", e.agent_collisions).set("obstacle_collisions", e.obstacle_collisions).set("steps", e.steps)
        .set("plan_ms", e.decision_ms);
}

inline madbp::ModelConfig model_config_of(const std::string& path) {
    return madbp::ModelConfig::from_metadata(madbp::load_safetensors(path).metadata, path);
}
// The executor's replan interval for a model file: the preset's follower.replan_every, which is
// written for the default window (ModelConfig{}: 16 steps), scaled to the file's window; so the
// paper's planner executes half of it (SPEC 8, m = H/2) and the tuned planner a quarter.
inline int model_replan(const std::string& path, bool paper_preset) {
    const madbp::ModelConfig mc = model_config_of(path), shipped;
    const int m = madbp::PlannerConfig::preset(paper_preset ? "paper" : "tuned").follower.replan_every;
    return std::max(1, m * mc.horizon * mc.waypoint_stride / (shipped.horizon * shipped.waypoint_stride));
}

// A method exactly as `madbp eval --method NAME [options]` builds it. A madbp model's replan
// interval follows its window (model_replan); other methods get kBaselineReplan.
// "madbp-kK": MA-DBP with neighbourhood planning of K agents per scene (`--neighbours K`);
// "madbp-paper": the paper's planner (`--preset paper`).
inline bool is_madbp(const std::string& method) { return method == "madbp" || method == "madbp-paper" || method.rfind("madbp-k", 0) == 0; }

inline MethodSpec registry_method(std::string name, std::vector<std::string> options, const std::string& map, int n,
                                  int* replan_used = nullptr) {
    static const std::vector<Method> all = methods();
    if (name.rfind("madbp-k", 0) == 0) {
        options.insert(options.end(), {"--neighbours", name.substr(7)});
        name = "madbp";
    } else if (name == "madbp-paper") {
        options.insert(options.end(), {"--preset", "paper"});
        name = "madbp";
    }
    MethodSetup setup;
    setup.map = map;
    setup.agents = n;
    if (name == "madbp") {
        auto it = std::find(options.begin(), options.end(), "--model");
        const auto preset = std::find(options.begin(), options.end(), "--preset");
        const bool paper = preset != options.end() && preset + 1 != options.end() && *(preset + 1) == "paper";
        if (it != options.end() && it + 1 != options.end()) setup.replan = model_replan(*(it + 1), paper);
    }
    if (replan_used) *replan_used = setup.replan > 0 ? setup.replan : kBaselineReplan;
    Args a(options);
    MethodSpec spec = find_method(all, name).make(a, setup);
    a.finish();
    return spec;
}

struct EpisodeSetup {
    std::string map;
    int agents = 2;
    double half_size = 1.2;
    int max_steps = 100;
    std::string scenario;  // an interaction scene instead of random spawns ("" for none)
    EpisodeSetup(std::string map_, int agents_, double half_size_ = 1.2, int max_steps_ = 100, std::string scenario_ = "")
        : map(std::move(map_)), agents(agents_), half_size(half_size_), max_steps(max_steps_), scenario(std::move(scenario_)) {}
};
inline madbp::EvalResult run_eval(const SuiteConfig& cfg, const EpisodeSetup& e, const madbp::PolicyFactory& factory) {
    madbp::set_num_threads(1);  // one core per episode; episodes run in parallel
    madbp::EvalConfig c;
    c.map = e.map;
    c.agents = e.agents;
    c.episodes = cfg.episodes;
    c.seed = 0;
    c.threads = cfg.threads;
    c.half_size = e.half_size;
    c.scenario = e.scenario;
    c.world.max_steps = e.max_steps;
    // no progress callback: the suite prints one line per cell instead
    return madbp::evaluate(c, factory);
}

// A cell evaluating a registry method; `model` ("" for none) is passed as --model.
inline SuiteCell eval_cell(const SuiteConfig& cfg, const std::string& id, const std::string& group, const std::string& method,
                           const EpisodeSetup& e, const std::string& model) {
    SuiteCell c;
    c.id = id;
    c.group = group;
    c.base.set("method", method).set("map", e.map).set("n", e.agents);
    if (!model.empty()) {
        c.needs = {model};
        c.base.set("model", model);
    }
    if (e.half_size != 1.2) c.base.set("half_size", e.half_size);
    if (e.max_steps != 100) c.base.set("max_steps", e.max_steps);
    if (!e.scenario.empty()) c.base.set("scenario", e.scenario);
    c.run = [&cfg, method, e, model](SuiteRecord& r) {
        int replan = 0;
        MethodSpec spec = registry_method(method, model.empty() ? std::vector<std::string>{} : std::vector<std::string>{"--model", model},
                                          e.map, e.agents, &replan);
        if (spec.n_train >= 0) r.set("n_train", spec.n_train);
        if (is_madbp(method)) r.set("model_H", model_config_of(model).horizon);
        if (is_madbp(method) || method == "line") r.set("replan", replan);
        put_eval_result(r, run_eval(cfg, e, spec.factory));
        return std::vector<SuiteRecord>{};
    };
    return c;
}

// A MAPPO policy trained on k agents driving a team of n: the actor sees only its own agent's
// observation, so it is the same network for any n. MappoPolicy checks the team size against
// its net's (the critic's input is n-wide), so the trained actor is copied into a net built
// for n; the critic is not used for acting.
inline madbp::MappoNet mappo_for_team(const madbp::MappoNet& trained, int n) {
    if (trained.config.agents == n) return trained.clone();
    madbp::MappoNetConfig nc = trained.config;
    nc.agents = n;
    madbp::MappoNet net(nc);
    for (const auto& e : trained.params->entries) {
        if (e.name.rfind("actor.", 0) != 0) continue;
        const auto* to = net.params->find(e.name);
        MADBP_ASSERT(to && to->numel() == e.numel());
        net.params->value.segment(to->offset, e.numel()) = trained.params->value.segment(e.offset, e.numel());
    }
    return net;
}
inline SuiteCell mappo_upscale_cell(const SuiteConfig& cfg, const std::string& id, const std::string& map, int k, int n,
                                    const std::string& model) {
    SuiteCell c;
    c.id = id;
    c.group = "fig4";
    c.needs = {model};
    c.base.set("method", "mappo").set("map", map).set("k", k).set("n", n).set("model", model);
    c.run = [&cfg, map, n, model](SuiteRecord& r) {
        const madbp::MappoNet trained = madbp::load_mappo(model);
        r.set("n_train", trained.config.agents);
        auto net = std::make_shared<const madbp::MappoNet>(mappo_for_team(trained, n));
        madbp::PolicyFactory factory = [net](const madbp::World&, uint64_t) {
            return std::unique_ptr<madbp::Policy>(new madbp::MappoPolicy(net->clone()));
        };
        put_eval_result(r, run_eval(cfg, EpisodeSetup{map, n}, factory));
        return std::vector<SuiteRecord>{};
    };
    return c;
}

// --- Dynamic teams (SPEC 2, 8, 9) -------------------------------------------------------------

// One episode whose team changes: cfg.dynamic_start agents, cfg.dynamic_join more at free
// random places at dynamic_join_step (drawn by spawn_agents, the sampler of make_random_world,
// which keeps clear of present agents, their goals, obstacles and walls, from a stream of the
// episode's seed), and the lowest id still present leaves at dynamic_leave_step. Success is the
// world's own: every present agent at its goal at the same step. `changed` tells whether the
// episode was still running when the last change was due (an early success ends it before).
inline madbp::EpisodeResult dynamic_episode(const SuiteConfig& cfg, const std::string& map, const madbp::PolicyFactory& factory,
                                            uint64_t seed, bool record, bool* changed) {
    madbp::WorldConfig wc;
    wc.max_steps = cfg.dynamic_max_steps;
    madbp::World world = madbp::make_random_world(map, cfg.dynamic_start, seed, 1.2, wc);
    std::unique_ptr<madbp::Policy> policy = factory(world, seed);
    madbp::Rng join_rng(seed ^ 0x6a6f696e73ull);  // its own stream: the first team is that of an ordinary episode
    bool left = false;
    auto on_step = [&](madbp::World& w) {
        if (w.t() == cfg.dynamic_join_step) madbp::spawn_agents(w, cfg.dynamic_join, join_rng);
        if (w.t() == cfg.dynamic_leave_step && w.size() > 0) {
            int lowest = w.agents()[0].id;
            for (const madbp::Agent& a : w.agents()) lowest = std::min(lowest, a.id);
            w.remove_agent(lowest);
            left = true;
        }
    };
    madbp::EpisodeResult r = madbp::run_episode(world, *policy, record, on_step);
    if (changed) *changed = left;
    return r;
}

// Success, its standard error, collisions and steps of a set of episodes, as evaluate() computes them.
inline madbp::EvalResult summarize_episodes(const std::vector<madbp::EpisodeResult>& runs) {
    madbp::EvalResult r;
    r.episodes = (int)runs.size();
    int wins = 0;
    double steps = 0;
    for (const madbp::EpisodeResult& e : runs) {
        wins += e.success;
        if (e.success) steps += e.steps;
        r.agent_collisions += e.agent_collisions;
        r.obstacle_collisions += e.obstacle_collisions;
        r.decision_ms += e.decision_ms;
    }
    const double N = std::max<size_t>(1, runs.size());
    r.success = wins / N;
    r.success_se = std::sqrt(r.success * (1 - r.success) / N);
    r.agent_collisions /= N;
    r.obstacle_collisions /= N;
    r.collisions = r.agent_collisions + r.obstacle_collisions;
    r.steps = wins ? steps / wins : NAN;
    r.decision_ms /= N;
    return r;
}

inline SuiteCell dynamic_cell(const SuiteConfig& cfg, const std::string& map, const std::string& method, const std::string& model) {
    SuiteCell c;
    c.id = "dynamic/" + map + "/" + method;
    c.group = "dynamic";
    c.base.set("method", method).set("map", map).set("n_start", cfg.dynamic_start).set("join", cfg.dynamic_join)
        .set("join_step", cfg.dynamic_join_step).set("leave_step", cfg.dynamic_leave_step).set("max_steps", cfg.dynamic_max_steps);
    if (!model.empty()) {
        c.needs = {model};
        c.base.set("model", model);
    }
    c.run = [&cfg, map, method, model](SuiteRecord& r) {
        MethodSpec spec = registry_method(method, model.empty() ? std::vector<std::string>{} : std::vector<std::string>{"--model", model},
                                          map, cfg.dynamic_start);
        madbp::set_num_threads(1);
        std::vector<madbp::EpisodeResult> runs(cfg.episodes);
        std::vector<char> changed(cfg.episodes, 0);
        std::string error;
        // Episode e depends only on its seed e, so the thread count never changes a result.
#pragma omp parallel for schedule(dynamic) num_threads(std::max(1, cfg.threads))
        for (int e = 0; e < cfg.episodes; ++e) {
            try {
                bool ch = false;
                runs[e] = dynamic_episode(cfg, map, spec.factory, (uint64_t)e, false, &ch);
                changed[e] = ch;
            } catch (const std::exception& ex) {
#pragma omp critical
                if (error.empty()) error = "episode with seed " + std::to_string(e) + ": " + ex.what();
            }
        }
        if (!error.empty()) throw std::runtime_error(error);
        put_eval_result(r, summarize_episodes(runs));
        long k = 0;
        for (char ch : changed) k += ch;
        r.set("team_changed", (double)k / cfg.episodes);
        return std::vector<SuiteRecord>{};
    };
    return c;
}

// --- fig3b: decision time per step ----------------------------------------------------------
inline SuiteCell fig3b_cell(const SuiteConfig& cfg, const std::string& model) {
    SuiteCell c;
    c.id = "fig3b";
    c.group = "fig3b";
    c.needs = {model};
    c.base.set("model", model).set("steps", cfg.fig3b_steps);
    c.run = [&cfg, model](SuiteRecord& r) {
        const int replan = model_replan(model, false);
        r.set("replan", replan);
        std::vector<SuiteRecord> rows;
        // measure_decision_times (methods_mappo.hpp): every method in one run on one thread.
        for (const DecisionTime& d : measure_decision_times(cfg.fig3b_counts, cfg.fig3b_steps, model, replan, 0)) {
            SuiteRecord row;
            row.id = "fig3b/n=" + std::to_string(d.n);
            row.status = "ok";
            row.set("n", d.n).set("mappo_us", d.mappo_us).set("clfqp_us", d.clfqp_us).set("madbp_us", d.madbp_us)
                .set("madbp_plan_ms", d.madbp_plan_ms).set("replan", replan);
            rows.push_back(row);
        }
        return rows;
    };
    return c;
}

// --- fig3a: training time, MAPPO on n against the MA-DBP pipeline on n/2 ----------------------
inline std::string fig3a_dir(const SuiteConfig& cfg) { return cfg.out + "/fig3a"; }
inline std::string fig3a_mappo_path(const SuiteConfig& cfg, int k) { return fig3a_dir(cfg) + "/mappo-" + std::to_string(k) + ".safetensors"; }
inline std::string fig3a_demos_path(const SuiteConfig& cfg, int n) { return fig3a_dir(cfg) + "/demos-" + std::to_string(n) + ".bin"; }
inline std::string fig3a_madbp_path(const SuiteConfig& cfg, int n) { return fig3a_dir(cfg) + "/madbp-" + std::to_string(n) + ".safetensors"; }
// MAPPO team sizes fig3a trains: each n, and 1..n/2 (the demonstrators), each once.
inline std::vector<int> fig3a_mappo_sizes(const SuiteConfig& cfg) {
    std::set<int> k;
    for (int n : cfg.fig3a_counts) {
        k.insert(n);
        for (int j = 1; j <= n / 2; ++j) k.insert(j);
    }
    return std::vector<int>(k.begin(), k.end());
}
inline double seconds_since(std::chrono::steady_clock::time_point t0) {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// Stages, in the order they depend on each other: MAPPO policies, demonstrations, MA-DBP
// training, evaluation. Every stage is timed in-process and stored as its own record.
inline void add_fig3a_cells(std::vector<SuiteCell>& cells, const SuiteConfig& cfg, int unit) {
    auto stage = [&](const std::string& id, const std::string& output) {
        SuiteCell c;
        c.id = id;
        c.group = "fig3a";
        c.unit = unit;
        c.output = output;
        return c;
    };
    for (int k : fig3a_mappo_sizes(cfg)) {
        SuiteCell c = stage("fig3a/mappo/k=" + std::to_string(k), fig3a_mappo_path(cfg, k));
        c.base.set("stage", "mappo").set("k", k);
        c.run = [&cfg, k](SuiteRecord& r) {
            madbp::MappoConfig m;
            m.map = "empty";
            m.agents = k;
            m.iterations = std::max(1L, std::lround(fig3a_mappo_iterations(k) * cfg.fig3a_mappo_scale));
            m.worlds = cfg.fig3a_mappo_worlds;
            m.threads = cfg.threads;
            m.seed = 0;
            m.out = fig3a_mappo_path(cfg, k);
            const auto t0 = std::chrono::steady_clock::now();
            madbp::MappoReport rep = madbp::train_mappo(m);
            r.set("threads", (long)cfg.threads).set("seconds", seconds_since(t0)).set("iterations", rep.iterations).set("env_steps", rep.env_steps)
                .set("train_success", rep.curve.rows.empty() ? NAN : rep.curve.rows.back()[rep.curve.column("success")]).set("file", m.out);
            return std::vector<SuiteRecord>{};
        };
        cells.push_back(c);
    }
    for (int n : cfg.fig3a_counts) {
        SuiteCell c = stage("fig3a/collect/n=" + std::to_string(n), fig3a_demos_path(cfg, n));
        c.base.set("stage", "collect").set("n", n).set("n_train", n / 2);
        c.run = [&cfg, n](SuiteRecord& r) {
            madbp::CollectConfig cc;
            cc.maps = {"empty"};
            cc.n_train_max = n / 2;
            cc.episodes = cfg.fig3a_collect_episodes;
            cc.successful_only = cfg.fig3a_successful_only;
            cc.threads = cfg.threads;
            cc.seed = 0;
            const std::string pattern = fig3a_dir(cfg) + "/mappo-{n}.safetensors";
            const auto t0 = std::chrono::steady_clock::now();
            madbp::DemoSet set = madbp::collect_demonstrations(cc, madbp::mappo_demonstrator(pattern), "mappo:" + pattern);
            const double secs = seconds_since(t0);
            madbp::save_demos(fig3a_demos_path(cfg, n), set);
            r.set("threads", (long)cfg.threads).set("seconds", secs).set("kept", (long)set.episodes.size()).set("asked", (long)cc.episodes * cc.n_train_max)
                .set("file", fig3a_demos_path(cfg, n));
            return std::vector<SuiteRecord>{};
        };
        cells.push_back(c);
    }
    for (int n : cfg.fig3a_counts) {
        SuiteCell c = stage("fig3a/train/n=" + std::to_string(n), fig3a_madbp_path(cfg, n));
        c.base.set("stage", "train").set("n", n).set("n_train", n / 2);
        c.run = [&cfg, n](SuiteRecord& r) {
            madbp::DemoSet demos = madbp::load_demos(fig3a_demos_path(cfg, n));
            madbp::TrainConfig tc;
            tc.n_train_max = n / 2;
            tc.steps = cfg.fig3a_madbp_steps;
            tc.batch = cfg.fig3a_batch;
            tc.threads = cfg.threads;
            tc.seed = 0;
            tc.out = fig3a_madbp_path(cfg, n);
            madbp::set_num_threads(cfg.threads);
            cfg.fig3a_model.validate();
            madbp::MadbpModel model(cfg.fig3a_model, tc.seed);
            const auto t0 = std::chrono::steady_clock::now();
            madbp::TrainReport rep = madbp::train(demos, model, tc);
            r.set("threads", (long)cfg.threads).set("seconds", seconds_since(t0)).set("steps", rep.steps).set("val_loss", rep.last_val.total).set("file", tc.out);
            return std::vector<SuiteRecord>{};
        };
        cells.push_back(c);
    }
    for (int n : cfg.fig3a_counts)
        for (const char* method : {"mappo", "madbp"}) {
            const std::string model = std::string(method) == "mappo" ? fig3a_mappo_path(cfg, n) : fig3a_madbp_path(cfg, n);
            SuiteCell c = eval_cell(cfg, "fig3a/eval/" + std::string(method) + "/n=" + std::to_string(n), "fig3a", method,
                                    EpisodeSetup{"empty", n}, model);
            c.unit = unit;
            c.needs.clear();  // written by the stages above: a missing one is an error, not a missing model
            c.base.set("stage", "eval");
            cells.push_back(c);
        }
}

// --- Pictures -----------------------------------------------------------------------------------
inline SuiteCell picture_cell(const SuiteConfig& cfg, const std::string& name, const std::string& map, int n, double half_size,
                              int max_steps, bool dynamic, const std::string& model, const std::string& method = "madbp") {
    SuiteCell c;
    c.id = "pictures/" + name;
    c.group = "pictures";
    c.needs = {model};
    c.output = cfg.out + "/episode-" + name + ".svg";
    c.base.set("method", method).set("map", map).set("n", n).set("seed", 0L).set("file", "episode-" + name + ".svg");
    c.run = [&cfg, map, n, half_size, max_steps, dynamic, model, method, path = c.output](SuiteRecord& r) {
        MethodSpec spec = registry_method(method, {"--model", model}, map, n);
        madbp::set_num_threads(1);
        madbp::EpisodeResult e;
        if (dynamic) {
            e = dynamic_episode(cfg, map, spec.factory, 0, true, nullptr);
        } else {
            madbp::WorldConfig wc;
            wc.max_steps = max_steps;
            madbp::World world = madbp::make_random_world(map, n, 0, half_size, wc);
            auto policy = spec.factory(world, 0);
            e = madbp::run_episode(world, *policy, true);
        }
        madbp::SvgOptions opt;
        opt.pixels_per_unit = 480 / (2 * half_size);
        opt.title = (method == "madbp" ? std::string("MA-DBP") : "MA-DBP (" + method.substr(6) + " neighbours)") + "  " + map + (dynamic ? "  n=" + std::to_string(cfg.dynamic_start) + " +" + std::to_string(cfg.dynamic_join) +
                                                      " at step " + std::to_string(cfg.dynamic_join_step) + " -1 at step " +
                                                      std::to_string(cfg.dynamic_leave_step)
                                                : "  n=" + std::to_string(n)) +
                    "  seed 0" + (e.success ? "  success in " + std::to_string(e.steps) + " steps" : "  failed") + "  collisions " +
                    std::to_string(e.collisions());
        write_report(path, madbp::render_svg(e.log, opt));
        r.set("success", e.success ? 1L : 0L).set("steps", e.steps).set("collisions", e.collisions());
        return std::vector<SuiteRecord>{};
    };
    return c;
}

// =============================================================================================
// The cell list, in its fixed global order.
// =============================================================================================

inline std::string table1_id(const std::string& map, int n, const std::string& method) {
    return "table1/" + map + "/n=" + std::to_string(n) + "/" + method;
}
inline std::string fig4_id(const std::string& method, const std::string& map, int k, int n) {
    return "fig4/" + map + "/k=" + std::to_string(k) + "/n=" + std::to_string(n) + "/" + method;
}
inline std::string table2_id(const std::string& variant, int k, int n) {
    return "table2/" + variant + "/k=" + std::to_string(k) + "/n=" + std::to_string(n);
}
inline std::string horizon_id(int H, int n) { return "horizon/H=" + std::to_string(H) + "/n=" + std::to_string(n); }
inline std::string large_id(const std::string& map, int n, const std::string& method) {
    return "large/" + map + "/n=" + std::to_string(n) + "/" + method;
}
inline std::string interaction_id(const std::string& scenario, const std::string& map, int n, const std::string& method) {
    return "interaction/" + scenario + "/" + map + "/n=" + std::to_string(n) + "/" + method;
}
inline const std::vector<std::string>& table2_variants() {
    static const std::vector<std::string> v = {"CT-LE", "CT-AAP", "MW-LE", "MW-AAP"};
    return v;
}

// Every cell of the suite. The cells keep a reference to cfg: it must outlive them.
inline std::vector<SuiteCell> suite_cells(const SuiteConfig& cfg) {
    const SuiteModels models{cfg.models};
    std::vector<SuiteCell> cells;
    int unit = 0;
    auto add = [&](SuiteCell c) {
        c.unit = unit++;
        cells.push_back(std::move(c));
    };
    for (auto& [map, counts] : cfg.table1_cells)
        for (int n : counts)
            for (const std::string& m : cfg.table1_methods) {
                const std::string model = m == "mappo" ? models.mappo(map, n) : m == "madiff" ? models.madiff(map, n)
                                        : is_madbp(m) ? models.madbp_default() : "";
                add(eval_cell(cfg, table1_id(map, n, m), "table1", m, EpisodeSetup{map, n}, model));
            }
    for (const std::string& map : cfg.fig4_maps)
        for (int k : cfg.fig4_train)
            for (int n : cfg.fig4_counts) {
                for (const std::string& m : cfg.fig4_planners) {
                    SuiteCell c = eval_cell(cfg, fig4_id(m, map, k, n), "fig4", m, EpisodeSetup{map, n}, models.madbp_trained_on(k));
                    c.base.set("k", k);
                    add(c);
                }
                add(mappo_upscale_cell(cfg, fig4_id("mappo", map, k, n), map, k, n, models.mappo(map, k)));
            }
    for (const std::string& v : table2_variants())
        for (int k : cfg.table2_train)
            for (int n : cfg.table2_counts) {
                SuiteCell c = eval_cell(cfg, table2_id(v, k, n), "table2", "madbp", EpisodeSetup{"empty", n},
                                        models.ablation(v.substr(0, 2), v.substr(3), k));
                c.base.set("variant", v).set("k", k);
                add(c);
            }
    for (int H : cfg.horizon_lengths)
        for (int n : cfg.horizon_counts) {
            SuiteCell c = eval_cell(cfg, horizon_id(H, n), "horizon", "madbp", EpisodeSetup{"empty", n}, models.horizon(H));
            c.base.set("H", H);
            add(c);
        }
    for (const std::string& map : cfg.dynamic_maps)
        for (const std::string& m : cfg.dynamic_methods) add(dynamic_cell(cfg, map, m, m == "madbp" ? models.madbp_default() : ""));
    for (const std::string& map : cfg.large_maps)
        for (int n : cfg.large_counts)
            for (const std::string& m : cfg.large_methods)
                add(eval_cell(cfg, large_id(map, n, m), "large", m, EpisodeSetup{map, n, cfg.large_half_size, cfg.large_max_steps},
                              is_madbp(m) ? models.madbp_default() : ""));
    for (const std::string& scenario : cfg.interaction_scenarios)
        for (const std::string& map : cfg.interaction_maps)
            for (int n : cfg.interaction_counts)
                for (const std::string& m : cfg.interaction_methods) {
                    add(eval_cell(cfg, interaction_id(scenario, map, n, m), "interaction", m, EpisodeSetup{map, n, 1.2, 100, scenario},
                                  is_madbp(m) ? models.madbp_default() : ""));
                }
    add(fig3b_cell(cfg, models.madbp_default()));
    add_fig3a_cells(cells, cfg, unit++);
    add(picture_cell(cfg, "barrier-n" + std::to_string(cfg.picture_barrier_agents), "barrier", cfg.picture_barrier_agents, 1.2, 100,
                     false, models.madbp_default()));
    add(picture_cell(cfg, "large-empty-n" + std::to_string(cfg.picture_large_agents), "empty", cfg.picture_large_agents,
                     cfg.large_half_size, cfg.large_max_steps, false, models.madbp_default(), "madbp-k4"));
    add(picture_cell(cfg, "dynamic-empty", "empty", cfg.dynamic_start, 1.2, cfg.dynamic_max_steps, true, models.madbp_default()));
    for (SuiteCell& c : cells) c.base.set("group", c.group);
    return cells;
}

inline bool suite_selected(const SuiteConfig& cfg, const SuiteCell& c) {
    const bool in_group = cfg.only.empty() || std::find(cfg.only.begin(), cfg.only.end(), c.group) != cfg.only.end();
    return in_group && c.unit % cfg.shard_count == cfg.shard_index;
}
inline bool suite_done(const SuiteStore& store, const SuiteCell& c) {
    auto it = store.find(c.id);
    return it != store.end() && it->second.ok() && (c.output.empty() || file_exists(c.output));
}

// Runs one cell; never throws (an error becomes the record's status).
inline std::vector<SuiteRecord> run_suite_cell(const SuiteCell& c) {
    SuiteRecord own = c.base;
    own.id = c.id;
    std::vector<SuiteRecord> out;
    std::string missing;
    for (const std::string& f : c.needs)
        if (missing.empty() && !file_exists(f)) missing = f;
    if (!missing.empty()) {
        own.status = "missing";
        own.set("why", "missing " + missing);
    } else {
        const auto t0 = std::chrono::steady_clock::now();
        try {
            out = c.run(own);
            own.status = "ok";
        } catch (const std::exception& e) {
            out.clear();
            own.status = "error";
            own.set("why", e.what());
        }
        own.set("cell_seconds", seconds_since(t0));
    }
    out.push_back(own);
    return out;
}

// =============================================================================================
// Reports: markdown tables, CSV files and SVG charts, regenerated from the store.
// =============================================================================================

// ".95" for a rate (the paper's style), "1.00" for 1.
inline std::string rate_text(double v) {
    if (!(v == v)) return "-";
    char b[16];
    std::snprintf(b, sizeof b, "%.2f", v);
    std::string s = b;
    return s.rfind("0.", 0) == 0 ? s.substr(1) : s;
}
inline std::string num_text(double v, int prec) {
    if (!(v == v)) return "-";
    char b[32];
    std::snprintf(b, sizeof b, "%.*f", prec, v);
    return b;
}
// A standard error as ".024".
inline std::string se_text(double v) {
    const std::string s = num_text(v, 3);
    return s.rfind("0.", 0) == 0 ? s.substr(1) : s;
}
// What a table shows for a cell that has no numbers.
inline std::string no_result_text(const SuiteStore& store, const std::string& id) {
    auto it = store.find(id);
    if (it == store.end()) return "not run";
    if (it->second.status == "missing") return "n/a (" + it->second.why() + ")";
    std::string why = it->second.why();
    if (why.size() > 80) why = why.substr(0, 77) + "...";
    return "error (" + why + ")";
}
inline const SuiteRecord* ok_record(const SuiteStore& store, const std::string& id) {
    auto it = store.find(id);
    return it != store.end() && it->second.ok() ? &it->second : nullptr;
}
// "success ± se / collisions per episode".
inline std::string eval_text(const SuiteStore& store, const std::string& id) {
    const SuiteRecord* r = ok_record(store, id);
    if (!r) return no_result_text(store, id);
    return rate_text(r->num("success")) + " ± " + se_text(r->num("success_se")) + " / " + num_text(r->num("collisions"), 2);
}
inline double success_of(const SuiteStore& store, const std::string& id) {
    const SuiteRecord* r = ok_record(store, id);
    return r ? r->num("success") : NAN;
}
// "Episodes per cell: 100" from the records, or the mix when cells ran with different counts.
inline std::string episodes_note(const SuiteStore& store, const std::string& prefix) {
    std::set<long> e;
    for (auto& kv : store)
        if (kv.first.rfind(prefix, 0) == 0 && kv.second.ok() && kv.second.num("episodes") == kv.second.num("episodes"))
            e.insert((long)kv.second.num("episodes"));
    if (e.empty()) return "No cell has run yet.";
    std::string s;
    for (long v : e) s += (s.empty() ? "" : ", ") + std::to_string(v);
    return "Episodes per cell: " + s + " (seeds 0..E-1)" + (e.size() > 1 ? ", mixed: cells ran with different --episodes." : ".");
}

struct MdTable {
    std::vector<std::string> header;
    std::vector<std::vector<std::string>> rows;
    std::string text() const {
        std::string s = "|";
        for (auto& h : header) s += " " + h + " |";
        s += "\n|";
        for (size_t i = 0; i < header.size(); ++i) s += "---|";
        s += "\n";
        for (auto& r : rows) {
            s += "|";
            for (auto& c : r) s += " " + c + " |";
            s += "\n";
        }
        return s;
    }
};

// One CSV per group: every record of the group's cells (and sub-records), one column per field.
inline void write_group_csv(const std::string& path, const std::vector<const SuiteRecord*>& records) {
    std::vector<std::string> cols = {"id", "status"};
    for (const SuiteRecord* r : records)
        for (auto& kv : r->fields)
            if (std::find(cols.begin(), cols.end(), kv.first) == cols.end()) cols.push_back(kv.first);
    auto quote = [](const std::string& s) {
        if (s.find_first_of(",\"") == std::string::npos) return s;
        std::string q = "\"";
        for (char ch : s) q += ch == '"' ? std::string("\"\"") : std::string(1, ch);
        return q + "\"";
    };
    std::string csv;
    for (size_t i = 0; i < cols.size(); ++i) csv += (i ? "," : "") + cols[i];
    csv += "\n";
    for (const SuiteRecord* r : records) {
        for (size_t i = 0; i < cols.size(); ++i)
            csv += (i ? "," : "") + quote(cols[i] == "id" ? r->id : cols[i] == "status" ? r->status : r->get(cols[i]));
        csv += "\n";
    }
    write_report(path, csv);
}

// --- SVG charts (the style of write_loss_svg: plain elements, no dependencies) -----------------
struct ChartSeries {
    std::string label, colour;
    std::vector<std::pair<double, double>> xy;  // NaN y: no point
    bool dashed = false;
    bool marks_only = false;  // crosses without a line (the paper's reference values)
};
struct ChartAxes {
    std::string title, x_label, y_label;
    std::vector<double> x_ticks;
    double y_lo = 0, y_hi = 1;
    bool log_y = false;
    int legend_rows = 0;  // 0: as many as the series need (fixed, panels side by side line up)
};
inline std::string svg_num(double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%.1f", v);
    return b;
}
inline std::string svg_text(double x, double y, const std::string& s, const std::string& extra = "") {
    std::string t;
    for (char ch : s) t += ch == '<' ? std::string("&lt;") : ch == '&' ? std::string("&amp;") : std::string(1, ch);
    return "<text x='" + svg_num(x) + "' y='" + svg_num(y) + "'" + extra + ">" + t + "</text>\n";
}
// A line chart in the box (left, top, w, h): plot area above, legend rows below it.
inline std::string line_chart(const ChartAxes& ax, const std::vector<ChartSeries>& series, double left, double top, double w, double h) {
    const double legend_h = 14.0 * (ax.legend_rows > 0 ? ax.legend_rows : (series.size() + 1) / 2) + 6;
    const double px = left + 50, py = top + 24, pw = w - 65, ph = h - 24 - 36 - legend_h;
    const double x_lo = ax.x_ticks.front(), x_hi = std::max(ax.x_ticks.back(), x_lo + 1e-9);
    auto fy = [&](double v) { return ax.log_y ? std::log10(std::max(v, 1e-300)) : v; };
    const double y_lo = fy(ax.y_lo), y_hi = fy(ax.y_hi);
    auto X = [&](double x) { return px + pw * (x - x_lo) / (x_hi - x_lo); };
    auto Y = [&](double y) { return py + ph * (1 - (std::min(std::max(fy(y), y_lo), y_hi) - y_lo) / (y_hi - y_lo)); };
    std::string s = svg_text(left + 50, top + 14, ax.title, " font-weight='bold'");
    s += "<rect x='" + svg_num(px) + "' y='" + svg_num(py) + "' width='" + svg_num(pw) + "' height='" + svg_num(ph) +
         "' fill='none' stroke='#888'/>\n";
    for (double x : ax.x_ticks) s += svg_text(X(x) - 4, py + ph + 14, num_text(x, x == std::floor(x) ? 0 : 1));
    s += svg_text(px + pw / 2 - 30, py + ph + 28, ax.x_label);
    std::vector<double> y_ticks;
    if (ax.log_y) for (double e = std::ceil(y_lo); e <= y_hi + 1e-9; e += 1) y_ticks.push_back(std::pow(10.0, e));
    else for (int k = 0; k <= 4; ++k) y_ticks.push_back(ax.y_lo + (ax.y_hi - ax.y_lo) * k / 4);
    for (double y : y_ticks) {
        s += "<line x1='" + svg_num(px) + "' x2='" + svg_num(px + pw) + "' y1='" + svg_num(Y(y)) + "' y2='" + svg_num(Y(y)) +
             "' stroke='#eee'/>\n";
        char b[32];
        std::snprintf(b, sizeof b, ax.log_y ? "%g" : "%.2f", y);
        s += svg_text(left + 4, Y(y) + 4, b);
    }
    s += svg_text(left + 4, py - 6, ax.y_label);
    for (size_t i = 0; i < series.size(); ++i) {
        const ChartSeries& c = series[i];
        std::string pts;
        for (auto& p : c.xy) {
            if (!(p.second == p.second)) continue;
            if (c.marks_only) {
                const double x = X(p.first), y = Y(p.second), a = 4;
                s += "<path d='M" + svg_num(x - a) + "," + svg_num(y - a) + " L" + svg_num(x + a) + "," + svg_num(y + a) + " M" +
                     svg_num(x - a) + "," + svg_num(y + a) + " L" + svg_num(x + a) + "," + svg_num(y - a) + "' stroke='" + c.colour +
                     "' stroke-width='2'/>\n";
            } else {
                pts += svg_num(X(p.first)) + "," + svg_num(Y(p.second)) + " ";
                s += "<circle cx='" + svg_num(X(p.first)) + "' cy='" + svg_num(Y(p.second)) + "' r='2.5' fill='" + c.colour + "'/>\n";
            }
        }
        if (!pts.empty())
            s += "<polyline fill='none' stroke='" + c.colour + "' stroke-width='1.5'" + (c.dashed ? " stroke-dasharray='5 3'" : "") +
                 " points='" + pts + "'/>\n";
        const double lx = left + 10 + (i % 2) * (w / 2), ly = py + ph + 46 + 14.0 * (i / 2);
        s += c.marks_only ? svg_text(lx, ly + 4, "x", " fill='" + c.colour + "'")
                          : "<line x1='" + svg_num(lx) + "' x2='" + svg_num(lx + 18) + "' y1='" + svg_num(ly) + "' y2='" + svg_num(ly) +
                                "' stroke='" + c.colour + "' stroke-width='1.5'" + (c.dashed ? " stroke-dasharray='5 3'" : "") + "/>\n";
        s += svg_text(lx + 24, ly + 4, c.label);
    }
    return s;
}
inline std::string svg_page(double w, double h, const std::string& body) {
    return "<svg xmlns='http://www.w3.org/2000/svg' width='" + svg_num(w) + "' height='" + svg_num(h) +
           "' font-family='sans-serif' font-size='11'>\n<rect width='" + svg_num(w) + "' height='" + svg_num(h) + "' fill='white'/>\n" +
           body + "</svg>\n";
}
inline const char* series_colour(int k) {
    static const char* c[] = {"#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f"};
    return c[((k % 8) + 8) % 8];
}
inline std::vector<double> ticks_of(const std::vector<int>& v) { return std::vector<double>(v.begin(), v.end()); }

// --- The reports of each group ----------------------------------------------------------------
inline const char* kBarrierNote =
    "Our barrier map is harder than the paper's (SPEC 2: a 0.5-wide gap in a wall across the whole world; the paper does "
    "not give its layout), so barrier numbers are not directly comparable with the paper's.";

inline std::string table1_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"map", "n"};
    for (const std::string& m : cfg.table1_methods) {
        bool in_paper = false;
        for (auto& p : paper_table1()) in_paper = in_paper || m == p.method;
        if (in_paper) t.header.push_back(method_title(m) + " (paper)");
        t.header.push_back(method_title(m));
    }
    for (auto& [map, counts] : cfg.table1_cells)
        for (int n : counts) {
            std::vector<std::string> row = {map == "barrier" ? "barrier*" : map, std::to_string(n)};
            for (const std::string& m : cfg.table1_methods) {
                bool in_paper = false;
                std::string paper = "-";
                for (auto& p : paper_table1()) {
                    in_paper = in_paper || m == p.method;
                    if (m == p.method && map == p.map && n == p.n) paper = rate_text(p.success) + " ± " + se_text(p.se);
                }
                if (in_paper) row.push_back(paper);
                row.push_back(eval_text(st, table1_id(map, n, m)));
            }
            t.rows.push_back(row);
        }
    return "# Table I: success with the same n in training and test (paper Table I)\n\n" + episodes_note(st, "table1/") +
           " Each cell: success ± standard error / collisions per episode. \"(paper)\" columns are the paper's "
           "published numbers (mean ± se over its 20 episodes). MAPPO and MADiff are trained per (map, n); MA-DBP is one "
           "model (models/madbp-default.safetensors) for every cell; \"MA-DBP\" is the tuned planner, \"paper's planner\" the same "
           "model with `--preset paper` (plain DDIM with goal inpainting, the SPEC 8 follower).\n\n" +
           t.text() + "\n\\* " + kBarrierNote + "\n";
}

inline std::string fig4_report(const SuiteConfig& cfg, const SuiteStore& st) {
    std::string md = "# Fig. 4: upscaling, trained on k agents, deployed on n\n\n" + episodes_note(st, "fig4/") +
                     " Each cell: success ± standard error / collisions per episode. MA-DBP k = 2, 3: models/paper/madbp-n{k}; "
                     "k = 4: the default model; \"MA-DBP\" is the tuned planner, \"paper's planner\" the same model with "
                     "`--preset paper` (plain DDIM with goal inpainting, the SPEC 8 follower). MAPPO k: the policy trained on k agents of the map, its actor run on every agent "
                     "of the larger (or smaller) team. \"paper\": the paper's MA-DBP on the empty map (its Table II MA-DBP row; "
                     "Fig. 4's own values are not in the paper's text).\n";
    for (const std::string& map : cfg.fig4_maps) {
        MdTable t;
        t.header = {"n"};
        std::vector<std::string> columns = cfg.fig4_planners;
        columns.push_back("mappo");
        for (const std::string& m : columns)
            for (int k : cfg.fig4_train) t.header.push_back(method_title(m) + " k=" + std::to_string(k));
        if (map == "empty") t.header.push_back("paper MA-DBP");
        for (int n : cfg.fig4_counts) {
            std::vector<std::string> row = {std::to_string(n)};
            for (const std::string& m : columns)
                for (int k : cfg.fig4_train) row.push_back(eval_text(st, fig4_id(m, map, k, n)));
            if (map == "empty") {
                std::string p;
                for (int k : cfg.fig4_train) {
                    const double v = paper_table2_value("MW-AAP", k, n);
                    if (v == v) p += (p.empty() ? "" : ", ") + std::string("k=") + std::to_string(k) + " " + rate_text(v);
                }
                row.push_back(p.empty() ? "-" : p);
            }
            t.rows.push_back(row);
        }
        md += "\n## " + map + "\n\n" + t.text();
        if (map == "barrier") md += "\n" + std::string(kBarrierNote) + "\n";
    }
    return md;
}
inline void write_fig4_svg(const SuiteConfig& cfg, const SuiteStore& st, const std::string& path) {
    const double W = 360, H = 330;
    std::string body;
    for (size_t m = 0; m < cfg.fig4_maps.size(); ++m) {
        const std::string& map = cfg.fig4_maps[m];
        std::vector<ChartSeries> series;
        for (size_t j = 0; j < cfg.fig4_train.size(); ++j) {
            const int k = cfg.fig4_train[j];
            for (const char* method : {"madbp", "mappo"}) {
                ChartSeries s{method_title(method) + " k=" + std::to_string(k), series_colour((int)j), {}, std::string(method) == "mappo"};
                for (int n : cfg.fig4_counts) s.xy.push_back({(double)n, success_of(st, fig4_id(method, map, k, n))});
                series.push_back(s);
            }
            if (map == "empty") {
                ChartSeries p{"paper MA-DBP k=" + std::to_string(k), series_colour((int)j), {}, false, true};
                for (int n : {6, 7}) p.xy.push_back({(double)n, paper_table2_value("MW-AAP", k, n)});
                series.push_back(p);
            }
        }
        ChartAxes ax{map + (map == "barrier" ? " (harder than the paper's)" : ""), "agents n", "success", ticks_of(cfg.fig4_counts)};
        ax.legend_rows = (int)(3 * cfg.fig4_train.size() + 1) / 2;  // the empty panel's: MA-DBP, MAPPO and paper per k
        body += line_chart(ax, series, W * m, 0, W, H);
    }
    write_report(path, svg_page(W * cfg.fig4_maps.size(), H, body));
}

inline std::string table2_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"model", "n_train"};
    for (int n : cfg.table2_counts) {
        t.header.push_back("n=" + std::to_string(n) + " (paper)");
        t.header.push_back("n=" + std::to_string(n));
    }
    for (const std::string& v : table2_variants())
        for (int k : cfg.table2_train) {
            std::vector<std::string> row = {variant_title(v), std::to_string(k)};
            for (int n : cfg.table2_counts) {
                row.push_back(rate_text(paper_table2_value(v, k, n)));
                row.push_back(eval_text(st, table2_id(v, k, n)));
            }
            t.rows.push_back(row);
        }
    return "# Table II: ablation, empty map (paper Table II)\n\n" + episodes_note(st, "table2/") +
           " Each cell: success ± standard error / collisions per episode; \"(paper)\": the paper's published success. "
           "Models: models/paper/ablation-{CT|MW}-{LE|AAP}-n{k}.safetensors; the tuned planner executes a quarter of each "
           "model's window H per plan (H/4, H read from the file).\n\n" +
           t.text();
}

inline std::string horizon_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"H", "n", "H in file", "replan", "success ± se / collisions", "steps", "plan_ms"};
    for (int H : cfg.horizon_lengths)
        for (int n : cfg.horizon_counts) {
            const std::string id = horizon_id(H, n);
            const SuiteRecord* r = ok_record(st, id);
            t.rows.push_back({std::to_string(H), std::to_string(n), r ? r->get("model_H") : "-", r ? r->get("replan") : "-", eval_text(st, id),
                              r ? num_text(r->num("steps"), 1) : "-", r ? num_text(r->num("plan_ms"), 2) : "-"});
        }
    return "# Window length H (MW + AAP, trained on n <= 4, empty map)\n\n" + episodes_note(st, "horizon/") +
           " Models: models/paper/ablation-MW-AAP-n4-h{H}.safetensors (H = 16: ablation-MW-AAP-n4). The tuned planner executes "
           "H/4 steps per plan (the replan column). plan_ms: mean wall time of one window plan (one core).\n\n" +
           t.text();
}
inline void write_horizon_svg(const SuiteConfig& cfg, const SuiteStore& st, const std::string& path) {
    std::vector<ChartSeries> series;
    for (size_t j = 0; j < cfg.horizon_counts.size(); ++j) {
        const int n = cfg.horizon_counts[j];
        ChartSeries s{"n=" + std::to_string(n), series_colour((int)j), {}};
        for (int H : cfg.horizon_lengths) s.xy.push_back({(double)H, success_of(st, horizon_id(H, n))});
        series.push_back(s);
    }
    write_report(path, svg_page(420, 330, line_chart({"success vs window length H (empty map)", "H", "success", ticks_of(cfg.horizon_lengths)},
                                                     series, 0, 0, 420, 330)));
}

inline std::string dynamic_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"map", "method", "success ± se", "collisions / episode", "steps", "team changed"};
    for (const std::string& map : cfg.dynamic_maps)
        for (const std::string& m : cfg.dynamic_methods) {
            const std::string id = "dynamic/" + map + "/" + m;
            const SuiteRecord* r = ok_record(st, id);
            t.rows.push_back({map == "barrier" ? "barrier*" : map, method_title(m),
                              r ? rate_text(r->num("success")) + " ± " + se_text(r->num("success_se")) : no_result_text(st, id),
                              r ? num_text(r->num("collisions"), 2) : "-", r ? num_text(r->num("steps"), 1) : "-",
                              r ? rate_text(r->num("team_changed")) : "-"});
        }
    return "# Dynamic teams: agents join and leave mid-episode (SPEC 2, 8)\n\n" + episodes_note(st, "dynamic/") + " Each episode starts with " +
           std::to_string(cfg.dynamic_start) + " agents; " + std::to_string(cfg.dynamic_join) + " join at step " +
           std::to_string(cfg.dynamic_join_step) + " at free random starts and goals; the lowest id present leaves at step " +
           std::to_string(cfg.dynamic_leave_step) + "; at most " + std::to_string(cfg.dynamic_max_steps) +
           " steps. Success: every agent present at its goal at the same step (the world's metric). steps: mean of "
           "successful episodes. \"team changed\": the fraction of episodes still running when the agent left (a team that "
           "finishes before that succeeds without the change).\n\n" +
           t.text() + "\n\\* " + kBarrierNote + "\n";
}

inline std::string large_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"map", "n", "method", "success ± se / collisions", "steps", "plan_ms"};
    for (const std::string& map : cfg.large_maps)
        for (int n : cfg.large_counts)
            for (const std::string& m : cfg.large_methods) {
                const std::string id = large_id(map, n, m);
                const SuiteRecord* r = ok_record(st, id);
                t.rows.push_back({map, std::to_string(n), method_title(m), eval_text(st, id), r ? num_text(r->num("steps"), 1) : "-",
                                  r ? num_text(r->num("plan_ms"), 2) : "-"});
            }
    return "# A world of twice the side (half-size " + num_text(cfg.large_half_size, 1) + ", " + std::to_string(cfg.large_max_steps) +
           " steps)\n\n" + episodes_note(st, "large/") +
           " Our goal (SPEC 9): MA-DBP >= .90 at n = 16 on the empty map; 32 reported. MA-DBP is the default model "
           "(trained in the standard world, half-size 1.2, with n <= 4); \"paper's planner\" is it with `--preset paper`.\n\n" +
           t.text();
}

// Interaction scenes: each (scene, map, n) row, a column per method.
inline std::string interaction_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"scene", "map", "n"};
    for (const std::string& m : cfg.interaction_methods) t.header.push_back(method_title(m));
    for (const std::string& m : cfg.interaction_methods) t.header.push_back(method_title(m) + " steps");
    for (const std::string& scenario : cfg.interaction_scenarios)
        for (const std::string& map : cfg.interaction_maps)
            for (int n : cfg.interaction_counts) {
                std::vector<std::string> row = {scenario, map == "barrier" ? "barrier*" : map, std::to_string(n)};
                for (const std::string& m : cfg.interaction_methods) row.push_back(eval_text(st, interaction_id(scenario, map, n, m)));
                for (const std::string& m : cfg.interaction_methods) {
                    const SuiteRecord* r = ok_record(st, interaction_id(scenario, map, n, m));
                    row.push_back(r ? num_text(r->num("steps"), 1) : "-");
                }
                t.rows.push_back(row);
            }
    return "# Interaction scenes: swaps, crossings, gaps, corridors, parked robots, circles\n\n" + episodes_note(st, "interaction/") +
           " Each cell: success ± standard error / collisions per episode; steps: mean of successful episodes. Scenes from "
           "`make_interaction_world` (madbp_sim.hpp Section 4b), 100 steps. \"MA-DBP\" is the tuned planner, \"paper's planner\" "
           "the same model with `--preset paper`.\n\n" + t.text() + "\n\\* " + kBarrierNote + "\n";
}

inline std::string fig3b_report(const SuiteConfig& cfg, const SuiteStore& st) {
    MdTable t;
    t.header = {"n", "MAPPO µs/step", "CLF-QP µs/step", "MA-DBP µs/step (plan amortised)", "MA-DBP ms/plan"};
    for (long n : cfg.fig3b_counts) {
        const SuiteRecord* r = ok_record(st, "fig3b/n=" + std::to_string(n));
        t.rows.push_back({std::to_string(n), r ? num_text(r->num("mappo_us"), 2) : "-", r ? num_text(r->num("clfqp_us"), 2) : "-",
                          r ? num_text(r->num("madbp_us"), 1) : "-", r ? num_text(r->num("madbp_plan_ms"), 3) : "-"});
    }
    const SuiteRecord* cell = ok_record(st, "fig3b");
    return "# Fig. 3b: decision time per step, empty map (one run, one thread)\n\n" +
           (cell ? "Measured over " + cell->get("steps") + " steps per team size; MA-DBP replans every " + cell->get("replan") +
                       " steps (its plan time is amortised over them), model " + cell->get("model") + "."
                 : "Not measured yet: " + no_result_text(st, "fig3b") + ".") +
           " Whole team per step. The paper reports 0.04 s per MA-DBP plan on an RTX 3090.\n\n" + t.text();
}
inline void write_fig3b_svg(const SuiteConfig& cfg, const SuiteStore& st, const std::string& path) {
    const char* keys[3] = {"mappo_us", "clfqp_us", "madbp_us"};
    const char* names[3] = {"MAPPO", "CLF-QP", "MA-DBP (plan amortised)"};
    std::vector<ChartSeries> series;
    double lo = 1e300, hi = 0;
    for (int k = 0; k < 3; ++k) {
        ChartSeries s{names[k], series_colour(k), {}};
        for (long n : cfg.fig3b_counts) {
            const SuiteRecord* r = ok_record(st, "fig3b/n=" + std::to_string(n));
            const double v = r ? r->num(keys[k]) : NAN;
            s.xy.push_back({(double)n, v > 0 ? v : NAN});
            if (v > 0) lo = std::min(lo, v), hi = std::max(hi, v);
        }
        series.push_back(s);
    }
    if (!(hi > 0)) lo = 0.1, hi = 1000;
    ChartAxes ax{"decision time per step vs team size (empty map)", "agents n", "µs per step (log)", {}, std::pow(10.0, std::floor(std::log10(lo))),
                 std::pow(10.0, std::ceil(std::log10(hi) + 1e-9)), true};
    for (long n : cfg.fig3b_counts) ax.x_ticks.push_back((double)n);
    write_report(path, svg_page(460, 330, line_chart(ax, series, 0, 0, 460, 330)));
}

// fig3a's totals: MAPPO trained on n, and the MA-DBP pipeline on n/2 (MAPPO on 1..n/2,
// demonstrations, training).
struct Fig3aTotals { double mappo = NAN, demonstrators = NAN, collect = NAN, train = NAN, pipeline = NAN; };
inline Fig3aTotals fig3a_totals(const SuiteStore& st, int n) {
    auto secs = [&](const std::string& id) {
        const SuiteRecord* r = ok_record(st, id);
        return r ? r->num("seconds") : NAN;
    };
    Fig3aTotals t;
    t.mappo = secs("fig3a/mappo/k=" + std::to_string(n));
    t.demonstrators = 0;
    for (int k = 1; k <= n / 2; ++k) t.demonstrators += secs("fig3a/mappo/k=" + std::to_string(k));
    t.collect = secs("fig3a/collect/n=" + std::to_string(n));
    t.train = secs("fig3a/train/n=" + std::to_string(n));
    t.pipeline = t.demonstrators + t.collect + t.train;
    return t;
}
inline std::string fig3a_report(const SuiteConfig& cfg, const SuiteStore& st, const std::vector<SuiteCell>& cells) {
    MdTable stages;
    stages.header = {"stage", "seconds", "details"};
    for (const SuiteCell& c : cells) {
        if (c.group != "fig3a" || c.base.get("stage") == "eval") continue;
        const SuiteRecord* r = ok_record(st, c.id);
        if (!r) {
            stages.rows.push_back({c.id, no_result_text(st, c.id), ""});
            continue;
        }
        const std::string stage = r->get("stage");
        std::string details = stage == "mappo"     ? "iterations " + r->get("iterations") + ", last rollout success " + rate_text(r->num("train_success"))
                              : stage == "collect" ? "kept " + r->get("kept") + " of " + r->get("asked") + " episodes"
                                                   : r->get("steps") + " steps, validation loss " + num_text(r->num("val_loss"), 4);
        stages.rows.push_back({c.id, num_text(r->num("seconds"), 1), details});
    }
    MdTable sum;
    sum.header = {"n", "MAPPO(n) s", "MA-DBP(n/2) pipeline s", "= MAPPO 1..n/2 + collect + train", "MAPPO time / pipeline time",
                  "MAPPO(n) success at n", "MA-DBP(n/2) success at n"};
    for (int n : cfg.fig3a_counts) {
        const Fig3aTotals t = fig3a_totals(st, n);
        const std::string sn = std::to_string(n);
        sum.rows.push_back({sn, num_text(t.mappo, 1), num_text(t.pipeline, 1),
                            num_text(t.demonstrators, 1) + " + " + num_text(t.collect, 1) + " + " + num_text(t.train, 1),
                            num_text(t.mappo / t.pipeline, 2), eval_text(st, "fig3a/eval/mappo/n=" + sn), eval_text(st, "fig3a/eval/madbp/n=" + sn)});
    }
    // The threads the stages were timed with, as recorded (stores before 2026-12-04 lack it: this run's).
    std::string threads = std::to_string(cfg.threads);
    if (const SuiteRecord* r = ok_record(st, "fig3a/mappo/k=1"); r && !r->get("threads").empty()) threads = r->get("threads");
    return "# Fig. 3a: training time, MAPPO on n agents against MA-DBP trained on n/2 (empty map)\n\n"
           "Everything timed in-process on this machine, " + threads + " threads. MA-DBP's time includes its "
           "demonstrators' training (MAPPO on 1..n/2 agents, each trained once and shared by both n), the demonstrations and "
           "its own training (" + std::to_string(cfg.fig3a_madbp_steps) + " steps, batch " + std::to_string(cfg.fig3a_batch) +
           "; " + std::to_string(cfg.fig3a_collect_episodes) + " demonstrations per team size). Success: success ± se / "
           "collisions at n. The paper reports up to 4x less training time for MA-DBP at n = 8. Files: " + fig3a_dir(cfg) + "/.\n\n" +
           sum.text() + "\n## Stages\n\n" + stages.text();
}
inline void write_fig3a_svg(const SuiteConfig& cfg, const SuiteStore& st, const std::string& path) {
    // Per n: one MAPPO bar and one stacked MA-DBP bar (demonstrators, collect, train).
    double hi = 1;
    std::vector<Fig3aTotals> totals;
    for (int n : cfg.fig3a_counts) {
        totals.push_back(fig3a_totals(st, n));
        for (double v : {totals.back().mappo, totals.back().pipeline}) if (v == v) hi = std::max(hi, v);
    }
    const double px = 60, py = 40, ph = 240, bar = 50, gap = 40;
    const double W = px + cfg.fig3a_counts.size() * (2 * bar + gap) + 200;
    auto Y = [&](double v) { return py + ph * (1 - v / hi); };
    std::string s = svg_text(px, 20, "Fig. 3a: training time (s) and success at n, empty map", " font-weight='bold'");
    s += "<line x1='" + svg_num(px) + "' x2='" + svg_num(W - 200) + "' y1='" + svg_num(py + ph) + "' y2='" + svg_num(py + ph) + "' stroke='#888'/>\n";
    const char* colours[4] = {"#1f77b4", "#aec7e8", "#ffbb78", "#ff7f0e"};
    for (size_t i = 0; i < totals.size(); ++i) {
        const Fig3aTotals& t = totals[i];
        const double x = px + 10 + i * (2 * bar + gap);
        const std::string sn = std::to_string(cfg.fig3a_counts[i]);
        auto rect = [&](double bx, double v0, double v1, const char* col) {
            if (!(v1 == v1) || !(v0 == v0)) return;
            s += "<rect x='" + svg_num(bx) + "' y='" + svg_num(Y(v1)) + "' width='" + svg_num(bar - 4) + "' height='" +
                 svg_num(Y(v0) - Y(v1)) + "' fill='" + col + "'/>\n";
        };
        rect(x, 0, t.mappo, colours[0]);
        rect(x + bar, 0, t.demonstrators, colours[1]);
        rect(x + bar, t.demonstrators, t.demonstrators + t.collect, colours[2]);
        rect(x + bar, t.demonstrators + t.collect, t.pipeline, colours[3]);
        s += svg_text(x, py + ph + 14, "MAPPO(" + sn + ")") + svg_text(x + bar, py + ph + 14, "MA-DBP(" + std::to_string(cfg.fig3a_counts[i] / 2) + ")");
        s += svg_text(x, py + ph + 28, "success " + rate_text(success_of(st, "fig3a/eval/mappo/n=" + sn))) +
             svg_text(x + bar, py + ph + 42, "success " + rate_text(success_of(st, "fig3a/eval/madbp/n=" + sn)));
        if (t.mappo == t.mappo) s += svg_text(x, Y(t.mappo) - 4, num_text(t.mappo, 0) + " s");
        if (t.pipeline == t.pipeline) s += svg_text(x + bar, Y(t.pipeline) - 4, num_text(t.pipeline, 0) + " s");
    }
    const char* names[4] = {"MAPPO trained on n", "MA-DBP: MAPPO on 1..n/2", "MA-DBP: demonstrations", "MA-DBP: training"};
    for (int k = 0; k < 4; ++k) {
        s += "<rect x='" + svg_num(W - 190) + "' y='" + svg_num(py + 16.0 * k) + "' width='12' height='12' fill='" + colours[k] + "'/>\n";
        s += svg_text(W - 172, py + 16.0 * k + 10, names[k]);
    }
    s += svg_text(px, py - 6, "0 .. " + num_text(hi, 0) + " s");
    write_report(path, svg_page(W, py + ph + 60, s));
}

inline std::string pictures_report(const SuiteConfig& cfg, const SuiteStore& st, const std::vector<SuiteCell>& cells) {
    std::string md;
    for (const SuiteCell& c : cells) {
        if (c.group != "pictures") continue;
        const SuiteRecord* r = ok_record(st, c.id);
        md += "- " + c.id.substr(9) + ": " +
              (r ? "[" + r->get("file") + "](" + r->get("file") + ") (MA-DBP, " + r->get("map") + ", seed 0, " +
                       (r->num("success") > 0 ? "success in " + r->get("steps") + " steps" : std::string("failed")) + ", " +
                       r->get("collisions") + " collisions)"
                 : no_result_text(st, c.id)) +
              "\n";
    }
    return md;
}

// Writes every report from the store.
inline void write_suite_reports(const SuiteConfig& cfg, const std::vector<SuiteCell>& cells, const SuiteStore& st) {
    const std::string& o = cfg.out;
    for (const std::string& g : suite_groups()) {  // CSV: every record of the group, in cell order
        std::vector<const SuiteRecord*> recs;
        for (const SuiteCell& c : cells) {
            if (c.group != g) continue;
            if (g == "fig3b")  // its per-n rows
                for (long n : cfg.fig3b_counts) {
                    auto row = st.find("fig3b/n=" + std::to_string(n));
                    if (row != st.end()) recs.push_back(&row->second);
                }
            auto it = st.find(c.id);
            if (it != st.end()) recs.push_back(&it->second);
        }
        if (g != "pictures") write_group_csv(o + "/" + g + ".csv", recs);
    }
    write_report(o + "/table1.md", table1_report(cfg, st));
    write_report(o + "/fig4.md", fig4_report(cfg, st));
    write_fig4_svg(cfg, st, o + "/fig4.svg");
    write_report(o + "/table2.md", table2_report(cfg, st));
    write_report(o + "/horizon.md", horizon_report(cfg, st));
    write_horizon_svg(cfg, st, o + "/horizon.svg");
    write_report(o + "/dynamic.md", dynamic_report(cfg, st));
    write_report(o + "/large.md", large_report(cfg, st));
    write_report(o + "/interaction.md", interaction_report(cfg, st));
    write_report(o + "/fig3b.md", fig3b_report(cfg, st));
    write_fig3b_svg(cfg, st, o + "/fig3b.svg");
    write_report(o + "/fig3a.md", fig3a_report(cfg, st, cells));
    write_fig3a_svg(cfg, st, o + "/fig3a.svg");

    std::map<std::string, std::map<std::string, int>> counts;  // group -> state -> cells
    for (const SuiteCell& c : cells) {
        auto it = st.find(c.id);
        counts[c.group][suite_done(st, c) ? "done" : it == st.end() ? "not run" : it->second.status]++;
    }
    std::string md = "# Evaluation suite results (`madbp eval --suite paper`)\n\nRegenerated from `cells.tsv` (one line per "
                     "finished cell) after every run; see docs/evaluation.md.\n\n";
    MdTable t;
    t.header = {"group", "report", "data", "chart", "cells"};
    const std::set<std::string> charts = {"fig4", "horizon", "fig3b", "fig3a"};
    for (const std::string& g : suite_groups()) {
        if (g == "pictures") continue;
        std::string state;
        for (auto& kv : counts[g]) state += (state.empty() ? "" : ", ") + std::to_string(kv.second) + " " + kv.first;
        t.rows.push_back({g, "[" + g + ".md](" + g + ".md)", "[" + g + ".csv](" + g + ".csv)",
                          charts.count(g) ? "[" + g + ".svg](" + g + ".svg)" : "-", state});
    }
    md += t.text() + "\n## Pictures\n\n" + pictures_report(cfg, st, cells);
    write_report(o + "/index.md", md);
}

// =============================================================================================
// The run
// =============================================================================================

struct SuiteSummary {
    int run = 0, skipped = 0, missing = 0, errors = 0;  // run: cells executed (ok or error)
    double seconds = 0;
};

inline void validate_suite_config(const SuiteConfig& cfg) {
    if (cfg.shard_count < 1 || cfg.shard_index < 0 || cfg.shard_index >= cfg.shard_count)
        throw std::invalid_argument("--shard: expected i/N with 0 <= i < N");
    if (cfg.episodes < 1) throw std::invalid_argument("--episodes: must be >= 1");
    if (cfg.threads < 1) throw std::invalid_argument("--threads: must be >= 1");
    for (int n : cfg.fig3a_counts) {
        if (n < 2 || n % 2) throw std::invalid_argument("fig3a: team sizes must be even and >= 2 (got " + std::to_string(n) + ")");
        fig3a_mappo_iterations(n);
        for (int k = 1; k <= n / 2; ++k) fig3a_mappo_iterations(k);
    }
    for (auto& maps : {cfg.fig4_maps, cfg.dynamic_maps, cfg.large_maps})
        for (const std::string& m : maps) {
            madbp::Rng probe(0);
            madbp::make_map(m, probe);  // an unknown name fails before any work
        }
}

inline int run_suite(const SuiteConfig& cfg, SuiteSummary* summary_out = nullptr) {
    validate_suite_config(cfg);
    const std::string store_path = cfg.out + "/cells.tsv";
    const std::vector<SuiteCell> cells = suite_cells(cfg);
    SuiteStore store = load_suite_store(store_path);
    if (cfg.list) {
        for (size_t i = 0; i < cells.size(); ++i) {
            const SuiteCell& c = cells[i];
            if (!suite_selected(cfg, c)) continue;
            auto it = store.find(c.id);
            const std::string state = suite_done(store, c) ? "done" : it == store.end() ? "todo" : it->second.status;
            std::printf("%4zu %4d  %-8s %s%s\n", i, c.unit, state.c_str(), c.id.c_str(),
                        state == "missing" || state == "error" ? ("  (" + it->second.why() + ")").c_str() : "");
        }
        return 0;
    }
    make_dirs(fig3a_dir(cfg));  // and cfg.out
    std::vector<const SuiteCell*> todo;
    SuiteSummary sum;
    for (const SuiteCell& c : cells) {
        if (!suite_selected(cfg, c)) continue;
        if (suite_done(store, c)) sum.skipped++;
        else todo.push_back(&c);
    }
    const bool tty = isatty(fileno(stderr));
    const auto t0 = std::chrono::steady_clock::now();
    for (size_t i = 0; i < todo.size(); ++i) {
        const SuiteCell& c = *todo[i];
        const auto t_cell = std::chrono::steady_clock::now();
        std::vector<SuiteRecord> recs = run_suite_cell(c);
        const SuiteRecord& own = recs.back();
        auto prev = store.find(c.id);
        // A cell still missing for the same reason adds no line (reruns do not grow the store).
        const bool same_as_before = own.status == "missing" && prev != store.end() && prev->second.status == "missing" &&
                                    prev->second.why() == own.why();
        if (!same_as_before)
            for (const SuiteRecord& r : recs) {
                append_suite_record(store_path, r);
                store[r.id] = r;
            }
        if (own.status == "missing") sum.missing++;
        else sum.run++;
        if (own.status == "error") {
            sum.errors++;
            std::fprintf(stderr, "suite: %s failed: %s\n", c.id.c_str(), own.why().c_str());
        }
        if (cfg.json) {
            for (const SuiteRecord& r : recs) std::printf("%s\n", r.json().c_str());
            std::fflush(stdout);
        }
        if (tty) {
            const double elapsed = seconds_since(t0), per_cell = elapsed / (i + 1);
            std::fprintf(stderr, "suite %zu/%zu  %-40s %-7s %6.1f s  %.2f cells/min  ETA %.0f min\n", i + 1, todo.size(), c.id.c_str(),
                         own.status.c_str(), seconds_since(t_cell), 60 / std::max(per_cell, 1e-9),
                         per_cell * (todo.size() - i - 1) / 60);
        }
    }
    write_suite_reports(cfg, cells, load_suite_store(store_path));  // with other shards' lines
    sum.seconds = seconds_since(t0);
    std::printf("suite: %d cells run, %d skipped (done), %d missing, %d errors in %.1f s; reports in %s/index.md\n", sum.run,
                sum.skipped, sum.missing, sum.errors, sum.seconds, cfg.out.c_str());
    if (summary_out) *summary_out = sum;
    return sum.errors ? 1 : 0;
}

// `madbp eval --suite paper [options]`.
inline int cmd_suite(Args& a) {
    if (a.flag("--help")) {
        std::printf("%s", kSuiteHelp);
        return 0;
    }
    SuiteConfig c = read_suite_options(a);
    a.finish();
    return run_suite(c);
}

}  // namespace madbp_cli
