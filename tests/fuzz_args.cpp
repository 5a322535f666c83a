// libFuzzer target for the tool's flag parser, madbp_cli::Args (`make fuzz`): the input is an
// argument list (arguments separated by NUL bytes). Each reader must either return a value in
// its range or throw std::invalid_argument, never crash or read out of bounds (ASan + UBSan are
// on), and every message must be one short line of printable ASCII: values are escaped and cut
// (madbp::printable), whatever bytes or lengths the arguments have.
#include "cli_common.hpp"

#include <string>
#include <vector>

static void check_message(const std::string& m) {
    if (m.empty() || m.size() > 600) __builtin_trap();
    for (unsigned char c : m)
        if (c < 0x20 || c >= 0x7f) __builtin_trap();
}

template <class F>
static void read(F&& f) {
    try {
        f();
    } catch (const std::invalid_argument& e) {
        check_message(e.what());
    }
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    std::vector<std::string> argv;
    std::string cur;
    for (size_t i = 0; i < size; ++i) {
        if (data[i] == 0) argv.push_back(cur), cur.clear();
        else cur += (char)data[i];
    }
    if (!cur.empty()) argv.push_back(cur);
    madbp_cli::Args a(argv);
    read([&] { if (a.integer("--episodes", 5, 1, 1000) < 1 || a.integer("--episodes", 5, 1, 1000) > 1000) __builtin_trap(); });
    read([&] {
        const double v = a.real("--half-size", 1.2, 0.6, 100);
        if (!(v >= 0.6 && v <= 100)) __builtin_trap();
    });
    read([&] {
        for (long v : a.integers("--agents", "2,4", 1, 64))
            if (v < 1 || v > 64) __builtin_trap();
    });
    read([&] {
        for (double v : a.reals("--weights", "1,2", 0, 10))
            if (!(v >= 0 && v <= 10)) __builtin_trap();
    });
    read([&] {
        for (const std::string& m : madbp_cli::split(a.str("--map", "empty"), "--map"))
            if (m.empty()) __builtin_trap();
    });
    read([&] { a.flag("--json"); });
    read([&] { a.all("--set"); });
    read([&] { a.str("--out", "x"); });
    read([&] { a.finish(); });
    return 0;
}
