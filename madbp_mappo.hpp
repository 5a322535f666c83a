// madbp_mappo.hpp - MAPPO (SPEC 3.3): the paper's demonstrator and baseline, trained in C++.
// Part of madbp (Multi-Agent Diffusion Based Planner), header-only C++17. MIT licence.
// Staging header: its contents are meant to be folded into madbp_train.hpp unchanged.
//
// What it is
//   Multi-agent PPO on the batched navigation world: VMAS-navigation observations with a
//   12-ray lidar, a shared-parameter Gaussian actor, a centralised critic, GAE, the clipped
//   PPO objective, Adam and global-norm gradient clipping, forward and backward written by
//   hand on the NN core (Linear, Tanh). One policy is trained per map and team size n, as in
//   the paper; it drives exactly n agents.
//
// Use
//   #include "madbp_mappo.hpp"
//   madbp::MappoConfig c;  c.map = "empty";  c.agents = 4;  c.out = "mappo-empty-4.safetensors";
//   madbp::train_mappo(c);                                   // + .train, .csv, .svg beside it
//   madbp::World world = madbp::make_random_world("empty", 4, /*seed=*/0);
//   madbp::MappoPolicy policy(madbp::load_mappo(c.out));     // the mean action, no sampling
//   while (!world.done()) world.step(policy.act(world));
//
// Shapes (as in madbp.hpp: an activation is (C, N), one column per sample)
//   O = 18 observation features, n = agents per world, W = worlds, T = steps per iteration,
//   S = T * W * n samples of a rollout, column s = (t * W + w) * n + i.
//
// Configuration macros: none beyond madbp.hpp's.

#ifndef MADBP_MAPPO_HPP
#define MADBP_MAPPO_HPP

#include "madbp_train.hpp"

#include <mutex>

namespace madbp {

// =============================================================================================
// MAPPO observations (SPEC 3.3; VMAS navigation)
// =============================================================================================

// Per agent, 18 numbers in this order (VMAS navigation's layout, lidar extended to the map):
//   [0, 2)   position p (x, y)
//   [2, 4)   velocity v
//   [4, 6)   p - goal (the relative goal, pointing from the goal to the agent)
//   [6, 18)  12 lidar readings. Ray k leaves the agent's centre at angle 2 pi k / 12 from +x,
//            counter-clockwise (k = 0: +x, k = 3: +y, k = 6: -x, k = 9: -y). It stops at the
//            first surface of another agent's disc, a static disc, a box or a border wall
//            within range 0.35. The reading is 0.35 - distance, as VMAS feeds its lidar
//            (max_range - measure): 0 when the ray hits nothing, larger when closer, 0.35
//            when the ray starts inside a surface.
constexpr int kLidarRays = 12;
constexpr double kLidarRange = 0.35;
constexpr int kMappoObs = 6 + kLidarRays;
constexpr const char* kMappoObsLayout = "pos2,vel2,pos-goal2,lidar12@0.35(range-distance)";

namespace detail {
constexpr double kNoHit = std::numeric_limits<double>::infinity();

// Distance along the ray p + t d (t >= 0, |d| = 1) to the disc (c, r); 0 from inside.
inline double ray_disc(Vec2 p, Vec2 d, Vec2 c, double r) {
    const Vec2 m = p - c;
    const double b = dot(m, d), q = dot(m, m) - r * r;
    if (q <= 0) return 0;
    const double disc = b * b - q;
    if (b > 0 || disc < 0) return kNoHit;  // pointing away, or passing by
    return -b - std::sqrt(disc);
}
// Distance along the ray to the box (slab method); 0 from inside.
inline double ray_box(Vec2 p, Vec2 d, const Box& box) {
    double t0 = 0, t1 = kNoHit;
    const double pp[2] = {p.x, p.y}, dd[2] = {d.x, d.y}, lo[2] = {box.lo.x, box.lo.y}, hi[2] = {box.hi.x, box.hi.y};
    for (int a = 0; a < 2; ++a) {
        if (std::fabs(dd[a]) < 1e-12) {
            if (pp[a] < lo[a] || pp[a] > hi[a]) return kNoHit;
            continue;
        }
        double ta = (lo[a] - pp[a]) / dd[a], tb = (hi[a] - pp[a]) / dd[a];
        if (ta > tb) std::swap(ta, tb);
        t0 = std::max(t0, ta);
        t1 = std::min(t1, tb);
        if (t0 > t1) return kNoHit;
    }
    return t0;
}
// Distance along the ray to the border walls of [-h, h]^2 from a point inside (0 outside).
inline double ray_border(Vec2 p, Vec2 d, double h) {
    double t = kNoHit;
    if (d.x > 1e-12) t = std::min(t, (h - p.x) / d.x);
    if (d.x < -1e-12) t = std::min(t, (-h - p.x) / d.x);
    if (d.y > 1e-12) t = std::min(t, (h - p.y) / d.y);
    if (d.y < -1e-12) t = std::min(t, (-h - p.y) / d.y);
    return std::max(0.0, t);
}
}  // namespace detail

// Distance from agent index `i` of `world` along the unit direction `dir` to the first surface
// (other agents, static discs, boxes, border walls), capped at `range`.
inline double lidar_distance(const World& world, int i, Vec2 dir, double range = kLidarRange) {
    const Map& map = world.map();
    const Vec2 p = world.agents()[i].pos;
    double t = std::min(range, detail::ray_border(p, dir, map.half_size));
    for (const Disc& o : map.discs) t = std::min(t, detail::ray_disc(p, dir, o.c, o.r));
    for (const Box& b : map.boxes) t = std::min(t, detail::ray_box(p, dir, b));
    const std::vector<Agent>& agents = world.agents();
    for (int j = 0; j < (int)agents.size(); ++j)
        if (j != i) t = std::min(t, detail::ray_disc(p, dir, agents[j].pos, world.config().radius));
    return t;
}

// Writes agent index `i`'s 18 observation numbers (layout above) to out[0..18).
inline void mappo_observe(const World& world, int i, float* out) {
    const Agent& a = world.agents()[i];
    const Vec2 rel = a.pos - a.goal;
    const float head[6] = {(float)a.pos.x, (float)a.pos.y, (float)a.vel.x, (float)a.vel.y, (float)rel.x, (float)rel.y};
    std::copy(head, head + 6, out);
    for (int k = 0; k < kLidarRays; ++k) {
        const double angle = 2 * M_PI * k / kLidarRays;
        out[6 + k] = (float)(kLidarRange - lidar_distance(world, i, {std::cos(angle), std::sin(angle)}));
    }
}

// Fixed input scaling of the networks (our observation normalisation): each feature divided by
// its natural range (world half-size 1.2 for positions, top speed 0.4, lidar range 0.35), so
// inputs are O(1) without running statistics that a checkpoint would have to carry.
inline float mappo_obs_scale(int feature) {
    if (feature < 2 || (feature >= 4 && feature < 6)) return 1.0f / 1.2f;
    if (feature < 4) return 1.0f / 0.4f;
    return (float)(1.0 / kLidarRange);
}

// Scaled observations of every agent of `world`, one column each, into columns
// [col, col + n) of `obs` (kMappoObs rows).
inline void mappo_observe_all(const World& world, Mat& obs, long col) {
    float raw[kMappoObs];
    for (int i = 0; i < world.size(); ++i) {
        mappo_observe(world, i, raw);
        for (int f = 0; f < kMappoObs; ++f) obs(f, col + i) = raw[f] * mappo_obs_scale(f);
    }
}

// Critic input of a team of n agents whose actor inputs are columns [col, col + n) of `obs`:
// for agent i, its own observation followed by the others' in index order (n * O rows). The
// critic is centralised (it sees every agent) yet per agent, so agents keep their own rewards.
inline void mappo_critic_input(const Mat& obs, long col, int n, Mat& critic, long out_col) {
    for (int i = 0; i < n; ++i) {
        critic.block(0, out_col + i, kMappoObs, 1) = obs.col(col + i);
        int slot = 1;
        for (int j = 0; j < n; ++j)
            if (j != i) critic.block((long)kMappoObs * slot++, out_col + i, kMappoObs, 1) = obs.col(col + j);
    }
}

// =============================================================================================
// MAPPO networks (SPEC 3.3)
// =============================================================================================

// x (in, N) -> Linear -> Tanh -> Linear -> Tanh -> Linear -> y (out, N). Keeps the
// activations of its last forward for backward.
struct Mlp {
    Linear l1, l2, l3;
    Tanh t1, t2;
    Mat h1, a1, h2, a2, da2, dh2, da1, dh1, dx;

    Mlp() = default;
    // `out_gain` scales the last layer's initial weights (0.01 for the policy mean, as PPO
    // implementations do, so the first actions are near zero and training starts unbiased).
    Mlp(ParamStore& ps, const std::string& name, int in, int hidden, int out, Rng& rng, float out_gain = 1.0f)
        : l1(ps, name + ".fc1", in, hidden, rng), l2(ps, name + ".fc2", hidden, hidden, rng), l3(ps, name + ".fc3", hidden, out, rng) {
        ps.value.segment(l3.w, hidden * out) *= out_gain;
    }
    void forward(const Mat& x, Mat& y) {
        l1.forward(x, h1);
        t1.forward(h1, a1);
        l2.forward(a1, h2);
        t2.forward(h2, a2);
        l3.forward(a2, y);
    }
    // Adds the parameter gradients of the loss whose gradient at y is dy (x as in forward).
    void backward(const Mat& x, const Mat& dy) {
        l3.backward(a2, dy, da2);
        t2.backward(h2, da2, dh2);
        l2.backward(a1, dh2, da1);
        t1.backward(h1, da1, dh1);
        l1.backward(x, dh1, dx);
    }
};

// Architecture of a MAPPO policy; stored in the checkpoint.
struct MappoNetConfig {
    int agents = 2;            // team size n the policy is built for (>= 1)
    int hidden = 64;           // width of both hidden layers of actor and critic
    float init_log_std = -0.5f;
};

// The shared actor (scaled observation -> mean force (2), plus a state-independent learned
// log-std (2)) and the centralised critic (n * O critic input -> value). One parameter store:
// entries "actor.fc{1,2,3}.{weight,bias}", "actor.log_std", "critic.fc{1,2,3}.{weight,bias}".
class MappoNet {
public:
    MappoNetConfig config;
    std::unique_ptr<ParamStore> params;  // heap-held: the layers keep pointers to it
    Mlp actor, critic;
    int log_std = -1;                    // offset of actor.log_std (2)

    explicit MappoNet(MappoNetConfig c, uint64_t seed = 0) : config(c), params(new ParamStore) {
        if (c.agents < 1 || c.agents > 64) throw std::invalid_argument("agents: must be in [1, 64] (got " + std::to_string(c.agents) + ")");
        if (c.hidden < 1 || c.hidden > 4096) throw std::invalid_argument("hidden: must be in [1, 4096] (got " + std::to_string(c.hidden) + ")");
        Rng rng(seed);
        actor = Mlp(*params, "actor", kMappoObs, c.hidden, 2, rng, 0.01f);
        log_std = params->add("actor.log_std", {2}, Init::zeros(), rng);
        params->vec(log_std, 2).setConstant(c.init_log_std);
        critic = Mlp(*params, "critic", kMappoObs * c.agents, c.hidden, 1, rng);
    }
    MappoNet(MappoNet&&) = default;
    MappoNet& operator=(MappoNet&&) = default;
    MappoNet clone() const {
        MappoNet m(config);
        m.params->value = params->value;
        return m;
    }
    Eigen::Vector2f log_std_value() const { return params->vec(log_std, 2); }
    std::map<std::string, std::string> metadata() const {
        return {{"format", "madbp-mappo"}, {"mappo.agents", std::to_string(config.agents)},
                {"mappo.hidden", std::to_string(config.hidden)}, {"mappo.obs", kMappoObsLayout}};
    }
};

// =============================================================================================
// Gaussian policy and the PPO objective (SPEC 3.3)
// =============================================================================================

// Diagonal Gaussian over the 2 force components. log N(a; mu, sigma) =
// sum_k -(a_k - mu_k)^2 / (2 sigma_k^2) - log sigma_k - log(2 pi) / 2. The gradients are
// d/dmu_k = (a_k - mu_k) / sigma_k^2 and d/dlog sigma_k = (a_k - mu_k)^2 / sigma_k^2 - 1.
// The sample is clipped to the action box only when stepping the world; log-probabilities
// are of the unclipped sample (as BenchMARL's Gaussian policy).
inline float gaussian_log_prob(const float* a, const float* mu, const float* log_sigma, float* dmu = nullptr,
                               float* dlog_sigma = nullptr) {
    float lp = 0;
    for (int k = 0; k < 2; ++k) {
        const float inv_var = std::exp(-2 * log_sigma[k]), diff = a[k] - mu[k];
        lp += -0.5f * diff * diff * inv_var - log_sigma[k] - 0.9189385332f;
        if (dmu) dmu[k] = diff * inv_var;
        if (dlog_sigma) dlog_sigma[k] = diff * diff * inv_var - 1;
    }
    return lp;
}
// Entropy sum_k (1/2 + log(2 pi)/2 + log sigma_k); its gradient is 1 per log sigma_k.
inline float gaussian_entropy(const float* log_sigma) { return 2 * (0.5f + 0.9189385332f) + log_sigma[0] + log_sigma[1]; }

// The clipped surrogate (PPO): mean over samples of -min(r A, clip(r, 1-eps, 1+eps) A), with
// r = exp(logp - logp_old). Writes dloss/dlogp per sample: -r A / N where the unclipped term
// is the minimum or r lies inside the clip range, else 0. Also the fraction of clipped samples.
inline double clipped_surrogate(const Vec& logp, const Vec& logp_old, const Vec& adv, float eps, Vec& dlogp,
                                double* clip_fraction = nullptr) {
    const long N = logp.size();
    MADBP_ASSERT(logp_old.size() == N && adv.size() == N && N > 0);
    dlogp.resize(N);
    double loss = 0;
    long clipped = 0;
    for (long s = 0; s < N; ++s) {
        const float r = std::exp(logp[s] - logp_old[s]), rc = std::clamp(r, 1 - eps, 1 + eps);
        const bool use_unclipped = r * adv[s] <= rc * adv[s] || r == rc;
        loss -= std::min(r * adv[s], rc * adv[s]);
        dlogp[s] = use_unclipped ? -r * adv[s] / N : 0.0f;
        clipped += !use_unclipped;
    }
    if (clip_fraction) *clip_fraction = (double)clipped / N;
    return loss / N;
}

// Generalised advantage estimation over one stream of T steps (entries `stride` apart):
// delta_t = r_t + gamma V_{t+1} (1 - term_t) - V_t, A_t = delta_t + gamma lambda (1 - term_t)
// A_{t+1}, returns R_t = A_t + V_t. V_T = `last_value` (the bootstrap of a stream cut by the
// iteration, or of a time-out, which our observations cannot tell from any other step).
// `terminal` marks steps that ended an episode by success: nothing follows them; the next
// entry starts a fresh episode.
inline void gae(const float* reward, const float* value, const uint8_t* terminal, float last_value, int T, long stride,
                float gamma, float lambda, float* adv, float* ret) {
    float next_value = last_value, next_adv = 0;
    for (int t = T - 1; t >= 0; --t) {
        const long s = t * stride;
        const float keep = terminal[s] ? 0.0f : 1.0f;
        const float delta = reward[s] + gamma * next_value * keep - value[s];
        adv[s] = delta + gamma * lambda * keep * next_adv;
        ret[s] = adv[s] + value[s];
        next_value = value[s];
        next_adv = adv[s];
    }
}

// One PPO minibatch's losses.
struct PpoTerms {
    double policy = 0, value = 0, entropy = 0, approx_kl = 0, clip_fraction = 0;
};

// Minibatch of samples (columns) and the coefficients of the loss
// policy + vf_coef * value - ent_coef * entropy, value = mean (V - R)^2 / 2.
struct PpoBatch {
    Mat obs, critic_in, act;   // (O, N), (n O, N), (2, N)
    Vec logp_old, adv, ret;    // (N)
};
struct PpoCoefficients {
    float clip = 0.2f, vf_coef = 0.5f, ent_coef = 1e-3f;
};

// Forward and backward of the full PPO loss on one minibatch: adds the gradients to
// net.params->grad (the caller zeroes them) and returns the terms. Workspaces in `ws`.
struct PpoWorkspace {
    Mat mean, value, dmean, dvalue;
    Vec logp, dlogp;
};
inline PpoTerms ppo_loss(MappoNet& net, const PpoBatch& b, const PpoCoefficients& k, PpoWorkspace& ws) {
    const long N = b.obs.cols();
    PpoTerms terms;
    net.actor.forward(b.obs, ws.mean);
    const Eigen::Vector2f ls = net.log_std_value();
    ws.logp.resize(N);
    for (long s = 0; s < N; ++s) ws.logp[s] = gaussian_log_prob(&b.act(0, s), &ws.mean(0, s), ls.data());
    terms.policy = clipped_surrogate(ws.logp, b.logp_old, b.adv, k.clip, ws.dlogp, &terms.clip_fraction);
    terms.approx_kl = (b.logp_old - ws.logp).mean();
    terms.entropy = gaussian_entropy(ls.data());
    // Chain rule through the log-probability: d/dmu and d/dlog sigma per sample.
    ws.dmean.resize(2, N);
    float dls[2] = {-k.ent_coef, -k.ent_coef};  // - ent_coef * dH/dlog sigma
    for (long s = 0; s < N; ++s) {
        float dmu[2], dsig[2];
        gaussian_log_prob(&b.act(0, s), &ws.mean(0, s), ls.data(), dmu, dsig);
        for (int c = 0; c < 2; ++c) {
            ws.dmean(c, s) = ws.dlogp[s] * dmu[c];
            dls[c] += ws.dlogp[s] * dsig[c];
        }
    }
    net.actor.backward(b.obs, ws.dmean);
    for (int c = 0; c < 2; ++c) net.params->grad[net.log_std + c] += dls[c];
    net.critic.forward(b.critic_in, ws.value);
    ws.dvalue = (ws.value.row(0) - b.ret.transpose()) * (k.vf_coef / N);
    terms.value = 0.5 * (ws.value.row(0) - b.ret.transpose()).squaredNorm() / N;
    net.critic.backward(b.critic_in, ws.dvalue);
    return terms;
}

// =============================================================================================
// MAPPO training (SPEC 3.3)
// =============================================================================================

// Rewards per agent and step (VMAS navigation's terms; our constants):
//   shaping * (distance to goal before the step - after it)     VMAS pos_shaping_factor 1
//   + success_bonus to every agent on the step the team succeeds (all at goal together)
//   + collision per contact the agent is in (agent-agent pair or agent-static)
//   + time per step (a small push toward finishing early)
// VMAS's collision penalty is -1, but with obstacles that is a whole episode's shaping for one
// step of contact and the policy grew timid: obstacles n = 2 reached .52 with (-1, bonus 1),
// .88 with (-0.1, 1) and .94 with (-0.1, 5) (200 iterations, 100 evaluation episodes; README).
struct MappoRewards {
    float shaping = 1.0f, success_bonus = 5.0f, collision = -0.1f, time = -0.01f;
    float at_goal = 0.0f;  // per step while within the goal tolerance
};

struct MappoConfig {
    std::string map = "empty";     // map name (SPEC 2)
    int agents = 2;                // team size n, in [1, 64]
    double half_size = 1.2;        // world half-size
    int hidden = 64;               // actor and critic width (2 hidden layers, Tanh)
    float init_log_std = -0.5f;
    int worlds = 32;               // worlds stepping together; each iteration plays max_steps (100) steps on each
    long iterations = 300;         // rollout + update rounds
    int epochs = 4;                // passes over each rollout
    int minibatches = 4;           // per epoch
    float lr = 3e-4f, gamma = 0.99f, lambda = 0.9f, max_grad_norm = 1.0f;
    PpoCoefficients ppo;
    MappoRewards rewards;
    uint64_t seed = 0;
    std::string out;               // policy file ("" = no files); + ".train" (resumable state), ".csv", ".svg"
    bool resume = false;           // continue from out + ".train"
    long checkpoint_every = 10;    // iterations
    int threads = 1;               // OpenMP threads (worlds, observations, products); results do not depend on it
    bool quiet = false;            // no progress line
    // Called after every iteration; false stops there, after a checkpoint (time budgets).
    std::function<bool(long iteration)> keep_going;

    void validate() const {
        Rng probe(0);
        make_map(map, probe, half_size);  // throws on an unknown name
        if (agents < 1 || agents > 64) throw std::invalid_argument("agents: must be in [1, 64] (got " + std::to_string(agents) + ")");
        if (worlds < 1 || iterations < 1 || epochs < 1 || minibatches < 1 || checkpoint_every < 1)
            throw std::invalid_argument("MappoConfig: worlds, iterations, epochs, minibatches, checkpoint_every must be >= 1");
        if (!(lr > 0 && gamma > 0 && gamma <= 1 && lambda >= 0 && lambda <= 1 && max_grad_norm > 0 && ppo.clip > 0))
            throw std::invalid_argument("MappoConfig: lr, gamma, lambda, max_grad_norm or clip out of range");
        if (resume && out.empty()) throw std::invalid_argument("resume: needs an output file");
    }
    // The hyper-parameters as checkpoint metadata (the record of how a policy was trained).
    std::map<std::string, std::string> metadata() const {
        auto f = [](double v) { char b[32]; std::snprintf(b, sizeof b, "%.6g", v); return std::string(b); };
        return {{"mappo.map", map}, {"mappo.half_size", f(half_size)}, {"mappo.worlds", std::to_string(worlds)},
                {"mappo.epochs", std::to_string(epochs)}, {"mappo.minibatches", std::to_string(minibatches)},
                {"mappo.lr", f(lr)}, {"mappo.gamma", f(gamma)}, {"mappo.lambda", f(lambda)}, {"mappo.clip", f(ppo.clip)},
                {"mappo.vf_coef", f(ppo.vf_coef)}, {"mappo.ent_coef", f(ppo.ent_coef)},
                {"mappo.max_grad_norm", f(max_grad_norm)}, {"mappo.seed", std::to_string(seed)},
                {"mappo.rewards", "shaping " + f(rewards.shaping) + ", success " + f(rewards.success_bonus) +
                                      ", collision " + f(rewards.collision) + ", time " + f(rewards.time) + ", at_goal " + f(rewards.at_goal)}};
    }
};

// One row of the training curve (out + ".csv"): statistics of each iteration's first episode
// per world (exactly `worlds` complete, unbiased episodes; later ones are cut by the iteration).
struct MappoCurveRow {
    long iteration = 0, env_steps = 0;  // env_steps: world steps so far
    double seconds = 0;                 // training wall time so far
    double success = 0, episode_return = 0;  // success rate, mean per-agent undiscounted return
    PpoTerms loss;                      // mean over the iteration's minibatches
};

struct MappoReport {
    long iterations = 0, env_steps = 0;
    double seconds = 0;
    std::vector<MappoCurveRow> curve;
};

namespace detail {

// Everything one iteration collects: columns s = (t * W + w) * n + i.
struct Rollout {
    Mat obs, critic_in, act;
    Vec logp, value, reward, adv, ret;
    std::vector<uint8_t> terminal;
    void resize(int O, int n, long S) {
        obs.resize(O, S);
        critic_in.resize((long)O * n, S);
        act.resize(2, S);
        logp.resize(S), value.resize(S), reward.resize(S), adv.resize(S), ret.resize(S);
        terminal.assign(S, 0);
    }
};

inline void write_mappo_curve(const std::string& path, const std::vector<MappoCurveRow>& curve) {
    std::string csv = "iteration,env_steps,seconds,success,episode_return,policy_loss,value_loss,entropy,approx_kl,clip_fraction\n";
    for (const MappoCurveRow& r : curve) {
        char buf[320];
        std::snprintf(buf, sizeof buf, "%ld,%ld,%.3f,%.4f,%.5g,%.5g,%.5g,%.5g,%.5g,%.4f\n", r.iteration, r.env_steps, r.seconds,
                      r.success, r.episode_return, r.loss.policy, r.loss.value, r.loss.entropy, r.loss.approx_kl, r.loss.clip_fraction);
        csv += buf;
    }
    write_file_atomic(path, std::vector<uint8_t>(csv.begin(), csv.end()));
}

// Reads the rows of a curve CSV up to `iteration` (resume); unreadable lines are skipped.
inline std::vector<MappoCurveRow> read_mappo_curve(const std::string& path, long iteration) {
    std::vector<MappoCurveRow> curve;
    std::ifstream in(path);
    std::string line;
    std::getline(in, line);  // header
    while (std::getline(in, line)) {
        MappoCurveRow r;
        PpoTerms& l = r.loss;
        if (std::sscanf(line.c_str(), "%ld,%ld,%lf,%lf,%lf,%lf,%lf,%lf,%lf,%lf", &r.iteration, &r.env_steps, &r.seconds, &r.success,
                        &r.episode_return, &l.policy, &l.value, &l.entropy, &l.approx_kl, &l.clip_fraction) == 10 &&
            r.iteration <= iteration)
            curve.push_back(r);
    }
    return curve;
}

// SVG of the success rate (left axis, 0..1) and the mean episode return (scaled to its own
// range) against world steps.
inline void write_mappo_svg(const std::string& path, const std::vector<MappoCurveRow>& curve, const std::string& title) {
    if (curve.empty()) return;
    double x_max = std::max<double>(1, curve.back().env_steps), r_min = 1e300, r_max = -1e300;
    for (auto& r : curve) r_min = std::min(r_min, r.episode_return), r_max = std::max(r_max, r.episode_return);
    if (!(r_max > r_min)) r_max = r_min + 1;
    auto X = [&](double s) { return 60 + 520 * s / x_max; };
    auto Y = [](double u) { return 320 - 290 * u; };  // u in [0, 1]
    std::string svg = "<svg xmlns='http://www.w3.org/2000/svg' width='600' height='360' font-family='sans-serif' font-size='11'>\n"
                      "<rect width='600' height='360' fill='white'/>\n<line x1='60' y1='320' x2='580' y2='320' stroke='#888'/>\n"
                      "<line x1='60' y1='30' x2='60' y2='320' stroke='#888'/>\n";
    const char* colors[2] = {"#2ca02c", "#1f77b4"};
    for (int k = 0; k < 2; ++k) {
        svg += "<polyline fill='none' stroke='" + std::string(colors[k]) + "' points='";
        for (auto& r : curve) {
            const double u = k == 0 ? r.success : (r.episode_return - r_min) / (r_max - r_min);
            svg += std::to_string(X((double)r.env_steps)) + "," + std::to_string(Y(u)) + " ";
        }
        svg += "'/>\n";
    }
    char buf[512];
    std::snprintf(buf, sizeof buf,
                  "<text x='60' y='20'>%s</text>\n<text x='400' y='20' fill='%s'>success rate (0..1)</text>\n"
                  "<text x='400' y='34' fill='%s'>episode return (%.3g .. %.3g)</text>\n"
                  "<text x='60' y='345'>world steps 0 .. %.0f</text>\n</svg>\n",
                  title.c_str(), colors[0], colors[1], r_min, r_max, x_max);
    svg += buf;
    write_file_atomic(path, std::vector<uint8_t>(svg.begin(), svg.end()));
}

}  // namespace detail

// Saves a policy file: the parameters and the metadata of net and training (no optimizer).
inline void save_mappo(const std::string& path, const MappoNet& net, std::map<std::string, std::string> extra = {}) {
    auto md = net.metadata();
    for (auto& kv : extra) md[kv.first] = kv.second;
    save_params(path, *net.params, md);
}

namespace detail {
inline int meta_int(const SafeTensors& st, const std::string& key, int lo, int hi) {
    const std::string& s = st.meta(key);
    char* end = nullptr;
    const long v = std::strtol(s.c_str(), &end, 10);
    if (s.empty() || *end != '\0' || v < lo || v > hi)
        throw std::runtime_error(st.source + ": __metadata__['" + key + "'] = '" + s + "' is not an integer in [" +
                                 std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return (int)v;
}
inline MappoNet mappo_from(const SafeTensors& st) {
    auto it = st.metadata.find("format");
    if (it == st.metadata.end() || it->second != "madbp-mappo")
        throw std::runtime_error(st.source + ": not a MAPPO policy (__metadata__['format'] is '" +
                                 (it == st.metadata.end() ? std::string("missing") : it->second) + "', expected 'madbp-mappo')");
    if (st.meta("mappo.obs") != kMappoObsLayout)
        throw std::runtime_error(st.source + ": observation layout '" + st.meta("mappo.obs") + "' is not this build's '" +
                                 kMappoObsLayout + "'");
    MappoNetConfig c;
    c.agents = meta_int(st, "mappo.agents", 1, 64);
    c.hidden = meta_int(st, "mappo.hidden", 1, 4096);
    MappoNet net(c);
    read_param_tensors(st, *net.params);
    for (long k = 0; k < net.params->size(); ++k)
        if (!std::isfinite(net.params->value[k])) throw std::runtime_error(st.source + ": a parameter is not finite");
    return net;
}
}  // namespace detail

// Loads a policy file (or a .train state file); a file that is not a MAPPO policy, or whose
// tensors do not match the architecture its metadata declares, throws std::runtime_error
// naming the file and the field.
inline MappoNet load_mappo(const std::string& path) { return detail::mappo_from(load_safetensors(path)); }

// Trains a MAPPO policy. Each iteration: `worlds` fresh random worlds (seeds from the run's
// RNG), max_steps (100) steps on each with the sampled actions, a world that succeeds is
// replaced at once by a fresh one; GAE; `epochs` passes of `minibatches` PPO steps (Adam,
// global-norm clip). Because every iteration starts from fresh worlds, the state at an
// iteration boundary is just (parameters, Adam, RNG): a resumed run continues exactly as an
// uninterrupted one. Deterministic for a seed, whatever the thread count.
inline MappoReport train_mappo(const MappoConfig& c, MappoNet* result = nullptr) {
    c.validate();
    set_num_threads(std::max(1, c.threads));
    MappoNetConfig nc;
    nc.agents = c.agents;
    nc.hidden = c.hidden;
    nc.init_log_std = c.init_log_std;
    MappoNet net(nc, c.seed);
    Adam adam;
    adam.lr = c.lr;
    Rng rng(c.seed ^ 0x3a990f00ull);
    MappoReport rep;
    long iteration = 0;
    double seconds_before = 0;
    const std::string state_path = c.out + ".train";
    if (c.resume) {
        SafeTensors st = load_safetensors(state_path);
        MappoNet saved = detail::mappo_from(st);
        if (saved.config.agents != c.agents || saved.config.hidden != c.hidden || st.meta("mappo.map") != c.map)
            throw std::runtime_error(state_path + ": trained for map '" + st.meta("mappo.map") + "' with " +
                                     std::to_string(saved.config.agents) + " agents and hidden " + std::to_string(saved.config.hidden) +
                                     ", not this run's");
        net.params->value = saved.params->value;
        read_adam(st, net.params->size(), adam);
        read_rng(st, "mappo.rng", rng);
        iteration = detail::meta_int(st, "mappo.iteration", 0, 1 << 30);
        seconds_before = std::atof(st.meta("mappo.seconds").c_str());
        rep.curve = detail::read_mappo_curve(c.out + ".csv", iteration);
    }
    const int n = c.agents, W = c.worlds, O = kMappoObs;
    WorldConfig wc;
    const int T = wc.max_steps;
    const long S = (long)T * W * n, per_step = (long)W * n;
    detail::Rollout ro;
    ro.resize(O, n, S);
    WorldBatch batch;
    std::vector<std::vector<Vec2>> actions(W, std::vector<Vec2>(n));
    Mat step_obs(O, per_step), step_critic((long)O * n, per_step), mean, values;
    std::vector<double> dist_before(per_step);
    PpoWorkspace ws;
    PpoBatch mb;
    const auto t_start = std::chrono::steady_clock::now();
    auto elapsed = [&] { return seconds_before + std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count(); };
    auto save_state = [&] {
        if (c.out.empty()) return;
        auto md = c.metadata();
        md["mappo.iteration"] = std::to_string(iteration);
        md["mappo.env_steps"] = std::to_string(iteration * (long)T * W);
        char secs[32];
        std::snprintf(secs, sizeof secs, "%.3f", elapsed());
        md["mappo.seconds"] = secs;
        save_mappo(c.out, net, md);
        for (auto& kv : net.metadata()) md[kv.first] = kv.second;
        std::vector<NamedTensor> tensors = param_tensors(*net.params);
        append_adam(adam, tensors, md);
        append_rng(rng, "mappo.rng", md);
        save_safetensors(state_path, tensors, md);
        detail::write_mappo_curve(c.out + ".csv", rep.curve);
        detail::write_mappo_svg(c.out + ".svg", rep.curve, "MAPPO " + c.map + " n=" + std::to_string(n));
    };
    auto fresh_world = [&](uint64_t seed) { return make_random_world(c.map, n, seed, c.half_size, wc); };
    auto observe_world = [&](int w) {
        mappo_observe_all(batch.worlds[w], step_obs, (long)w * n);
        mappo_critic_input(step_obs, (long)w * n, n, step_critic, (long)w * n);
    };
    ProgressLine progress("mappo " + c.map + " n=" + std::to_string(n), c.iterations, c.quiet);
    progress.done = iteration;
    while (iteration < c.iterations) {
        // ---- Rollout: T steps on W worlds.
        batch.worlds.clear();
        for (int w = 0; w < W; ++w) batch.worlds.push_back(fresh_world(rng.next_u64()));
        std::vector<uint8_t> first_done(W, 0), first_success(W, 0);
        std::vector<double> first_return(W, 0);
#pragma omp parallel for schedule(static)
        for (int w = 0; w < W; ++w) observe_world(w);
        for (int t = 0; t < T; ++t) {
            const long col = t * per_step;
            net.actor.forward(step_obs, mean);
            net.critic.forward(step_critic, values);
            const Eigen::Vector2f ls = net.log_std_value();
            for (long k = 0; k < per_step; ++k) {
                float a[2];
                for (int d = 0; d < 2; ++d) a[d] = mean(d, k) + std::exp(ls[d]) * (float)rng.normal();
                ro.act(0, col + k) = a[0], ro.act(1, col + k) = a[1];
                ro.logp[col + k] = gaussian_log_prob(a, &mean(0, k), ls.data());
                actions[k / n][k % n] = clamp_box(Vec2{a[0], a[1]}, wc.max_action);
                const Agent& ag = batch.worlds[k / n].agents()[k % n];
                dist_before[k] = norm(ag.pos - ag.goal);
            }
            ro.obs.middleCols(col, per_step) = step_obs;
            ro.critic_in.middleCols(col, per_step) = step_critic;
            ro.value.segment(col, per_step) = values.row(0).transpose();
            batch.step(actions);
            // Rewards, episode ends (success: terminal, then a fresh world), next observations.
            std::vector<uint64_t> reseed(W);
            for (int w = 0; w < W; ++w) reseed[w] = batch.worlds[w].done() ? rng.next_u64() : 0;
#pragma omp parallel for schedule(static)
            for (int w = 0; w < W; ++w) {
                World& world = batch.worlds[w];
                std::vector<int> contacts(n, 0);
                for (auto pr : world.last_agent_contacts()) contacts[world.index_of(pr.first)]++, contacts[world.index_of(pr.second)]++;
                for (int id : world.last_static_contacts()) contacts[world.index_of(id)]++;
                const bool success = world.metrics().success;
                for (int i = 0; i < n; ++i) {
                    const long s = col + (long)w * n + i;
                    const Agent& ag = world.agents()[i];
                    ro.reward[s] = c.rewards.shaping * (float)(dist_before[(long)w * n + i] - norm(ag.pos - ag.goal)) +
                                   c.rewards.collision * contacts[i] + c.rewards.time + (success ? c.rewards.success_bonus : 0.0f) +
                                   (world.at_goal(ag) ? c.rewards.at_goal : 0.0f);
                    ro.terminal[s] = success;
                    if (!first_done[w]) first_return[w] += ro.reward[s] / n;
                }
                if (world.done()) {
                    if (!first_done[w]) first_done[w] = 1, first_success[w] = success;
                    if (t + 1 < T) world = fresh_world(reseed[w]);
                }
                observe_world(w);
            }
        }
        // ---- Advantages: bootstrap every stream with V(state after the last step).
        net.critic.forward(step_critic, values);
        for (long k = 0; k < per_step; ++k)
            gae(ro.reward.data() + k, ro.value.data() + k, ro.terminal.data() + k, values(0, k), T, per_step, c.gamma, c.lambda,
                ro.adv.data() + k, ro.ret.data() + k);
        const float adv_mean = ro.adv.mean();
        const float adv_std = std::sqrt((ro.adv.array() - adv_mean).square().mean()) + 1e-8f;
        ro.adv = (ro.adv.array() - adv_mean) / adv_std;  // normalised over the whole rollout
        // ---- PPO epochs over shuffled minibatches.
        std::vector<long> order(S);
        for (long s = 0; s < S; ++s) order[s] = s;
        PpoTerms sum;
        int updates = 0;
        for (int e = 0; e < c.epochs; ++e) {
            for (long s = S - 1; s > 0; --s) std::swap(order[s], order[(long)(rng.uniform() * (s + 1))]);
            for (int m = 0; m < c.minibatches; ++m) {
                const long b0 = S * m / c.minibatches, B = S * (m + 1) / c.minibatches - b0;
                if (B == 0) continue;
                mb.obs.resize(O, B), mb.critic_in.resize((long)O * n, B), mb.act.resize(2, B);
                mb.logp_old.resize(B), mb.adv.resize(B), mb.ret.resize(B);
                for (long j = 0; j < B; ++j) {
                    const long s = order[b0 + j];
                    mb.obs.col(j) = ro.obs.col(s);
                    mb.critic_in.col(j) = ro.critic_in.col(s);
                    mb.act.col(j) = ro.act.col(s);
                    mb.logp_old[j] = ro.logp[s], mb.adv[j] = ro.adv[s], mb.ret[j] = ro.ret[s];
                }
                net.params->zero_grad();
                PpoTerms l = ppo_loss(net, mb, c.ppo, ws);
                if (!std::isfinite(l.policy) || !std::isfinite(l.value))
                    throw std::runtime_error("mappo: loss became non-finite at iteration " + std::to_string(iteration));
                clip_grad_norm(*net.params, c.max_grad_norm);
                adam.update(*net.params);
                sum.policy += l.policy, sum.value += l.value, sum.entropy += l.entropy;
                sum.approx_kl += l.approx_kl, sum.clip_fraction += l.clip_fraction;
                ++updates;
            }
        }
        ++iteration;
        MappoCurveRow row;
        row.iteration = iteration;
        row.env_steps = iteration * (long)T * W;
        row.seconds = elapsed();
        for (int w = 0; w < W; ++w) row.success += first_success[w], row.episode_return += first_return[w];
        row.success /= W, row.episode_return /= W;
        const double u = std::max(1, updates);
        row.loss = {sum.policy / u, sum.value / u, sum.entropy / u, sum.approx_kl / u, sum.clip_fraction / u};
        rep.curve.push_back(row);
        const bool stop = c.keep_going && !c.keep_going(iteration);
        if (iteration % c.checkpoint_every == 0 || iteration == c.iterations || stop) save_state();
        char extra[96];
        std::snprintf(extra, sizeof extra, "success %.2f  return %.3f", row.success, row.episode_return);
        progress.tick(1, extra);
        if (stop) break;
    }
    rep.iterations = iteration;
    rep.env_steps = iteration * (long)T * W;
    rep.seconds = elapsed();
    if (result) *result = std::move(net);
    return rep;
}

// =============================================================================================
// Running a trained policy (SPEC 3.3, 9)
// =============================================================================================

// Drives a team with the actor's mean action (deterministic, no safety filter: MAPPO runs raw,
// as in the paper), clipped to the action box. The team must have exactly the policy's n
// agents (std::invalid_argument otherwise): MAPPO is built per team size. plan_ms() is the
// mean wall time of one act() call (the per-step decision time of Fig. 3b).
class MappoPolicy : public Policy {
public:
    explicit MappoPolicy(MappoNet net) : net_(std::move(net)) {}
    std::vector<Vec2> act(const World& world) override {
        const auto t0 = std::chrono::steady_clock::now();
        const int n = net_.config.agents;
        if (world.size() != n)
            throw std::invalid_argument("mappo: the policy was trained for " + std::to_string(n) + " agents, the world has " +
                                        std::to_string(world.size()) + " (MAPPO is trained per team size)");
        obs_.resize(kMappoObs, n);
        mappo_observe_all(world, obs_, 0);
        net_.actor.forward(obs_, mean_);
        std::vector<Vec2> u(n);
        for (int i = 0; i < n; ++i) u[i] = clamp_box(Vec2{mean_(0, i), mean_(1, i)}, world.config().max_action);
        total_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        ++calls_;
        return u;
    }
    double plan_ms() const override { return calls_ ? total_ms_ / calls_ : 0; }
    int agents() const { return net_.config.agents; }

private:
    MappoNet net_;
    Mat obs_, mean_;
    double total_ms_ = 0;
    long calls_ = 0;
};

// Per-episode MAPPO policies from policy files, loaded once each (every episode gets its own
// copy, so episodes can run in parallel). Usable for evaluation and as the demonstrator of
// `collect` (SPEC 7: the paper's source of demonstrations). Since a policy drives one team
// size and collect records teams of 1..n_train_max, `path` may contain "{n}", replaced by the
// episode's team size (e.g. "models/mappo/empty-{n}.safetensors"); without it every episode
// must have the policy's n. A missing file or a wrong n throws when the episode starts.
inline DemonstratorFactory mappo_demonstrator(const std::string& path) {
    struct Cache {
        std::mutex mutex;
        std::map<int, std::shared_ptr<const MappoNet>> nets;
    };
    const size_t slot = path.find("{n}");
    auto cache = std::make_shared<Cache>();
    if (slot == std::string::npos) {
        auto net = std::make_shared<const MappoNet>(load_mappo(path));  // fail early on a bad file
        cache->nets[net->config.agents] = net;
    }
    return [path, slot, cache](const World& world, uint64_t) {
        std::shared_ptr<const MappoNet> net;
        {
            std::lock_guard<std::mutex> lock(cache->mutex);
            if (slot == std::string::npos) net = cache->nets.begin()->second;
            else {
                auto& entry = cache->nets[world.size()];
                if (!entry) {
                    std::string file = path;
                    file.replace(slot, 3, std::to_string(world.size()));
                    entry = std::make_shared<const MappoNet>(load_mappo(file));
                    if (entry->config.agents != world.size()) {
                        const int trained = entry->config.agents;
                        entry.reset();
                        throw std::invalid_argument(file + ": trained for " + std::to_string(trained) + " agents, not " +
                                                    std::to_string(world.size()));
                    }
                }
                net = entry;
            }
        }
        return std::unique_ptr<Policy>(new MappoPolicy(net->clone()));
    };
}

}  // namespace madbp

#endif  // MADBP_MAPPO_HPP
