// cli_common.hpp - argument parsing and output helpers shared by the madbp command-line tool.
// Not part of the library: the tool's own plumbing.
#pragma once
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <chrono>
#include <cstring>
#include <memory>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "madbp_train.hpp"  // ProgressFn, Curve

namespace madbp_cli {

// A comma-separated list given to flag `key`; an empty list or an empty item ("a,,b", "a,")
// is an error naming the flag.
inline std::vector<std::string> split(const std::string& s, const std::string& key = "list") {
    std::vector<std::string> out;
    size_t start = 0;
    for (size_t comma; start <= s.size(); start = comma + 1) {
        comma = s.find(',', start);
        if (comma == std::string::npos) comma = s.size();
        if (comma == start) throw std::invalid_argument(key + ": empty item in '" + madbp::printable(s) + "'");
        out.push_back(s.substr(start, comma - start));
    }
    return out;
}

// "--key value", "--key=value" and "--flag" arguments. Every key a subcommand reads is
// recorded, so that an unknown flag (a typo) is reported instead of silently ignored: call
// finish() after reading. A value may start with a single '-' (--goal-reach -0.5: then the
// reader's range decides); an empty value (--episodes=, --out "") is an error, never the default.
// A key given twice is an error naming it, except one read with all() (--set a=1 --set b=2).
// Every message that shows a value shows it through madbp::printable (escaped, cut).
struct Args {
    std::map<std::string, std::string> values;                 // the last value of each key
    std::map<std::string, std::vector<std::string>> repeats;   // every value of each key, in order (all())
    std::map<std::string, int> given;                          // how often each key or flag was given
    std::set<std::string> flags, used;
    std::vector<std::string> positional;

    Args(int argc, char** argv, int first = 2) : Args(std::vector<std::string>(argv + std::min(first, argc), argv + argc)) {}
    // Options built in code, e.g. Args({"--model", path}) for a method the suite runs.
    explicit Args(const std::vector<std::string>& args) {
        const size_t n = args.size();
        for (size_t i = 0; i < n; ++i) {
            const std::string& a = args[i];
            if (a.rfind("--", 0) == 0) {
                auto eq = a.find('=');
                std::string key = a, value;
                ++given[eq == std::string::npos ? a : a.substr(0, eq)];
                if (eq != std::string::npos) key = a.substr(0, eq), value = a.substr(eq + 1);
                else if (i + 1 < n && args[i + 1].rfind("--", 0) != 0) value = args[++i];
                else { flags.insert(a); continue; }
                values[key] = value;
                repeats[key].push_back(value);
            } else {
                positional.push_back(a);
            }
        }
    }
    // `key` as a flag or a value is read once: given twice, which one was meant is a guess.
    void once(const std::string& key) {
        used.insert(key);
        auto it = given.find(key);
        if (it != given.end() && it->second > 1)
            throw std::invalid_argument(madbp::printable(key) + ": given " + std::to_string(it->second) + " times; give it once");
    }
    bool flag(const std::string& key) {
        once(key);
        if (values.count(key)) throw std::invalid_argument(key + ": is a flag and takes no value (got '" + madbp::printable(values[key]) + "')");
        return flags.count(key) > 0;
    }
    // Every value of a key that may be given more than once (--set a=1 --set b=2), in order.
    std::vector<std::string> all(const std::string& key) {
        used.insert(key);
        if (flags.count(key)) throw std::invalid_argument(key + ": needs a value");
        auto it = repeats.find(key);
        return it == repeats.end() ? std::vector<std::string>{} : it->second;
    }
    bool has(const std::string& key) const { return values.count(key) || flags.count(key); }
    std::string str(const std::string& key, const std::string& def) {
        once(key);
        if (flags.count(key)) throw std::invalid_argument(key + ": needs a value");
        auto it = values.find(key);
        if (it != values.end() && it->second.empty())
            throw std::invalid_argument(key + ": empty value (give a value, or leave " + key + " out for its default)");
        return it == values.end() ? def : it->second;
    }
    long integer(const std::string& key, long def, long lo = -(1L << 40), long hi = (1L << 40)) {
        std::string s = str(key, "");
        return s.empty() ? def : parse_integer(key, s, lo, hi);
    }
    double real(const std::string& key, double def, double lo = -1e300, double hi = 1e300) {
        std::string s = str(key, "");
        return s.empty() ? def : parse_real(key, s, lo, hi);
    }
    // Comma-separated integers, e.g. --agents 2,4,6.
    std::vector<long> integers(const std::string& key, const std::string& def, long lo = 0, long hi = 1L << 40) {
        std::vector<long> out;
        for (const std::string& item : split(str(key, def), key)) out.push_back(parse_integer(key, item, lo, hi));
        return out;
    }
    // Comma-separated numbers, e.g. --weights .85,.025,.025,.1.
    std::vector<double> reals(const std::string& key, const std::string& def, double lo = -1e300, double hi = 1e300) {
        std::vector<double> out;
        for (const std::string& item : split(str(key, def), key)) out.push_back(parse_real(key, item, lo, hi));
        return out;
    }
    // Throws on any argument no reader asked for.
    void finish() const {
        for (auto& kv : values) if (!used.count(kv.first)) throw std::invalid_argument("unknown option " + madbp::printable(kv.first));
        for (auto& f : flags) if (!used.count(f)) throw std::invalid_argument("unknown option " + madbp::printable(f));
        if (!positional.empty()) throw std::invalid_argument("unexpected argument '" + madbp::printable(positional[0]) + "'");
    }

    // "--key: 1e309 is out of range [lo, hi]" and the like: a number too large for the parser
    // is out of range, not "not a number".
    static std::string range_error(const std::string& key, const std::string& s, const std::string& lo, const std::string& hi) {
        return key + ": " + madbp::printable(s) + " is out of range [" + lo + ", " + hi + "]";
    }
    static long parse_integer(const std::string& key, const std::string& s, long lo, long hi) {
        size_t pos = 0;
        long v = 0;
        try {
            v = std::stol(s, &pos);
        } catch (const std::out_of_range&) {
            throw std::invalid_argument(range_error(key, s, std::to_string(lo), std::to_string(hi)));
        } catch (...) {
            pos = 0;
        }
        if (pos != s.size() || s.empty()) throw std::invalid_argument(key + ": expected an integer, got '" + madbp::printable(s) + "'");
        if (v < lo || v > hi) throw std::invalid_argument(range_error(key, s, std::to_string(lo), std::to_string(hi)));
        return v;
    }
    static double parse_real(const std::string& key, const std::string& s, double lo, double hi) {
        size_t pos = 0;
        double v = 0;
        bool huge = false;
        try {
            v = std::stod(s, &pos);
        } catch (const std::out_of_range&) {  // 1e309 (huge), or 1e-400 (underflow: its nearest double)
            char* end = nullptr;
            v = std::strtod(s.c_str(), &end);
            pos = (size_t)(end - s.c_str());
            huge = std::isinf(v);
        } catch (...) {
            pos = 0;
        }
        if (pos != s.size() || s.empty() || (!huge && !(v == v)))
            throw std::invalid_argument(key + ": expected a number, got '" + madbp::printable(s) + "'");
        if (huge || v < lo || v > hi) throw std::invalid_argument(range_error(key, s, madbp::number_text(lo), madbp::number_text(hi)));
        return v;
    }
};

// Applies the planner flags that change settings to `settings`: --neighbours, --sensing-radius
// (the daily ones) and every --set GROUP.NAME=VALUE (repeatable; the PlannerConfig table's names);
// then validates them all.
inline void apply_planner_settings(Args& a, madbp::PlannerConfig& settings) {
    const std::pair<const char*, const char*> daily[] = {{"--neighbours", "neighbourhood.neighbours"},
                                                         {"--sensing-radius", "neighbourhood.sensing_radius"}};
    for (const auto& [flag, name] : daily) {
        const std::string v = a.str(flag, "");
        if (!v.empty()) settings.set(name, v);
    }
    for (const std::string& item : a.all("--set")) {
        const size_t eq = item.find('=');
        if (eq == std::string::npos || eq == 0)
            throw std::invalid_argument("--set: expected GROUP.NAME=VALUE like guidance.keep_right=300, got '" + madbp::printable(item) + "'");
        settings.set(item.substr(0, eq), item.substr(eq + 1));
    }
    settings.validate();
}

// The dataset --data `path` names, for training a model of `n_max` robots: it must have
// episodes (the message names the file) and teams that fit.
inline madbp::DemoSet load_training_data(const std::string& path, int n_max) {
    madbp::DemoSet demos = madbp::load_demos(path);
    if (demos.episodes.empty()) throw std::invalid_argument(madbp::printable(path, 256) + ": the dataset has no episodes");
    madbp::validate_demos(demos, n_max, path);  // every team must fit the model's n_max
    return demos;
}

// A file a command writes, with the flag that named it (for messages).
struct FileArg {
    std::string flag, path;
};

// True when `a` and `b` name one existing file (device and inode, links followed).
inline bool same_file(const std::string& a, const std::string& b) {
    struct stat sa, sb;
    return ::stat(a.c_str(), &sa) == 0 && ::stat(b.c_str(), &sb) == 0 && sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
}

// The outputs of a run, claimed before its work starts, so that hours of training never end
// in a refused write: each output and each output + sidecar suffix (a run's FILE.train,
// FILE.csv, ...) must not be a file any other flag names (--data, --model, --scene: an input;
// std::invalid_argument naming both flags) and must be a file madbp may replace
// (madbp::check_output); each output is then locked for the run (madbp::OutputLock, which
// covers its sidecars): a second run writing it is told so.
inline std::vector<std::unique_ptr<madbp::OutputLock>> claim_outputs(const Args& a, const std::vector<FileArg>& outputs,
                                                                     const std::vector<std::string>& sidecars = {}) {
    std::vector<std::unique_ptr<madbp::OutputLock>> locks;
    for (const FileArg& out : outputs) {
        std::vector<std::string> paths = {out.path};
        for (const std::string& s : sidecars) paths.push_back(out.path + s);
        for (const std::string& path : paths) {
            for (const auto& kv : a.repeats)
                for (const std::string& in : kv.second)
                    if (kv.first != out.flag && same_file(path, in))
                        throw std::invalid_argument(out.flag + " " + madbp::printable(path, 256) + " is the same file as " + kv.first + " " +
                                                    madbp::printable(in, 256) + "; choose another output");
            madbp::check_output(path);
        }
        locks.push_back(std::make_unique<madbp::OutputLock>(out.path));
    }
    return locks;
}

// Throws madbp::EnvironmentError when what was written to `f` (standard output) is lost: a
// full disk, /dev/full, a closed descriptor. Results that never arrived are not a success.
inline void check_written(FILE* f, const char* name = "standard output") {
    errno = 0;
    const bool flushed = std::fflush(f) == 0;
    if (flushed && !std::ferror(f)) return;
    throw madbp::EnvironmentError(std::string("cannot write the results to ") + name + (errno ? std::string(": ") + std::strerror(errno) : ""));
}

// `world` `steps` steps on with every robot held still: a plan of it right after a plan of
// `world` starts from that plan's windows (SamplerConfig::warm_start). bench --plan times such
// warm plans, bench_alloc counts their allocations.
inline madbp::World held_still(madbp::World world, int steps) {
    for (int k = 0; k < steps; ++k) world.step(std::vector<madbp::Vec2>((size_t)world.size(), madbp::Vec2{0, 0}));
    return world;
}

// A --scene fixes the map, the team and the world size: --map, --agents or --half-size beside
// it is an error, not silently ignored.
inline void refuse_scene_overrides(const Args& a, const std::string& scene_path) {
    if (scene_path.empty()) return;
    for (const char* k : {"--map", "--agents", "--half-size"})
        if (a.has(k))
            throw std::invalid_argument(std::string(k) + ": --scene " + scene_path + " fixes the map, the team and the world size; leave " + k + " out");
}

// One JSON object per line, built field by field: Json().add("method", m).add("n", 4).line().
struct Json {
    std::string body;
    Json& raw(const std::string& k, const std::string& v) {
        body += (body.empty() ? "" : ", ") + ("\"" + k + "\": ") + v;
        return *this;
    }
    Json& add(const std::string& k, const std::string& v) {
        std::string esc;
        for (char c : v) {
            if (c == '"' || c == '\\') esc += '\\';
            if ((unsigned char)c < 0x20) { esc += ' '; continue; }
            esc += c;
        }
        return raw(k, "\"" + esc + "\"");
    }
    Json& add(const std::string& k, const char* v) { return add(k, std::string(v)); }
    Json& add(const std::string& k, double v) {
        char buf[64];
        if (v == v && v - v == 0) std::snprintf(buf, sizeof buf, "%.6g", v);
        else std::snprintf(buf, sizeof buf, "null");
        return raw(k, buf);
    }
    Json& add(const std::string& k, long v) { return raw(k, std::to_string(v)); }
    Json& add(const std::string& k, int v) { return raw(k, std::to_string(v)); }
    Json& add(const std::string& k, bool v) { return raw(k, v ? "true" : "false"); }
    std::string line() const { return "{" + body + "}"; }
};

// --agents of eval, render and bench: up to the team a scene file may hold.
constexpr long kMaxTeam = madbp::kMaxSceneAgents;

// --half-size of random worlds. Not given, each team size n gets the constant-density
// madbp::default_half_size(n) (1.2 up to 8 robots, 3.4 at 64, 13.6 at 1024); an interaction
// scene (--scenario) the standard 1.2, since its layouts are drawn for that world, not spawned.
struct HalfSize {
    double given = 0;  // 0: not given
    double of(long n, const std::string& scenario = "") const {
        return given > 0 ? given : scenario.empty() ? madbp::default_half_size((int)n) : 1.2;
    }
};
inline HalfSize read_half_size(Args& a) { return {a.real("--half-size", 0, 0.6, madbp::kMaxHalfSize)}; }

// Makes the random world of `seed` before any long run, so that a team too large for its world
// fails at once, naming the flag (the library names its field, half_size).
inline void check_random_world(const std::string& map, long n, uint64_t seed, double half_size) {
    try {
        madbp::make_random_world(map, (int)n, seed, half_size);
    } catch (const std::runtime_error& e) {
        const std::string what = e.what(), field = "half_size: ";
        if (what.rfind(field, 0) != 0) throw;
        throw std::invalid_argument("--half-size: " + what.substr(field.size()));
    }
}

// A madbp::ProgressFn that draws "label  120/1000  37.2/s  ETA 24s  note" in place on stderr
// when it is a terminal, and nothing otherwise (CI logs).
inline madbp::ProgressFn progress_line(const std::string& label) {
    if (!isatty(fileno(stderr))) return nullptr;
    struct Line {
        std::string label;
        std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now(), last{};
        long first = -1;  // the count at the first call (a resumed run starts part-way)
        bool open = false;
        ~Line() { if (open) std::fprintf(stderr, "\n"); }
    };
    auto line = std::make_shared<Line>();
    line->label = label;
    return [line](long done, long total, const std::string& note) {
        Line& l = *line;
        const auto now = std::chrono::steady_clock::now();
        if (l.first < 0) l.first = std::max(0L, done - 1), l.start = now;  // done 0: a note before the first unit
        if (done < total && now - l.last < std::chrono::milliseconds(200)) return;
        l.last = now;
        const double secs = std::chrono::duration<double>(now - l.start).count(), rate = secs > 0 ? (done - l.first) / secs : 0;
        const std::string eta = rate > 0 ? "ETA " + std::to_string(std::lround((total - done) / rate)) + "s" : "ETA -";
        std::fprintf(stderr, "\r%s  %ld/%ld  %.1f/s  %s  %s\033[K", l.label.c_str(), done, total, rate, eta.c_str(), note.c_str());
        l.open = done < total;
        if (!l.open) std::fprintf(stderr, "\n");
        std::fflush(stderr);
    };
}

// An SVG line chart of a training curve: `series` columns against column 0 (step). Log scale
// (shared axis) for losses; otherwise each series is scaled to its own range (noted in the key).
inline void write_curve_svg(const std::string& path, const madbp::Curve& curve, const std::vector<std::string>& series,
                            const std::string& title, bool log_scale) {
    if (curve.rows.empty()) return;
    const double x_max = std::max(1.0, curve.rows.back()[0]);
    auto X = [&](double s) { return 60 + 520 * s / x_max; };
    auto num = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.1f", v); return std::string(b); };
    const char* colors[4] = {"#1f77b4", "#d62728", "#2ca02c", "#9467bd"};
    double lo_all = 1e300, hi_all = -1e300;
    for (const std::string& name : series) {
        const int k = curve.column(name);
        for (const auto& r : curve.rows)
            if (!log_scale || r[k] > 0) lo_all = std::min(lo_all, r[k]), hi_all = std::max(hi_all, r[k]);
    }
    if (!(hi_all >= lo_all)) return;
    std::string svg = "<svg xmlns='http://www.w3.org/2000/svg' width='600' height='360' font-family='sans-serif' font-size='11'>\n"
                      "<rect width='600' height='360' fill='white'/>\n<text x='60' y='14'>" + title + "</text>\n";
    for (size_t s = 0; s < series.size() && s < 4; ++s) {
        const int k = curve.column(series[s]);
        double lo = lo_all, hi = hi_all;
        if (!log_scale) {
            lo = 1e300, hi = -1e300;
            for (const auto& r : curve.rows) lo = std::min(lo, r[k]), hi = std::max(hi, r[k]);
            if (!(hi > lo)) hi = lo + 1;
        }
        auto Y = [&](double v) {
            const double u = log_scale ? (std::log10(std::max(v, lo)) - std::log10(lo)) / std::max(1e-9, std::log10(hi) - std::log10(lo))
                                       : (v - lo) / (hi - lo);
            return 320 - 290 * u;
        };
        svg += "<polyline fill='none' stroke='" + std::string(colors[s]) + "' points='";
        for (const auto& r : curve.rows)
            if (!log_scale || r[k] > 0) svg += num(X(r[0])) + "," + num(Y(r[k])) + " ";
        char key[160];
        std::snprintf(key, sizeof key, "%s (%.3g .. %.3g)", series[s].c_str(), lo, hi);
        svg += "'/>\n<text x='380' y='" + std::to_string(30 + 14 * s) + "' fill='" + colors[s] + "'>" + key + "</text>\n";
    }
    char foot[160];
    std::snprintf(foot, sizeof foot, "<text x='60' y='345'>%s 0 .. %.0f%s</text>\n</svg>\n", curve.columns[0].c_str(), x_max,
                  log_scale ? " (log scale)" : " (each series on its own scale)");
    svg += foot;
    madbp::write_text_file(path, svg);
}

// The options of `madbp convert`, read and checked: the rows come from --scen FILE (from row
// --offset) or are drawn with --random-scen from --seed (madbp::random_movingai_scenario), never
// both; --offset and --write-scen belong to one source each, so the other combination is an
// error naming the flags, not silently ignored.
struct ConvertOptions {
    std::string map_path, scen_path, out, write_scen;
    int agents = 0, offset = 0;
    double cell = 0.3;
    bool random_scen = false, json = false;
    uint64_t seed = 0;
};
inline ConvertOptions read_convert_options(Args& a) {
    ConvertOptions o;
    o.map_path = a.str("--movingai", "");
    o.scen_path = a.str("--scen", "");
    o.random_scen = a.flag("--random-scen");
    o.write_scen = a.str("--write-scen", "");
    o.out = a.str("--out", "");
    o.agents = (int)a.integer("--agents", 0, 1, madbp::kMaxSceneAgents);
    o.cell = a.real("--cell", 0.3, 0.2, madbp::kMaxHalfSize);
    o.offset = (int)a.integer("--offset", 0, 0, 1L << 30);
    o.seed = (uint64_t)a.integer("--seed", 0, 0);
    o.json = a.flag("--json");
    a.finish();
    if (o.random_scen && !o.scen_path.empty()) throw std::invalid_argument("--random-scen: give --scen FILE or --random-scen, not both");
    if (o.random_scen && a.has("--offset"))
        throw std::invalid_argument("--offset: has no meaning with --random-scen (the rows are drawn from --seed); leave --offset out");
    if (!o.random_scen && a.has("--seed")) throw std::invalid_argument("--seed: picks the rows of --random-scen; with --scen FILE use --offset");
    if (!o.random_scen && !o.write_scen.empty()) throw std::invalid_argument("--write-scen: saves the rows of --random-scen; it needs --random-scen");
    if (!o.write_scen.empty() && o.write_scen == o.out) throw std::invalid_argument("--write-scen: is the same file as --out; choose another");
    if (o.map_path.empty() || (o.scen_path.empty() && !o.random_scen) || o.out.empty() || o.agents == 0)
        throw std::invalid_argument("needs --movingai MAP.map, --scen FILE.scen or --random-scen, --agents N and --out FILE.scene (see --help)");
    return o;
}

}  // namespace madbp_cli
