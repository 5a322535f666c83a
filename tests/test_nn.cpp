// Tests of the neural-network core (madbp.hpp, SPEC section 4).
//
// Every layer's backward is compared with central differences of a naive double-precision
// reference forward written here (so the reference gradient is accurate to ~1e-9, and the
// float32 layer is checked against an independent implementation), with masks and batch > 1.
// Forward passes are also checked on small hand-worked examples. The allocation test at the end
// replaces operator new and malloc in this translation unit, counting only while a flag is set.
// GCC 12 with AVX-512 warns about Eigen's double-precision kernels used by the references.
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif
#include "madbp.hpp"

#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <functional>

using madbp::Mat;
using madbp::ParamStore;
using madbp::Rng;
using madbp::Vec;
using MatD = Eigen::MatrixXd;
using VecD = Eigen::VectorXd;

// ---------------------------------------------------------------------------------------------
// Allocation counting: tests/main.cpp includes alloc_counter.hpp (once per program).
#include "alloc_counter_api.hpp"

// ---------------------------------------------------------------------------------------------
// Helpers.

// Restores the default thread settings (OpenMP's count, Eigen's own GEMM threading) for the
// tests that follow in the same binary.
struct ThreadSettingsGuard {
#ifdef _OPENMP
    int omp_threads = omp_get_max_threads();
    ~ThreadSettingsGuard() {
        omp_set_num_threads(omp_threads);
        Eigen::setNbThreads(0);  // 0: follow OpenMP again
    }
#endif
};

static Mat randn(long rows, long cols, Rng& rng, double scale = 1.0) {
    Mat m(rows, cols);
    for (long i = 0; i < m.size(); ++i) m.data()[i] = (float)(scale * rng.normal());
    return m;
}

static Eigen::Map<const MatD> pmat(const VecD& p, int offset, int rows, int cols) { return {p.data() + offset, rows, cols}; }
static Eigen::Map<const VecD> pvec(const VecD& p, int offset, int n) { return {p.data() + offset, n}; }

// Compares a layer's analytic gradients (float32) with central differences of a
// double-precision reference forward. `backward(dy, dinputs)` must write every dinputs[i]
// (already sized and filled with garbage, to prove it overwrites) and add into ps->grad.
struct GradCheck {
    ParamStore* ps = nullptr;
    std::vector<Mat> inputs;
    std::vector<bool> differentiable;  // per input; default all
    std::function<MatD(const std::vector<MatD>&, const VecD&)> reference;
    std::function<void(const Mat&, std::vector<Mat>&)> backward;
    int samples = 60;          // entries checked per tensor (all when fewer)
    double tol = 2e-3;         // max |analytic - numeric| / (|numeric| + 1% of the tensor's scale)
    double forward_tol = 1e-4; // max |y - y_ref| / max |y_ref|
    double tamper = 1.0;       // multiplies the analytic gradients (to prove the check can fail)
    std::string worst;

    double max_error(const Mat& y) {
        std::vector<MatD> x;
        for (auto& m : inputs) x.push_back(m.cast<double>());
        VecD p = ps ? VecD(ps->value.cast<double>()) : VecD();
        const MatD yref = reference(x, p);
        REQUIRE(yref.rows() == y.rows());
        REQUIRE(yref.cols() == y.cols());
        const double fwd = (y.cast<double>() - yref).cwiseAbs().maxCoeff() / (yref.cwiseAbs().maxCoeff() + 1e-12);
        CHECK(fwd < forward_tol);

        Rng rng(7);
        MatD R(yref.rows(), yref.cols());
        for (long i = 0; i < R.size(); ++i) R.data()[i] = rng.normal();
        const Mat dy = R.cast<float>();
        auto garbage = [&] {
            std::vector<Mat> d;
            for (auto& m : inputs) d.push_back(Mat::Constant(m.rows(), m.cols(), 1e3f));
            return d;
        };
        std::vector<Mat> d1 = garbage(), d2 = garbage();
        if (ps) ps->zero_grad();
        backward(dy, d1);
        const Vec g1 = ps ? ps->grad : Vec();
        backward(dy, d2);
        if (ps) {  // backward adds into parameter gradients
            const double scale = 1.0 + g1.cwiseAbs().maxCoeff();
            CHECK((ps->grad - 2 * g1).cwiseAbs().maxCoeff() <= 1e-5 * scale);
        }
        for (size_t i = 0; i < d1.size(); ++i) {  // and overwrites input gradients
            REQUIRE(d1[i].rows() == inputs[i].rows());
            REQUIRE(d1[i].cols() == inputs[i].cols());
            CHECK((d1[i] - d2[i]).cwiseAbs().maxCoeff() <= 1e-6 * (1.0 + d1[i].cwiseAbs().maxCoeff()));
        }

        auto loss = [&]() { return (R.array() * reference(x, p).array()).sum(); };
        auto numeric = [&](double& v) {
            const double v0 = v, h = 1e-5 * std::max(1.0, std::abs(v0));
            v = v0 + h;
            const double lp = loss();
            v = v0 - h;
            const double lm = loss();
            v = v0;
            return (lp - lm) / (2 * h);
        };
        // Numeric gradients of every checked entry first: the error of an entry is measured
        // against its own size plus 1% of its tensor's largest gradient plus 0.01% of the
        // largest gradient anywhere (some gradients are exactly 0, e.g. a bias before a norm).
        struct Entry { std::string label; long index; double analytic, numeric; size_t tensor; };
        std::vector<Entry> entries;
        std::vector<double> tensor_scale;
        Rng pick(11);
        auto sample_tensor = [&](double* data, const float* analytic, long n, const std::string& label) {
            std::vector<long> idx;
            if (n <= samples) for (long i = 0; i < n; ++i) idx.push_back(i);
            else for (int s = 0; s < samples; ++s) idx.push_back((long)(pick.uniform() * n));
            tensor_scale.push_back(0);
            for (long i : idx) {
                const double num = numeric(data[i]);
                entries.push_back({label, i, tamper * analytic[i], num, tensor_scale.size() - 1});
                tensor_scale.back() = std::max(tensor_scale.back(), std::abs(num));
            }
        };
        for (size_t i = 0; i < x.size(); ++i)
            if (differentiable.empty() || differentiable[i]) sample_tensor(x[i].data(), d1[i].data(), x[i].size(), "input " + std::to_string(i));
        if (ps)
            for (auto& e : ps->entries)
                if (e.trainable) sample_tensor(p.data() + e.offset, g1.data() + e.offset, e.numel(), e.name);
        const double global_scale = *std::max_element(tensor_scale.begin(), tensor_scale.end());
        double max_err = 0;
        for (const Entry& e : entries) {
            const double err = std::abs(e.analytic - e.numeric) /
                               (std::abs(e.numeric) + 1e-2 * tensor_scale[e.tensor] + 1e-4 * global_scale + 1e-9);
            if (err > max_err) {
                max_err = err;
                worst = e.label + "[" + std::to_string(e.index) + "]: analytic " + std::to_string(e.analytic) + " numeric " +
                        std::to_string(e.numeric);
            }
        }
        return max_err;
    }
    void check(const Mat& y) {
        const double err = max_error(y);
        INFO("worst gradient entry: " << worst);
        CHECK(err < tol);
    }
};

// The common case: a layer with one input x. forward(x, y) and backward(x, dy, dx) call the
// layer; reference(x, params) is its double-precision twin.
static void check_layer(ParamStore* ps, const Mat& x, std::function<MatD(const MatD&, const VecD&)> reference,
                        std::function<void(const Mat&, Mat&)> forward, std::function<void(const Mat&, const Mat&, Mat&)> backward,
                        double tol = 2e-3) {
    GradCheck gc;
    gc.ps = ps;
    gc.inputs = {x};
    gc.tol = tol;
    gc.reference = [&](const std::vector<MatD>& in, const VecD& p) { return reference(in[0], p); };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { backward(gc.inputs[0], dy, dx[0]); };
    Mat y;
    forward(gc.inputs[0], y);
    gc.check(y);
}

// ---------------------------------------------------------------------------------------------
// Double-precision references, written as plainly as possible.

static MatD ref_linear(const MatD& x, const VecD& p, const madbp::Linear& l) {
    MatD y = pmat(p, l.w, l.out, l.in) * x;
    if (l.b >= 0) y.colwise() += pvec(p, l.b, l.out);
    return y;
}

static MatD ref_layernorm(const MatD& x, const VecD& p, const madbp::LayerNorm& ln) {
    MatD y(x.rows(), x.cols());
    for (long j = 0; j < x.cols(); ++j) {
        const double mu = x.col(j).mean();
        const double var = (x.col(j).array() - mu).square().mean();
        for (long c = 0; c < x.rows(); ++c)
            y(c, j) = (x(c, j) - mu) / std::sqrt(var + 1e-5) * p[ln.gain + c] + p[ln.bias + c];
    }
    return y;
}

static MatD ref_attention(const MatD& qin, int Lq, const MatD& kvin, int Lk, int B, const float* mask, const VecD& p,
                          const madbp::MultiHeadAttention& a) {
    const int D = a.D, H = a.heads, dh = D / H;
    auto proj = [&](int w, int b, const MatD& x) {
        MatD out = pmat(p, w, D, D) * x;
        out.colwise() += pvec(p, b, D);
        return out;
    };
    const MatD Q = proj(a.wq, a.bq, qin), K = proj(a.wk, a.bk, kvin), V = proj(a.wv, a.bv, kvin);
    MatD ctx = MatD::Zero(D, (long)Lq * B);
    std::vector<bool> dead(B, true);
    for (int b = 0; b < B; ++b)
        for (int k = 0; k < Lk; ++k)
            if (!mask || mask[b * Lk + k] != 0) dead[b] = false;
    for (int b = 0; b < B; ++b)
        for (int h = 0; h < H; ++h)
            for (int q = 0; q < Lq; ++q) {
                if (dead[b]) continue;
                std::vector<double> s(Lk, 0.0);
                double mx = -1e300, sum = 0;
                for (int k = 0; k < Lk; ++k) {
                    if (mask && mask[b * Lk + k] == 0) continue;
                    for (int d = 0; d < dh; ++d) s[k] += Q(h * dh + d, b * Lq + q) * K(h * dh + d, b * Lk + k);
                    s[k] /= std::sqrt((double)dh);
                    mx = std::max(mx, s[k]);
                }
                for (int k = 0; k < Lk; ++k) {
                    s[k] = (mask && mask[b * Lk + k] == 0) ? 0.0 : std::exp(s[k] - mx);
                    sum += s[k];
                }
                for (int k = 0; k < Lk; ++k)
                    for (int d = 0; d < dh; ++d) ctx(h * dh + d, b * Lq + q) += s[k] / sum * V(h * dh + d, b * Lk + k);
            }
    MatD y = proj(a.wo, a.bo, ctx);
    for (int b = 0; b < B; ++b)
        if (dead[b]) y.middleCols((long)b * Lq, Lq).setZero();
    return y;
}

static MatD ref_conv1d(const MatD& x, int T, const VecD& p, const madbp::Conv1d& c) {
    const int B = (int)(x.cols() / T), pad = c.k / 2;
    auto W = pmat(p, c.w, c.cout, c.k * c.cin);
    MatD y(c.cout, x.cols());
    for (int b = 0; b < B; ++b)
        for (int t = 0; t < T; ++t)
            for (int o = 0; o < c.cout; ++o) {
                double acc = p[c.b + o];
                for (int j = 0; j < c.k; ++j) {
                    const int ti = t + j - pad;
                    if (ti < 0 || ti >= T) continue;
                    for (int i = 0; i < c.cin; ++i) acc += W(o, j * c.cin + i) * x(i, b * T + ti);
                }
                y(o, b * T + t) = acc;
            }
    return y;
}

static MatD ref_conv_transpose(const MatD& x, int T, const VecD& p, const madbp::ConvTranspose1d& c) {
    const int B = (int)(x.cols() / T), k = madbp::ConvTranspose1d::k;
    auto W = pmat(p, c.w, k * c.cout, c.cin);
    MatD y(c.cout, 2 * x.cols());
    for (long j = 0; j < y.cols(); ++j) y.col(j) = pvec(p, c.b, c.cout);
    for (int b = 0; b < B; ++b)
        for (int t = 0; t < T; ++t)
            for (int j = 0; j < k; ++j) {
                const int to = 2 * t - 1 + j;
                if (to < 0 || to >= 2 * T) continue;
                for (int o = 0; o < c.cout; ++o)
                    for (int i = 0; i < c.cin; ++i) y(o, b * 2 * T + to) += W(j * c.cout + o, i) * x(i, b * T + t);
            }
    return y;
}

static MatD ref_batchnorm(const MatD& x, const float* mask, const VecD& p, const madbp::BatchNorm1d& bn, bool training) {
    const long C = x.rows(), N = x.cols();
    VecD mean(C), var(C);
    double n = 0;
    for (long j = 0; j < N; ++j) n += (!mask || mask[j] != 0) ? 1 : 0;
    if (training && n > 0) {
        mean.setZero();
        var.setZero();
        for (long j = 0; j < N; ++j)
            if (!mask || mask[j] != 0) mean += x.col(j);
        mean /= n;
        for (long j = 0; j < N; ++j)
            if (!mask || mask[j] != 0) var.array() += (x.col(j) - mean).array().square();
        var /= n;
    } else {
        mean = bn.ps->state_vec(bn.running_mean, (int)C).cast<double>();  // running statistics: state, not weights
        var = bn.ps->state_vec(bn.running_var, (int)C).cast<double>();
    }
    MatD y(C, N);
    for (long j = 0; j < N; ++j)
        for (long c = 0; c < C; ++c) y(c, j) = (x(c, j) - mean[c]) / std::sqrt(var[c] + 1e-5) * p[bn.gain + c] + p[bn.bias + c];
    return y;
}

static MatD ref_conv2d(const MatD& x, int H, int W, const VecD& p, const madbp::Conv2d& c) {
    const int Ho = c.out_size(H), Wo = c.out_size(W), B = (int)(x.cols() / (H * W));
    auto Wt = pmat(p, c.w, c.cout, c.k * c.k * c.cin);
    MatD y(c.cout, (long)Ho * Wo * B);
    for (int b = 0; b < B; ++b)
        for (int oy = 0; oy < Ho; ++oy)
            for (int ox = 0; ox < Wo; ++ox)
                for (int o = 0; o < c.cout; ++o) {
                    double acc = p[c.b + o];
                    for (int ky = 0; ky < c.k; ++ky)
                        for (int kx = 0; kx < c.k; ++kx) {
                            const int iy = oy * c.stride - c.pad + ky, ix = ox * c.stride - c.pad + kx;
                            if (iy < 0 || iy >= H || ix < 0 || ix >= W) continue;
                            for (int i = 0; i < c.cin; ++i) acc += Wt(o, (ky * c.k + kx) * c.cin + i) * x(i, b * H * W + iy * W + ix);
                        }
                    y(o, (long)b * Ho * Wo + oy * Wo + ox) = acc;
                }
    return y;
}

// ---------------------------------------------------------------------------------------------
// The gradient checker itself must be able to fail.

TEST_CASE("nn: the gradient check detects a 1% gradient error") {
    Rng rng(1);
    ParamStore ps;
    madbp::Linear lin(ps, "lin", 5, 4, rng);
    GradCheck gc;
    gc.ps = &ps;
    gc.inputs = {randn(5, 6, rng)};
    gc.reference = [&](const std::vector<MatD>& x, const VecD& p) { return ref_linear(x[0], p, lin); };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { lin.backward(gc.inputs[0], dy, dx[0]); };
    Mat y;
    lin.forward(gc.inputs[0], y);
    CHECK(gc.max_error(y) < gc.tol);
    gc.tamper = 1.01;
    CHECK(gc.max_error(y) > gc.tol);
}

// ---------------------------------------------------------------------------------------------
// Linear

TEST_CASE("nn: Linear forward on a hand-worked 2x2 example") {
    Rng rng(0);
    ParamStore ps;
    madbp::Linear lin(ps, "lin", 2, 2, rng);
    ps.view(lin.w, 2, 2) << 1, 2, 3, 4;  // W (out, in)
    ps.vec(lin.b, 2) << 0.5f, -1;
    Mat x(2, 2), y;
    x << 1, 0, -1, 2;  // columns (1, -1) and (0, 2)
    lin.forward(x, y);
    CHECK(y(0, 0) == doctest::Approx(-0.5));
    CHECK(y(1, 0) == doctest::Approx(-2.0));
    CHECK(y(0, 1) == doctest::Approx(4.5));
    CHECK(y(1, 1) == doctest::Approx(7.0));
    // Listed {in, out}: row-major (in, out) is W^T, so numpy's x @ W gives the same result.
    CHECK(ps.entries[0].shape == std::vector<int>{2, 2});
    CHECK(ps.value[0] == 1);
    CHECK(ps.value[1] == 3);
}

TEST_CASE("nn: Linear gradients, with and without bias") {
    for (bool bias : {true, false}) {
        Rng rng(2);
        ParamStore ps;
        madbp::Linear lin(ps, "lin", 7, 5, rng, bias);
        check_layer(
            &ps, randn(7, 9, rng), [&](const MatD& x, const VecD& p) { return ref_linear(x, p, lin); },
            [&](const Mat& x, Mat& y) { lin.forward(x, y); }, [&](const Mat& x, const Mat& dy, Mat& dx) { lin.backward(x, dy, dx); });
    }
}

// ---------------------------------------------------------------------------------------------
// LayerNorm

TEST_CASE("nn: LayerNorm forward on a known column") {
    Rng rng(0);
    ParamStore ps;
    madbp::LayerNorm ln(ps, "ln", 4, rng);
    Mat x(4, 1), y;
    x << 1, 2, 3, 4;  // mean 2.5, variance 1.25
    ln.forward(x, y);
    const double r = 1.0 / std::sqrt(1.25 + 1e-5);
    CHECK(y(0) == doctest::Approx(-1.5 * r));
    CHECK(y(1) == doctest::Approx(-0.5 * r));
    CHECK(y(3) == doctest::Approx(1.5 * r));
    ps.vec(ln.gain, 4).setConstant(2);
    ps.vec(ln.bias, 4).setConstant(1);
    ln.forward(x, y);
    CHECK(y(0) == doctest::Approx(1 - 3 * r));
}

TEST_CASE("nn: LayerNorm gradients") {
    Rng rng(3);
    ParamStore ps;
    madbp::LayerNorm ln(ps, "ln", 6, rng);
    ps.value = randn(ps.size(), 1, rng);  // gain and bias away from 1 and 0
    check_layer(
        &ps, randn(6, 5, rng, 2.0), [&](const MatD& x, const VecD& p) { return ref_layernorm(x, p, ln); },
        [&](const Mat& x, Mat& y) { ln.forward(x, y); }, [&](const Mat& x, const Mat& dy, Mat& dx) { ln.backward(x, dy, dx); });
}

// ---------------------------------------------------------------------------------------------
// Multi-head attention

TEST_CASE("nn: attention with a masked key equals attention over the other keys") {
    Rng rng(4);
    ParamStore ps;
    madbp::MultiHeadAttention att(ps, "att", 8, 2, rng);
    const int Lq = 3, Lk = 4;
    Mat q = randn(8, Lq * 2, rng), kv = randn(8, Lk * 2, rng), y, y0, y1;
    float mask[8] = {1, 1, 0, 1, 1, 1, 1, 1};  // item 0 masks its key 2
    att.forward(q, Lq, kv, Lk, 2, mask, y);
    // Item 0 alone with key 2 removed, item 1 alone with all keys.
    Mat kv0(8, 3);
    kv0 << kv.col(0), kv.col(1), kv.col(3);
    att.forward(q.leftCols(Lq), Lq, kv0, 3, 1, nullptr, y0);
    att.forward(q.rightCols(Lq), Lq, kv.rightCols(Lk), Lk, 1, nullptr, y1);
    CHECK((y.leftCols(Lq) - y0).cwiseAbs().maxCoeff() < 1e-5);
    CHECK((y.rightCols(Lq) - y1).cwiseAbs().maxCoeff() < 1e-5);
    // Changing the masked key's value changes nothing.
    kv.col(2).setConstant(1e4f);
    Mat y2;
    att.forward(q, Lq, kv, Lk, 2, mask, y2);
    CHECK((y2 - y).cwiseAbs().maxCoeff() == 0);
}

TEST_CASE("nn: attention over one key returns that key's value projection") {
    Rng rng(5);
    ParamStore ps;
    madbp::MultiHeadAttention att(ps, "att", 4, 2, rng);
    ps.vec(att.bv, 4) << 1, 2, 3, 4;
    Mat q = randn(4, 3, rng), kv = randn(4, 1, rng), y;
    att.forward(q, 3, kv, 1, 1, nullptr, y);
    // softmax over a single key is 1: every query gets Wo (Wv kv + bv) + bo.
    const Vec v = ps.view(att.wv, 4, 4) * kv.col(0) + ps.vec(att.bv, 4);
    const Vec expect = ps.view(att.wo, 4, 4) * v + ps.vec(att.bo, 4);
    for (int j = 0; j < 3; ++j) CHECK((y.col(j) - expect).cwiseAbs().maxCoeff() < 1e-5);
}

TEST_CASE("nn: attention gradients, cross-attention with masks, batch 3, a fully masked item") {
    Rng rng(6);
    ParamStore ps;
    madbp::MultiHeadAttention att(ps, "att", 8, 2, rng);
    ps.value = randn(ps.size(), 1, rng, 0.5);  // non-zero biases too
    const int Lq = 3, Lk = 4, B = 3;
    const float mask[Lk * B] = {1, 0, 1, 1, 0, 0, 0, 0, 0, 1, 1, 1};  // item 1 fully masked
    GradCheck gc;
    gc.ps = &ps;
    gc.inputs = {randn(8, Lq * B, rng), randn(8, Lk * B, rng)};
    gc.reference = [&](const std::vector<MatD>& x, const VecD& p) { return ref_attention(x[0], Lq, x[1], Lk, B, mask, p, att); };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& d) {
        att.backward(gc.inputs[0], Lq, gc.inputs[1], Lk, B, mask, dy, d[0], d[1]);
    };
    Mat y;
    att.forward(gc.inputs[0], Lq, gc.inputs[1], Lk, B, mask, y);
    CHECK(y.allFinite());
    CHECK(y.middleCols(Lq, Lq).cwiseAbs().maxCoeff() == 0);  // the fully masked item
    gc.check(y);
    std::vector<Mat> d(2);
    att.backward(gc.inputs[0], Lq, gc.inputs[1], Lk, B, mask, Mat::Ones(8, Lq * B), d[0], d[1]);
    CHECK(d[0].middleCols(Lq, Lq).cwiseAbs().maxCoeff() == 0);
    CHECK(d[1].middleCols(Lk, Lk).cwiseAbs().maxCoeff() == 0);
}

TEST_CASE("nn: self-attention gradients (same matrix twice, input gradients summed)") {
    Rng rng(7);
    ParamStore ps;
    madbp::MultiHeadAttention att(ps, "att", 6, 3, rng);
    const int L = 5, B = 2;
    const float mask[L * B] = {1, 1, 1, 0, 0, 1, 1, 1, 1, 1};
    GradCheck gc;
    gc.ps = &ps;
    gc.inputs = {randn(6, L * B, rng)};
    gc.reference = [&](const std::vector<MatD>& x, const VecD& p) { return ref_attention(x[0], L, x[0], L, B, mask, p, att); };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& d) {
        Mat dq, dkv;
        att.backward(gc.inputs[0], L, gc.inputs[0], L, B, mask, dy, dq, dkv);
        d[0] = dq + dkv;
    };
    Mat y;
    att.forward(gc.inputs[0], L, gc.inputs[0], L, B, mask, y);
    gc.check(y);
}

TEST_CASE("nn: layers split work over threads with the same results, forward and backward") {
    Rng rng(8);
    ParamStore ps;
    const int D = 64, L = 16, B = 32;  // large enough to take the OpenMP paths
    madbp::MultiHeadAttention att(ps, "att", D, 4, rng);
    madbp::Conv1d conv(ps, "conv", D, D, 5, rng);
    Mat x = randn(D, L * B, rng), dy = randn(D, L * B, rng);
    std::vector<float> mask(L * B, 1.0f);
    for (int i = 0; i < L * B; i += 3) mask[i] = 0;
    Mat y[2], dq[2], dkv[2], dx[2], yc[2];
    ThreadSettingsGuard restore;
    Vec grad[2];
    for (int t = 0; t < 2; ++t) {
        madbp::set_num_threads(t + 1);
        ps.zero_grad();
        att.forward(x, L, x, L, B, mask.data(), y[t]);
        att.backward(x, L, x, L, B, mask.data(), dy, dq[t], dkv[t]);
        conv.forward(x, L, yc[t]);
        conv.backward(x, L, dy, dx[t]);
        grad[t] = ps.grad;
    }
    auto close = [](const auto& a, const auto& b) { return (a - b).cwiseAbs().maxCoeff() <= 1e-5 * (1 + a.cwiseAbs().maxCoeff()); };
    CHECK(close(y[0], y[1]));
    CHECK(close(dq[0], dq[1]));
    CHECK(close(dkv[0], dkv[1]));
    CHECK(close(yc[0], yc[1]));
    CHECK(close(dx[0], dx[1]));
    CHECK(close(grad[0], grad[1]));
}

// ---------------------------------------------------------------------------------------------
// Conv1d, ConvTranspose1d

TEST_CASE("nn: Conv1d forward with a known kernel keeps items apart") {
    Rng rng(0);
    ParamStore ps;
    madbp::Conv1d conv(ps, "conv", 1, 1, 3, rng);
    ps.view(conv.w, 1, 3) << 1, 2, 3;  // taps x(t-1), x(t), x(t+1)
    ps.vec(conv.b, 1).setZero();
    Mat x(1, 8), y;
    x << 1, 2, 3, 4, 10, 20, 30, 40;  // two items of T = 4
    conv.forward(x, 4, y);
    Mat expect(1, 8);
    expect << 8, 14, 20, 11, 80, 140, 200, 110;
    CHECK((y - expect).cwiseAbs().maxCoeff() < 1e-5);
}

TEST_CASE("nn: Conv1d gradients, k 3 and 5, batch 3") {
    for (int k : {3, 5}) {
        Rng rng(9 + k);
        ParamStore ps;
        madbp::Conv1d conv(ps, "conv", 3, 4, k, rng);
        const int T = 6;
        check_layer(
            &ps, randn(3, T * 3, rng), [&](const MatD& x, const VecD& p) { return ref_conv1d(x, T, p, conv); },
            [&](const Mat& x, Mat& y) { conv.forward(x, T, y); }, [&](const Mat& x, const Mat& dy, Mat& dx) { conv.backward(x, T, dy, dx); });
    }
}

TEST_CASE("nn: ConvTranspose1d forward with a known kernel doubles T") {
    Rng rng(0);
    ParamStore ps;
    madbp::ConvTranspose1d up(ps, "up", 1, 1, rng);
    ps.view(up.w, 4, 1) << 1, 2, 3, 4;
    ps.vec(up.b, 1).setZero();
    Mat x(1, 4), y;
    x << 1, 1, 0, 1;  // items [1, 1] and [0, 1]
    up.forward(x, 2, y);
    Mat expect(1, 8);
    expect << 2, 4, 6, 3, 0, 1, 2, 3;
    CHECK((y - expect).cwiseAbs().maxCoeff() < 1e-6);
}

TEST_CASE("nn: ConvTranspose1d gradients") {
    Rng rng(12);
    ParamStore ps;
    madbp::ConvTranspose1d up(ps, "up", 3, 2, rng);
    const int T = 4;
    check_layer(
        &ps, randn(3, T * 2, rng), [&](const MatD& x, const VecD& p) { return ref_conv_transpose(x, T, p, up); },
        [&](const Mat& x, Mat& y) { up.forward(x, T, y); }, [&](const Mat& x, const Mat& dy, Mat& dx) { up.backward(x, T, dy, dx); });
}

// ---------------------------------------------------------------------------------------------
// BatchNorm1d

TEST_CASE("nn: BatchNorm1d masked columns do not change the unmasked outputs or the statistics") {
    Rng rng(13);
    ParamStore ps;
    madbp::BatchNorm1d bn(ps, "bn", 3, rng);
    Mat x = randn(3, 8, rng), y1, y2;
    const float mask[8] = {1, 1, 0, 1, 0, 1, 1, 0};
    bn.forward(x, mask, y1);
    const Vec rm1 = ps.state_vec(bn.running_mean, 3), rv1 = ps.state_vec(bn.running_var, 3);
    ps.state_vec(bn.running_mean, 3).setZero();
    ps.state_vec(bn.running_var, 3).setOnes();
    for (int j : {2, 4, 7}) x.col(j).setConstant(1e3f);
    bn.forward(x, mask, y2);
    for (int j : {0, 1, 3, 5, 6}) CHECK((y1.col(j) - y2.col(j)).cwiseAbs().maxCoeff() == 0);
    CHECK((rm1 - ps.state_vec(bn.running_mean, 3)).cwiseAbs().maxCoeff() == 0);
    CHECK((rv1 - ps.state_vec(bn.running_var, 3)).cwiseAbs().maxCoeff() == 0);
    // Running statistics after one step: 0.1 * mean and 0.9 + 0.1 * unbiased variance.
    Vec mean = Vec::Zero(3), var = Vec::Zero(3);
    for (int j : {0, 1, 3, 5, 6}) mean += x.col(j) / 5;
    for (int j : {0, 1, 3, 5, 6}) var.array() += (x.col(j) - mean).array().square() / 4;
    CHECK((ps.state_vec(bn.running_mean, 3) - 0.1f * mean).cwiseAbs().maxCoeff() < 1e-6);
    CHECK((ps.state_vec(bn.running_var, 3) - (0.9f * Vec::Ones(3) + 0.1f * var)).cwiseAbs().maxCoeff() < 1e-5);
}

TEST_CASE("nn: BatchNorm1d gradients in training mode with a mask, and in eval mode") {
    for (bool training : {true, false}) {
        Rng rng(14);
        ParamStore ps;
        madbp::BatchNorm1d bn(ps, "bn", 4, rng);
        ps.value = randn(ps.size(), 1, rng, 0.5);
        ps.state_vec(bn.running_var, 4) = ps.state_vec(bn.running_var, 4).cwiseAbs().array() + 0.5f;
        bn.training = training;
        const float mask[10] = {1, 0, 1, 1, 1, 0, 1, 1, 0, 1};
        GradCheck gc;
        gc.ps = &ps;
        gc.inputs = {randn(4, 10, rng, 2.0)};
        Mat y;
        bn.forward(gc.inputs[0], mask, y);
        // Training mode updated the running statistics; the reference in training mode does
        // not read them, in eval mode forward did not change them.
        gc.reference = [&](const std::vector<MatD>& x, const VecD& p) { return ref_batchnorm(x[0], mask, p, bn, training); };
        gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { bn.backward(gc.inputs[0], mask, dy, dx[0]); };
        gc.check(y);
    }
}

TEST_CASE("nn: BatchNorm1d eval mode uses the running statistics") {
    Rng rng(0);
    ParamStore ps;
    madbp::BatchNorm1d bn(ps, "bn", 1, rng);
    ps.state_vec(bn.running_mean, 1) << 2;
    ps.state_vec(bn.running_var, 1) << 4;
    bn.training = false;
    Mat x(1, 2), y;
    x << 2, 6;
    bn.forward(x, nullptr, y);
    CHECK(y(0) == doctest::Approx(0.0));
    CHECK(y(1) == doctest::Approx(4.0 / std::sqrt(4.0 + 1e-5)));
    CHECK(ps.state_vec(bn.running_mean, 1)[0] == 2);
}

// ---------------------------------------------------------------------------------------------
// MaxPool1d, Upsample1d

TEST_CASE("nn: MaxPool1d forward, and ties send the gradient to the first element") {
    madbp::MaxPool1d pool;
    Mat x(1, 8), y, dx;
    x << 1, 3, 2, 2, 5, 4, -1, 0;
    pool.forward(x, 4, y);
    Mat expect(1, 4);
    expect << 3, 2, 5, 0;
    CHECK((y - expect).cwiseAbs().maxCoeff() == 0);
    pool.backward(x, 4, Mat::Ones(1, 4), dx);
    Mat dexpect(1, 8);
    dexpect << 0, 1, 1, 0, 1, 0, 0, 1;
    CHECK((dx - dexpect).cwiseAbs().maxCoeff() == 0);
}

TEST_CASE("nn: MaxPool1d gradients away from ties") {
    Rng rng(15);
    madbp::MaxPool1d pool;
    Mat x = randn(3, 8 * 2, rng);
    for (long o = 0; o < x.cols() / 2; ++o)  // keep each pair at least 0.1 apart
        for (long c = 0; c < 3; ++c)
            if (std::abs(x(c, 2 * o) - x(c, 2 * o + 1)) < 0.1f) x(c, 2 * o) += 0.2f;
    GradCheck gc;
    gc.inputs = {x};
    gc.reference = [&](const std::vector<MatD>& in, const VecD&) {
        MatD y(in[0].rows(), in[0].cols() / 2);
        for (long o = 0; o < y.cols(); ++o)
            for (long c = 0; c < y.rows(); ++c) y(c, o) = std::max(in[0](c, 2 * o), in[0](c, 2 * o + 1));
        return y;
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { pool.backward(gc.inputs[0], 8, dy, dx[0]); };
    Mat y;
    pool.forward(x, 8, y);
    gc.check(y);
}

TEST_CASE("nn: Upsample1d forward and gradients") {
    Rng rng(16);
    madbp::Upsample1d up;
    Mat x(1, 2), y;
    x << 1, 2;
    up.forward(x, y);
    CHECK(y.cols() == 4);
    CHECK(y(0) == 1);
    CHECK(y(1) == 1);
    CHECK(y(2) == 2);
    CHECK(y(3) == 2);
    GradCheck gc;
    gc.inputs = {randn(3, 10, rng)};
    gc.reference = [&](const std::vector<MatD>& in, const VecD&) {
        MatD out(in[0].rows(), 2 * in[0].cols());
        for (long t = 0; t < in[0].cols(); ++t) out.col(2 * t) = out.col(2 * t + 1) = in[0].col(t);
        return out;
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { up.backward(gc.inputs[0], dy, dx[0]); };
    up.forward(gc.inputs[0], y);
    gc.check(y);
}

// ---------------------------------------------------------------------------------------------
// Conv2d

TEST_CASE("nn: Conv2d forward with a known kernel, and output sizes with stride") {
    Rng rng(0);
    ParamStore ps;
    madbp::Conv2d conv(ps, "conv", 1, 1, 2, 1, 0, rng);
    ps.view(conv.w, 1, 4).setOnes();
    ps.vec(conv.b, 1).setZero();
    Mat x(1, 9), y;
    x << 1, 2, 3, 4, 5, 6, 7, 8, 9;  // one 3x3 image, row-major
    conv.forward(x, 3, 3, y);
    Mat expect(1, 4);
    expect << 12, 16, 24, 28;  // sums of the 2x2 windows
    CHECK((y - expect).cwiseAbs().maxCoeff() < 1e-5);
    madbp::Conv2d strided(ps, "strided", 1, 2, 3, 2, 1, rng);
    CHECK(strided.out_size(32) == 16);
    CHECK(strided.out_size(5) == 3);
}

TEST_CASE("nn: Conv2d gradients with stride 2 and padding, batch 2") {
    Rng rng(17);
    ParamStore ps;
    madbp::Conv2d conv(ps, "conv", 2, 3, 3, 2, 1, rng);
    const int H = 5, W = 4;
    GradCheck gc;
    gc.ps = &ps;
    gc.inputs = {randn(2, H * W * 2, rng)};
    gc.reference = [&](const std::vector<MatD>& x, const VecD& p) { return ref_conv2d(x[0], H, W, p, conv); };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) { conv.backward(gc.inputs[0], H, W, dy, dx[0]); };
    Mat y;
    conv.forward(gc.inputs[0], H, W, y);
    CHECK(y.cols() == 3 * 2 * 2);
    gc.check(y);
}

// ---------------------------------------------------------------------------------------------
// Activations

template <class Act>
static void check_activation(Act act, std::function<double(double)> f, bool avoid_zero) {
    Rng rng(18);
    Mat x = randn(4, 6, rng, 2.0);
    if (avoid_zero)  // ReLU's kink at 0: keep inputs at least 0.05 away
        for (long i = 0; i < x.size(); ++i) x.data()[i] += x.data()[i] >= 0 ? 0.05f : -0.05f;
    check_layer(
        nullptr, x, [&](const MatD& x, const VecD&) { return MatD(x.unaryExpr(f)); },
        [&](const Mat& x, Mat& y) { act.forward(x, y); }, [&](const Mat& x, const Mat& dy, Mat& dx) { act.backward(x, dy, dx); });
}

TEST_CASE("nn: ReLU, SiLU, Mish, Tanh gradients") {
    check_activation(madbp::ReLU{}, [](double v) { return v > 0 ? v : 0.0; }, true);
    check_activation(madbp::SiLU{}, [](double v) { return v / (1 + std::exp(-v)); }, false);
    check_activation(madbp::Mish{}, [](double v) { return v * std::tanh(std::log1p(std::exp(v))); }, false);
    check_activation(madbp::Tanh{}, [](double v) { return std::tanh(v); }, false);
}

TEST_CASE("nn: Mish and SiLU stay finite for large inputs") {
    Mat x(1, 4), y;
    x << -100, -30, 30, 100;
    madbp::Mish().forward(x, y);
    CHECK(y.allFinite());
    CHECK(y(3) == doctest::Approx(100));
    madbp::SiLU().forward(x, y);
    CHECK(y.allFinite());
}

// ---------------------------------------------------------------------------------------------
// Embedding, sinusoidal embedding, FiLM

TEST_CASE("nn: Embedding forward, gradients, and out-of-range ids") {
    Rng rng(19);
    ParamStore ps;
    madbp::Embedding emb(ps, "emb", 5, 3, rng);
    const int ids[6] = {4, 0, 4, 2, 1, 0};
    Mat y;
    emb.forward(ids, 6, y);
    CHECK((y.col(0) - ps.view(emb.table, 3, 5).col(4)).cwiseAbs().maxCoeff() == 0);
    GradCheck gc;
    gc.ps = &ps;
    gc.reference = [&](const std::vector<MatD>&, const VecD& p) {
        MatD out(3, 6);
        for (int n = 0; n < 6; ++n) out.col(n) = pmat(p, emb.table, 3, 5).col(ids[n]);
        return out;
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>&) { emb.backward(ids, 6, dy); };
    gc.check(y);
    const int bad[2] = {1, 5};
    CHECK_THROWS_AS(emb.forward(bad, 2, y), std::invalid_argument);
    const int negative[1] = {-1};
    CHECK_THROWS_AS(emb.forward(negative, 1, y), std::invalid_argument);
}

TEST_CASE("nn: sinusoidal embedding values and derivative") {
    Mat y;
    const float t0[2] = {0, 1};
    madbp::sinusoidal_embedding(t0, 2, 4, y);  // frequencies 1 and 1e-4
    CHECK(y(0, 0) == 0);
    CHECK(y(2, 0) == 1);
    CHECK(y(0, 1) == doctest::Approx(std::sin(1.0)));
    CHECK(y(1, 1) == doctest::Approx(std::sin(1e-4)));
    CHECK(y(2, 1) == doctest::Approx(std::cos(1.0)));
    Rng rng(20);
    GradCheck gc;
    gc.inputs = {Mat(1, 5)};
    gc.inputs[0] << 0.5f, 3, 17, 42, 99;
    const int dim = 16;
    gc.reference = [&](const std::vector<MatD>& in, const VecD&) {
        MatD out(dim, in[0].cols());
        for (long n = 0; n < in[0].cols(); ++n)
            for (int i = 0; i < dim / 2; ++i) {
                const double f = std::exp(-std::log(10000.0) * i / (dim / 2 - 1));
                out(i, n) = std::sin(in[0](0, n) * f);
                out(dim / 2 + i, n) = std::cos(in[0](0, n) * f);
            }
        return out;
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& d) {
        madbp::sinusoidal_embedding_backward(gc.inputs[0].data(), 5, dim, dy, d[0].data());
    };
    madbp::sinusoidal_embedding(gc.inputs[0].data(), 5, dim, y);
    gc.check(y);
}

TEST_CASE("nn: FiLM forward and gradients") {
    Rng rng(21);
    const int C = 3, T = 4, B = 2;
    Mat x = randn(C, T * B, rng), gamma = randn(C, B, rng), beta = randn(C, B, rng), y;
    madbp::film_forward(x, T, gamma, beta, y);
    CHECK(y(1, T + 2) == doctest::Approx(x(1, T + 2) * (1 + gamma(1, 1)) + beta(1, 1)));
    GradCheck gc;
    gc.inputs = {x, gamma, beta};
    gc.reference = [&](const std::vector<MatD>& in, const VecD&) {
        MatD out(C, T * B);
        for (int b = 0; b < B; ++b)
            for (int t = 0; t < T; ++t)
                for (int c = 0; c < C; ++c) out(c, b * T + t) = in[0](c, b * T + t) * (1 + in[1](c, b)) + in[2](c, b);
        return out;
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& d) { madbp::film_backward(x, T, gamma, dy, d[0], d[1], d[2]); };
    gc.check(y);
}

// ---------------------------------------------------------------------------------------------
// A small network end to end: layers chained, the gradient of the whole checked at once.

TEST_CASE("nn: a chained block (Conv1d, BatchNorm, Mish, MaxPool, Upsample, FiLM, Linear) checks end to end") {
    Rng rng(22);
    ParamStore ps;
    madbp::Conv1d conv(ps, "conv", 2, 4, 3, rng);
    madbp::BatchNorm1d bn(ps, "bn", 4, rng);
    madbp::Mish act;
    madbp::MaxPool1d pool;
    madbp::Upsample1d up;
    madbp::Linear head(ps, "head", 4, 2, rng);
    const int T = 4, B = 3;
    const float mask[T * B] = {1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0};  // item 2 is padding
    Mat gamma = randn(4, B, rng, 0.3), beta = randn(4, B, rng, 0.3);
    Mat h1, h2, h3, h4, h5, h6, y;
    auto forward = [&](const Mat& x) {
        conv.forward(x, T, h1);
        bn.forward(h1, mask, h2);
        act.forward(h2, h3);
        pool.forward(h3, T, h4);
        up.forward(h4, h5);
        madbp::film_forward(h5, T, gamma, beta, h6);
        head.forward(h6, y);
    };
    GradCheck gc;
    gc.ps = &ps;
    gc.inputs = {randn(2, T * B, rng)};
    forward(gc.inputs[0]);
    // The reference: the same chain in double from the layer references above.
    gc.reference = [&](const std::vector<MatD>& in, const VecD& p) {
        MatD a = ref_conv1d(in[0], T, p, conv);
        a = ref_batchnorm(a, mask, p, bn, true);
        a = a.unaryExpr([](double v) { return v * std::tanh(std::log1p(std::exp(v))); }).eval();
        MatD pooled(a.rows(), a.cols() / 2), upsampled(a.rows(), a.cols());
        for (long o = 0; o < pooled.cols(); ++o) pooled.col(o) = a.col(2 * o).cwiseMax(a.col(2 * o + 1));
        for (long o = 0; o < pooled.cols(); ++o) upsampled.col(2 * o) = upsampled.col(2 * o + 1) = pooled.col(o);
        for (int b = 0; b < B; ++b)
            for (int t = 0; t < T; ++t)
                upsampled.col(b * T + t) = upsampled.col(b * T + t).cwiseProduct((1.0 + gamma.col(b).cast<double>().array()).matrix()) +
                                           beta.col(b).cast<double>();
        return ref_linear(upsampled, p, head);
    };
    gc.backward = [&](const Mat& dy, std::vector<Mat>& dx) {
        Mat d6, d5, d4, d3, d2, d1, dg, db;
        head.backward(h6, dy, d6);
        madbp::film_backward(h5, T, gamma, d6, d5, dg, db);
        up.backward(h4, d5, d4);
        pool.backward(h3, T, d4, d3);
        act.backward(h2, d3, d2);
        bn.backward(h1, mask, d2, d1);
        conv.backward(gc.inputs[0], T, d1, dx[0]);
    };
    gc.tol = 5e-3;  // max-pool pairs may sit close together after BatchNorm
    gc.check(y);
}

// ---------------------------------------------------------------------------------------------
// Optimisation

TEST_CASE("nn: Adam matches a hand-computed first and second step, eps outside the root") {
    Rng rng(0);
    ParamStore ps;
    ps.add("w", {1}, madbp::Init::ones(), rng);
    ps.add("stat", {1}, madbp::Init::ones(), rng, false);
    madbp::Adam adam;
    adam.lr = 0.1f;
    adam.eps = 0.1f;  // large, so eps inside the square root would give a different answer
    REQUIRE(ps.size() == 1);  // the state lives apart from the weights
    ps.grad << 0.5f;
    adam.update(ps);
    // m = 0.05, v = 0.00025, m_hat = 0.5, v_hat = 0.25: step = 0.1 * 0.5 / (0.5 + 0.1).
    CHECK(ps.value[0] == doctest::Approx(1.0 - 0.1 * 0.5 / 0.6).epsilon(1e-6));
    CHECK(ps.state[0] == 1.0f);  // non-trainable: untouched
    CHECK(adam.step == 1);
    ps.grad << -0.25f;
    adam.update(ps);
    const double m = 0.9 * 0.05 + 0.1 * -0.25, v = 0.999 * 0.00025 + 0.001 * 0.0625;
    const double mhat = m / (1 - 0.81), vhat = v / (1 - 0.999 * 0.999);
    CHECK(ps.value[0] == doctest::Approx(1.0 - 0.1 * 0.5 / 0.6 - 0.1 * mhat / (std::sqrt(vhat) + 0.1)).epsilon(1e-5));
    // Decoupled weight decay: with zero gradient, p -= lr * wd * p.
    madbp::Adam decay;
    decay.lr = 0.1f;
    decay.weight_decay = 0.5f;
    ps.value << 2.0f;
    ps.zero_grad();
    decay.update(ps);
    CHECK(ps.value[0] == doctest::Approx(2.0 - 0.1 * 0.5 * 2.0));
}

TEST_CASE("nn: clip_grad_norm scales trainable gradients and returns the norm before clipping") {
    Rng rng(0);
    ParamStore ps;
    ps.add("a", {2}, madbp::Init::zeros(), rng);
    ps.add("stat", {1}, madbp::Init::zeros(), rng, false);
    REQUIRE(ps.grad.size() == 2);  // state has no gradient
    ps.grad << 3, 4;
    CHECK(madbp::clip_grad_norm(ps, 1.0f) == doctest::Approx(5.0));
    CHECK(ps.grad[0] == doctest::Approx(0.6).epsilon(1e-5));
    CHECK(ps.grad[1] == doctest::Approx(0.8).epsilon(1e-5));
    CHECK(madbp::clip_grad_norm(ps, 10.0f) == doctest::Approx(1.0).epsilon(1e-5));  // under the limit
    CHECK(ps.grad[1] == doctest::Approx(0.8).epsilon(1e-5));
}

TEST_CASE("nn: EMA copies first, then averages the weights and leaves the state alone") {
    Rng rng(0);
    ParamStore ps;
    ps.add("w", {1}, madbp::Init::zeros(), rng);
    ps.add("stat", {1}, madbp::Init::zeros(), rng, false);
    madbp::Ema ema;
    ema.decay = 0.9f;
    ps.value << 1;
    ema.update(ps);
    CHECK(ema.shadow[0] == 1);
    ps.value << 2;
    ps.state << 5;
    ema.update(ps);
    CHECK(ema.shadow.size() == 1);
    CHECK(ema.shadow[0] == doctest::Approx(1.1));
    ema.copy_to(ps);
    CHECK(ps.value[0] == doctest::Approx(1.1));
    CHECK(ps.state[0] == 5);  // the live statistics go with the EMA weights
}

TEST_CASE("nn: a two-layer MLP trained with Adam fits a regression problem (MSE < 2e-3)") {
    // y = sin(2 x0) * cos(x1) on 256 points of [-1, 1]^2; the target's variance is ~0.2.
    Rng rng(23);
    const int N = 256;
    Mat x(2, N), target(1, N);
    for (int n = 0; n < N; ++n) {
        x(0, n) = (float)rng.uniform(-1, 1);
        x(1, n) = (float)rng.uniform(-1, 1);
        target(0, n) = std::sin(2 * x(0, n)) * std::cos(x(1, n));
    }
    ParamStore ps;
    madbp::Linear fc1(ps, "fc1", 2, 32, rng), fc2(ps, "fc2", 32, 1, rng);
    madbp::Tanh act;
    madbp::Adam adam;
    adam.lr = 1e-2f;
    Mat h, a, y, dy, da, dh, dx;
    float mse = 1;
    for (int step = 0; step < 1500; ++step) {
        fc1.forward(x, h);
        act.forward(h, a);
        fc2.forward(a, y);
        mse = (y - target).squaredNorm() / N;
        dy = 2 * (y - target) / N;
        ps.zero_grad();
        fc2.backward(a, dy, da);
        act.backward(h, da, dh);
        fc1.backward(x, dh, dx);
        madbp::clip_grad_norm(ps, 1.0f);
        adam.update(ps);
    }
    MESSAGE("MLP regression MSE after 1500 Adam steps: " << mse);
    CHECK(mse < 2e-3);
}

// ---------------------------------------------------------------------------------------------
// No heap allocation in a steady-state forward pass.

TEST_CASE("nn: a steady-state forward pass allocates nothing") {
    Rng rng(24);
    ParamStore ps;
    const int D = 64, T = 16, B = 16;
    madbp::Linear lin(ps, "lin", D, D, rng);
    madbp::LayerNorm ln(ps, "ln", D, rng);
    madbp::MultiHeadAttention att(ps, "att", D, 4, rng);
    madbp::Conv1d conv(ps, "conv", D, D, 5, rng);
    madbp::BatchNorm1d bn(ps, "bn", D, rng), bn_eval(ps, "bn_eval", D, rng);
    bn_eval.training = false;
    madbp::MultiHeadAttention cross(ps, "cross", D, 4, rng);
    madbp::MaxPool1d pool;
    madbp::Upsample1d up;
    madbp::ConvTranspose1d upconv(ps, "upconv", D, D, rng);
    madbp::Conv2d conv2d(ps, "conv2d", 1, 8, 3, 2, 1, rng);
    madbp::Mish mish;
    madbp::SiLU silu;
    madbp::ReLU relu;
    madbp::Tanh tanh_;
    madbp::Embedding emb(ps, "emb", 10, D, rng);
    Mat queries = randn(D, 8 * B, rng);
    Mat x = randn(D, T * B, rng), grid = randn(1, 32 * 32 * 2, rng), gamma = randn(D, B, rng), beta = randn(D, B, rng);
    std::vector<float> mask(T * B, 1.0f), steps(B);
    std::vector<int> ids(B);
    for (int i = 0; i < T * B; i += 5) mask[i] = 0;
    for (int b = 0; b < B; ++b) steps[b] = (float)b, ids[b] = b % 10;
    Mat h1, h2, h3, h4, h5, h6, h7, h8, h9, h10, h11, h12, h13, g1, e1, e2, c1, c2;
    auto forward = [&] {
        lin.forward(x, h1);
        ln.forward(h1, h2);
        att.forward(h2, T, h2, T, B, mask.data(), h3);
        conv.forward(h3, T, h4);
        bn.forward(h4, mask.data(), h5);
        mish.forward(h5, h6);
        pool.forward(h6, T, h7);
        up.forward(h7, h8);
        upconv.forward(h7, T / 2, h9);
        madbp::film_forward(h9, T, gamma, beta, h10);
        silu.forward(h10, h11);
        relu.forward(h11, h12);
        tanh_.forward(h12, h13);
        conv2d.forward(grid, 32, 32, g1);
        emb.forward(ids.data(), B, e1);
        madbp::sinusoidal_embedding(steps.data(), B, D, e2);
        bn_eval.forward(h4, nullptr, c1);
        cross.forward(queries, 8, h2, T, B, nullptr, c2);  // 8 queries per item, T keys, no mask
    };
    ThreadSettingsGuard restore;
    for (int threads : {1, 2}) {
        madbp::set_num_threads(threads);
        forward();  // first pass sizes every buffer
        forward();
        g_allocs = 0;
        g_count_allocs = true;
        forward();
        g_count_allocs = false;
#if MADBP_TEST_COUNT_ALLOCS
        INFO("threads " << threads);
        CHECK(g_allocs.load() == 0);
#else
        MESSAGE("allocation counting is off under AddressSanitizer");
#endif
    }
    // The counter works: a fresh matrix allocates.
    g_allocs = 0;
    g_count_allocs = true;
    Mat fresh(D, 100);
    fresh.setZero();
    g_count_allocs = false;
#if MADBP_TEST_COUNT_ALLOCS
    CHECK(g_allocs.load() > 0);
#endif
    CHECK(fresh.sum() == 0);
}
