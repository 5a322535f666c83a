// limits_helpers.hpp - what the tests of hostile inputs share (test_limits.cpp, issue 15;
// test_trust.cpp, issue 48; test_checkpoint.cpp, test_movingai.cpp): messages, temporary directories, a forked child under a memory
// cap, small valid model and dataset files.
#pragma once
#include "madbp_train.hpp"
#include "tiny_model.hpp"

#include <doctest/doctest.h>

#include <dirent.h>
#include <functional>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

using namespace madbp;

#if defined(__SANITIZE_ADDRESS__)
#define MADBP_TEST_ASAN 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MADBP_TEST_ASAN 1
#endif
#endif

inline bool contains(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

// The message `fn` throws ("" when it returns).
inline std::string error_of(const std::function<void()>& fn) {
    try {
        fn();
    } catch (const std::exception& e) {
        return e.what();
    }
    return "";
}

// A fresh directory under /tmp, removed with its files at scope exit.
struct TempDir {
    std::string path;
    TempDir() {
        char tmpl[] = "/tmp/madbp_limits_XXXXXX";
        REQUIRE(mkdtemp(tmpl) != nullptr);
        path = tmpl;
    }
    ~TempDir() {
        for (auto& f : files()) ::unlink((path + "/" + f).c_str());
        ::rmdir(path.c_str());
    }
    std::vector<std::string> files() const {  // the names in it, "." and ".." left out
        std::vector<std::string> out;
        if (DIR* d = opendir(path.c_str())) {
            while (dirent* e = readdir(d))
                if (std::string(e->d_name) != "." && std::string(e->d_name) != "..") out.push_back(e->d_name);
            closedir(d);
        }
        return out;
    }
    std::string file(const std::string& name) const { return path + "/" + name; }
};

inline size_t address_space_bytes() {
    long pages = 0;
    if (FILE* f = std::fopen("/proc/self/statm", "r")) {
        if (std::fscanf(f, "%ld", &pages) != 1) pages = 0;
        std::fclose(f);
    }
    return (size_t)pages * (size_t)sysconf(_SC_PAGESIZE);
}

// Runs `fn` in a forked child whose address space may grow by at most `extra_mib` MiB, and
// returns what happened: "ok" or "ok: <what fn returned>", "threw: <message>", "bad_alloc", or
// "died: ..." (the child must not use OpenMP: a forked libgomp can hang).
inline std::string capped(size_t extra_mib, const std::function<std::string()>& fn) {
    int fds[2];
    REQUIRE(::pipe(fds) == 0);
    const pid_t pid = ::fork();
    REQUIRE(pid >= 0);
    if (pid == 0) {
        ::close(fds[0]);
#ifndef MADBP_TEST_ASAN
        const rlim_t cap = (rlim_t)(address_space_bytes() + (extra_mib << 20));
        rlimit lim{cap, cap};
        ::setrlimit(RLIMIT_AS, &lim);
#endif
        std::string out;
        try {
            const std::string r = fn();
            out = r.empty() ? "ok" : "ok: " + r;
        } catch (const std::bad_alloc&) {
            out = "bad_alloc";
        } catch (const std::exception& e) {
            out = std::string("threw: ") + e.what();
        }
        for (size_t done = 0; done < out.size();) {
            const ssize_t w = ::write(fds[1], out.data() + done, out.size() - done);
            if (w <= 0) break;
            done += (size_t)w;
        }
        ::_exit(0);
    }
    ::close(fds[1]);
    std::string out;
    char buf[4096];
    for (ssize_t got; (got = ::read(fds[0], buf, sizeof buf)) > 0;) out.append(buf, (size_t)got);
    ::close(fds[0]);
    int status = 0;
    ::waitpid(pid, &status, 0);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0)
        out += "died: " + (WIFSIGNALED(status) ? "signal " + std::to_string(WTERMSIG(status)) : "exit " + std::to_string(WEXITSTATUS(status)));
    return out;
}

// A small valid model file whose metadata is then rewritten with `changes`.
inline std::string model_with(const TempDir& dir, const std::string& name, const std::map<std::string, std::string>& changes) {
    const std::string path = dir.file(name);
    save_model(path, MadbpModel(tiny_config(), 1));
    SafeTensors st = load_safetensors(path);
    for (auto& kv : changes) st.metadata[kv.first] = kv.second;
    save_safetensors(path, st.tensors, st.metadata);
    return path;
}

// One episode: 1 agent, 2 steps, an empty 1.2 world; valid as built.
inline DemoSet one_episode() {
    Demonstration d;
    d.map_name = "empty";
    d.map.half_size = 1.2;
    d.agents = 1;
    d.steps = 2;
    d.success = true;
    d.goals = {{0.5, 0.5}};
    d.pos = {{0, 0}, {0.02, 0.02}, {0.05, 0.05}};
    d.vel = {{0, 0}, {0.2, 0.2}, {0.3, 0.3}};
    d.act = {{1, 1}, {1, 1}};
    DemoSet set;
    set.demonstrator = "test";
    set.episodes.push_back(d);
    return set;
}

