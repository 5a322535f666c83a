// bench_nn.hpp - `madbp bench --nn`: forward-pass GFLOP/s of the neural-network kernels at the
// MA-DBP model's shapes, each beside the rate of a plain Eigen matrix product of the same
// FLOP count measured in the same run (the ratio is what to watch: it does not depend on the
// machine much). Not part of the library: the tool's benchmark plumbing.
#pragma once
#include "cli_common.hpp"
#include "madbp.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <functional>
#include <string>
#include <vector>

namespace bench_nn_detail {

// Seconds per call of fn: one warm-up call, then doubling repetitions until a batch takes at
// least `seconds`; the best of three such batches.
inline double seconds_per_call(const std::function<void()>& fn, double seconds) {
    using clock = std::chrono::steady_clock;
    fn();
    long reps = 1;
    double best = 1e300;
    for (int round = 0; round < 3; ++round) {
        while (true) {
            auto t0 = clock::now();
            for (long i = 0; i < reps; ++i) fn();
            const double dt = std::chrono::duration<double>(clock::now() - t0).count();
            if (dt >= seconds / 3 || reps >= (1L << 30)) {
                best = std::min(best, dt / reps);
                break;
            }
            reps *= 2;
        }
    }
    return best;
}

struct Kernel {
    std::string name, shape;
    double flops;               // per forward call
    std::function<void()> run;  // one forward call
};

}  // namespace bench_nn_detail

inline int bench_nn(madbp_cli::Args& args) {
    using namespace bench_nn_detail;
    using madbp::Mat;
    if (args.flag("--help")) {
        std::printf(
            "madbp bench --nn - forward GFLOP/s of Linear, Conv1d and attention at the model's shapes,\n"
            "beside an Eigen matrix product of the same FLOP count (ratio = kernel / GEMM)\n"
            "  --threads LIST thread counts, e.g. 1,2 (default 1,2)\n"
            "  --seconds S    time per measurement (default 0.3)\n"
            "  --seed S       seed of the weights and inputs (default 0)\n"
            "  --json         one JSON object per kernel and thread count\n");
        return 0;
    }
    const std::vector<long> threads = args.integers("--threads", "1,2", 1, 256);
    const double seconds = args.real("--seconds", 0.3, 0.001, 60);
    const uint64_t seed = (uint64_t)args.integer("--seed", 0, 0);
    const bool json = args.flag("--json");
    args.finish();

    madbp::Rng rng(seed);
    auto randn = [&](long r, long c) {
        Mat m(r, c);
        for (long i = 0; i < m.size(); ++i) m.data()[i] = (float)rng.normal();
        return m;
    };
    madbp::ParamStore ps;
    const int T = 16, B = 8, n_agents = 8;
    madbp::Linear lin64(ps, "lin64", 64, 64, rng), lin256(ps, "lin256", 64, 256, rng);
    madbp::Conv1d conv64(ps, "conv64", 64, 64, 5, rng), conv32(ps, "conv32", 32, 32, 5, rng);
    madbp::MultiHeadAttention att_time(ps, "att_time", 64, 4, rng), att_agent(ps, "att_agent", 64, 4, rng);
    const Mat x64 = randn(64, T * B), x32 = randn(32, T * B);
    // Time axis: 16 steps x 8 items; agent axis: 8 agents x 16 items (the same 128 tokens).
    const Mat tokens = randn(64, T * n_agents);
    std::vector<float> agent_mask(T * n_agents, 1.0f);
    for (int item = 0; item < T; ++item) agent_mask[item * n_agents + n_agents - 1] = 0;  // one padded agent
    Mat y1, y2, y3, y4, y5, y6;
    const double N = T * B;
    auto attention_flops = [](double D, double L, double items) { return 8 * D * D * L * items + 4 * L * L * D * items; };
    const std::vector<Kernel> kernels = {
        {"linear", "64->64 N=128", 2.0 * 64 * 64 * N, [&] { lin64.forward(x64, y1); }},
        {"linear", "64->256 N=128", 2.0 * 64 * 256 * N, [&] { lin256.forward(x64, y2); }},
        {"conv1d", "64->64 k=5 T=16 B=8", 2.0 * 64 * 64 * 5 * N, [&] { conv64.forward(x64, T, y3); }},
        {"conv1d", "32->32 k=5 T=16 B=8", 2.0 * 32 * 32 * 5 * N, [&] { conv32.forward(x32, T, y4); }},
        {"attention", "D=64 h=4 time L=16 x 8", attention_flops(64, 16, 8),
         [&] { att_time.forward(tokens, T, tokens, T, B, nullptr, y5); }},
        {"attention", "D=64 h=4 agents L=8 x 16", attention_flops(64, 8, 16),
         [&] { att_agent.forward(tokens, n_agents, tokens, n_agents, T, agent_mask.data(), y6); }},
    };
    for (long th : threads) {
        for (const Kernel& k : kernels) {
            madbp::set_num_threads((int)th);
            const double t_kernel = seconds_per_call(k.run, seconds);
            // The reference: a square product with the same FLOP count, Eigen's own threading.
            const int n = std::max(8, (int)std::lround(std::cbrt(k.flops / 2)));
            const Mat A = randn(n, n), Bm = randn(n, n);
            Mat C(n, n);
            Eigen::setNbThreads((int)th);
            const double t_gemm = seconds_per_call([&] { C.noalias() = A * Bm; }, seconds);
            madbp::set_num_threads((int)th);
            const double gflops = k.flops / t_kernel * 1e-9, gemm = 2.0 * n * n * n / t_gemm * 1e-9;
            if (json) {
                std::printf("%s\n", madbp_cli::Json()
                                        .add("bench", "nn")
                                        .add("kernel", k.name)
                                        .add("shape", k.shape)
                                        .add("threads", (int)th)
                                        .add("us_per_call", t_kernel * 1e6)
                                        .add("gflops", gflops)
                                        .add("gemm_n", n)
                                        .add("gemm_gflops", gemm)
                                        .add("ratio", gflops / gemm)
                                        .line()
                                        .c_str());
            } else {
                std::printf("%-9s %-26s threads %ld: %7.1f us %6.1f GFLOP/s | Eigen GEMM n=%-3d %6.1f GFLOP/s | ratio %.2f\n",
                            k.name.c_str(), k.shape.c_str(), th, t_kernel * 1e6, gflops, n, gemm, gflops / gemm);
            }
            std::fflush(stdout);
        }
    }
    return 0;
}
