// Development file: the MA-DBP model section, appended to madbp.hpp when it lands.
#pragma once
#include "madbp.hpp"
#include <algorithm>
#include <map>
#include <memory>
#include <numeric>

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
    Prediction prediction = Prediction::Eps;

    int levels() const { return (int)channels.size(); }
    int image_tokens() const { return (grid / 8) * (grid / 8); }
    // Throws std::invalid_argument naming the field when a value is unusable.
    void validate() const {
        auto bad = [](const std::string& f, const std::string& why) { throw std::invalid_argument("model config " + f + ": " + why); };
        if (channels.empty() || channels.size() > 4) bad("channels", "needs 1 to 4 levels");
        for (int c : channels) if (c < 1 || c > 1024) bad("channels", "each width must be in [1, 1024]");
        if (horizon < 2 || horizon % (1 << levels()) != 0) bad("horizon", std::to_string(horizon) + " must be >= 2 and a multiple of 2^levels");
        if (dim < 4 || dim % 2 || heads < 1 || dim % heads) bad("dim/heads", "dim must be even, >= 4 and divisible by heads");
        if (n_max < 1 || n_max > 1024) bad("n_max", "must be in [1, 1024]");
        if (grid < 8 || grid % 8) bad("grid", "must be a positive multiple of 8");
        if (local_grid < 0 || local_grid % 4 || local_grid > 256) bad("local_grid", "must be 0 or a multiple of 4 up to 256");
        if (!(local_extent > 0) || !std::isfinite(local_extent)) bad("local_extent", "must be positive");
        if (kernel < 1 || kernel % 2 == 0) bad("kernel", "must be odd");
        if (diffusion_steps < 2 || sample_steps < 1 || sample_steps > diffusion_steps) bad("sample_steps", "must be in [1, diffusion_steps]");
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
        return {{"model", "madbp"}, {"horizon", std::to_string(horizon)}, {"dim", std::to_string(dim)},
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
        try {
            c.position_scale = std::stof(get("position_scale"));
            c.window_scale = std::stof(get("window_scale"));
            c.local_extent = std::stof(get("local_extent"));
        } catch (const std::runtime_error&) {
            throw;
        } catch (...) {
            throw std::runtime_error(source + ": metadata fields 'position_scale' / 'window_scale' must be numbers");
        }
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

    int agents() const { return B * n; }
    void resize(int B_, int n_, int G, int Gl = 0) {
        B = B_;
        n = n_;
        agent_mask.assign((size_t)B * n, 0.0f);
        slot.assign((size_t)B * n, 0);
        count.assign(B, 0);
        pose.setZero(4, B * n);
        grid.setZero(1, (long)G * G * B);
        local.setZero(1, (long)Gl * Gl * B * n);
    }
    void resize(int B_, int n_, const ModelConfig& c) { resize(B_, n_, c.grid, c.local_grid); }
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
    long parameter_count() const {
        long n = 0;
        for (auto& e : params->entries) if (e.trainable) n += e.numel();
        return n;
    }
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
        const int B = batch.B, n = batch.n, A = B * n, G = c.grid, P = c.image_tokens();
        auto& e = enc_;
        e.g1.forward(batch.grid, G, G, e.g1o);
        e.r1.forward(e.g1o, e.g1a);
        e.g2.forward(e.g1a, G / 2, G / 2, e.g2o);
        e.r2.forward(e.g2o, e.g2a);
        e.g3.forward(e.g2a, G / 4, G / 4, e.img);
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
            e.l3.forward(e.l2a, Gl / 4, Gl / 4, e.tmp);
            e.pose_tok += e.tmp;
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
        (void)A;
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
        make_column_masks(batch);
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
        Mat g1o, g1a, g2o, g2a, img, tmp, p1, p1a, pose_tok, count_tok, kv, att, pre_ln, l1o, l1a, l2o, l2a;
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
        std::vector<Mat> skip, pooled, cat, up_out;
        Mat mid_out, up_buf;
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
        u.d_skip.resize(L);
    }

    void check_batch(const SceneBatch& b) const {
        const long A = (long)b.B * b.n;
        if (b.B < 1 || b.n < 1) throw std::invalid_argument("scene batch: needs B >= 1 and n >= 1");
        if (b.n > config.n_max)
            throw std::invalid_argument("scene batch: " + std::to_string(b.n) + " agent slots exceed the model's n_max = " + std::to_string(config.n_max));
        if ((long)b.agent_mask.size() != A || (long)b.slot.size() != A || (long)b.count.size() != b.B || b.pose.rows() != 4 ||
            b.pose.cols() != A || b.grid.rows() != 1 || b.grid.cols() != (long)config.grid * config.grid * b.B ||
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
            u.upsample[l].forward(up_input(l), u.up_buf);  // nearest x2, then the skip below it
            const long cu = u.up_buf.rows(), cs = u.skip[l].rows();
            u.cat[l].resize(cu + cs, u.up_buf.cols());
            u.cat[l].topRows(cu) = u.up_buf;
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
    // The S diffusion steps DDIM visits, descending: K, ..., K/S (rounded), then 0 (clean).
    std::vector<int> ddim_steps(int S) const {
        if (S < 1 || S > K) throw std::invalid_argument("sample_steps: " + std::to_string(S) + " must be in [1, " + std::to_string(K) + "]");
        std::vector<int> ks;
        for (int s = S; s >= 1; --s) ks.push_back((int)std::lround((double)s * K / S));
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
    float goal_reach = 0.55f;    // "within reach": distance to goal in world units at most this
};

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
        const int k = (int)std::lround((double)s * schedule.K / S);
        const int k_prev = (int)std::lround((double)(s - 1) * schedule.K / S);
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

    explicit DiffusionPlanner(MadbpModel model, uint64_t seed = 0)
        : model_(std::move(model)), schedule_(model_.config.diffusion_steps), rng_(seed) {
        model_.set_training(false);
        sampler.sample_steps = model_.config.sample_steps;
    }
    const ModelConfig& config() const { return model_.config; }
    MadbpModel& model() { return model_; }
    void reseed(uint64_t seed) { rng_.reseed(seed); }

    // A window for all present agents of `world`: waypoints for steps t+1 .. t+H-1.
    Plan plan(const World& world) {
        Plan p;
        plan_into(world, p);
        return p;
    }
    // As plan(), reusing `out`'s storage: no heap allocation once sizes are steady.
    void plan_into(const World& world, Plan& out) {
        auto t0 = std::chrono::steady_clock::now();
        const ModelConfig& c = model_.config;
        const int n = world.size(), H = c.horizon, G = c.grid;
        if (n > c.n_max)
            throw std::invalid_argument("planner: " + std::to_string(n) + " agents exceed the model's n_max = " + std::to_string(c.n_max));
        out.ids.resize(n);
        out.waypoints.resize(n);
        if (n == 0) { out.plan_ms = 0; return; }
        if (batch_.B != 1 || batch_.n != n) batch_.resize(1, n, c);
        update_grid(world.map());
        for (int i = 0; i < n; ++i) {
            const Agent& a = world.agents()[i];
            require_finite(a.pos.x, "agent " + std::to_string(a.id) + " position x");
            require_finite(a.pos.y, "agent " + std::to_string(a.id) + " position y");
            require_finite(a.goal.x, "agent " + std::to_string(a.id) + " goal x");
            require_finite(a.goal.y, "agent " + std::to_string(a.id) + " goal y");
            batch_.agent_mask[i] = 1;
            batch_.slot[i] = i;
            batch_.pose.col(i) << (float)(a.pos.x / c.position_scale), (float)(a.pos.y / c.position_scale),
                (float)(a.goal.x / c.position_scale), (float)(a.goal.y / c.position_scale);
            fill_local_crop(batch_, i, world.map(), a.pos, c);
        }
        batch_.count[0] = n;
        sample_windows(model_, schedule_, batch_, sampler, rng_, x_, eps_, steps_);
        for (int i = 0; i < n; ++i) {
            out.ids[i] = world.agents()[i].id;
            out.waypoints[i].resize(H - 1);
            const Vec2 p0 = world.agents()[i].pos;
            for (int t = 1; t < H; ++t) {
                auto w = x_.col((long)i * H + t);
                out.waypoints[i][t - 1] = p0 + Vec2{w(0) * (double)c.window_scale, w(1) * (double)c.window_scale};
            }
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
    std::vector<int> steps_;

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
