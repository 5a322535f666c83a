// Tests of files you can trust (issue 48, docs/limits.md): safe writes, honest exit codes,
// bounded reads, strict flags and plausible inputs; one test case per cause the issue found,
// each failing on the code before it. The whole file runs in about a second.
#include "limits_helpers.hpp"
#include "methods.hpp"  // the tool's Args, claim_outputs, check_written

#include <csignal>
#include <thread>
#include <fcntl.h>
#include <sys/stat.h>

using madbp_cli::Args;

namespace {

std::string read_text(const std::string& path) {
    std::string text;
    detail::read_bounded(path, 1 << 20, "test", text);
    return text;
}

mode_t mode_of(const std::string& path) {
    struct stat sb;
    REQUIRE(::lstat(path.c_str(), &sb) == 0);
    return sb.st_mode;
}

// What `fn` does in a forked child: "ok", or the message it throws prefixed by "runtime: " or
// "environment: " (an EnvironmentError). The child forgets the parent's output locks, as
// another run would not have them.
std::string in_child(const std::function<void()>& fn) {
    return capped(256, [&] {
        detail::held_locks().clear();
        try {
            fn();
        } catch (const EnvironmentError& e) {
            return std::string("environment: ") + e.what();
        }
        return std::string();
    });
}

}  // namespace

TEST_CASE("trust: --out naming a device, a FIFO or a directory is refused, the target untouched") {
    TempDir dir;
    const std::string fifo = dir.file("fifo"), sub = dir.file("sub");
    REQUIRE(::mkfifo(fifo.c_str(), 0644) == 0);
    REQUIRE(::mkdir(sub.c_str(), 0755) == 0);
    // Before: the FIFO (or /dev/null, as root) was replaced by a regular file.
    CHECK(contains(error_of([&] { write_text_file(fifo, "x"); }), "fifo: is a device, FIFO or socket, not a regular file to write"));
    CHECK(S_ISFIFO(mode_of(fifo)));
    CHECK(contains(error_of([&] { write_text_file(sub, "x"); }), "sub: is a directory"));
    CHECK(S_ISDIR(mode_of(sub)));
    CHECK(contains(error_of([] { write_text_file("/dev/null", "x"); }), "/dev/null: is a device"));
    CHECK(S_ISCHR(mode_of("/dev/null")));
    ::rmdir(sub.c_str());
}

TEST_CASE("trust: a symlink at OUT.tmp is not followed; a symlink at OUT is refused") {
    TempDir dir;
    const std::string out = dir.file("out.svg"), victim = dir.file("victim");
    write_text_file(victim, "keep");
    REQUIRE(::symlink(victim.c_str(), (out + ".tmp").c_str()) == 0);
    write_text_file(out, "new");  // before: wrote "new" into the victim through out.svg.tmp
    CHECK(read_text(victim) == "keep");
    CHECK(read_text(out) == "new");
    CHECK(S_ISLNK(mode_of(out + ".tmp")));
    const std::string link = dir.file("link.svg");
    REQUIRE(::symlink(victim.c_str(), link.c_str()) == 0);
    CHECK(contains(error_of([&] { write_text_file(link, "x"); }), "link.svg: is a symbolic link"));
    CHECK(read_text(victim) == "keep");
    CHECK(S_ISLNK(mode_of(link)));
}

TEST_CASE("trust: a read-only output is refused; an existing output keeps its mode") {
    TempDir dir;
    const std::string out = dir.file("model.safetensors");
    write_text_file(out, "old");
    REQUIRE(::chmod(out.c_str(), 0444) == 0);
    // Before: silently replaced, mode reset to 0644 (root passes access(W_OK): the mode decides).
    CHECK(contains(error_of([&] { write_text_file(out, "new"); }), "is read-only"));
    CHECK(read_text(out) == "old");
    REQUIRE(::chmod(out.c_str(), 0640) == 0);
    write_text_file(out, "new");
    CHECK(read_text(out) == "new");
    CHECK((mode_of(out) & 07777) == 0640);
    // No temporary or lock file is left behind.
    CHECK(error_of([&] { read_text(out + ".lock"); }) != "");
}

TEST_CASE("trust: a second run writing the same output is told that another run writes it") {
    TempDir dir;
    const std::string out = dir.file("model.safetensors");
    OutputLock held(out);          // this process: the run that writes it
    write_text_file(out, "mine");  // locks on one output nest within a process
    // Before: both runs shared out.tmp; one died after its work, or one result silently won.
    const std::string r = in_child([&] { write_text_file(out, "theirs"); });
    CHECK(contains(r, "model.safetensors: another run is writing it"));
    CHECK(read_text(out) == "mine");
    const std::string r2 = in_child([&] { OutputLock again(out); });
    CHECK(contains(r2, "another run is writing it"));
}

TEST_CASE("trust: released, the lock lets the next run write; its lock file is gone") {
    TempDir dir;
    const std::string out = dir.file("demos.bin");
    { OutputLock held(out); }
    CHECK(in_child([&] { write_text_file(out, "next"); }) == "ok");
    CHECK(read_text(out) == "next");
    struct stat sb;
    CHECK(::lstat((out + ".lock").c_str(), &sb) != 0);
}

TEST_CASE("trust: a write the disk refuses is an EnvironmentError and leaves the old file") {
    TempDir dir;
    const std::string out = dir.file("big.csv");
    write_text_file(out, "old");
    // RLIMIT_FSIZE stands in for a full disk: write() fails (EFBIG) part-way.
    const std::string r = in_child([&] {
        std::signal(SIGXFSZ, SIG_IGN);
        rlimit lim{1000, 1000};
        ::setrlimit(RLIMIT_FSIZE, &lim);
        write_text_file(out, std::string(100000, 'x'));
    });
    CHECK(contains(r, "environment: "));
    CHECK(contains(r, "write failed"));
    CHECK(read_text(out) == "old");
    DIR* d = opendir(dir.path.c_str());
    int files = 0;
    while (dirent* e = readdir(d)) files += e->d_name[0] != '.';
    closedir(d);
    CHECK(files == 1);  // no temporary file left
}

TEST_CASE("trust: train --data X --out X is refused naming both flags") {
    TempDir dir;
    const std::string data = dir.file("demos.bin");
    save_demos(data, one_episode());
    Args a({"--data", data, "--out", data});
    const std::string e = error_of([&] { madbp_cli::claim_outputs(a, {{"--out", data}}, {".train"}); });
    CHECK(contains(e, "--out " + data + " is the same file as --data " + data));
    // Another spelling of the same file, or an input that is a run's sidecar.
    Args b({"--data", dir.path + "/./demos.bin", "--out", dir.file("demos")});
    CHECK(contains(error_of([&] { madbp_cli::claim_outputs(b, {{"--out", dir.file("demos")}}, {".bin"}); }), "is the same file as --data"));
    Args c({"--data", data, "--out", dir.file("model")});
    CHECK(error_of([&] { madbp_cli::claim_outputs(c, {{"--out", dir.file("model")}}, {".train"}); }) == "");
}

TEST_CASE("trust: results written to a full or closed stdout are an EnvironmentError") {
    FILE* full = std::fopen("/dev/full", "w");
    REQUIRE(full != nullptr);
    std::fprintf(full, "method map n success\n");
    bool environment = false;
    try {
        madbp_cli::check_written(full);
    } catch (const EnvironmentError& e) {
        environment = contains(e.what(), "cannot write the results to standard output");
    }
    CHECK(environment);
    std::fclose(full);
}

namespace {
// A two-step training run of the tiny model into `out` (its .train, .csv beside it).
TrainConfig tiny_run(const std::string& out, long steps) {
    TrainConfig tc;
    tc.out = out;
    tc.steps = steps;
    tc.batch = 2;
    tc.threads = 1;
    tc.checkpoint_every = 1;
    tc.log_every = 1;
    tc.val_batches = 1;
    return tc;
}
// The state file of `out` with `changes` in its metadata.
void edit_state(const std::string& out, const std::map<std::string, std::string>& changes) {
    SafeTensors st = load_safetensors(out + ".train");
    for (auto& kv : changes) st.metadata[kv.first] = kv.second;
    save_safetensors(out + ".train", st.tensors, st.metadata);
}
// Trains the tiny model 2 steps into `out`; returns the config that resumes it.
TrainConfig trained_two_steps(const std::string& out) {
    MadbpModel model(tiny_config(), 1);
    train(one_episode(), model, tiny_run(out, 2));
    TrainConfig again = tiny_run(out, 2);
    again.resume = true;
    return again;
}
}  // namespace

TEST_CASE("trust: a training state past --steps is an error, not a summary without a model") {
    TempDir dir;
    const std::string out = dir.file("m.safetensors");
    const DemoSet demos = one_episode();
    const TrainConfig again = trained_two_steps(out);
    MadbpModel m2(tiny_config(), 1);
    CHECK(train(demos, m2, again).steps == 2);  // at its last step: nothing left to do, fine
    // The state of a longer run with this one's identity (the identity holds --steps for
    // MA-DBP and MADiff; a MAPPO run may ask for fewer iterations).
    edit_state(out, {{"train.step", "5"}, {"optim.adam.step", "5"}});
    CHECK_THROWS_WITH_AS(train(demos, m2, again), doctest::Contains("m.safetensors.train: the training state is at step 5, past this run's last step 2"),
                         std::invalid_argument);
}

TEST_CASE("trust: inconsistent optimiser state (Adam step != train step, NaN smoothing) is refused on resume") {
    TempDir dir;
    const std::string out = dir.file("m.safetensors");
    const DemoSet demos = one_episode();
    const TrainConfig again = trained_two_steps(out);
    edit_state(out, {{"optim.adam.step", "7"}});
    MadbpModel m2(tiny_config(), 1);
    CHECK(contains(error_of([&] { train(demos, m2, again); }), "'optim.adam.step'] = 7 does not match train.step = 2"));
    edit_state(out, {{"optim.adam.step", "2"}, {"train.smooth", "nan 0 0 0 0"}});
    CHECK(contains(error_of([&] { train(demos, m2, again); }), "'train.smooth'] is not 5 finite numbers"));
    edit_state(out, {{"train.smooth", "1 1 1 1 1"}});
    CHECK(train(demos, m2, again).steps == 2);
}

TEST_CASE("trust: mappo --resume with fewer --iterations than its state is an error") {
    TempDir dir;
    MappoConfig c;
    c.out = dir.file("p.safetensors");
    c.iterations = 2;
    c.worlds = 1;
    c.threads = 1;
    c.checkpoint_every = 1;
    train_mappo(c);
    c.resume = true;
    c.iterations = 1;
    CHECK(contains(error_of([&] { train_mappo(c); }), "the training state is at step 2, past this run's last step 1"));
    c.iterations = 3;
    CHECK(train_mappo(c).iterations == 3);  // the Adam step count matches epochs x minibatches per iteration
}

TEST_CASE("trust: yes | madbp train --data /dev/stdin stops at the signature, not after 1 GiB") {
    // Before: the whole pipe was read up to kMaxDatasetBytes first (1.8 GB resident).
    const std::string r = capped(64, [] {
        int fds[2];
        if (::pipe(fds) != 0) return std::string("no pipe");
        std::signal(SIGPIPE, SIG_IGN);
        std::thread yes([w = fds[1]] {
            const std::string line(4096, 'y');
            while (::write(w, line.data(), line.size()) > 0) {}
            ::close(w);
        });
        std::string e = error_of([&] { load_demos("/proc/self/fd/" + std::to_string(fds[0])); });
        ::close(fds[0]);  // the writer sees EPIPE and stops
        yes.join();
        return e;
    });
    CHECK(contains(r, "not a madbp dataset (magic 'MADBPDS1' missing)"));
}

namespace {
// The message reading `key` from `args` with `read` throws ("" when it returns).
std::string flag_error(std::vector<std::string> args, const std::function<void(Args&)>& read) {
    Args a(args);
    return error_of([&] { read(a); });
}
}  // namespace

TEST_CASE("trust: a trailing or empty list item (--agents 2, --maps empty, --channels 32,) is an error") {
    auto agents = [](Args& a) { a.integers("--agents", "2,4,6", 1, 64); };
    CHECK(contains(flag_error({"--agents", "2,"}, agents), "--agents: empty item in '2,'"));
    CHECK(contains(flag_error({"--agents", ",2"}, agents), "empty item"));
    CHECK(contains(flag_error({"--agents", "2,,4"}, agents), "empty item"));
    CHECK(flag_error({"--agents", "2,4"}, agents) == "");
    CHECK(contains(error_of([] { madbp_cli::split("empty,", "--maps"); }), "--maps: empty item in 'empty,'"));
    CHECK(contains(error_of([] { madbp_cli::parse_scenario_mix("swap:0.2,"); }), "--scenarios: empty item"));
}

TEST_CASE("trust: a flag given twice is an error naming it, except a repeatable one read with all()") {
    CHECK(contains(flag_error({"--episodes", "5", "--episodes", "7"}, [](Args& a) { a.integer("--episodes", 1); }),
                   "--episodes: given 2 times; give it once"));
    CHECK(contains(flag_error({"--json", "--json"}, [](Args& a) { a.flag("--json"); }), "--json: given 2 times"));
    CHECK(contains(flag_error({"--out=a", "--out", "b"}, [](Args& a) { a.str("--out", ""); }), "--out: given 2 times"));
    Args a({"--set", "a.b=1", "--set", "c.d=2"});
    CHECK(a.all("--set") == std::vector<std::string>{"a.b=1", "c.d=2"});
    CHECK(error_of([&] { a.finish(); }) == "");
}

TEST_CASE("trust: range errors print the range; 1e309 and 10^23 are out of range, not 'not a number'") {
    auto half = [](Args& a) { a.real("--half-size", 1.2, 0.6, 100); };
    CHECK(contains(flag_error({"--half-size", "500"}, half), "--half-size: 500 is out of range [0.6, 100]"));
    CHECK(contains(flag_error({"--half-size", "1e309"}, half), "--half-size: 1e309 is out of range [0.6, 100]"));
    CHECK(contains(flag_error({"--half-size", "abc"}, half), "expected a number"));
    auto episodes = [](Args& a) { a.integer("--episodes", 1, 1, 1000000); };
    CHECK(contains(flag_error({"--episodes", "100000000000000000000000"}, episodes), "is out of range [1, 1000000]"));
    CHECK(contains(flag_error({"--episodes", "4000000000"}, episodes), "4000000000 is out of range [1, 1000000]"));
    CHECK(contains(flag_error({"--weights", "1,1e309"}, [](Args& a) { a.reals("--weights", "", 0, 1e6); }), "1e309 is out of range [0, 1e+06]"));
}

TEST_CASE("trust: escape bytes and 100 KB values are escaped and cut in messages") {
    const std::string evil = "a\033[2J\033]0;owned\007b";
    const std::string e = flag_error({"--episodes", evil}, [](Args& a) { a.integer("--episodes", 1); });
    CHECK(contains(e, "a\\x1b[2J\\x1b]0;owned\\x07b"));
    CHECK(e.find('\033') == std::string::npos);
    const std::string big(100000, 'x');
    const std::string e2 = flag_error({"--agents", big}, [](Args& a) { a.integers("--agents", "2", 1, 64); });
    CHECK(e2.size() < 200);
    CHECK(contains(e2, "..."));
    CHECK(contains(flag_error({"--bogus\033", "1"}, [](Args& a) { a.finish(); }), "unknown option --bogus\\x1b"));
}

TEST_CASE("trust: an empty dataset names its file; all-zero loss weights are refused") {
    TempDir dir;
    const std::string path = dir.file("none.bin");
    save_demos(path, DemoSet{});
    CHECK(contains(error_of([&] { madbp_cli::load_training_data(path, 6); }), "none.bin: the dataset has no episodes"));
    TrainConfig tc = tiny_run(dir.file("m"), 1);
    tc.loss_weights = {0, 0, 0, 0};
    MadbpModel model(tiny_config(), 1);
    CHECK(contains(error_of([&] { train(one_episode(), model, tc); }), "loss_weights are all 0"));
}

TEST_CASE("trust: dataset velocities, actions and map names must be plausible") {
    auto refused = [](const std::function<void(Demonstration&)>& change) {
        DemoSet set = one_episode();
        change(set.episodes[0]);
        return error_of([&] { validate_demos(set); });
    };
    CHECK(refused([](Demonstration&) {}) == "");
    // Before: 1e30 set MADiff's normaliser to 2.5e30; actions of 1e12 and "empTy" passed.
    CHECK(contains(refused([](Demonstration& d) { d.vel[1] = {1e30, 0}; }), "vel[1] = (1e+30, 0): speed above kMaxDatasetSpeed = 10"));
    CHECK(contains(refused([](Demonstration& d) { d.act[0] = {0, 1e12}; }), "act[0] = (0, 1e+12) outside the action bound kMaxDatasetAction = 1"));
    CHECK(contains(refused([](Demonstration& d) { d.map_name = "empTy"; }), "map name 'empTy' is not MAP or MAP/SCENARIO"));
    CHECK(contains(refused([](Demonstration& d) { d.map_name = "empty/sWap"; }), "map name 'empty/sWap'"));
    CHECK(refused([](Demonstration& d) { d.map_name = "barrier/corridor"; }) == "");
    CHECK(refused([](Demonstration& d) { d.act[0] = {1, -1}; }) == "");
}

TEST_CASE("trust: a MADiff checkpoint with swapped or huge norm.lo / norm.hi is refused") {
    TempDir dir;
    const std::string path = dir.file("madiff.safetensors");
    MadiffConfig mc;
    mc.channels = {8, 8};
    mc.dim = 8;
    mc.inv_hidden = 8;
    mc.heads = 2;
    MadiffModel model(mc);
    Vec lo = Vec::Constant(kMappoObs, -1.5f), hi = Vec::Constant(kMappoObs, 1.5f);
    model.set_limits(lo, hi);
    save_madiff(path, model);
    CHECK(error_of([&] { load_madiff(path); }) == "");
    SafeTensors st = load_safetensors(path);
    auto tensor = [&](const char* name) -> NamedTensor& {
        for (NamedTensor& t : st.tensors)
            if (t.name == name) return t;
        FAIL("no tensor " << name);
        return st.tensors[0];
    };
    std::swap(tensor("norm.lo").data, tensor("norm.hi").data);
    save_safetensors(path, st.tensors, st.metadata);
    CHECK(contains(error_of([&] { load_madiff(path); }), "norm.lo[0] = 1.5, norm.hi[0] = -1.5: needs lo < hi"));
    std::swap(tensor("norm.lo").data, tensor("norm.hi").data);
    tensor("norm.hi").data[3] = 2.5e30f;
    save_safetensors(path, st.tensors, st.metadata);
    CHECK(contains(error_of([&] { load_madiff(path); }), "norm.hi[3] = 2.5e+30: needs lo < hi within +-kMaxMadiffLimit = 1000"));
}

TEST_CASE("trust: checkpoint lengths (position_scale, local_extent, ...) of 1e30 or 1e-30 are refused") {
    TempDir dir;
    CHECK(error_of([&] { load_model(model_with(dir, "ok.safetensors", {})); }) == "");
    for (const char* field : {"position_scale", "local_extent", "window_scale", "subgoal_distance"})
        for (const char* value : {"1e30", "1e-30"}) {
            const std::string e = error_of([&] { load_model(model_with(dir, "m.safetensors", {{field, value}})); });
            CAPTURE(field);
            CAPTURE(value);
            CHECK(contains(e, std::string(field) + ": "));
            CHECK(contains(e, "is outside [kMinModelLength, kMaxModelLength] = [0.001, 1000] world units"));
        }
    CHECK(error_of([&] { load_model(model_with(dir, "off.safetensors", {{"subgoal_distance", "0"}})); }) == "");
}

TEST_CASE("trust: scene obstacles wholly outside the world, or with numbers like 1e308, are refused") {
    auto scene = [](const std::string& obstacle) {
        return error_of([&] { parse_scene("madbp-scene 1\nworld 1.2\n" + obstacle + "\nagent 0 0 0.5 0.5\n", "s.scene"); });
    };
    CHECK(scene("box -0.1 -1.5 0.1 -1.0") == "");  // partly inside: a wall at the edge
    CHECK(scene("disc 1.25 0 0.1") == "");
    CHECK(contains(scene("box 5 5 6 6"), "s.scene:3: box lies wholly outside the world (half-size 1.2)"));
    CHECK(contains(scene("disc 0 1.5 0.2"), "s.scene:3: disc lies wholly outside the world"));
    CHECK(contains(scene("box 1e307 0 1e308 1"), "'1e307' exceeds the limit kMaxSceneCoordinate = 1000"));
}

TEST_CASE("trust: 0 is no silent 'default' for madiff --sample-steps or --time-budget") {
    // Before: an explicit 0 meant the model's sample steps, or no budget at all.
    CHECK(contains(flag_error({"--sample-steps", "0"}, [](Args& a) { madbp_cli::madiff_method(a, madbp_cli::MethodSetup{}); }),
                   "--sample-steps: 0 is out of range [1, 100000]"));
    CHECK(contains(flag_error({"--time-budget", "0"}, [](Args& a) { madbp_cli::cmd_madiff(a); }), "--time-budget: 0 is out of range [0.001, 1e+09]"));
    CHECK(contains(flag_error({"--time-budget", "0"}, [](Args& a) { madbp_cli::cmd_mappo(a); }), "--time-budget: 0 is out of range"));
}

TEST_CASE("trust: mappo's reward flags refuse a penalty given as a reward") {
    CHECK(contains(flag_error({"--reward-collision", "1"}, [](Args& a) { madbp_cli::cmd_mappo(a); }), "--reward-collision: 1 is out of range [-1000, 0]"));
    CHECK(contains(flag_error({"--reward-at-goal", "-1"}, [](Args& a) { madbp_cli::cmd_mappo(a); }), "--reward-at-goal: -1 is out of range [0, 1000]"));
}
