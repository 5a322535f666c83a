// cli_common.hpp - argument parsing and output helpers shared by the madbp command-line tool.
// Not part of the library: the tool's own plumbing.
#pragma once
#include <algorithm>
#include <cstdio>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace madbp_cli {

// "--key value" and "--flag" arguments. Every key a subcommand reads is recorded, so that an
// unknown flag (a typo) is reported instead of silently ignored: call finish() after reading.
struct Args {
    std::map<std::string, std::string> values;
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
                if (eq != std::string::npos) values[a.substr(0, eq)] = a.substr(eq + 1);
                else if (i + 1 < n && args[i + 1].rfind("--", 0) != 0) values[a] = args[++i];
                else flags.insert(a);
            } else {
                positional.push_back(a);
            }
        }
    }
    bool flag(const std::string& key) {
        used.insert(key);
        if (values.count(key)) throw std::invalid_argument(key + ": is a flag and takes no value (got '" + values[key] + "')");
        return flags.count(key) > 0;
    }
    bool has(const std::string& key) const { return values.count(key) || flags.count(key); }
    std::string str(const std::string& key, const std::string& def) {
        used.insert(key);
        if (flags.count(key)) throw std::invalid_argument(key + ": needs a value");
        auto it = values.find(key);
        return it == values.end() ? def : it->second;
    }
    long integer(const std::string& key, long def, long lo = -(1L << 40), long hi = (1L << 40)) {
        std::string s = str(key, "");
        if (s.empty()) return def;
        size_t pos = 0;
        long v = 0;
        try { v = std::stol(s, &pos); } catch (...) { pos = 0; }
        if (pos != s.size()) throw std::invalid_argument(key + ": expected an integer, got '" + s + "'");
        if (v < lo || v > hi)
            throw std::invalid_argument(key + ": " + s + " is out of range [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
        return v;
    }
    double real(const std::string& key, double def, double lo = -1e300, double hi = 1e300) {
        std::string s = str(key, "");
        if (s.empty()) return def;
        size_t pos = 0;
        double v = 0;
        try { v = std::stod(s, &pos); } catch (...) { pos = 0; }
        if (pos != s.size() || !(v == v)) throw std::invalid_argument(key + ": expected a number, got '" + s + "'");
        if (v < lo || v > hi) throw std::invalid_argument(key + ": " + s + " is out of range");
        return v;
    }
    // Comma-separated integers, e.g. --agents 2,4,6.
    std::vector<long> integers(const std::string& key, const std::string& def, long lo = 0, long hi = 1L << 40) {
        std::string s = str(key, def);
        std::vector<long> out;
        std::stringstream ss(s);
        std::string item;
        while (std::getline(ss, item, ',')) {
            size_t pos = 0;
            long v = 0;
            try { v = std::stol(item, &pos); } catch (...) { pos = 0; }
            if (item.empty() || pos != item.size()) throw std::invalid_argument(key + ": expected integers like 2,4,6, got '" + s + "'");
            if (v < lo || v > hi) throw std::invalid_argument(key + ": " + item + " is out of range");
            out.push_back(v);
        }
        if (out.empty()) throw std::invalid_argument(key + ": empty list");
        return out;
    }
    // Throws on any argument no reader asked for.
    void finish() const {
        for (auto& kv : values) if (!used.count(kv.first)) throw std::invalid_argument("unknown option " + kv.first);
        for (auto& f : flags) if (!used.count(f)) throw std::invalid_argument("unknown option " + f);
        if (!positional.empty()) throw std::invalid_argument("unexpected argument '" + positional[0] + "'");
    }
};

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

}  // namespace madbp_cli
