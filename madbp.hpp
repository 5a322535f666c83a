// madbp.hpp - neural-network core, checkpoints, the MA-DBP model and its planner.
// Part of madbp (Multi-Agent Diffusion Based Planner), header-only C++17. MIT licence.
//
// What it is
//   A small neural-network library written by hand on Eigen (SPEC.md section 4): layers as
//   plain structs with forward/backward, all parameters of a model in one flat buffer, Adam,
//   gradient clipping, a weight EMA, and safetensors checkpoints (SPEC section 11) that
//   Python's safetensors/numpy can read. The MA-DBP model (SPEC section 5) is built on it.
//
// Conventions (read these once)
//   Mat = Eigen::MatrixXf, column-major float32. An activation is a (C, N) matrix: one
//   column per position, one row per channel. B items of length T are stored with column
//   index b*T + t (time fastest within an item); 2-D maps of H x W use b*H*W + y*W + x.
//   forward() resizes its output and keeps in the layer what backward() needs, so each layer
//   instance is used once per forward pass. backward() takes the same inputs as forward (minus
//   the output), then dy, then the input gradient(s); it ADDS into the parameter gradients of
//   the ParamStore and WRITES (overwrites) the input gradients. Outputs must not alias inputs.
//   Parameter shapes are listed row-major, as in the checkpoint file (numpy order); the
//   column-major Eigen matrix of an entry {r, c} is (c, r). So Linear's W (out, in) is listed
//   {in, out}: numpy computes y = x @ W + b, like Flax's Dense kernel.
//
// Use: plan with a trained model (SPEC 8)
//   #include "madbp.hpp"
//   madbp::World world = madbp::make_random_world("barrier", 4, /*seed=*/0);
//   madbp::DiffusionPlanner planner(madbp::load_model("models/madbp-default.safetensors"));
//   madbp::PlanFollower follower([&](const madbp::World& w) { return planner.plan(w); });
//   while (!world.done()) world.step(follower.act(world));   // replans every 8 steps
//
// Use: the layers (SPEC 4)
//   madbp::Rng rng(0);
//   madbp::ParamStore ps;
//   madbp::Linear fc1(ps, "fc1", 2, 64, rng), fc2(ps, "fc2", 64, 1, rng);
//   madbp::Tanh act;
//   madbp::Adam adam;                       // lr 3e-4, eps outside the square root
//   madbp::Mat h, a, y, dy, da, dh, dx;
//   fc1.forward(x, h); act.forward(h, a); fc2.forward(a, y);        // x is (2, N)
//   dy = 2 * (y - target) / N;                                       // d(mean squared error)
//   ps.zero_grad();
//   fc2.backward(a, dy, da); act.backward(h, da, dh); fc1.backward(x, dh, dx);
//   madbp::clip_grad_norm(ps, 1.0f);
//   adam.update(ps);
//   madbp::save_params("model.safetensors", ps, {{"step", "100"}});
//
// Threads
//   Layers split large products and the attention loop over OpenMP threads themselves. Call
//   madbp::set_num_threads(n) once: it sets OpenMP's thread count and turns Eigen's own GEMM
//   threading off, because Eigen allocates packing buffers on every multi-threaded product and
//   the steady-state forward pass is meant to allocate nothing.
//
// Configuration macros (define before including)
//   MADBP_ASSERT(cond)             programmer-error check (see madbp_sim.hpp); default assert.
//   EIGEN_STACK_ALLOCATION_LIMIT   madbp sets 1 MiB when undefined, so Eigen's single-threaded
//                                  GEMM packs its blocks on the stack, not the heap. Include
//                                  madbp.hpp before any Eigen header for it to take effect.
//
// Changelog
//   0.1  neural-network core, safetensors checkpoints, MA-DBP model, DDIM sampler, planner.

#ifndef MADBP_HPP
#define MADBP_HPP

#ifndef EIGEN_STACK_ALLOCATION_LIMIT
#define EIGEN_STACK_ALLOCATION_LIMIT (1 << 20)
#endif

// GCC 12 with AVX-512 reports false "may be used uninitialized" warnings inside the compiler's
// own intrinsics headers when Eigen's kernels are inlined; silence them for those headers only.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif
#include "madbp_sim.hpp"

#include <Eigen/Dense>
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fcntl.h>
#include <limits>
#include <map>
#include <memory>
#include <numeric>
#include <sstream>
#include <stdexcept>
#include <string>
#include <sys/stat.h>
#include <unistd.h>
#include <vector>
#ifdef _OPENMP
#include <omp.h>
#endif

namespace madbp {

// ===== Neural-network core =====

using Mat = Eigen::MatrixXf;
using Vec = Eigen::VectorXf;

// Sets the number of threads madbp's layers use and keeps Eigen's products single-threaded
// (madbp splits them itself; Eigen's threaded GEMM allocates on every call).
inline void set_num_threads(int n) {
    MADBP_ASSERT(n >= 1);
#ifdef _OPENMP
    omp_set_num_threads(n);
#endif
    Eigen::setNbThreads(1);
}

namespace detail {

inline int max_threads() {
#ifdef _OPENMP
    return omp_in_parallel() ? 1 : omp_get_max_threads();
#else
    return 1;
#endif
}

// Threads worth using for `flops` of work: a parallel region costs a few microseconds, so
// below ~1 MFLOP (under 10 us on one core) one thread is faster.
inline int threads_for(double flops) {
    int t = max_threads();
    if (t <= 1 || flops < 1e6) return 1;
    return std::min<int>(t, std::max(1, (int)(flops / 5e5)));
}

// Runs fn(i, thread) for i in [0, n) on `threads` threads; thread in [0, threads) indexes
// per-thread scratch. One thread runs a plain loop: even a one-thread OpenMP region allocates
// its team in libgomp.
template <class F>
inline void parallel_for(int n, int threads, const F& fn) {
#ifdef _OPENMP
    if (threads > 1) {
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int i = 0; i < n; ++i) fn(i, omp_get_thread_num());
        return;
    }
#endif
    for (int i = 0; i < n; ++i) fn(i, 0);
}

// Column range [c0, c1) of n columns for thread t of nt, in multiples of 8 columns.
inline void thread_columns(int n, int t, int nt, int& c0, int& c1) {
    const int chunk = ((n + nt - 1) / nt + 7) / 8 * 8;
    c0 = std::min(n, t * chunk);
    c1 = std::min(n, c0 + chunk);
}

// y = A * x (or y += A * x), splitting the columns of x and y over threads. y must already
// have its size.
template <class Lhs>
inline void product_by_columns(const Lhs& A, const Mat& x, Mat& y, bool add = false) {
    const int n = (int)x.cols();
    const int threads = threads_for(2.0 * A.rows() * A.cols() * n);
    if (threads <= 1 || n < 16) {
        if (add) y.noalias() += A * x;
        else y.noalias() = A * x;
        return;
    }
#ifdef _OPENMP
#pragma omp parallel num_threads(threads)
    {
        int c0, c1;
        thread_columns(n, omp_get_thread_num(), omp_get_num_threads(), c0, c1);
        if (c1 > c0) {
            if (add) y.middleCols(c0, c1 - c0).noalias() += A * x.middleCols(c0, c1 - c0);
            else y.middleCols(c0, c1 - c0).noalias() = A * x.middleCols(c0, c1 - c0);
        }
    }
#endif
}

// dW += dy * x^T (a weight gradient), splitting the columns of dW (rows of x) over threads.
inline void add_product_transposed(Eigen::Map<Mat> dW, const Mat& dy, const Mat& x) {
    const int n = (int)dW.cols();
    const int threads = threads_for(2.0 * dW.rows() * n * dy.cols());
    if (threads <= 1 || n < 16) {
        dW.noalias() += dy * x.transpose();
        return;
    }
#ifdef _OPENMP
#pragma omp parallel num_threads(threads)
    {
        int c0, c1;
        thread_columns(n, omp_get_thread_num(), omp_get_num_threads(), c0, c1);
        if (c1 > c0) dW.middleCols(c0, c1 - c0).noalias() += dy * x.middleRows(c0, c1 - c0).transpose();
    }
#endif
}

inline long shape_numel(const std::vector<int>& shape) {
    long n = 1;
    for (int d : shape) n *= d;
    return n;
}

inline std::string shape_string(const std::vector<int>& shape) {
    std::string s = "[";
    for (size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
    return s + "]";
}

}  // namespace detail

// How ParamStore::add initialises a tensor. Linear/Conv use uniform(1/sqrt(fan_in)) as
// PyTorch does.
struct Init {
    enum Kind { Zeros, Ones, Uniform, Normal } kind = Zeros;
    float scale = 0;  // Uniform: bound (values in [-bound, bound)); Normal: standard deviation
    static Init zeros() { return {Zeros, 0}; }
    static Init ones() { return {Ones, 0}; }
    static Init uniform(float bound) { return {Uniform, bound}; }
    static Init normal(float std) { return {Normal, std}; }
};

// value (P), grad (P): all parameters of a model in one flat buffer, entries are named views.
struct ParamStore {
    Vec value, grad;
    struct Entry {
        std::string name;
        int offset;
        std::vector<int> shape;  // row-major, as in the checkpoint (see Conventions)
        bool trainable;          // false: state such as BatchNorm running statistics
        int numel() const { return (int)detail::shape_numel(shape); }
    };
    std::vector<Entry> entries;

    // Appends a tensor initialised now and returns its offset. Names must be unique and must
    // not start with "optim." (reserved for optimizer state in checkpoints).
    int add(const std::string& name, std::vector<int> shape, Init init, Rng& rng, bool trainable = true) {
        MADBP_ASSERT(find(name) == nullptr);
        MADBP_ASSERT(name.rfind("optim.", 0) != 0 && !name.empty());
        MADBP_ASSERT(std::all_of(shape.begin(), shape.end(), [](int d) { return d >= 0; }));
        const int offset = size();
        const int n = (int)detail::shape_numel(shape);
        value.conservativeResize(offset + n);
        grad.conservativeResize(offset + n);
        grad.segment(offset, n).setZero();
        for (int i = 0; i < n; ++i) {
            float v = 0;
            switch (init.kind) {
                case Init::Zeros: v = 0; break;
                case Init::Ones: v = 1; break;
                case Init::Uniform: v = (float)rng.uniform(-init.scale, init.scale); break;
                case Init::Normal: v = (float)(init.scale * rng.normal()); break;
            }
            value[offset + i] = v;
        }
        entries.push_back({name, offset, std::move(shape), trainable});
        return offset;
    }
    const Entry* find(const std::string& name) const {
        for (auto& e : entries)
            if (e.name == name) return &e;
        return nullptr;
    }
    Eigen::Map<Mat> view(int offset, int rows, int cols) { return {value.data() + offset, rows, cols}; }
    Eigen::Map<const Mat> view(int offset, int rows, int cols) const { return {value.data() + offset, rows, cols}; }
    Eigen::Map<Mat> grad_view(int offset, int rows, int cols) { return {grad.data() + offset, rows, cols}; }
    Eigen::Map<const Mat> grad_view(int offset, int rows, int cols) const { return {grad.data() + offset, rows, cols}; }
    Eigen::Map<Vec> vec(int offset, int n) { return {value.data() + offset, n}; }
    Eigen::Map<const Vec> vec(int offset, int n) const { return {value.data() + offset, n}; }
    Eigen::Map<Vec> grad_vec(int offset, int n) { return {grad.data() + offset, n}; }
    void zero_grad() { grad.setZero(); }
    int size() const { return (int)value.size(); }
    long trainable_count() const {  // parameters, without state such as running statistics
        long n = 0;
        for (auto& e : entries) if (e.trainable) n += e.numel();
        return n;
    }
};

// ---------------------------------------------------------------------------------------------
// Linear: x (in, N) -> y (out, N). W (out, in) listed {in, out}; b (out). backward(x, dy, dx).
struct Linear {
    ParamStore* ps = nullptr;
    int in = 0, out = 0, w = -1, b = -1;  // b = -1: no bias

    Linear() = default;
    Linear(ParamStore& ps_, const std::string& name, int in_, int out_, Rng& rng, bool bias = true)
        : ps(&ps_), in(in_), out(out_) {
        const float bound = 1.0f / std::sqrt((float)in);
        w = ps->add(name + ".weight", {in, out}, Init::uniform(bound), rng);
        if (bias) b = ps->add(name + ".bias", {out}, Init::uniform(bound), rng);
    }
    void forward(const Mat& x, Mat& y) {
        MADBP_ASSERT(x.rows() == in);
        y.resize(out, x.cols());
        detail::product_by_columns(ps->view(w, out, in), x, y);
        if (b >= 0) y.colwise() += ps->vec(b, out);
    }
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        MADBP_ASSERT(dy.rows() == out && dy.cols() == x.cols());
        detail::add_product_transposed(ps->grad_view(w, out, in), dy, x);
        if (b >= 0) ps->grad_vec(b, out) += dy.rowwise().sum();
        dx.resize(in, x.cols());
        detail::product_by_columns(ps->view(w, out, in).transpose(), dy, dx);
    }
};

// LayerNorm over rows (features) of each column: x (C, N) -> y (C, N); gain, bias (C).
// eps 1e-5. backward(x, dy, dx).
struct LayerNorm {
    ParamStore* ps = nullptr;
    int C = 0, gain = -1, bias = -1;
    float eps = 1e-5f;
    Eigen::RowVectorXf mean, rstd;  // (N), kept for backward
    Vec xhat, dnorm;                // (C) scratch of one column

    LayerNorm() = default;
    LayerNorm(ParamStore& ps_, const std::string& name, int C_, Rng& rng) : ps(&ps_), C(C_) {
        gain = ps->add(name + ".weight", {C}, Init::ones(), rng);
        bias = ps->add(name + ".bias", {C}, Init::zeros(), rng);
    }
    void forward(const Mat& x, Mat& y) {
        MADBP_ASSERT(x.rows() == C);
        const int N = (int)x.cols();
        mean.resize(N);
        rstd.resize(N);
        y.resize(C, N);
        auto g = ps->vec(gain, C);
        auto b = ps->vec(bias, C);
        for (int j = 0; j < N; ++j) {
            const float mu = x.col(j).mean();
            const float var = (x.col(j).array() - mu).square().mean();
            mean[j] = mu;
            rstd[j] = 1.0f / std::sqrt(var + eps);
            y.col(j) = ((x.col(j).array() - mu) * rstd[j]) * g.array() + b.array();
        }
    }
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        const int N = (int)x.cols();
        auto g = ps->vec(gain, C);
        auto dg = ps->grad_vec(gain, C);
        auto db = ps->grad_vec(bias, C);
        dx.resize(C, N);
        for (int j = 0; j < N; ++j) {
            xhat = (x.col(j).array() - mean[j]) * rstd[j];
            dnorm = g.cwiseProduct(dy.col(j));
            dg += dy.col(j).cwiseProduct(xhat);
            db += dy.col(j);
            const float mean_dnorm = dnorm.mean(), mean_dnorm_xhat = dnorm.dot(xhat) / C;
            dx.col(j) = rstd[j] * (dnorm.array() - mean_dnorm - xhat.array() * mean_dnorm_xhat);
        }
    }
};

// ---------------------------------------------------------------------------------------------
// Multi-head attention: q_in (D, Lq*B), kv_in (D, Lk*B) -> y (D, Lq*B). Wq, Wk, Wv, Wo (D, D)
// listed {D, D}, biases (D). key_mask: Lk*B of 0/1 (1 = attend) or nullptr. An item whose
// keys are all masked outputs 0 and passes no gradient. backward takes forward's arguments,
// then dy, then writes dq_in and dkv_in, which must be two different matrices (self-attention:
// pass x twice, add the two). The (item, head) loop runs on OpenMP threads when large enough.
struct MultiHeadAttention {
    ParamStore* ps = nullptr;
    int D = 0, heads = 0, wq = -1, bq = -1, wk = -1, bk = -1, wv = -1, bv = -1, wo = -1, bo = -1;
    // Kept for backward: projections, attention weights per (item, head), context.
    Mat Q, K, V;     // (D, Lq*B), (D, Lk*B), (D, Lk*B)
    Mat P;           // (Lk, Lq*B*heads): block (b*heads + h) holds softmax weights, keys x queries
    Mat ctx;         // (D, Lq*B) attention output before Wo
    Vec mask;        // (Lk*B) copy of key_mask (ones when nullptr)
    Vec mask_bias;   // (Lk*B) 0 for keys attended, -1e30 for masked ones
    Eigen::Matrix<unsigned char, Eigen::Dynamic, 1> dead;  // (B) 1 when every key is masked
    Mat dctx, dQ, dK, dV, dy_live;  // backward scratch
    std::vector<Mat> dS;            // (Lk, Lq) per thread: score gradients of one (item, head)

    MultiHeadAttention() = default;
    MultiHeadAttention(ParamStore& ps_, const std::string& name, int dim, int heads_, Rng& rng)
        : ps(&ps_), D(dim), heads(heads_) {
        MADBP_ASSERT(heads > 0 && dim % heads == 0);
        const float bound = 1.0f / std::sqrt((float)dim);
        wq = ps->add(name + ".q.weight", {D, D}, Init::uniform(bound), rng);
        bq = ps->add(name + ".q.bias", {D}, Init::zeros(), rng);
        wk = ps->add(name + ".k.weight", {D, D}, Init::uniform(bound), rng);
        bk = ps->add(name + ".k.bias", {D}, Init::zeros(), rng);
        wv = ps->add(name + ".v.weight", {D, D}, Init::uniform(bound), rng);
        bv = ps->add(name + ".v.bias", {D}, Init::zeros(), rng);
        wo = ps->add(name + ".o.weight", {D, D}, Init::uniform(bound), rng);
        bo = ps->add(name + ".o.bias", {D}, Init::zeros(), rng);
    }

    void forward(const Mat& q_in, int Lq, const Mat& kv_in, int Lk, int B, const float* key_mask, Mat& y) {
        MADBP_ASSERT(q_in.rows() == D && kv_in.rows() == D);
        MADBP_ASSERT(q_in.cols() == (long)Lq * B && kv_in.cols() == (long)Lk * B);
        project(wq, bq, q_in, Q);
        project(wk, bk, kv_in, K);
        project(wv, bv, kv_in, V);
        mask.resize(Lk * B);
        if (key_mask) mask = Eigen::Map<const Vec>(key_mask, Lk * B);
        else mask.setOnes();
        mask_bias = (mask.array() != 0).select(Vec::Zero(Lk * B), -1e30f);
        dead.resize(B);
        for (int b = 0; b < B; ++b) dead[b] = (mask.segment(b * Lk, Lk).array() != 0).any() ? 0 : 1;
        P.resize(Lk, (long)Lq * B * heads);
        ctx.resize(D, (long)Lq * B);
        const int dh = D / heads;
        const float scale = 1.0f / std::sqrt((float)dh);
        const int blocks = B * heads;
        const int threads = detail::threads_for(4.0 * blocks * Lq * Lk * dh);
        detail::parallel_for(blocks, threads, [&](int bh, int) {
            const int b = bh / heads, h = bh % heads;
            auto Pb = P.middleCols((long)bh * Lq, Lq);
            auto out = ctx.block(h * dh, (long)b * Lq, dh, Lq);
            if (dead[b]) {
                Pb.setZero();
                out.setZero();
                return;
            }
            Pb.noalias() = K.block(h * dh, (long)b * Lk, dh, Lk).transpose() * Q.block(h * dh, (long)b * Lq, dh, Lq);
            // Softmax over the unmasked keys of each query, vectorised along the keys: masked
            // keys get a score of -1e30, so exp() makes them exactly 0.
            const auto bias = mask_bias.segment((long)b * Lk, Lk).array();
            for (int q = 0; q < Lq; ++q) {
                auto s = Pb.col(q).array();
                s = s * scale + bias;
                s = (s - s.maxCoeff()).exp();
                s *= 1.0f / s.sum();
            }
            out.noalias() = V.block(h * dh, (long)b * Lk, dh, Lk) * Pb;
        });
        y.resize(D, (long)Lq * B);
        detail::product_by_columns(ps->view(wo, D, D), ctx, y);
        y.colwise() += ps->vec(bo, D);
        for (int b = 0; b < B; ++b)
            if (dead[b]) y.middleCols((long)b * Lq, Lq).setZero();
    }

    void backward(const Mat& q_in, int Lq, const Mat& kv_in, int Lk, int B, const float* key_mask, const Mat& dy,
                  Mat& dq_in, Mat& dkv_in) {
        MADBP_ASSERT(dy.rows() == D && dy.cols() == (long)Lq * B);
        dy_live = dy;  // dead items pass no gradient (their output is a constant 0)
        for (int b = 0; b < B; ++b)
            if (dead[b]) dy_live.middleCols((long)b * Lq, Lq).setZero();
        detail::add_product_transposed(ps->grad_view(wo, D, D), dy_live, ctx);
        ps->grad_vec(bo, D) += dy_live.rowwise().sum();
        dctx.resize(D, (long)Lq * B);
        detail::product_by_columns(ps->view(wo, D, D).transpose(), dy_live, dctx);
        dQ.resize(D, (long)Lq * B);
        dK.resize(D, (long)Lk * B);
        dV.resize(D, (long)Lk * B);
        const int dh = D / heads;
        const float scale = 1.0f / std::sqrt((float)dh);
        const int blocks = B * heads;
        const int threads = detail::threads_for(8.0 * blocks * Lq * Lk * dh);
        dS.resize(std::max(threads, (int)dS.size()));
        for (Mat& m : dS) m.resize(Lk, Lq);
        detail::parallel_for(blocks, threads, [&](int bh, int thread) {
            Mat& dS_t = dS[thread];
            const int b = bh / heads, h = bh % heads;
            auto Pb = P.middleCols((long)bh * Lq, Lq);
            auto dout = dctx.block(h * dh, (long)b * Lq, dh, Lq);
            auto Qb = Q.block(h * dh, (long)b * Lq, dh, Lq);
            auto Kb = K.block(h * dh, (long)b * Lk, dh, Lk);
            auto Vb = V.block(h * dh, (long)b * Lk, dh, Lk);
            // out = V P  =>  dV = dout P^T, dP = V^T dout.
            dV.block(h * dh, (long)b * Lk, dh, Lk).noalias() = dout * Pb.transpose();
            dS_t.noalias() = Vb.transpose() * dout;
            // Softmax backward per query column: dS = P .* (dP - sum(P .* dP)).
            for (int q = 0; q < Lq; ++q) {
                const float dot = Pb.col(q).dot(dS_t.col(q));
                dS_t.col(q) = Pb.col(q).cwiseProduct((dS_t.col(q).array() - dot).matrix()) * scale;
            }
            // S = K^T Q * scale  =>  dQ = K dS, dK = Q dS^T (scale folded into dS).
            dQ.block(h * dh, (long)b * Lq, dh, Lq).noalias() = Kb * dS_t;
            dK.block(h * dh, (long)b * Lk, dh, Lk).noalias() = Qb * dS_t.transpose();
        });
        project_backward(wq, bq, q_in, dQ, dq_in, false);
        project_backward(wk, bk, kv_in, dK, dkv_in, false);
        project_backward(wv, bv, kv_in, dV, dkv_in, true);
    }

    // out = W x + b for one of the four projections.
    void project(int w, int b, const Mat& x, Mat& out) {
        out.resize(D, x.cols());
        detail::product_by_columns(ps->view(w, D, D), x, out);
        out.colwise() += ps->vec(b, D);
    }
    void project_backward(int w, int b, const Mat& x, const Mat& dout, Mat& dx, bool accumulate) {
        detail::add_product_transposed(ps->grad_view(w, D, D), dout, x);
        ps->grad_vec(b, D) += dout.rowwise().sum();
        if (accumulate) {
            detail::product_by_columns(ps->view(w, D, D).transpose(), dout, dx, true);
        } else {
            dx.resize(D, x.cols());
            detail::product_by_columns(ps->view(w, D, D).transpose(), dout, dx);
        }
    }
};

// ---------------------------------------------------------------------------------------------
// im2col for 1-D convolution with same padding inside each item: x (cin, T*B) ->
// cols (k*cin, T*B), row j*cin + c holds x(c, t + j - pad) of the same item, 0 outside it.
namespace detail {
inline void im2col_1d(const Mat& x, int T, int k, Mat& cols) {
    const int cin = (int)x.rows(), B = (int)(x.cols() / T), pad = k / 2;
    cols.resize((long)k * cin, x.cols());
    for (int b = 0; b < B; ++b)
        for (int j = 0; j < k; ++j) {
            const int s = j - pad, t0 = std::max(0, -s), t1 = std::min(T, T - s);
            auto dst = cols.block((long)j * cin, (long)b * T, cin, T);
            dst.leftCols(t0).setZero();
            dst.rightCols(T - t1).setZero();
            if (t1 > t0) dst.middleCols(t0, t1 - t0) = x.block(0, (long)b * T + t0 + s, cin, t1 - t0);
        }
}
// The adjoint of im2col_1d: dx (cin, T*B) = sum over taps of the shifted rows of dcols.
inline void col2im_1d(const Mat& dcols, int T, int k, int cin, Mat& dx) {
    const int B = (int)(dcols.cols() / T), pad = k / 2;
    dx.setZero(cin, dcols.cols());
    for (int b = 0; b < B; ++b)
        for (int j = 0; j < k; ++j) {
            const int s = j - pad, t0 = std::max(0, -s), t1 = std::min(T, T - s);
            if (t1 > t0)
                dx.block(0, (long)b * T + t0 + s, cin, t1 - t0) += dcols.block((long)j * cin, (long)b * T + t0, cin, t1 - t0);
        }
}
}  // namespace detail

// Conv1d, stride 1, same padding (k odd), zero padding per item: x (cin, T*B) -> y (cout, T*B).
// W (cout, k*cin) listed {k, cin, cout} (Flax's kernel layout); b (cout). im2col + one GEMM.
// backward(x, T, dy, dx).
struct Conv1d {
    ParamStore* ps = nullptr;
    int cin = 0, cout = 0, k = 0, w = -1, b = -1;
    Mat cols, dcols;  // (k*cin, T*B): im2col of the last input, and its gradient

    Conv1d() = default;
    Conv1d(ParamStore& ps_, const std::string& name, int cin_, int cout_, int k_, Rng& rng)
        : ps(&ps_), cin(cin_), cout(cout_), k(k_) {
        MADBP_ASSERT(k % 2 == 1);
        const float bound = 1.0f / std::sqrt((float)(cin * k));
        w = ps->add(name + ".weight", {k, cin, cout}, Init::uniform(bound), rng);
        b = ps->add(name + ".bias", {cout}, Init::uniform(bound), rng);
    }
    void forward(const Mat& x, int T, Mat& y) {
        MADBP_ASSERT(x.rows() == cin && T > 0 && x.cols() % T == 0);
        detail::im2col_1d(x, T, k, cols);
        y.resize(cout, x.cols());
        detail::product_by_columns(ps->view(w, cout, k * cin), cols, y);
        y.colwise() += ps->vec(b, cout);
    }
    void backward(const Mat& x, int T, const Mat& dy, Mat& dx) {
        detail::add_product_transposed(ps->grad_view(w, cout, k * cin), dy, cols);
        ps->grad_vec(b, cout) += dy.rowwise().sum();
        dcols.resize((long)k * cin, dy.cols());
        detail::product_by_columns(ps->view(w, cout, k * cin).transpose(), dy, dcols);
        detail::col2im_1d(dcols, T, k, cin, dx);
    }
};

// ConvTranspose1d, k 4, stride 2, pad 1 (as PyTorch's): x (cin, T*B) -> y (cout, 2T*B), the
// learned alternative to Upsample1d. Input t feeds outputs 2t - 1 + j, j = 0..3, within its
// item. W (4*cout, cin) listed {cin, 4, cout}; b (cout). backward(x, T, dy, dx).
struct ConvTranspose1d {
    static constexpr int k = 4;
    ParamStore* ps = nullptr;
    int cin = 0, cout = 0, w = -1, b = -1;
    Mat cols, dcols;  // (4*cout, T*B): W x before the overlap-add, and its gradient

    ConvTranspose1d() = default;
    ConvTranspose1d(ParamStore& ps_, const std::string& name, int cin_, int cout_, Rng& rng)
        : ps(&ps_), cin(cin_), cout(cout_) {
        const float bound = 1.0f / std::sqrt((float)(cout * k));  // PyTorch's fan_in for this layer
        w = ps->add(name + ".weight", {cin, k, cout}, Init::uniform(bound), rng);
        b = ps->add(name + ".bias", {cout}, Init::uniform(bound), rng);
    }
    void forward(const Mat& x, int T, Mat& y) {
        MADBP_ASSERT(x.rows() == cin && T > 0 && x.cols() % T == 0);
        const int B = (int)(x.cols() / T);
        cols.resize((long)k * cout, x.cols());
        detail::product_by_columns(ps->view(w, k * cout, cin), x, cols);
        y.resize(cout, x.cols() * 2);
        y.colwise() = ps->vec(b, cout);
        for (int bi = 0; bi < B; ++bi)
            for (int t = 0; t < T; ++t)
                for (int j = 0; j < k; ++j) {
                    const int to = 2 * t - 1 + j;
                    if (to >= 0 && to < 2 * T) y.col((long)bi * 2 * T + to) += cols.col((long)bi * T + t).segment(j * cout, cout);
                }
    }
    void backward(const Mat& x, int T, const Mat& dy, Mat& dx) {
        const int B = (int)(x.cols() / T);
        ps->grad_vec(b, cout) += dy.rowwise().sum();
        dcols.resize((long)k * cout, x.cols());
        for (int bi = 0; bi < B; ++bi)
            for (int t = 0; t < T; ++t)
                for (int j = 0; j < k; ++j) {
                    const int to = 2 * t - 1 + j;
                    auto d = dcols.col((long)bi * T + t).segment(j * cout, cout);
                    if (to >= 0 && to < 2 * T) d = dy.col((long)bi * 2 * T + to);
                    else d.setZero();
                }
        detail::add_product_transposed(ps->grad_view(w, k * cout, cin), dcols, x);
        dx.resize(cin, x.cols());
        detail::product_by_columns(ps->view(w, k * cout, cin).transpose(), dcols, dx);
    }
};

// BatchNorm1d over columns, per channel: x (C, N) -> y (C, N); gain, bias (C) trainable;
// running_mean, running_var (C) non-trainable (momentum 0.1, eps 1e-5, unbiased running var
// as PyTorch). column_mask: N of 0/1 or nullptr. In training mode the statistics count only
// columns whose mask is 1; every column is normalised with them, and only masked-in columns
// receive gradient through the statistics (the exact gradient of this forward). With no
// masked-in column the running statistics are used and left alone. Eval mode uses the running
// statistics. backward(x, column_mask, dy, dx).
struct BatchNorm1d {
    ParamStore* ps = nullptr;
    int C = 0, gain = -1, bias = -1, running_mean = -1, running_var = -1;
    bool training = true;
    float momentum = 0.1f, eps = 1e-5f;
    Vec mean, rstd, dxhat_sum, dxhat_xhat_sum;  // (C)
    Mat xhat;                                   // (C, N) normalised input, kept for backward
    bool used_batch_stats = false;
    float count = 0;  // masked-in columns of the last training forward

    BatchNorm1d() = default;
    BatchNorm1d(ParamStore& ps_, const std::string& name, int C_, Rng& rng) : ps(&ps_), C(C_) {
        gain = ps->add(name + ".weight", {C}, Init::ones(), rng);
        bias = ps->add(name + ".bias", {C}, Init::zeros(), rng);
        running_mean = ps->add(name + ".running_mean", {C}, Init::zeros(), rng, false);
        running_var = ps->add(name + ".running_var", {C}, Init::ones(), rng, false);
    }
    static bool on(const float* column_mask, int j) { return !column_mask || column_mask[j] != 0; }

    void forward(const Mat& x, const float* column_mask, Mat& y) {
        MADBP_ASSERT(x.rows() == C);
        const int N = (int)x.cols();
        mean.resize(C);
        rstd.resize(C);
        count = 0;
        if (training)
            for (int j = 0; j < N; ++j) count += on(column_mask, j) ? 1.0f : 0.0f;
        used_batch_stats = training && count > 0;
        auto rm = ps->vec(running_mean, C);
        auto rv = ps->vec(running_var, C);
        if (used_batch_stats) {
            mean.setZero();
            for (int j = 0; j < N; ++j)
                if (on(column_mask, j)) mean += x.col(j);
            mean /= count;
            rstd.setZero();  // the biased variance first
            for (int j = 0; j < N; ++j)
                if (on(column_mask, j)) rstd.array() += (x.col(j) - mean).array().square();
            rstd /= count;
            const float unbias = count > 1 ? count / (count - 1) : 1.0f;
            rm = (1 - momentum) * rm + momentum * mean;
            rv = (1 - momentum) * rv + (momentum * unbias) * rstd;
            rstd = (rstd.array() + eps).rsqrt();
        } else {
            mean = rm;
            rstd = (rv.array() + eps).rsqrt();
        }
        xhat.resize(C, N);
        xhat = (x.colwise() - mean).array().colwise() * rstd.array();
        y.resize(C, N);
        y = (xhat.array().colwise() * ps->vec(gain, C).array()).colwise() + ps->vec(bias, C).array();
    }
    void backward(const Mat& x, const float* column_mask, const Mat& dy, Mat& dx) {
        const int N = (int)x.cols();
        auto g = ps->vec(gain, C);
        ps->grad_vec(gain, C) += dy.cwiseProduct(xhat).rowwise().sum();
        ps->grad_vec(bias, C) += dy.rowwise().sum();
        dx.resize(C, N);
        // dxhat = dy * gain; dx = rstd * (dxhat - m_j/n * (sum dxhat + xhat * sum dxhat*xhat)).
        dx = dy.array().colwise() * (g.array() * rstd.array());  // rstd * dxhat
        if (!used_batch_stats) return;
        // Both sums run over every column: masked-out columns are normalised with the batch
        // statistics too. Pre-scaled by rstd / n.
        dxhat_sum = dy.rowwise().sum().cwiseProduct(g).cwiseProduct(rstd) / count;
        dxhat_xhat_sum = dy.cwiseProduct(xhat).rowwise().sum().cwiseProduct(g).cwiseProduct(rstd) / count;
        for (int j = 0; j < N; ++j)
            if (on(column_mask, j)) dx.col(j) -= dxhat_sum + xhat.col(j).cwiseProduct(dxhat_xhat_sum);
    }
};

// MaxPool1d, kernel 2, stride 2 over time per item (T even): x (C, T*B) -> y (C, T/2*B).
// Ties send the gradient to the first element. backward(x, T, dy, dx).
struct MaxPool1d {
    Eigen::Matrix<unsigned char, Eigen::Dynamic, Eigen::Dynamic> second;  // (C, T/2*B) 1: max at 2t+1

    void forward(const Mat& x, int T, Mat& y) {
        MADBP_ASSERT(T % 2 == 0 && x.cols() % T == 0);
        const long half = x.cols() / 2;
        y.resize(x.rows(), half);
        second.resize(x.rows(), half);
        for (long o = 0; o < half; ++o)  // T even, so pairs (2o, 2o+1) never straddle items
            for (long c = 0; c < x.rows(); ++c) {
                const float a = x(c, 2 * o), b = x(c, 2 * o + 1);
                second(c, o) = b > a;
                y(c, o) = b > a ? b : a;
            }
    }
    void backward(const Mat& x, int T, const Mat& dy, Mat& dx) {
        dx.resize(x.rows(), x.cols());
        for (long o = 0; o < dy.cols(); ++o)
            for (long c = 0; c < x.rows(); ++c) {
                dx(c, 2 * o) = second(c, o) ? 0.0f : dy(c, o);
                dx(c, 2 * o + 1) = second(c, o) ? dy(c, o) : 0.0f;
            }
    }
};

// Upsample1d, nearest x2 over time: x (C, T*B) -> y (C, 2T*B); y(2t) = y(2t+1) = x(t).
// backward(x, dy, dx).
struct Upsample1d {
    void forward(const Mat& x, Mat& y) {
        y.resize(x.rows(), x.cols() * 2);
        for (long t = 0; t < x.cols(); ++t) y.col(2 * t) = y.col(2 * t + 1) = x.col(t);
    }
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        dx.resize(x.rows(), x.cols());
        for (long t = 0; t < x.cols(); ++t) dx.col(t) = dy.col(2 * t) + dy.col(2 * t + 1);
    }
};

// Conv2d with stride and zero padding: x (cin, H*W*B), column b*H*W + y*W + x ->
// y (cout, H'*W'*B), H' = (H + 2 pad - k) / stride + 1. W (cout, k*k*cin) listed
// {k, k, cin, cout} (HWIO); b (cout). im2col + one GEMM. backward(x, H, W, dy, dx).
struct Conv2d {
    ParamStore* ps = nullptr;
    int cin = 0, cout = 0, k = 0, stride = 1, pad = 0, w = -1, b = -1;
    int H = 0, W = 0, Ho = 0, Wo = 0;  // sizes of the last forward
    Mat cols, dcols;                   // (k*k*cin, Ho*Wo*B)

    Conv2d() = default;
    Conv2d(ParamStore& ps_, const std::string& name, int cin_, int cout_, int k_, int stride_, int pad_, Rng& rng)
        : ps(&ps_), cin(cin_), cout(cout_), k(k_), stride(stride_), pad(pad_) {
        MADBP_ASSERT(k > 0 && stride > 0 && pad >= 0);
        const float bound = 1.0f / std::sqrt((float)(cin * k * k));
        w = ps->add(name + ".weight", {k, k, cin, cout}, Init::uniform(bound), rng);
        b = ps->add(name + ".bias", {cout}, Init::uniform(bound), rng);
    }
    int out_size(int n) const { return (n + 2 * pad - k) / stride + 1; }

    // Calls f(col, row, in) for every tap of every output position: `col` indexes cols, `row`
    // the tap's first row in it, `in` the input column it reads, or -1 in the zero padding.
    template <class F>
    void for_each_tap(long B, const F& f) const {
        for (long bi = 0; bi < B; ++bi)
            for (int oy = 0; oy < Ho; ++oy)
                for (int ox = 0; ox < Wo; ++ox)
                    for (int ky = 0; ky < k; ++ky)
                        for (int kx = 0; kx < k; ++kx) {
                            const int iy = oy * stride - pad + ky, ix = ox * stride - pad + kx;
                            const bool inside = iy >= 0 && iy < H && ix >= 0 && ix < W;
                            f(bi * Ho * Wo + oy * Wo + ox, (ky * k + kx) * cin, inside ? bi * H * W + iy * W + ix : -1);
                        }
    }
    void forward(const Mat& x, int H_, int W_, Mat& y) {
        H = H_, W = W_, Ho = out_size(H), Wo = out_size(W);
        MADBP_ASSERT(x.rows() == cin && x.cols() % ((long)H * W) == 0 && Ho > 0 && Wo > 0);
        const long B = x.cols() / ((long)H * W);
        cols.resize((long)k * k * cin, Ho * Wo * B);
        for_each_tap(B, [&](long col, int row, long in) {
            if (in < 0) cols.col(col).segment(row, cin).setZero();
            else cols.col(col).segment(row, cin) = x.col(in);
        });
        y.resize(cout, cols.cols());
        detail::product_by_columns(ps->view(w, cout, k * k * cin), cols, y);
        y.colwise() += ps->vec(b, cout);
    }
    void backward(const Mat& x, int H_, int W_, const Mat& dy, Mat& dx) {
        MADBP_ASSERT(H_ == H && W_ == W);
        const long B = x.cols() / ((long)H * W);
        detail::add_product_transposed(ps->grad_view(w, cout, k * k * cin), dy, cols);
        ps->grad_vec(b, cout) += dy.rowwise().sum();
        dcols.resize(cols.rows(), cols.cols());
        detail::product_by_columns(ps->view(w, cout, k * k * cin).transpose(), dy, dcols);
        dx.setZero(cin, x.cols());
        for_each_tap(B, [&](long col, int row, long in) {
            if (in >= 0) dx.col(in) += dcols.col(col).segment(row, cin);
        });
    }
};

// ---------------------------------------------------------------------------------------------
// Element-wise activations: x (C, N) -> y (C, N). backward(x, dy, dx).
struct ReLU {
    void forward(const Mat& x, Mat& y) { y = x.cwiseMax(0.0f); }
    void backward(const Mat& x, const Mat& dy, Mat& dx) { dx = (x.array() > 0).select(dy, 0.0f); }
};

namespace detail {
inline float sigmoid(float x) { return 1.0f / (1.0f + std::exp(-x)); }
inline float softplus(float x) { return x > 20.0f ? x : std::log1p(std::exp(x)); }
}  // namespace detail

// SiLU (swish): y = x * sigmoid(x).
struct SiLU {
    void forward(const Mat& x, Mat& y) {
        y = x.unaryExpr([](float v) { return v * detail::sigmoid(v); });
    }
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        dx = x.binaryExpr(dy, [](float v, float d) {
            const float s = detail::sigmoid(v);
            return d * s * (1.0f + v * (1.0f - s));
        });
    }
};

// Mish: y = x * tanh(softplus(x)) (Diffuser's U-Net activation). With e = exp(x),
// tanh(log(1 + e)) = e (e + 2) / (e (e + 2) + 2): one vectorised exp instead of three scalar
// libm calls (x is capped at 20, where the ratio is 1 in float).
struct Mish {
    Mat e, t;  // exp(min(x, 20)) and tanh(softplus(x)), kept between forward and backward
    void forward(const Mat& x, Mat& y) {
        e = x.array().min(20.0f).exp();
        t = (e.array() * (e.array() + 2)) / (e.array() * (e.array() + 2) + 2);
        y = x.array() * t.array();
    }
    // d/dx = t + x (1 - t^2) sigmoid(x), sigmoid(x) = e / (1 + e).
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        dx = dy.array() * (t.array() + x.array() * (1 - t.array().square()) * (e.array() / (1 + e.array())));
    }
};

struct Tanh {
    void forward(const Mat& x, Mat& y) { y = x.array().tanh(); }
    void backward(const Mat& x, const Mat& dy, Mat& dx) {
        dx = x.binaryExpr(dy, [](float v, float d) {
            const float t = std::tanh(v);
            return d * (1.0f - t * t);
        });
    }
};

// Embedding: ids (N) in [0, count) -> y (dim, N). Table (dim, count) listed {count, dim},
// N(0, 1) initialised as PyTorch. An id out of range throws std::invalid_argument.
// backward(ids, N, dy) adds into the table rows used.
struct Embedding {
    ParamStore* ps = nullptr;
    int count = 0, dim = 0, table = -1;

    Embedding() = default;
    Embedding(ParamStore& ps_, const std::string& name, int count_, int dim_, Rng& rng)
        : ps(&ps_), count(count_), dim(dim_) {
        table = ps->add(name + ".weight", {count, dim}, Init::normal(1.0f), rng);
    }
    void check(const int* ids, int N) const {
        for (int n = 0; n < N; ++n)
            if (ids[n] < 0 || ids[n] >= count)
                throw std::invalid_argument("embedding id: " + std::to_string(ids[n]) + " at position " +
                                            std::to_string(n) + " is outside [0, " + std::to_string(count) + ")");
    }
    void forward(const int* ids, int N, Mat& y) {
        check(ids, N);
        auto tab = ps->view(table, dim, count);
        y.resize(dim, N);
        for (int n = 0; n < N; ++n) y.col(n) = tab.col(ids[n]);
    }
    void backward(const int* ids, int N, const Mat& dy) {
        check(ids, N);
        auto gtab = ps->grad_view(table, dim, count);
        for (int n = 0; n < N; ++n) gtab.col(ids[n]) += dy.col(n);
    }
};

// Sinusoidal embedding of scalars (the diffusion step) as DDPM/Diffuser: t (N) -> y (dim, N),
// rows [0, dim/2) sin(t f_i), rows [dim/2, dim) cos(t f_i), f_i = exp(-ln(10000) i / (dim/2 - 1)).
// dim even, >= 4.
inline double sinusoidal_frequency(int i, int dim) { return std::exp(-std::log(10000.0) * i / (dim / 2 - 1)); }

inline void sinusoidal_embedding(const float* t, int N, int dim, Mat& y) {
    MADBP_ASSERT(dim % 2 == 0 && dim >= 4);
    const int half = dim / 2;
    y.resize(dim, N);
    for (int n = 0; n < N; ++n)
        for (int i = 0; i < half; ++i) {
            const double arg = t[n] * sinusoidal_frequency(i, dim);
            y(i, n) = (float)std::sin(arg);
            y(half + i, n) = (float)std::cos(arg);
        }
}
// Writes dt[n] = sum_i dy(i, n) * d y(i, n) / d t[n].
inline void sinusoidal_embedding_backward(const float* t, int N, int dim, const Mat& dy, float* dt) {
    const int half = dim / 2;
    for (int n = 0; n < N; ++n) {
        double acc = 0;
        for (int i = 0; i < half; ++i) {
            const double f = sinusoidal_frequency(i, dim), arg = t[n] * f;
            acc += dy(i, n) * f * std::cos(arg) - dy(half + i, n) * f * std::sin(arg);
        }
        dt[n] = (float)acc;
    }
}

// FiLM: x (C, T*B), gamma, beta (C, B) -> y (C, T*B) = x * (1 + gamma) + beta, per item.
inline void film_forward(const Mat& x, int T, const Mat& gamma, const Mat& beta, Mat& y) {
    const long B = gamma.cols();
    MADBP_ASSERT(x.cols() == T * B && gamma.rows() == x.rows() && beta.rows() == x.rows() && beta.cols() == B);
    y.resize(x.rows(), x.cols());
    for (long b = 0; b < B; ++b) {  // as x + x * gamma + beta: Eigen broadcasts plain columns without a temporary
        auto yb = y.middleCols(b * T, T).array();
        yb = (x.middleCols(b * T, T).array().colwise() * gamma.col(b).array()).colwise() + beta.col(b).array();
        yb += x.middleCols(b * T, T).array();
    }
}
// Writes dx (C, T*B), dgamma and dbeta (C, B).
inline void film_backward(const Mat& x, int T, const Mat& gamma, const Mat& dy, Mat& dx, Mat& dgamma, Mat& dbeta) {
    const long B = gamma.cols();
    dx.resize(x.rows(), x.cols());
    dgamma.resize(gamma.rows(), B);
    dbeta.resize(gamma.rows(), B);
    for (long b = 0; b < B; ++b) {
        dx.middleCols(b * T, T) = dy.middleCols(b * T, T).array().colwise() * gamma.col(b).array();
        dx.middleCols(b * T, T) += dy.middleCols(b * T, T);
        dgamma.col(b) = dy.middleCols(b * T, T).cwiseProduct(x.middleCols(b * T, T)).rowwise().sum();
        dbeta.col(b) = dy.middleCols(b * T, T).rowwise().sum();
    }
}

// ---------------------------------------------------------------------------------------------
// Optimisation. Adam with bias correction and eps outside the square root; weight_decay is
// decoupled (AdamW: p -= lr * wd * p). Skips non-trainable entries. m and v (P) are the
// state to checkpoint with `step` (see append_adam / read_adam).
struct Adam {
    float lr = 3e-4f, beta1 = 0.9f, beta2 = 0.999f, eps = 1e-8f, weight_decay = 0;
    long step = 0;
    Vec m, v;

    void update(ParamStore& ps) {
        if (m.size() != ps.size() || v.size() != ps.size()) {
            MADBP_ASSERT(step == 0);  // resumed state must match the store
            m.setZero(ps.size());
            v.setZero(ps.size());
        }
        ++step;
        const float bc1 = (float)(1.0 - std::pow((double)beta1, (double)step));
        const float bc2 = (float)(1.0 - std::pow((double)beta2, (double)step));
        for (auto& e : ps.entries) {
            if (!e.trainable) continue;
            const int o = e.offset, n = e.numel();
            auto p = ps.value.segment(o, n).array();
            auto g = ps.grad.segment(o, n).array();
            auto mm = m.segment(o, n).array();
            auto vv = v.segment(o, n).array();
            mm = beta1 * mm + (1 - beta1) * g;
            vv = beta2 * vv + (1 - beta2) * g.square();
            p -= lr * ((mm / bc1) / ((vv / bc2).sqrt() + eps) + weight_decay * p);
        }
    }
};

// Scales the trainable gradients so that their global L2 norm is at most max_norm (PyTorch's
// clip_grad_norm_); returns the norm before clipping. A non-finite norm leaves the gradients
// untouched, so the caller can skip the step.
inline float clip_grad_norm(ParamStore& ps, float max_norm) {
    double sq = 0;
    for (auto& e : ps.entries)
        if (e.trainable) sq += ps.grad.segment(e.offset, e.numel()).cast<double>().squaredNorm();
    const double norm = std::sqrt(sq);
    if (std::isfinite(norm) && norm > max_norm) {
        const float scale = (float)(max_norm / (norm + 1e-6));
        for (auto& e : ps.entries)
            if (e.trainable) ps.grad.segment(e.offset, e.numel()) *= scale;
    }
    return (float)norm;
}

// Exponential moving average of the weights: shadow = decay * shadow + (1 - decay) * value
// for trainable entries; non-trainable ones (running statistics) are copied. The first update
// copies everything. shadow (P) is the state to checkpoint.
struct Ema {
    float decay = 0.995f;
    Vec shadow;

    void update(const ParamStore& ps) {
        if (shadow.size() != ps.size()) {
            shadow = ps.value;
            return;
        }
        for (auto& e : ps.entries) {
            auto s = shadow.segment(e.offset, e.numel());
            auto p = ps.value.segment(e.offset, e.numel());
            if (e.trainable) s = decay * s + (1 - decay) * p;
            else s = p;
        }
    }
    void copy_to(ParamStore& ps) const {
        MADBP_ASSERT(shadow.size() == ps.size());
        ps.value = shadow;
    }
};

// ===== Checkpoints (safetensors) =====
//
// File layout (huggingface safetensors): u64 little-endian N; N bytes of UTF-8 JSON
// {"__metadata__": {"key": "value", ...}, "name": {"dtype": "F32", "shape": [..],
// "data_offsets": [begin, end]}, ...}, padded with spaces so the payload starts 8-aligned;
// then the payload, raw little-endian float32, offsets relative to its start. Read in Python
// with safetensors.numpy.load_file(path) or json + numpy.frombuffer.

static_assert(std::numeric_limits<float>::is_iec559, "checkpoints store IEEE float32");
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "madbp checkpoints are little-endian; add a byte swap for this platform"
#endif

// shape row-major (numpy order); data holds prod(shape) values in that order.
struct NamedTensor {
    std::string name;
    std::vector<int> shape;
    std::vector<float> data;
};

// The tensors (in payload order) and metadata of a checkpoint.
struct SafeTensors {
    std::string source;  // the file name, for error messages
    std::vector<NamedTensor> tensors;
    std::map<std::string, std::string> metadata;

    const NamedTensor* find(const std::string& name) const {
        for (auto& t : tensors)
            if (t.name == name) return &t;
        return nullptr;
    }
    const NamedTensor& at(const std::string& name) const {
        if (const NamedTensor* t = find(name)) return *t;
        throw std::runtime_error(source + ": tensor '" + name + "' is missing");
    }
    const std::string& meta(const std::string& key) const {
        auto it = metadata.find(key);
        if (it == metadata.end()) throw std::runtime_error(source + ": __metadata__ has no '" + key + "'");
        return it->second;
    }
};

namespace detail {

inline bool valid_utf8(const uint8_t* s, size_t n) {
    size_t i = 0;
    while (i < n) {
        const uint8_t c = s[i];
        int len;
        uint32_t cp;
        if (c < 0x80) { ++i; continue; }
        else if ((c & 0xE0) == 0xC0) { len = 2; cp = c & 0x1F; }
        else if ((c & 0xF0) == 0xE0) { len = 3; cp = c & 0x0F; }
        else if ((c & 0xF8) == 0xF0) { len = 4; cp = c & 0x07; }
        else return false;
        if (i + len > n) return false;
        for (int k = 1; k < len; ++k) {
            if ((s[i + k] & 0xC0) != 0x80) return false;
            cp = (cp << 6) | (s[i + k] & 0x3F);
        }
        // Reject overlong forms, surrogates and values past U+10FFFF.
        if ((len == 2 && cp < 0x80) || (len == 3 && cp < 0x800) || (len == 4 && cp < 0x10000) || cp > 0x10FFFF ||
            (cp >= 0xD800 && cp <= 0xDFFF))
            return false;
        i += len;
    }
    return true;
}

// A JSON value from a safetensors header. Numbers keep their literal text; objects keep their
// members in file order (keys[i] names items[i]).
struct JsonValue {
    enum Type { Null, Bool, Number, String, Array, Object } type = Null;
    std::string text;  // String: decoded value; Number: literal; Bool: "true"/"false"
    std::vector<std::string> keys;
    std::vector<JsonValue> items;
};

// Strict RFC 8259 parser for the header; nesting is limited so hostile input cannot exhaust
// the stack.
struct JsonParser {
    const char* p;
    const char* end;
    const std::string& source;
    const char* begin;
    int depth = 0;

    JsonParser(const char* data, size_t n, const std::string& source_) : p(data), end(data + n), source(source_), begin(data) {}

    [[noreturn]] void fail(const std::string& what) const {
        throw std::runtime_error(source + ": header JSON: " + what + " at byte " + std::to_string(p - begin) + " of the header");
    }
    void skip_ws() {
        while (p < end && (*p == ' ' || *p == '\t' || *p == '\n' || *p == '\r')) ++p;
    }
    bool eat(char c) {
        skip_ws();
        if (p < end && *p == c) { ++p; return true; }
        return false;
    }
    void expect(char c) {
        if (!eat(c)) fail(std::string("expected '") + c + "'");
    }
    JsonValue parse_document() {
        JsonValue v = value();
        skip_ws();
        if (p != end) fail("unexpected text after the header object");
        return v;
    }
    JsonValue value() {
        skip_ws();
        if (p >= end) fail("unexpected end");
        JsonValue v;
        const char c = *p;
        if (c == '{' || c == '[') {
            if (++depth > 16) fail("nesting deeper than 16");
            ++p;
            const char close = c == '{' ? '}' : ']';
            v.type = c == '{' ? JsonValue::Object : JsonValue::Array;
            if (!eat(close)) {
                do {
                    if (v.type == JsonValue::Object) {
                        skip_ws();
                        if (p >= end || *p != '"') fail("expected a string key");
                        v.keys.push_back(string());
                        expect(':');
                    }
                    v.items.push_back(value());
                } while (eat(','));
                expect(close);
            }
            --depth;
        } else if (c == '"') {
            v.type = JsonValue::String;
            v.text = string();
        } else if (c == '-' || (c >= '0' && c <= '9')) {
            v.type = JsonValue::Number;
            v.text = number();
        } else if (literal("true") || literal("false")) {
            v.type = JsonValue::Bool;
            v.text = p[-1] == 'e' && p[-2] == 'u' ? "true" : "false";
        } else if (literal("null")) {
            v.type = JsonValue::Null;
        } else {
            fail("unexpected character");
        }
        return v;
    }
    bool literal(const char* word) {
        const size_t n = std::strlen(word);
        if ((size_t)(end - p) >= n && std::memcmp(p, word, n) == 0) { p += n; return true; }
        return false;
    }
    std::string number() {
        const char* start = p;
        auto digits = [&] {
            const char* d = p;
            while (p < end && *p >= '0' && *p <= '9') ++p;
            if (p == d) fail("malformed number");
        };
        if (*p == '-') ++p;
        if (p < end && *p == '0') ++p;
        else digits();
        if (p < end && *p == '.') { ++p; digits(); }
        if (p < end && (*p == 'e' || *p == 'E')) {
            ++p;
            if (p < end && (*p == '+' || *p == '-')) ++p;
            digits();
        }
        return std::string(start, p);
    }
    unsigned hex4() {
        if (end - p < 4) fail("truncated \\u escape");
        unsigned v = 0;
        for (int i = 0; i < 4; ++i, ++p) {
            const char c = *p;
            v <<= 4;
            if (c >= '0' && c <= '9') v |= c - '0';
            else if (c >= 'a' && c <= 'f') v |= c - 'a' + 10;
            else if (c >= 'A' && c <= 'F') v |= c - 'A' + 10;
            else fail("bad \\u escape");
        }
        return v;
    }
    static void put_utf8(std::string& out, uint32_t cp) {
        if (cp < 0x80) out += (char)cp;
        else if (cp < 0x800) { out += (char)(0xC0 | (cp >> 6)); out += (char)(0x80 | (cp & 0x3F)); }
        else if (cp < 0x10000) {
            out += (char)(0xE0 | (cp >> 12)); out += (char)(0x80 | ((cp >> 6) & 0x3F)); out += (char)(0x80 | (cp & 0x3F));
        } else {
            out += (char)(0xF0 | (cp >> 18)); out += (char)(0x80 | ((cp >> 12) & 0x3F));
            out += (char)(0x80 | ((cp >> 6) & 0x3F)); out += (char)(0x80 | (cp & 0x3F));
        }
    }
    std::string string() {
        ++p;  // the opening quote
        std::string out;
        while (true) {
            if (p >= end) fail("unterminated string");
            const unsigned char c = (unsigned char)*p++;
            if (c == '"') return out;
            if (c < 0x20) fail("control character in a string");
            if (c != '\\') { out += (char)c; continue; }
            if (p >= end) fail("unterminated escape");
            const char e = *p++;
            switch (e) {
                case '"': out += '"'; break;
                case '\\': out += '\\'; break;
                case '/': out += '/'; break;
                case 'b': out += '\b'; break;
                case 'f': out += '\f'; break;
                case 'n': out += '\n'; break;
                case 'r': out += '\r'; break;
                case 't': out += '\t'; break;
                case 'u': {
                    uint32_t cp = hex4();
                    if (cp >= 0xDC00 && cp <= 0xDFFF) fail("lone low surrogate in \\u escape");
                    if (cp >= 0xD800 && cp <= 0xDBFF) {
                        if (end - p < 2 || p[0] != '\\' || p[1] != 'u') fail("high surrogate without its pair");
                        p += 2;
                        const uint32_t lo = hex4();
                        if (lo < 0xDC00 || lo > 0xDFFF) fail("high surrogate without its pair");
                        cp = 0x10000 + ((cp - 0xD800) << 10) + (lo - 0xDC00);
                    }
                    put_utf8(out, cp);
                    break;
                }
                default: fail("unknown escape");
            }
        }
    }
};

inline void json_escape(std::string& out, const std::string& s) {
    out += '"';
    for (unsigned char c : s) {
        if (c == '"') out += "\\\"";
        else if (c == '\\') out += "\\\\";
        else if (c < 0x20) {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\u%04x", c);
            out += buf;
        } else out += (char)c;
    }
    out += '"';
}

// A non-negative integer field (shape entry or offset); fails naming `field`.
inline uint64_t json_uint(const JsonValue& v, const std::string& source, const std::string& field) {
    if (v.type != JsonValue::Number) throw std::runtime_error(source + ": " + field + " is not a number");
    if (v.text.empty() || v.text.size() > 19 || v.text.find_first_not_of("0123456789") != std::string::npos)
        throw std::runtime_error(source + ": " + field + " = " + v.text.substr(0, 32) + " is not a non-negative integer below 1e19");
    return std::stoull(v.text);
}

inline float load_f32_le(const uint8_t* p) {
    float f;
    std::memcpy(&f, p, 4);
    return f;
}

}  // namespace detail

constexpr uint64_t kSafetensorsMaxHeader = 100000000;  // the reference implementation's limit

// Parses and validates a whole safetensors file held in memory. Throws std::runtime_error
// naming `source` and the offending field on anything but a well-formed file of finite F32
// tensors whose offsets tile the payload exactly.
inline SafeTensors parse_safetensors(const uint8_t* data, size_t size, const std::string& source = "<memory>") {
    using detail::JsonValue;
    auto fail = [&](const std::string& what) -> void { throw std::runtime_error(source + ": " + what); };
    if (size < 8) fail("file is " + std::to_string(size) + " bytes, shorter than the 8-byte header size");
    uint64_t n = 0;
    for (int i = 7; i >= 0; --i) n = (n << 8) | data[i];
    if (n > kSafetensorsMaxHeader) fail("header size " + std::to_string(n) + " exceeds the 100 MB limit");
    if (n > size - 8)
        fail("header size " + std::to_string(n) + " runs past the end of the file (" + std::to_string(size) + " bytes)");
    const uint8_t* header = data + 8;
    if (!detail::valid_utf8(header, n)) fail("header is not valid UTF-8");
    if (n == 0 || header[0] != '{') fail("header does not start with '{'");
    detail::JsonParser parser((const char*)header, n, source);
    const JsonValue root = parser.parse_document();
    if (root.type != JsonValue::Object) fail("header is not a JSON object");

    SafeTensors st;
    st.source = source;
    const uint64_t payload = size - 8 - n;
    struct Span { uint64_t begin, end; size_t tensor; };
    std::vector<Span> spans;
    std::vector<std::string> seen;
    for (size_t i = 0; i < root.keys.size(); ++i) {
        const std::string& key = root.keys[i];
        const JsonValue& v = root.items[i];
        if (std::find(seen.begin(), seen.end(), key) != seen.end()) fail("duplicate key '" + key + "' in the header");
        seen.push_back(key);
        if (key == "__metadata__") {
            if (v.type != JsonValue::Object) fail("__metadata__ is not an object");
            for (size_t k = 0; k < v.keys.size(); ++k) {
                if (v.items[k].type != JsonValue::String) fail("__metadata__['" + v.keys[k] + "'] is not a string");
                if (!st.metadata.emplace(v.keys[k], v.items[k].text).second) fail("__metadata__ has key '" + v.keys[k] + "' twice");
            }
            continue;
        }
        if (key.empty()) fail("empty tensor name in the header");
        const std::string where = "tensor '" + key + "'";
        if (v.type != JsonValue::Object) fail(where + " is not an object");
        const JsonValue *dtype = nullptr, *shape = nullptr, *offsets = nullptr;
        for (size_t k = 0; k < v.keys.size(); ++k) {
            const JsonValue** slot = v.keys[k] == "dtype" ? &dtype : v.keys[k] == "shape" ? &shape
                                   : v.keys[k] == "data_offsets" ? &offsets : nullptr;
            if (!slot) fail(where + ": unknown field '" + v.keys[k] + "'");
            if (*slot) fail(where + ": field '" + v.keys[k] + "' given twice");
            *slot = &v.items[k];
        }
        if (!dtype || !shape || !offsets) fail(where + ": needs dtype, shape and data_offsets");
        if (dtype->type != JsonValue::String) fail(where + ": dtype is not a string");
        if (dtype->text != "F32") fail(where + ": dtype '" + dtype->text.substr(0, 16) + "' is not supported (only F32)");
        if (shape->type != JsonValue::Array) fail(where + ": shape is not an array");
        if (offsets->type != JsonValue::Array || offsets->items.size() != 2) fail(where + ": data_offsets is not [begin, end]");
        NamedTensor t;
        t.name = key;
        uint64_t numel = 1;
        bool overflow = false;
        for (size_t d = 0; d < shape->items.size(); ++d) {
            const uint64_t dim = detail::json_uint(shape->items[d], source, where + ": shape[" + std::to_string(d) + "]");
            if (dim > (uint64_t)std::numeric_limits<int>::max()) fail(where + ": shape[" + std::to_string(d) + "] is too large");
            t.shape.push_back((int)dim);
            if (dim != 0 && numel > std::numeric_limits<uint64_t>::max() / 4 / dim) overflow = true;
            numel *= dim;
        }
        const uint64_t begin = detail::json_uint(offsets->items[0], source, where + ": data_offsets[0]");
        const uint64_t end = detail::json_uint(offsets->items[1], source, where + ": data_offsets[1]");
        const std::string range = "[" + std::to_string(begin) + ", " + std::to_string(end) + "]";
        if (end < begin) fail(where + ": data_offsets " + range + " end before they begin");
        if (end > payload) fail(where + ": data_offsets " + range + " run past the payload (" + std::to_string(payload) + " bytes)");
        if (overflow || numel * 4 != end - begin)
            fail(where + ": shape " + detail::shape_string(t.shape) + " of F32 needs " + (overflow ? "too many" : std::to_string(numel * 4)) +
                 " bytes but data_offsets " + range + " hold " + std::to_string(end - begin));
        spans.push_back({begin, end, st.tensors.size()});
        st.tensors.push_back(std::move(t));
    }
    // The tensors must tile the payload: sorted by offset, each begins where the last ended.
    std::sort(spans.begin(), spans.end(), [](const Span& a, const Span& b) {
        return a.begin != b.begin ? a.begin < b.begin : a.end < b.end;
    });
    uint64_t expected = 0;
    for (const Span& s : spans) {
        const std::string& name = st.tensors[s.tensor].name;
        if (s.begin != expected)
            fail("tensor '" + name + "': data_offsets begin at " + std::to_string(s.begin) + " but the previous tensor ends at " +
                 std::to_string(expected) + (s.begin < expected ? " (overlap)" : " (gap)"));
        expected = s.end;
    }
    if (expected != payload)
        fail("tensors cover " + std::to_string(expected) + " bytes of a " + std::to_string(payload) + "-byte payload");
    const uint8_t* base = data + 8 + n;
    std::vector<NamedTensor> ordered;  // payload order
    for (const Span& s : spans) {
        NamedTensor& t = st.tensors[s.tensor];
        const size_t count = (size_t)((s.end - s.begin) / 4);
        t.data.resize(count);
        for (size_t i = 0; i < count; ++i) {
            const float f = detail::load_f32_le(base + s.begin + 4 * i);
            if (!std::isfinite(f))
                fail("tensor '" + t.name + "': element " + std::to_string(i) + " is " + (std::isnan(f) ? "NaN" : "infinite"));
            t.data[i] = f;
        }
        ordered.push_back(std::move(t));
    }
    st.tensors = std::move(ordered);
    return st;
}

// Serialises tensors (in the given order) and metadata into safetensors bytes. Throws
// std::invalid_argument on an empty, duplicate, reserved or non-UTF-8 name, a shape that does
// not match the data, or a non-finite value (which the reader would refuse).
inline std::vector<uint8_t> serialize_safetensors(const std::vector<NamedTensor>& tensors,
                                                  const std::map<std::string, std::string>& metadata) {
    auto utf8 = [](const std::string& s) { return detail::valid_utf8((const uint8_t*)s.data(), s.size()); };
    std::string header = "{";
    bool first = true;
    if (!metadata.empty()) {
        header += "\"__metadata__\":{";
        for (auto& kv : metadata) {
            if (!utf8(kv.first) || !utf8(kv.second)) throw std::invalid_argument("metadata '" + kv.first + "': not valid UTF-8");
            if (!first) header += ',';
            first = false;
            detail::json_escape(header, kv.first);
            header += ':';
            detail::json_escape(header, kv.second);
        }
        header += '}';
        first = false;
    }
    std::vector<std::string> names;
    uint64_t offset = 0;
    for (const NamedTensor& t : tensors) {
        if (t.name.empty() || t.name == "__metadata__" || !utf8(t.name))
            throw std::invalid_argument("tensor name '" + t.name + "': empty, reserved or not UTF-8");
        if (std::find(names.begin(), names.end(), t.name) != names.end())
            throw std::invalid_argument("tensor name '" + t.name + "': given twice");
        names.push_back(t.name);
        long numel = 1;
        for (int d : t.shape) {
            if (d < 0) throw std::invalid_argument("tensor '" + t.name + "': negative dimension in shape");
            numel *= d;
        }
        if ((size_t)numel != t.data.size())
            throw std::invalid_argument("tensor '" + t.name + "': shape " + detail::shape_string(t.shape) + " holds " +
                                        std::to_string(numel) + " values but data has " + std::to_string(t.data.size()));
        for (size_t i = 0; i < t.data.size(); ++i)
            if (!std::isfinite(t.data[i]))
                throw std::invalid_argument("tensor '" + t.name + "': element " + std::to_string(i) + " is not finite");
        if (!first) header += ',';
        first = false;
        detail::json_escape(header, t.name);
        header += ":{\"dtype\":\"F32\",\"shape\":[";
        for (size_t d = 0; d < t.shape.size(); ++d) header += (d ? "," : "") + std::to_string(t.shape[d]);
        header += "],\"data_offsets\":[" + std::to_string(offset) + "," + std::to_string(offset + 4 * numel) + "]}";
        offset += 4 * numel;
    }
    header += '}';
    while (header.size() % 8 != 0) header += ' ';  // payload 8-aligned, as the Python writer does
    std::vector<uint8_t> out(8 + header.size() + offset);
    uint64_t n = header.size();
    for (int i = 0; i < 8; ++i) out[i] = (uint8_t)(n >> (8 * i));
    std::memcpy(out.data() + 8, header.data(), header.size());
    uint8_t* dst = out.data() + 8 + header.size();
    for (const NamedTensor& t : tensors) {
        if (!t.data.empty()) std::memcpy(dst, t.data.data(), 4 * t.data.size());
        dst += 4 * t.data.size();
    }
    return out;
}

namespace detail {
[[noreturn]] inline void io_fail(const std::string& path, const std::string& what) {
    throw std::runtime_error(path + ": " + what + ": " + std::strerror(errno));
}
}  // namespace detail

// Writes bytes to `path` atomically: `path.tmp` is written and fsynced, then renamed over
// `path` (and the directory fsynced), so a crash leaves either the old file or the new one.
inline void write_file_atomic(const std::string& path, const std::vector<uint8_t>& bytes) {
    const std::string tmp = path + ".tmp";
    const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (fd < 0) detail::io_fail(tmp, "cannot create");
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t w = ::write(fd, bytes.data() + done, bytes.size() - done);
        if (w < 0 && errno == EINTR) continue;
        if (w <= 0) {
            const int err = errno;
            ::close(fd);
            ::unlink(tmp.c_str());
            errno = err;
            detail::io_fail(tmp, "write failed");
        }
        done += (size_t)w;
    }
    if (::fsync(fd) != 0 || ::close(fd) != 0) {
        const int err = errno;
        ::unlink(tmp.c_str());
        errno = err;
        detail::io_fail(tmp, "fsync/close failed");
    }
    if (::rename(tmp.c_str(), path.c_str()) != 0) {
        const int err = errno;
        ::unlink(tmp.c_str());
        errno = err;
        detail::io_fail(path, "rename from " + tmp + " failed");
    }
    const size_t slash = path.find_last_of('/');
    const std::string dir = slash == std::string::npos ? "." : slash == 0 ? "/" : path.substr(0, slash);
    const int dfd = ::open(dir.c_str(), O_RDONLY | O_CLOEXEC);
    if (dfd >= 0) {  // best effort: some file systems refuse fsync on directories
        ::fsync(dfd);
        ::close(dfd);
    }
}

inline std::vector<uint8_t> read_file(const std::string& path) {
    FILE* f = std::fopen(path.c_str(), "rb");
    if (!f) detail::io_fail(path, "cannot open");
    std::vector<uint8_t> bytes;
    uint8_t buf[1 << 16];
    size_t got;
    while ((got = std::fread(buf, 1, sizeof buf, f)) > 0) bytes.insert(bytes.end(), buf, buf + got);
    const bool error = std::ferror(f);
    std::fclose(f);
    if (error) detail::io_fail(path, "read failed");
    return bytes;
}

inline void save_safetensors(const std::string& path, const std::vector<NamedTensor>& tensors,
                             const std::map<std::string, std::string>& metadata) {
    write_file_atomic(path, serialize_safetensors(tensors, metadata));
}

inline SafeTensors load_safetensors(const std::string& path) {
    const std::vector<uint8_t> bytes = read_file(path);
    return parse_safetensors(bytes.data(), bytes.size(), path);
}

// --- Parameters and training state in checkpoints -------------------------------------------

inline NamedTensor make_tensor(const std::string& name, std::vector<int> shape, const float* data) {
    NamedTensor t{name, std::move(shape), {}};
    t.data.assign(data, data + detail::shape_numel(t.shape));
    return t;
}

// One tensor per store entry, named and shaped as the entry.
inline std::vector<NamedTensor> param_tensors(const ParamStore& ps) {
    std::vector<NamedTensor> out;
    for (auto& e : ps.entries) out.push_back(make_tensor(e.name, e.shape, ps.value.data() + e.offset));
    return out;
}

// Fills every store entry from the tensor of the same name; names and shapes must match
// exactly. Tensors named "optim.*" (training state) are ignored; any other tensor the store
// does not have is an error (a checkpoint of another model configuration).
inline void read_param_tensors(const SafeTensors& st, ParamStore& ps) {
    for (auto& e : ps.entries) {
        const NamedTensor& t = st.at(e.name);
        if (t.shape != e.shape)
            throw std::runtime_error(st.source + ": tensor '" + e.name + "' has shape " + detail::shape_string(t.shape) +
                                     " but the model expects " + detail::shape_string(e.shape));
    }
    for (auto& t : st.tensors)
        if (t.name.rfind("optim.", 0) != 0 && !ps.find(t.name))
            throw std::runtime_error(st.source + ": tensor '" + t.name + "' is not a parameter of this model");
    for (auto& e : ps.entries) {
        const NamedTensor& t = st.at(e.name);
        std::copy(t.data.begin(), t.data.end(), ps.value.data() + e.offset);
    }
}

inline void save_params(const std::string& path, const ParamStore& ps, const std::map<std::string, std::string>& metadata) {
    save_safetensors(path, param_tensors(ps), metadata);
}

inline void load_params(const std::string& path, ParamStore& ps) { read_param_tensors(load_safetensors(path), ps); }

// Reads a flat tensor of exactly n values into out (used for optimizer state).
inline void read_flat(const SafeTensors& st, const std::string& name, int n, Vec& out) {
    const NamedTensor& t = st.at(name);
    if (t.shape != std::vector<int>{n})
        throw std::runtime_error(st.source + ": tensor '" + name + "' has shape " + detail::shape_string(t.shape) + " but [" +
                                 std::to_string(n) + "] is expected");
    out = Eigen::Map<const Vec>(t.data.data(), n);
}

// Adam state: tensors optim.adam.m / optim.adam.v (P) and metadata "optim.adam.step".
// Only the moments and step are saved; hyper-parameters belong to the training config.
inline void append_adam(const Adam& adam, std::vector<NamedTensor>& tensors, std::map<std::string, std::string>& metadata) {
    tensors.push_back(make_tensor("optim.adam.m", {(int)adam.m.size()}, adam.m.data()));
    tensors.push_back(make_tensor("optim.adam.v", {(int)adam.v.size()}, adam.v.data()));
    metadata["optim.adam.step"] = std::to_string(adam.step);
}
inline void read_adam(const SafeTensors& st, int param_count, Adam& adam) {
    const std::string& s = st.meta("optim.adam.step");
    if (s.empty() || s.size() > 18 || s.find_first_not_of("0123456789") != std::string::npos)
        throw std::runtime_error(st.source + ": __metadata__['optim.adam.step'] = '" + s + "' is not a step count");
    read_flat(st, "optim.adam.m", param_count, adam.m);
    read_flat(st, "optim.adam.v", param_count, adam.v);
    adam.step = std::stol(s);
}

// EMA state: tensor optim.ema.shadow (P) and metadata "optim.ema.decay".
inline void append_ema(const Ema& ema, std::vector<NamedTensor>& tensors, std::map<std::string, std::string>& metadata) {
    tensors.push_back(make_tensor("optim.ema.shadow", {(int)ema.shadow.size()}, ema.shadow.data()));
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.9g", ema.decay);
    metadata["optim.ema.decay"] = buf;
}
inline void read_ema(const SafeTensors& st, int param_count, Ema& ema) {
    read_flat(st, "optim.ema.shadow", param_count, ema.shadow);
    const std::string& s = st.meta("optim.ema.decay");
    char* endp = nullptr;
    const float d = std::strtof(s.c_str(), &endp);
    if (s.empty() || *endp != '\0' || !(d >= 0 && d <= 1))
        throw std::runtime_error(st.source + ": __metadata__['optim.ema.decay'] = '" + s + "' is not a decay in [0, 1]");
    ema.decay = d;
}

// RNG state as metadata "<key>" = four decimal words (float tensors cannot hold u64 exactly).
inline void append_rng(const Rng& rng, const std::string& key, std::map<std::string, std::string>& metadata) {
    std::string s;
    for (int i = 0; i < 4; ++i) s += (i ? " " : "") + std::to_string(rng.s[i]);
    metadata[key] = s;
}
inline void read_rng(const SafeTensors& st, const std::string& key, Rng& rng) {
    const std::string& s = st.meta(key);
    uint64_t w[4];
    const char* p = s.c_str();
    for (int i = 0; i < 4; ++i) {
        char* endp = nullptr;
        errno = 0;
        if (*p < '0' || *p > '9') endp = const_cast<char*>(p);
        else w[i] = std::strtoull(p, &endp, 10);
        if (endp == p || errno == ERANGE || (i < 3 ? *endp != ' ' : *endp != '\0'))
            throw std::runtime_error(st.source + ": __metadata__['" + key + "'] = '" + s.substr(0, 80) + "' is not four 64-bit words");
        p = endp + (i < 3 ? 1 : 0);
    }
    if ((w[0] | w[1] | w[2] | w[3]) == 0) throw std::runtime_error(st.source + ": __metadata__['" + key + "'] is the all-zero state");
    for (int i = 0; i < 4; ++i) rng.s[i] = w[i];
}

}  // namespace madbp

// ===== MA-DBP model, diffusion and planner =====

namespace madbp {

// =============================================================================================
// MA-DBP model (SPEC 5): axial attention processor, context encoder, FiLM U-Net
// =============================================================================================
// Shapes: B scenes, n agent slots per scene (padded; inactive slots masked), A = B*n agent
// columns, H window length, D embedding width, d = 2 (positions), P = (G/8)^2 image tokens.
// A window tensor is (2, H*A) with column a*H + t (agent-major, time fastest), a = b*n + i,
// which is also the U-Net's layout (agents folded into the batch). Context positions (pose)
// are normalised by ModelConfig::position_scale (world units / scale). The diffused window
// holds each agent's displacement from its current position, (p_t - p_0) / window_scale, so
// column t = 0 is always 0 (inpainted) and the same motion looks the same anywhere in the
// world. The processor's Linear sees [displacement; current position], which contains the
// paper's Linear(absolute positions) as a special case.

enum class Processor { AAP, LE };      // axial attention processor | linear encoder (ablation)
enum class WindowMode { MW, CT };      // moving window | complete trajectory (ablation)
enum class Prediction { Eps, X0 };     // the network predicts the noise (paper) | the clean window

struct ModelConfig {
    int horizon = 16;                  // H, waypoints per window incl. the current position; multiple of 2^levels
    int waypoint_stride = 1;           // world steps between consecutive waypoints (the window spans (H-1)*stride steps)
    int dim = 64;                      // D, AAP / context embedding width
    int heads = 4;                     // attention heads, divides dim
    int n_max = 32;                    // agent slots of PE_agent: the largest team the model plans for
    int grid = 32;                     // G, occupancy grid side, multiple of 8
    int local_grid = 16;               // side of each agent's own crop of the map (0: none), multiple of 4
    float local_extent = 0.8f;         // the crop covers +-local_extent world units around the agent
    std::vector<int> channels = {32, 64};  // U-Net widths per level (levels = size)
    int kernel = 5;                    // U-Net Conv1d kernel, odd
    int diffusion_steps = 100;         // K (training)
    int sample_steps = 10;             // S (DDIM, default)
    Processor processor = Processor::AAP;
    WindowMode window = WindowMode::MW;
    float position_scale = 1.2f;       // world units per normalised pose unit (the training world's half-size)
    float window_scale = 0.6f;         // world units per normalised displacement (~ top speed x window time)
    Prediction prediction = Prediction::X0;  // measured better than the paper's eps here (README)

    int levels() const { return (int)channels.size(); }
    int image_tokens() const { return (grid / 8) * (grid / 8); }
    // Throws std::invalid_argument naming the field when a value is unusable.
    void validate() const {
        auto bad = [](const std::string& f, const std::string& why) { throw std::invalid_argument("model config " + f + ": " + why); };
        if (channels.empty() || channels.size() > 4) bad("channels", "needs 1 to 4 levels");
        for (int c : channels) if (c < 1 || c > 1024) bad("channels", "each width must be in [1, 1024]");
        if (horizon < 2 || horizon > 4096 || horizon % (1 << levels()) != 0)
            bad("horizon", std::to_string(horizon) + " must be in [2, 4096] and a multiple of 2^levels");
        if (dim < 4 || dim > 4096 || dim % 2 || heads < 1 || heads > 64 || dim % heads)
            bad("dim/heads", "dim must be even, in [4, 4096] and divisible by heads (1 to 64)");
        if (n_max < 1 || n_max > 1024) bad("n_max", "must be in [1, 1024]");
        if (grid < 8 || grid > 1024 || grid % 8) bad("grid", "must be a multiple of 8 in [8, 1024]");
        if (local_grid < 0 || local_grid % 4 || local_grid > 256) bad("local_grid", "must be 0 or a multiple of 4 up to 256");
        if (!(local_extent > 0) || !std::isfinite(local_extent)) bad("local_extent", "must be positive");
        if (kernel < 1 || kernel % 2 == 0) bad("kernel", "must be odd");
        if (waypoint_stride < 1 || waypoint_stride > 16) bad("waypoint_stride", "must be in [1, 16]");
        if (diffusion_steps < 2 || diffusion_steps > 100000) bad("diffusion_steps", "must be in [2, 100000]");
        if (sample_steps < 1 || sample_steps > diffusion_steps) bad("sample_steps", "must be in [1, diffusion_steps]");
        if (!(position_scale > 0) || !std::isfinite(position_scale)) bad("position_scale", "must be positive");
        if (!(window_scale > 0) || !std::isfinite(window_scale)) bad("window_scale", "must be positive");
    }
    std::map<std::string, std::string> to_metadata() const {
        std::string ch;
        for (size_t i = 0; i < channels.size(); ++i) ch += (i ? "," : "") + std::to_string(channels[i]);
        char scale[32];
        std::snprintf(scale, sizeof scale, "%.9g", position_scale);
        char wscale[32], lext[32];
        std::snprintf(wscale, sizeof wscale, "%.9g", window_scale);
        std::snprintf(lext, sizeof lext, "%.9g", local_extent);
        return {{"model", "madbp"}, {"horizon", std::to_string(horizon)}, {"waypoint_stride", std::to_string(waypoint_stride)}, {"dim", std::to_string(dim)},
                {"heads", std::to_string(heads)}, {"n_max", std::to_string(n_max)}, {"grid", std::to_string(grid)},
                {"channels", ch}, {"kernel", std::to_string(kernel)}, {"diffusion_steps", std::to_string(diffusion_steps)},
                {"sample_steps", std::to_string(sample_steps)}, {"processor", processor == Processor::AAP ? "AAP" : "LE"},
                {"window", window == WindowMode::MW ? "MW" : "CT"}, {"position_scale", scale}, {"window_scale", wscale},
                {"prediction", prediction == Prediction::Eps ? "eps" : "x0"}, {"local_grid", std::to_string(local_grid)},
                {"local_extent", lext}};
    }
    static ModelConfig from_metadata(const std::map<std::string, std::string>& md, const std::string& source) {
        auto get = [&](const std::string& k) -> const std::string& {
            auto it = md.find(k);
            if (it == md.end()) throw std::runtime_error(source + ": metadata field '" + k + "' is missing");
            return it->second;
        };
        auto integer = [&](const std::string& k) {
            const std::string& s = get(k);
            size_t pos = 0;
            long v = 0;
            try { v = std::stol(s, &pos); } catch (...) { pos = 0; }
            if (pos != s.size() || s.empty() || v < -(1L << 30) || v > (1L << 30))
                throw std::runtime_error(source + ": metadata field '" + k + "' is not an integer ('" + s + "')");
            return (int)v;
        };
        if (get("model") != "madbp") throw std::runtime_error(source + ": not an MA-DBP checkpoint (model = '" + get("model") + "')");
        ModelConfig c;
        c.horizon = integer("horizon");
        c.waypoint_stride = integer("waypoint_stride");
        c.dim = integer("dim");
        c.heads = integer("heads");
        c.n_max = integer("n_max");
        c.grid = integer("grid");
        c.kernel = integer("kernel");
        c.diffusion_steps = integer("diffusion_steps");
        c.sample_steps = integer("sample_steps");
        c.local_grid = integer("local_grid");
        c.channels.clear();
        std::stringstream ss(get("channels"));
        std::string item;
        while (std::getline(ss, item, ',')) {
            size_t pos = 0;
            int v = 0;
            try { v = std::stoi(item, &pos); } catch (...) { pos = 0; }
            if (pos == 0 || pos != item.size()) throw std::runtime_error(source + ": metadata field 'channels' is malformed");
            c.channels.push_back(v);
        }
        const std::string& p = get("processor");
        if (p != "AAP" && p != "LE") throw std::runtime_error(source + ": metadata field 'processor' must be AAP or LE");
        c.processor = p == "AAP" ? Processor::AAP : Processor::LE;
        const std::string& w = get("window");
        if (w != "MW" && w != "CT") throw std::runtime_error(source + ": metadata field 'window' must be MW or CT");
        c.window = w == "MW" ? WindowMode::MW : WindowMode::CT;
        auto real = [&](const std::string& k) {
            const std::string& s = get(k);
            char* end = nullptr;
            const float v = std::strtof(s.c_str(), &end);
            if (s.empty() || *end != '\0') throw std::runtime_error(source + ": metadata field '" + k + "' is not a number ('" + s + "')");
            return v;
        };
        c.position_scale = real("position_scale");
        c.window_scale = real("window_scale");
        c.local_extent = real("local_extent");
        const std::string& pr = get("prediction");
        if (pr != "eps" && pr != "x0") throw std::runtime_error(source + ": metadata field 'prediction' must be eps or x0");
        c.prediction = pr == "eps" ? Prediction::Eps : Prediction::X0;
        try { c.validate(); } catch (const std::invalid_argument& e) { throw std::runtime_error(source + ": " + e.what()); }
        return c;
    }
};

// The conditioning of one batch: B scenes with n agent slots each.
struct SceneBatch {
    int B = 0, n = 0;
    std::vector<float> agent_mask;  // (A) 1 = active agent, 0 = padding
    std::vector<int> slot;          // (A) PE_agent slot in [0, n_max), distinct within a scene
    std::vector<int> count;         // (B) active agents per scene (n_a)
    Mat pose;                       // (4, A) normalised current position x, y and goal x, y
    Mat grid;                       // (1, G*G*B) occupancy grid per scene, column b*G*G + row*G + col
    Mat local;                      // (1, Gl*Gl*A) each agent's crop of the map (local_crop), when Gl > 0
    bool shared_grid = false;       // grid holds one map for every scene (planning only; encoded once)

    int agents() const { return B * n; }
    int grid_scenes() const { return shared_grid ? 1 : B; }
    void resize(int B_, int n_, int G, int Gl = 0, bool shared = false) {
        B = B_;
        n = n_;
        shared_grid = shared;
        agent_mask.assign((size_t)B * n, 0.0f);
        slot.assign((size_t)B * n, 0);
        count.assign(B, 0);
        pose.setZero(4, B * n);
        grid.setZero(1, (long)G * G * grid_scenes());
        local.setZero(1, (long)Gl * Gl * B * n);
    }
    void resize(int B_, int n_, const ModelConfig& c, bool shared = false) { resize(B_, n_, c.grid, c.local_grid, shared); }
};

// An agent's own view of the static map: Gl x Gl cells of width 2 * extent / Gl centred on p
// (world units), row-major from the lowest y; a cell is 1 when an obstacle or wall surface is
// within half a cell of its centre (so thin walls are never missed) or it lies beyond the walls.
inline void local_crop(const Map& map, Vec2 p, int Gl, double extent, float* out) {
    const double w = 2 * extent / Gl;
    for (int row = 0; row < Gl; ++row)
        for (int col = 0; col < Gl; ++col) {
            const Vec2 c{p.x - extent + (col + 0.5) * w, p.y - extent + (row + 0.5) * w};
            out[row * Gl + col] = static_clearance(map, c) < 0.5 * w ? 1.0f : 0.0f;
        }
}
inline void fill_local_crop(SceneBatch& batch, int a, const Map& map, Vec2 p, const ModelConfig& c) {
    if (c.local_grid > 0) local_crop(map, p, c.local_grid, c.local_extent, batch.local.data() + (long)a * c.local_grid * c.local_grid);
}

namespace detail {
// x (C, H*A) agent-major (column a*H + t, a = b*n + i) <-> y (C, n*B*H) time-major
// (column (b*H + t)*n + i), the layout of attention over agents.
inline void agent_to_time_major(const Mat& x, int B, int n, int H, Mat& y) {
    y.resize(x.rows(), x.cols());
    for (int b = 0; b < B; ++b)
        for (int i = 0; i < n; ++i)
            for (int t = 0; t < H; ++t) y.col(((long)b * H + t) * n + i) = x.col(((long)b * n + i) * H + t);
}
inline void time_to_agent_major(const Mat& y, int B, int n, int H, Mat& x) {
    x.resize(y.rows(), y.cols());
    for (int b = 0; b < B; ++b)
        for (int i = 0; i < n; ++i)
            for (int t = 0; t < H; ++t) x.col(((long)b * n + i) * H + t) = y.col(((long)b * H + t) * n + i);
}
}  // namespace detail

// One U-Net level's block: x (cin, T*A) -> y (cout, T*A):
// Conv1d -> BatchNorm -> ReLU -> FiLM(cond) -> Conv1d -> BatchNorm -> ReLU.
// cond (D, A) gives gamma, beta (cout, A) through a Linear; BatchNorm counts active columns only.
struct ConvBlock {
    Conv1d conv1, conv2;
    BatchNorm1d bn1, bn2;
    ReLU relu1, relu2;
    Linear film;
    int cout = 0;
    Mat c1, n1, a1, gb, gamma, beta, f1, c2, n2;  // forward intermediates
    Mat d_a, d_b, d_gamma, d_beta, d_gb, d_cond;  // backward scratch

    ConvBlock() = default;
    ConvBlock(ParamStore& ps, const std::string& name, int cin, int cout_, int k, int cond_dim, Rng& rng)
        : conv1(ps, name + ".conv1", cin, cout_, k, rng), conv2(ps, name + ".conv2", cout_, cout_, k, rng),
          bn1(ps, name + ".bn1", cout_, rng), bn2(ps, name + ".bn2", cout_, rng),
          film(ps, name + ".film", cond_dim, 2 * cout_, rng), cout(cout_) {}

    void set_training(bool on) { bn1.training = bn2.training = on; }
    void forward(const Mat& x, int T, const Mat& cond, const float* mask, Mat& y) {
        conv1.forward(x, T, c1);
        bn1.forward(c1, mask, n1);
        relu1.forward(n1, a1);
        film.forward(cond, gb);
        gamma = gb.topRows(cout);
        beta = gb.bottomRows(cout);
        film_forward(a1, T, gamma, beta, f1);
        conv2.forward(f1, T, c2);
        bn2.forward(c2, mask, n2);
        relu2.forward(n2, y);
    }
    // Writes dx; ADDS the gradient with respect to cond into dcond.
    void backward(const Mat& x, int T, const Mat& cond, const float* mask, const Mat& dy, Mat& dx, Mat& dcond) {
        relu2.backward(n2, dy, d_a);
        bn2.backward(c2, mask, d_a, d_b);
        conv2.backward(f1, T, d_b, d_a);
        film_backward(a1, T, gamma, d_a, d_b, d_gamma, d_beta);
        d_gb.resize(2 * cout, d_gamma.cols());
        d_gb.topRows(cout) = d_gamma;
        d_gb.bottomRows(cout) = d_beta;
        film.backward(cond, d_gb, d_cond);
        dcond += d_cond;
        relu1.backward(n1, d_b, d_a);
        bn1.backward(c1, mask, d_a, d_b);
        conv1.backward(x, T, d_b, dx);
    }
};

// The denoiser eps_theta(X^k, k, c). Not copyable (layers point into its ParamStore); movable
// through the unique_ptr. Use: encode_context(batch) once per scene batch, then denoise(x, k)
// as often as the sampler needs; backward(d_eps) after one encode_context + denoise pair.
class MadbpModel {
public:
    ModelConfig config;
    std::unique_ptr<ParamStore> params;

    explicit MadbpModel(const ModelConfig& cfg, uint64_t seed = 0) : config(cfg), params(new ParamStore) {
        config.validate();
        build(seed);
    }
    MadbpModel(MadbpModel&&) = default;
    MadbpModel& operator=(MadbpModel&&) = default;
    MadbpModel(const MadbpModel&) = delete;
    MadbpModel& operator=(const MadbpModel&) = delete;

    // An independent copy (same config, parameters and mode) with its own workspaces.
    MadbpModel clone() const {
        MadbpModel m(config);
        m.params->value = params->value;
        m.set_training(training_);
        return m;
    }
    long parameter_count() const { return params->trainable_count(); }
    // Training mode: BatchNorm uses (masked) batch statistics and updates its running ones.
    void set_training(bool on) {
        training_ = on;
        for (auto& b : net_.down) b.set_training(on);
        for (auto& b : net_.up) b.set_training(on);
        net_.mid.set_training(on);
    }
    bool training() const { return training_; }

    // Context encoder (SPEC 5): grid CNN tokens, pose MLP, agent-count embedding, fused by
    // attention into ctx (D, A). Keeps `batch` (by reference) for denoise and backward.
    void encode_context(const SceneBatch& batch) {
        const ModelConfig& c = config;
        check_batch(batch);
        batch_ = &batch;
        const int B = batch.B, n = batch.n, G = c.grid, P = c.image_tokens();
        auto& e = enc_;
        e.g1.forward(batch.grid, G, G, e.g1o);
        e.r1.forward(e.g1o, e.g1a);
        e.g2.forward(e.g1a, G / 2, G / 2, e.g2o);
        e.r2.forward(e.g2o, e.g2a);
        if (batch.shared_grid) {  // one map for every scene: encode it once, give each scene a copy
            e.g3.forward(e.g2a, G / 4, G / 4, e.img_one);
            e.img.resize(c.dim, (long)P * B);
            for (int b = 0; b < B; ++b) e.img.middleCols((long)b * P, P) = e.img_one;
        } else {
            e.g3.forward(e.g2a, G / 4, G / 4, e.img);
        }
        e.img_ids.resize((size_t)P * B);
        for (int j = 0; j < P * B; ++j) e.img_ids[j] = j % P;
        e.pe_img.forward(e.img_ids.data(), P * B, e.tmp);
        e.img += e.tmp;
        e.pose1.forward(batch.pose, e.p1);
        e.pose_act.forward(e.p1, e.p1a);
        e.pose2.forward(e.p1a, e.pose_tok);
        if (c.local_grid > 0) {  // each agent's own crop of the map, added to its pose token
            const int Gl = c.local_grid;
            e.l1.forward(batch.local, Gl, Gl, e.l1o);
            e.r3.forward(e.l1o, e.l1a);
            e.l2.forward(e.l1a, Gl / 2, Gl / 2, e.l2o);
            e.r4.forward(e.l2o, e.l2a);
            e.l3.forward(e.l2a, Gl / 4, Gl / 4, e.local_tok);
            e.pose_tok += e.local_tok;
        }
        e.count_ids.assign(batch.count.begin(), batch.count.end());
        e.count_emb.forward(e.count_ids.data(), B, e.count_tok);
        // Keys of scene b: its P image tokens, its n pose tokens (inactive masked), its count token.
        const int Lk = P + n + 1;
        e.kv.resize(c.dim, (long)Lk * B);
        e.kv_mask.resize((size_t)Lk * B);
        for (int b = 0; b < B; ++b) {
            const long o = (long)b * Lk;
            e.kv.middleCols(o, P) = e.img.middleCols((long)b * P, P);
            e.kv.middleCols(o + P, n) = e.pose_tok.middleCols((long)b * n, n);
            e.kv.col(o + P + n) = e.count_tok.col(b);
            for (int j = 0; j < P; ++j) e.kv_mask[o + j] = 1.0f;
            for (int i = 0; i < n; ++i) e.kv_mask[o + P + i] = batch.agent_mask[(size_t)b * n + i];
            e.kv_mask[o + P + n] = 1.0f;
        }
        e.fuse.forward(e.pose_tok, n, e.kv, Lk, B, e.kv_mask.data(), e.att);
        e.pre_ln = e.pose_tok + e.att;
        e.ln.forward(e.pre_ln, ctx_);
        make_column_masks(batch);  // for the U-Net's BatchNorm; constant while the batch is
    }

    // eps (2, H*A) = eps_theta(x_noisy (2, H*A), k (B) diffusion step per scene, context).
    void denoise(const Mat& x_noisy, const int* k, Mat& eps) {
        const ModelConfig& c = config;
        MADBP_ASSERT(batch_ != nullptr);
        const SceneBatch& batch = *batch_;
        const int B = batch.B, n = batch.n, A = B * n, H = c.horizon;
        MADBP_ASSERT(x_noisy.rows() == 2 && x_noisy.cols() == (long)H * A);
        // Diffusion-step embedding, added to each agent's context, then FiLM at every level.
        auto& s = step_;
        s.k.resize(B);
        for (int b = 0; b < B; ++b) s.k[b] = (float)k[b];
        sinusoidal_embedding(s.k.data(), B, c.dim, s.sin);
        s.l1.forward(s.sin, s.h1);
        s.act.forward(s.h1, s.h1a);
        s.l2.forward(s.h1a, s.tok);
        s.cond_pre.resize(c.dim, A);
        for (int a = 0; a < A; ++a) s.cond_pre.col(a) = ctx_.col(a) + s.tok.col(a / n);
        s.cond_act.forward(s.cond_pre, cond_);
        process(x_noisy, batch);
        unet_forward(proc_.out, eps);
    }

    // Backward of the last encode_context + denoise: ADDS every parameter's gradient.
    void backward(const Mat& d_eps) {
        const ModelConfig& c = config;
        const SceneBatch& batch = *batch_;
        const int B = batch.B, n = batch.n, A = B * n;
        d_cond_.setZero(c.dim, A);
        unet_backward(d_eps, d_proc_);
        process_backward(d_proc_, batch);
        // cond = Mish(ctx + step_tok[scene]).
        auto& s = step_;
        s.cond_act.backward(s.cond_pre, d_cond_, s.d_pre);
        s.d_tok.setZero(c.dim, B);
        for (int a = 0; a < A; ++a) s.d_tok.col(a / n) += s.d_pre.col(a);
        s.l2.backward(s.h1a, s.d_tok, s.d_h1a);
        s.act.backward(s.h1, s.d_h1a, s.d_h1);
        s.l1.backward(s.sin, s.d_h1, s.d_sin);
        context_backward(s.d_pre, batch);
    }

    const Mat& context() const { return ctx_; }

private:
    bool training_ = true;
    const SceneBatch* batch_ = nullptr;
    Mat ctx_, cond_, d_cond_, d_proc_;
    std::vector<float> colmask_[5];  // per U-Net resolution: (T_l * A) active-agent column masks

    struct Encoder {
        Conv2d g1, g2, g3, l1, l2, l3;
        ReLU r1, r2, r3, r4;
        Embedding pe_img, count_emb;
        Linear pose1, pose2;
        Mish pose_act;
        MultiHeadAttention fuse;
        LayerNorm ln;
        std::vector<int> img_ids, count_ids;
        std::vector<float> kv_mask;
        Mat g1o, g1a, g2o, g2a, img, img_one, tmp, local_tok, p1, p1a, pose_tok, count_tok, kv, att, pre_ln, l1o, l1a, l2o, l2a;
        Mat d_l1o, d_l1a, d_l2o, d_l2a, d_local;
        Mat d_pre, d_pose, d_kv, d_img, d_g2a, d_g2o, d_g1a, d_g1o, d_grid, d_p1a, d_p1, d_posein, d_count;
    } enc_;
    struct StepEmbed {
        Linear l1, l2;
        Mish act, cond_act;
        std::vector<float> k;
        Mat sin, h1, h1a, tok, cond_pre;
        Mat d_pre, d_tok, d_h1a, d_h1, d_sin;
    } step_;
    struct Processor_ {
        Linear in_proj, mlp1, mlp2;
        Embedding pe_agent, pe_time;
        MultiHeadAttention time_attn, agent_attn;
        LayerNorm ln_time, ln_agent;
        Mish mlp_act;
        std::vector<int> slot_ids, time_ids;
        std::vector<float> agent_key_mask;
        Mat in, proj, pe, pos, att_t, sum_t, xt, xt_tm, att_a_tm, att_a, sum_a, xat, m1, m1a, m2, out;
        Mat d_xat, d_m2, d_m1a, d_m1, d_tmp, d_sum_a, d_xt, d_tm, d_q, d_kv, d_sum_t, d_pos, d_x;
    } proc_;
    struct UNet {
        std::vector<ConvBlock> down, up;
        ConvBlock mid;
        std::vector<MaxPool1d> pool;
        std::vector<Upsample1d> upsample;
        Conv1d decoder;
        std::vector<Mat> skip, pooled, cat, up_out, up_buf;
        Mat mid_out;
        Mat d_cur, d_cat, d_up, d_prev, d_pool, d_in;
        std::vector<Mat> d_skip;
    } net_;

    void build(uint64_t seed) {
        Rng rng(seed);
        ParamStore& ps = *params;
        const ModelConfig& c = config;
        const int D = c.dim;
        auto& p = proc_;
        p.in_proj = Linear(ps, "aap.in_proj", 4, D, rng);
        if (c.processor == Processor::AAP) {
            p.pe_agent = Embedding(ps, "aap.pe_agent", c.n_max, D, rng);
            p.pe_time = Embedding(ps, "aap.pe_time", c.horizon, D, rng);
            p.time_attn = MultiHeadAttention(ps, "aap.time_attn", D, c.heads, rng);
            p.ln_time = LayerNorm(ps, "aap.ln_time", D, rng);
            p.agent_attn = MultiHeadAttention(ps, "aap.agent_attn", D, c.heads, rng);
            p.ln_agent = LayerNorm(ps, "aap.ln_agent", D, rng);
            p.mlp1 = Linear(ps, "aap.mlp1", D, 2 * D, rng);
            p.mlp2 = Linear(ps, "aap.mlp2", 2 * D, D, rng);
        }
        auto& e = enc_;
        e.g1 = Conv2d(ps, "ctx.grid1", 1, 16, 3, 2, 1, rng);
        e.g2 = Conv2d(ps, "ctx.grid2", 16, 32, 3, 2, 1, rng);
        e.g3 = Conv2d(ps, "ctx.grid3", 32, D, 3, 2, 1, rng);
        e.pe_img = Embedding(ps, "ctx.pe_img", c.image_tokens(), D, rng);
        e.pose1 = Linear(ps, "ctx.pose1", 4, D, rng);
        e.pose2 = Linear(ps, "ctx.pose2", D, D, rng);
        if (c.local_grid > 0) {
            e.l1 = Conv2d(ps, "ctx.local1", 1, 8, 3, 2, 1, rng);
            e.l2 = Conv2d(ps, "ctx.local2", 8, 16, 3, 2, 1, rng);
            e.l3 = Conv2d(ps, "ctx.local3", 16, D, c.local_grid / 4, 1, 0, rng);  // the whole 4x4-reduced crop -> one token
        }
        e.count_emb = Embedding(ps, "ctx.count", c.n_max + 1, D, rng);
        e.fuse = MultiHeadAttention(ps, "ctx.fuse", D, c.heads, rng);
        e.ln = LayerNorm(ps, "ctx.ln", D, rng);
        step_.l1 = Linear(ps, "step.l1", D, 2 * D, rng);
        step_.l2 = Linear(ps, "step.l2", 2 * D, D, rng);
        auto& u = net_;
        const int L = c.levels();
        int cin = D;
        for (int l = 0; l < L; ++l) {
            u.down.emplace_back(ps, "unet.down" + std::to_string(l), cin, c.channels[l], c.kernel, D, rng);
            cin = c.channels[l];
        }
        u.mid = ConvBlock(ps, "unet.mid", cin, cin, c.kernel, D, rng);
        u.up.resize(L);
        for (int l = L - 1; l >= 0; --l) {
            u.up[l] = ConvBlock(ps, "unet.up" + std::to_string(l), cin + c.channels[l], c.channels[l], c.kernel, D, rng);
            cin = c.channels[l];
        }
        u.decoder = Conv1d(ps, "unet.decoder", c.channels[0], 2, 1, rng);
        u.pool.resize(L);
        u.upsample.resize(L);
        u.skip.resize(L);
        u.pooled.resize(L);
        u.cat.resize(L);
        u.up_out.resize(L);
        u.up_buf.resize(L);
        u.d_skip.resize(L);
    }

    void check_batch(const SceneBatch& b) const {
        const long A = (long)b.B * b.n;
        if (b.B < 1 || b.n < 1) throw std::invalid_argument("scene batch: needs B >= 1 and n >= 1");
        if (b.n > config.n_max)
            throw std::invalid_argument("scene batch: " + std::to_string(b.n) + " agent slots exceed the model's n_max = " + std::to_string(config.n_max));
        if ((long)b.agent_mask.size() != A || (long)b.slot.size() != A || (long)b.count.size() != b.B || b.pose.rows() != 4 ||
            b.pose.cols() != A || b.grid.rows() != 1 || b.grid.cols() != (long)config.grid * config.grid * b.grid_scenes() ||
            b.local.cols() != (long)config.local_grid * config.local_grid * A)
            throw std::invalid_argument("scene batch: array sizes do not match B = " + std::to_string(b.B) + ", n = " + std::to_string(b.n));
        for (int s = 0; s < b.B; ++s)
            if (b.count[s] < 0 || b.count[s] > config.n_max)
                throw std::invalid_argument("scene batch: count " + std::to_string(b.count[s]) + " outside [0, n_max]");
        for (long a = 0; a < A; ++a)
            if (b.slot[a] < 0 || b.slot[a] >= config.n_max) throw std::invalid_argument("scene batch: slot outside [0, n_max)");
        if (!b.pose.allFinite()) throw std::invalid_argument("scene batch: pose (positions or goals) is not finite");
    }

    void make_column_masks(const SceneBatch& batch) {
        const int A = batch.agents();
        for (int l = 0; l <= config.levels(); ++l) {
            const int T = config.horizon >> l;
            colmask_[l].resize((size_t)T * A);
            for (int a = 0; a < A; ++a)
                for (int t = 0; t < T; ++t) colmask_[l][(size_t)a * T + t] = batch.agent_mask[a];
        }
    }

    // The trajectory processor (SPEC 5): x (2, H*A) -> out (D, H*A).
    void process(const Mat& x, const SceneBatch& batch) {
        const int B = batch.B, n = batch.n, A = B * n, H = config.horizon;
        auto& p = proc_;
        // in_ (4, H*A): the window and, on every column, the agent's current position.
        p.in.resize(4, (long)H * A);
        p.in.topRows(2) = x;
        for (int a = 0; a < A; ++a) p.in.block(2, (long)a * H, 2, H).colwise() = batch.pose.col(a).head<2>();
        p.in_proj.forward(p.in, p.proj);
        if (config.processor == Processor::LE) {
            p.out = p.proj;
            return;
        }
        p.slot_ids.resize((size_t)H * A);
        p.time_ids.resize((size_t)H * A);
        for (int a = 0; a < A; ++a)
            for (int t = 0; t < H; ++t) {
                p.slot_ids[(size_t)a * H + t] = batch.slot[a];
                p.time_ids[(size_t)a * H + t] = t;
            }
        p.pe_agent.forward(p.slot_ids.data(), H * A, p.pe);
        p.pos = p.proj + p.pe;
        p.pe_time.forward(p.time_ids.data(), H * A, p.pe);
        p.pos += p.pe;
        // Attention over time within each agent, residual + LayerNorm.
        p.time_attn.forward(p.pos, H, p.pos, H, A, nullptr, p.att_t);
        p.sum_t = p.pos + p.att_t;
        p.ln_time.forward(p.sum_t, p.xt);
        // Attention over agents at each time step (inactive agents masked as keys).
        detail::agent_to_time_major(p.xt, B, n, H, p.xt_tm);
        p.agent_key_mask.resize((size_t)H * A);
        for (int b = 0; b < B; ++b)
            for (int t = 0; t < H; ++t)
                for (int i = 0; i < n; ++i) p.agent_key_mask[((size_t)b * H + t) * n + i] = batch.agent_mask[(size_t)b * n + i];
        p.agent_attn.forward(p.xt_tm, n, p.xt_tm, n, B * H, p.agent_key_mask.data(), p.att_a_tm);
        detail::time_to_agent_major(p.att_a_tm, B, n, H, p.att_a);
        p.sum_a = p.xt + p.att_a;
        p.ln_agent.forward(p.sum_a, p.xat);
        // X~ = X_at + MLP(X_at).
        p.mlp1.forward(p.xat, p.m1);
        p.mlp_act.forward(p.m1, p.m1a);
        p.mlp2.forward(p.m1a, p.m2);
        p.out = p.xat + p.m2;
    }
    void process_backward(const Mat& d_out, const SceneBatch& batch) {
        const int B = batch.B, n = batch.n, A = B * n, H = config.horizon;
        auto& p = proc_;
        if (config.processor == Processor::LE) {
            p.in_proj.backward(p.in, d_out, p.d_x);
            return;
        }
        p.mlp2.backward(p.m1a, d_out, p.d_m1a);
        p.mlp_act.backward(p.m1, p.d_m1a, p.d_m1);
        p.mlp1.backward(p.xat, p.d_m1, p.d_xat);
        p.d_xat += d_out;
        p.ln_agent.backward(p.sum_a, p.d_xat, p.d_sum_a);
        detail::agent_to_time_major(p.d_sum_a, B, n, H, p.d_tm);
        p.agent_attn.backward(p.xt_tm, n, p.xt_tm, n, B * H, p.agent_key_mask.data(), p.d_tm, p.d_q, p.d_kv);
        p.d_q += p.d_kv;
        detail::time_to_agent_major(p.d_q, B, n, H, p.d_xt);
        p.d_xt += p.d_sum_a;
        p.ln_time.backward(p.sum_t, p.d_xt, p.d_sum_t);
        p.time_attn.backward(p.pos, H, p.pos, H, A, nullptr, p.d_sum_t, p.d_q, p.d_kv);
        p.d_pos = p.d_sum_t + p.d_q + p.d_kv;
        p.pe_agent.backward(p.slot_ids.data(), H * A, p.d_pos);
        p.pe_time.backward(p.time_ids.data(), H * A, p.d_pos);
        p.in_proj.backward(p.in, p.d_pos, p.d_x);
    }

    // Inputs of the down and up blocks, as forward left them.
    const Mat& down_input(int l) const { return l == 0 ? proc_.out : net_.pooled[l - 1]; }
    const Mat& up_input(int l) const { return l == config.levels() - 1 ? net_.mid_out : net_.up_out[l + 1]; }

    void unet_forward(const Mat& x, Mat& eps) {
        auto& u = net_;
        const int L = config.levels(), H = config.horizon;
        MADBP_ASSERT(&x == &proc_.out);
        for (int l = 0; l < L; ++l) {
            u.down[l].forward(down_input(l), H >> l, cond_, colmask_[l].data(), u.skip[l]);
            u.pool[l].forward(u.skip[l], H >> l, u.pooled[l]);
        }
        u.mid.forward(u.pooled[L - 1], H >> L, cond_, colmask_[L].data(), u.mid_out);
        for (int l = L - 1; l >= 0; --l) {
            u.upsample[l].forward(up_input(l), u.up_buf[l]);  // nearest x2, then the skip below it
            const long cu = u.up_buf[l].rows(), cs = u.skip[l].rows();
            u.cat[l].resize(cu + cs, u.up_buf[l].cols());
            u.cat[l].topRows(cu) = u.up_buf[l];
            u.cat[l].bottomRows(cs) = u.skip[l];
            u.up[l].forward(u.cat[l], H >> l, cond_, colmask_[l].data(), u.up_out[l]);
        }
        u.decoder.forward(u.up_out[0], H, eps);
    }
    void unet_backward(const Mat& d_eps, Mat& d_x) {
        auto& u = net_;
        const int L = config.levels(), H = config.horizon;
        u.decoder.backward(u.up_out[0], H, d_eps, u.d_cur);
        for (int l = 0; l < L; ++l) {
            u.up[l].backward(u.cat[l], H >> l, cond_, colmask_[l].data(), u.d_cur, u.d_cat, d_cond_);
            const long cu = up_input(l).rows(), cs = u.skip[l].rows();
            u.d_skip[l] = u.d_cat.bottomRows(cs);
            u.d_up = u.d_cat.topRows(cu);
            u.upsample[l].backward(up_input(l), u.d_up, u.d_cur);
        }
        u.mid.backward(u.pooled[L - 1], H >> L, cond_, colmask_[L].data(), u.d_cur, u.d_pool, d_cond_);
        for (int l = L - 1; l >= 0; --l) {
            u.pool[l].backward(u.skip[l], H >> l, u.d_pool, u.d_in);
            u.d_skip[l] += u.d_in;
            u.down[l].backward(down_input(l), H >> l, cond_, colmask_[l].data(), u.d_skip[l], u.d_pool, d_cond_);
        }
        d_x = u.d_pool;
    }

    // d_ctx (D, A) -> parameter gradients of the context encoder.
    void context_backward(const Mat& d_ctx, const SceneBatch& batch) {
        const int B = batch.B, n = batch.n, G = config.grid, P = config.image_tokens(), Lk = P + n + 1;
        auto& e = enc_;
        if (batch.shared_grid) throw std::logic_error("context backward: training needs one grid per scene (shared_grid is for planning)");
        e.ln.backward(e.pre_ln, d_ctx, e.d_pre);
        e.fuse.backward(e.pose_tok, n, e.kv, Lk, B, e.kv_mask.data(), e.d_pre, e.d_pose, e.d_kv);
        e.d_pose += e.d_pre;
        e.d_img.resize(config.dim, (long)P * B);
        e.d_count.resize(config.dim, B);
        for (int b = 0; b < B; ++b) {
            const long o = (long)b * Lk;
            e.d_img.middleCols((long)b * P, P) = e.d_kv.middleCols(o, P);
            e.d_pose.middleCols((long)b * n, n) += e.d_kv.middleCols(o + P, n);
            e.d_count.col(b) = e.d_kv.col(o + P + n);
        }
        e.count_emb.backward(e.count_ids.data(), B, e.d_count);
        e.pose2.backward(e.p1a, e.d_pose, e.d_p1a);
        e.pose_act.backward(e.p1, e.d_p1a, e.d_p1);
        e.pose1.backward(batch.pose, e.d_p1, e.d_posein);
        if (config.local_grid > 0) {
            const int Gl = config.local_grid;
            e.l3.backward(e.l2a, Gl / 4, Gl / 4, e.d_pose, e.d_l2a);
            e.r4.backward(e.l2o, e.d_l2a, e.d_l2o);
            e.l2.backward(e.l1a, Gl / 2, Gl / 2, e.d_l2o, e.d_l1a);
            e.r3.backward(e.l1o, e.d_l1a, e.d_l1o);
            e.l1.backward(batch.local, Gl, Gl, e.d_l1o, e.d_local);
        }
        e.pe_img.backward(e.img_ids.data(), P * B, e.d_img);
        e.g3.backward(e.g2a, G / 4, G / 4, e.d_img, e.d_g2a);
        e.r2.backward(e.g2o, e.d_g2a, e.d_g2o);
        e.g2.backward(e.g1a, G / 2, G / 2, e.d_g2o, e.d_g1a);
        e.r1.backward(e.g1o, e.d_g1a, e.d_g1o);
        e.g1.backward(batch.grid, G, G, e.d_g1o, e.d_grid);
    }
};

// Model checkpoints (SPEC 11): the parameters as safetensors, the ModelConfig in __metadata__
// (plus any `extra` fields: demonstrator, training step, ...). load_model validates the file
// and that its tensors match the configuration it declares; errors name the file and field.
inline void save_model(const std::string& path, const MadbpModel& model, std::map<std::string, std::string> extra = {}) {
    auto md = model.config.to_metadata();
    for (auto& kv : extra) md[kv.first] = kv.second;
    save_params(path, *model.params, md);
}
inline MadbpModel load_model(const std::string& path) {
    SafeTensors st = load_safetensors(path);
    MadbpModel model(ModelConfig::from_metadata(st.metadata, path));
    read_param_tensors(st, *model.params);
    model.set_training(false);
    return model;
}

// =============================================================================================
// Diffusion (SPEC 6): cosine schedule, training-time noising, DDIM sampler with inpainting
// =============================================================================================

// alpha_bar[k] for k = 0..K (alpha_bar[0] = 1): the cosine schedule of Nichol & Dhariwal
// (s = 0.008), betas clipped to 0.999 as in Diffuser.
struct NoiseSchedule {
    int K = 0;
    std::vector<double> alpha_bar;
    explicit NoiseSchedule(int K_ = 100) : K(K_) {
        if (K < 1) throw std::invalid_argument("noise schedule: K must be >= 1");
        auto f = [&](int k) { double c = std::cos(((double)k / K + 0.008) / 1.008 * M_PI / 2); return c * c; };
        alpha_bar.resize(K + 1);
        alpha_bar[0] = 1;
        for (int k = 1; k <= K; ++k) {
            double beta = std::min(1 - f(k) / f(k - 1), 0.999);
            alpha_bar[k] = alpha_bar[k - 1] * (1 - beta);
        }
    }
    // The diffusion step of DDIM step s of S (s = S .. 1 visits K .. K/S, s = 0 is clean).
    int ddim_step(int s, int S) const { return (int)std::lround((double)s * K / S); }
    // The S diffusion steps DDIM visits, descending: K, ..., K/S (rounded), then 0 (clean).
    std::vector<int> ddim_steps(int S) const {
        if (S < 1 || S > K) throw std::invalid_argument("sample_steps: " + std::to_string(S) + " must be in [1, " + std::to_string(K) + "]");
        std::vector<int> ks;
        for (int s = S; s >= 1; --s) ks.push_back(ddim_step(s, S));
        ks.push_back(0);
        return ks;
    }
};

// x0_hat from an eps prediction at step k (paper Alg. 2 line 4), element-wise.
inline float predict_x0(float x_k, float eps, double alpha_bar) {
    return (float)((x_k - std::sqrt(1 - alpha_bar) * eps) / std::sqrt(alpha_bar));
}

// Sampling options (SPEC 6, paper Alg. 2).
struct SamplerConfig {
    int sample_steps = 10;       // S, DDIM steps (eta = 0), in [1, K]
    float clip = 1.5f;           // x0_hat clipped to [-clip, clip] (normalised displacements; Diffuser's clip_denoised)
    bool goal_inpaint = true;    // pin the window's last waypoint to the goal when it is within reach
    float goal_reach = 0.55f;    // "within reach": distance to goal in world units at most this (see default_goal_reach)
};

// About the distance a window covers at the expert's cruising pace (0.55 units for 15 steps):
// goals nearer than this get the window's end pinned to them (training and sampling agree).
inline float default_goal_reach(const ModelConfig& c) { return (float)(0.55 * (c.horizon - 1) * c.waypoint_stride / 15.0); }

// Where the sampler pins the window of agent a (normalised displacement units): t = 0 always
// (zero displacement); t = H-1 to the goal when `goal_inpaint` and the goal is within reach.
inline bool goal_within_reach(const SceneBatch& batch, int a, const ModelConfig& c, float reach_world, Eigen::Vector2f* end) {
    const Eigen::Vector2f to_goal = (batch.pose.col(a).tail<2>() - batch.pose.col(a).head<2>()) * c.position_scale;
    if (to_goal.norm() > reach_world) return false;
    if (end) *end = to_goal / c.window_scale;
    return true;
}

// Draws windows for a batch of scenes with DDIM: x (2, H*A) starts as N(0, I); after every
// step the pinned waypoints are re-imposed and inactive agents are zeroed (paper Alg. 2).
// `model.encode_context(batch)` is called here. Output: normalised displacements.
// Denoiser: MadbpModel, or anything with `config`, encode_context(batch), denoise(x, k, out).
template <class Denoiser>
void sample_windows(Denoiser& model, const NoiseSchedule& schedule, const SceneBatch& batch, const SamplerConfig& sc,
                    Rng& rng, Mat& x, Mat& out, std::vector<int>& step_buf) {
    const ModelConfig& c = model.config;
    const int A = batch.agents(), H = c.horizon, B = batch.B, S = sc.sample_steps;
    if (S < 1 || S > schedule.K) throw std::invalid_argument("sample_steps: " + std::to_string(S) + " must be in [1, " + std::to_string(schedule.K) + "]");
    model.encode_context(batch);
    x.resize(2, (long)H * A);
    for (long j = 0; j < x.size(); ++j) x.data()[j] = (float)rng.normal();
    auto impose = [&]() {
        for (int a = 0; a < A; ++a) {
            auto w = x.middleCols((long)a * H, H);
            if (batch.agent_mask[a] == 0) { w.setZero(); continue; }
            w.col(0).setZero();
            Eigen::Vector2f end;
            if (sc.goal_inpaint && goal_within_reach(batch, a, c, sc.goal_reach, &end)) w.col(H - 1) = end;
        }
    };
    impose();
    step_buf.resize(B);
    for (int s = S; s >= 1; --s) {
        const int k = schedule.ddim_step(s, S), k_prev = schedule.ddim_step(s - 1, S);
        std::fill(step_buf.begin(), step_buf.end(), k);
        model.denoise(x, step_buf.data(), out);
        const double ab = schedule.alpha_bar[k], ab_prev = schedule.alpha_bar[k_prev];
        const float sa = (float)std::sqrt(ab), s1a = (float)std::sqrt(1 - ab);
        const float sap = (float)std::sqrt(ab_prev), s1ap = (float)std::sqrt(1 - ab_prev);
        const bool eps_mode = c.prediction == Prediction::Eps;
        for (long j = 0; j < x.size(); ++j) {
            const float xj = x.data()[j], oj = out.data()[j];
            const float x0 = std::clamp(eps_mode ? (xj - s1a * oj) / sa : oj, -sc.clip, sc.clip);
            const float e = (xj - sa * x0) / s1a;  // the noise consistent with the clipped x0
            x.data()[j] = sap * x0 + s1ap * e;
        }
        impose();
    }
}

// =============================================================================================
// Moving-window planner (SPEC 8)
// =============================================================================================

// Plans a window for every present agent of a World with one shared model. Plug it into a
// PlanFollower (madbp_sim.hpp) to execute the first m waypoints and replan:
//   madbp::DiffusionPlanner planner(madbp::load_model("models/madbp-default.safetensors"));
//   madbp::PlanFollower follower([&](const madbp::World& w) { return planner.plan(w); });
class DiffusionPlanner {
public:
    SamplerConfig sampler;
    // Neighbourhood planning for teams larger than the model was trained on: with K > 0 and
    // more than K agents, each agent's window comes from its own scene of itself and its K-1
    // nearest agents (n scenes of K agents, sampled as one batch), so the model never attends
    // over more agents than it saw in training. 0: the whole team in one scene (the paper's).
    int neighbours = 0;

    explicit DiffusionPlanner(MadbpModel model, uint64_t seed = 0)
        : model_(std::move(model)), schedule_(model_.config.diffusion_steps), rng_(seed) {
        model_.set_training(false);
        sampler.sample_steps = model_.config.sample_steps;
        sampler.goal_reach = default_goal_reach(model_.config);
    }
    const ModelConfig& config() const { return model_.config; }
    MadbpModel& model() { return model_; }
    void reseed(uint64_t seed) { rng_.reseed(seed); }

    // A window for all present agents of `world`: waypoints for steps t+1 .. t+(H-1)*stride
    // (with a waypoint stride > 1, the steps between two sampled waypoints are interpolated).
    Plan plan(const World& world) {
        Plan p;
        plan_into(world, p);
        return p;
    }
    // As plan(), reusing `out`'s storage: no heap allocation once sizes are steady.
    void plan_into(const World& world, Plan& out) {
        auto t0 = std::chrono::steady_clock::now();
        const ModelConfig& c = model_.config;
        const int n = world.size(), H = c.horizon;
        out.ids.resize(n);
        out.waypoints.resize(n);
        if (n == 0) { out.plan_ms = 0; return; }
        for (const Agent& a : world.agents())
            if (!std::isfinite(a.pos.x + a.pos.y + a.goal.x + a.goal.y))  // the message only on failure: no allocation
                throw std::invalid_argument("planner: agent " + std::to_string(a.id) + " has a non-finite position or goal");
        if (neighbours < 0) throw std::invalid_argument("planner: neighbours must be >= 0 (got " + std::to_string(neighbours) + ")");
        const bool local = neighbours > 0 && neighbours < n;
        const int scenes = local ? n : 1, per_scene = local ? neighbours : n;
        if (per_scene > c.n_max)
            throw std::invalid_argument("planner: " + std::to_string(per_scene) + " agents per scene exceed the model's n_max = " +
                                        std::to_string(c.n_max) + (local ? "" : "; larger teams need neighbourhood planning (neighbours = K <= n_max, --neighbours K)"));
        if (batch_.B != scenes || batch_.n != per_scene) {  // a team of another size: new buffers, grid redrawn
            batch_.resize(scenes, per_scene, c, /*shared grid*/ true);
            grid_valid_ = false;
        }
        update_grid(world.map());
        // Scene b holds agent b first, then its nearest agents (all agents in order when not local).
        for (int b = 0; b < scenes; ++b) {
            members_.resize(n);
            for (int i = 0; i < n; ++i) members_[i] = i;
            if (local) {
                const Vec2 pb = world.agents()[b].pos;
                auto dist = [&](int i) { const Vec2 d = world.agents()[i].pos - pb; return i == b ? -1.0 : dot(d, d); };
                std::partial_sort(members_.begin(), members_.begin() + per_scene, members_.end(),
                                  [&](int i, int j) { return dist(i) < dist(j) || (dist(i) == dist(j) && i < j); });
            }
            for (int k = 0; k < per_scene; ++k) {
                const Agent& a = world.agents()[members_[k]];
                const int col = b * per_scene + k;
                batch_.agent_mask[col] = 1;
                batch_.slot[col] = k;
                batch_.pose.col(col) << (float)(a.pos.x / c.position_scale), (float)(a.pos.y / c.position_scale),
                    (float)(a.goal.x / c.position_scale), (float)(a.goal.y / c.position_scale);
                fill_local_crop(batch_, col, world.map(), a.pos, c);
            }
            batch_.count[b] = per_scene;
        }
        sample_windows(model_, schedule_, batch_, sampler, rng_, x_, eps_, steps_);
        for (int i = 0; i < n; ++i) {
            out.ids[i] = world.agents()[i].id;
            const long col = local ? (long)i * per_scene : i;  // agent i's window: first of scene i, or column i
            const int stride = c.waypoint_stride;
            out.waypoints[i].resize((size_t)(H - 1) * stride);
            const Vec2 p0 = world.agents()[i].pos;
            auto at = [&](int t) { return p0 + Vec2{x_(0, col * H + t) * (double)c.window_scale, x_(1, col * H + t) * (double)c.window_scale}; };
            for (int t = 1; t < H; ++t)
                for (int s = 1; s <= stride; ++s)  // linear between sampled waypoints t-1 and t
                    out.waypoints[i][(size_t)(t - 1) * stride + s - 1] = at(t - 1) + (at(t) - at(t - 1)) * ((double)s / stride);
        }
        out.plan_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    }

private:
    MadbpModel model_;
    NoiseSchedule schedule_;
    Rng rng_;
    SceneBatch batch_;
    Map grid_map_;
    bool grid_valid_ = false;
    Mat x_, eps_;
    std::vector<int> steps_, members_;

    // Rasterizes the map only when it changed since the last plan.
    void update_grid(const Map& map) {
        if (grid_valid_ && same_map(map, grid_map_)) return;
        Grid g = occupancy_grid(map, model_.config.grid);
        for (int j = 0; j < model_.config.grid * model_.config.grid; ++j) batch_.grid(0, j) = g.cells[j];
        grid_map_ = map;
        grid_valid_ = true;
    }
    static bool same_map(const Map& a, const Map& b) {
        if (a.half_size != b.half_size || a.discs.size() != b.discs.size() || a.boxes.size() != b.boxes.size()) return false;
        for (size_t i = 0; i < a.discs.size(); ++i)
            if (!(a.discs[i].c == b.discs[i].c) || a.discs[i].r != b.discs[i].r) return false;
        for (size_t i = 0; i < a.boxes.size(); ++i)
            if (!(a.boxes[i].lo == b.boxes[i].lo) || !(a.boxes[i].hi == b.boxes[i].hi)) return false;
        return true;
    }
};

}  // namespace madbp

#endif  // MADBP_HPP
