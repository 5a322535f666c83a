// madbp_ref.cpp - the C++ side of examples/python/check.py: prints, as one JSON object, what the
// library itself computes, for numpy to compare against.
//   madbp_ref layer MODEL NAME [N]   madbp::Linear NAME of checkpoint MODEL on a fixed input x
//                                    (N columns, default 5): {"x": (N, in), "y": (N, out)}
//   madbp_ref demos FILE             madbp::load_demos(FILE), every field and value
// Floats are printed with 9 significant digits, so they read back as the same float32.
// Build: g++ -O2 $(pkg-config --cflags madbp) -o madbp_ref madbp_ref.cpp $(pkg-config --libs madbp)
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "madbp_train.hpp"

namespace {

void print_floats(const float* v, int n) {
    std::printf("[");
    for (int i = 0; i < n; ++i) std::printf("%s%.9g", i ? "," : "", v[i]);
    std::printf("]");
}
void print_vec2s(const char* key, const std::vector<madbp::Vec2>& v) {
    std::printf(",\"%s\":[", key);
    for (size_t i = 0; i < v.size(); ++i) std::printf("%s[%.9g,%.9g]", i ? "," : "", (float)v[i].x, (float)v[i].y);
    std::printf("]");
}

// A Linear layer built by the library, its weight and bias copied from the checkpoint by name.
int layer(const std::string& model, const std::string& name, int N) {
    const madbp::SafeTensors st = madbp::load_safetensors(model);
    const madbp::NamedTensor& w = st.at(name + ".weight");
    if (w.shape.size() != 2) throw std::runtime_error(model + ": '" + name + ".weight' is not a matrix");
    const int in = w.shape[0], out = w.shape[1];  // listed {in, out}
    madbp::ParamStore ps;
    madbp::Rng rng(0);
    madbp::Linear fc(ps, name, in, out, rng, st.find(name + ".bias") != nullptr);
    for (const madbp::ParamStore::Entry& e : ps.entries) {
        const madbp::NamedTensor& t = st.at(e.name);
        if (t.shape != e.shape) throw std::runtime_error(model + ": '" + e.name + "' has an unexpected shape");
        std::copy(t.data.begin(), t.data.end(), ps.data(e));
    }
    madbp::Mat x(in, N), y;  // one column per input
    for (int j = 0; j < N; ++j)
        for (int i = 0; i < in; ++i) x(i, j) = (float)std::sin(0.37 * i + 1.3 * j + 0.1);
    fc.forward(x, y);
    std::printf("{\"layer\":\"%s\",\"in\":%d,\"out\":%d,\"x\":[", name.c_str(), in, out);
    for (int j = 0; j < N; ++j) {
        std::printf(j ? "," : "");
        print_floats(x.col(j).data(), in);
    }
    std::printf("],\"y\":[");
    for (int j = 0; j < N; ++j) {
        std::printf(j ? "," : "");
        print_floats(y.col(j).data(), out);
    }
    std::printf("]}\n");
    return 0;
}

int demos(const std::string& path) {
    const madbp::DemoSet set = madbp::load_demos(path);
    std::printf("{\"demonstrator\":\"%s\",\"episodes\":[", set.demonstrator.c_str());
    for (size_t e = 0; e < set.episodes.size(); ++e) {
        const madbp::Demonstration& d = set.episodes[e];
        std::printf("%s{\"map_name\":\"%s\",\"half_size\":%.17g,\"agents\":%d,\"steps\":%d,\"success\":%s,\"discs\":[", e ? "," : "",
                    d.map_name.c_str(), d.map.half_size, d.agents, d.steps, d.success ? "true" : "false");
        for (size_t i = 0; i < d.map.discs.size(); ++i)
            std::printf("%s[%.17g,%.17g,%.17g]", i ? "," : "", d.map.discs[i].c.x, d.map.discs[i].c.y, d.map.discs[i].r);
        std::printf("],\"boxes\":[");
        for (size_t i = 0; i < d.map.boxes.size(); ++i) {
            const madbp::Box& b = d.map.boxes[i];
            std::printf("%s[%.17g,%.17g,%.17g,%.17g]", i ? "," : "", b.lo.x, b.lo.y, b.hi.x, b.hi.y);
        }
        std::printf("]");
        print_vec2s("goals", d.goals);
        print_vec2s("pos", d.pos);
        print_vec2s("vel", d.vel);
        print_vec2s("act", d.act);
        std::printf("}");
    }
    std::printf("]}\n");
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    try {
        const std::string mode = argc > 1 ? argv[1] : "";
        if (mode == "layer" && (argc == 4 || argc == 5)) return layer(argv[2], argv[3], argc == 5 ? std::stoi(argv[4]) : 5);
        if (mode == "demos" && argc == 3) return demos(argv[2]);
        std::fprintf(stderr, "usage: madbp_ref layer MODEL NAME [N] | madbp_ref demos FILE\n");
        return 2;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "madbp_ref: %s\n", e.what());
        return 1;
    }
}
