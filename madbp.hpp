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
//   madbp::DiffusionPlanner planner(madbp::load_model(madbp::default_model_path()));
//   madbp::PlanFollower follower = madbp::make_follower(planner);
//   while (!world.done()) world.step(follower.act(world));   // replans every 4 steps
// default_model_path() finds the shipped model madbp-default.safetensors: $MADBP_MODEL if set
// (the file itself; missing is an error), else the first that exists of <executable>/../share/
// madbp/models (an install, also moved), MADBP_MODEL_DIR (macro set by the CMake package and
// madbp.pc), <this header>/../share/madbp/models, ./models, <this header>/models (a checkout).
// Every setting a plan uses is in planner.settings (PlannerConfig: neighbourhood, sampler,
// guidance, traffic, follower; Section 7), tuned by default; PlannerConfig::paper() is the
// paper's planner, and planner_settings() lists every setting with its range and meaning:
//   madbp::DiffusionPlanner paper(model, /*seed=*/0, madbp::PlannerConfig::paper());
//   planner.settings.set("guidance.keep_right", "300");     // or planner.settings.guidance.keep_right = 300
// Worlds larger than the training world and teams larger than n_max plan in neighbourhoods by
// themselves (settings.neighbourhood). One robot planning for itself (decentralised):
//   planner.plan_robot(map, my_id, my_pos, my_goal, others /* {pos, goal} received */, window);
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
// Contents (in the order of the data: layers -> checkpoints -> model parts -> model -> sampler
// -> planner; SPEC sections of docs/design.md in brackets)
//   1 NN core: Mat, set_num_threads, Init, ParamStore (weights + state), Linear, LayerNorm,
//     MultiHeadAttention, Conv1d, ConvTranspose1d, BatchNorm1d, MaxPool1d, Upsample1d, Conv2d,
//     ReLU, SiLU, Mish, Tanh, Embedding, sinusoidal_embedding, film_forward, Adam,
//     clip_grad_norm, Ema                                                              [4]
//   2 checkpoints: NamedTensor, SafeTensors, parse/serialize_safetensors (files are written by
//     madbp_sim.hpp's write_file_atomic),
//     save/load_safetensors, param_tensors, read_param_tensors, save/load_params       [11]
//   3 model inputs: ModelConfig (SceneFrame), SceneBatch, scene_origin, encode_map,
//     route_goal, encode_agent, end_pinned                                              [5]
//   4 model parts: ConvBlock, AgentAttention, FilmUNet, StepEmbedding, ContextEncoder,
//     TrajectoryProcessor                                                              [5]
//   5 the model: MadbpModel, save_model, load_model, default_model_path (the shipped model:
//     $MADBP_MODEL, the install, the checkout)                                         [5, 11]
//   6 diffusion: NoiseSchedule, detail::ddim_loop (the one DDIM loop: plain, guided, MADiff),
//     DistanceField, MapFields, WindowCost, SamplerConfig, sample_windows (DDIM with inpainting,
//     guidance, best-of-k, keep-right, end bend, warm start)                            [6]
//   7 planner settings: TrafficConfig, PlannerConfig (tuned(), paper(), validate, set),
//     PlannerSetting, planner_settings (the table), kSmallPlanWindows                 [8]
//   8 traffic conventions: PassageControl (one-lane passages: take turns, go around, queue),
//     passage_traffic (the guided expert takes the same turns), CrowdRoutes (routes around
//     crowds)                                                                           [8]
//   9 planner: DiffusionPlanner (plan, neighbourhoods, plan_robot), make_follower,
//     DecentralisedTeam                                                                [8]
//
// Changelog
//   0.4  Neighbourhood scenes cover the team (neighbourhood.cover, default 3; 0 = a scene per
//        robot, the paper preset): each window is computed about once a plan, not K times.
//        Scenes are sampled in chunks (workspace.chunk_scenes) on set_num_threads' threads,
//        bit-identical on any thread count; planner_workspace_bytes() is checked against
//        workspace.max_mb before a plan. last_window_agent(i). plan_robot routes only its scene.
//        traffic.free_clear 0.102 (was 0.12): one-cell aisles at cell 0.25 are passages.
//        The planner's route guide keeps band fields (RouteGuide::band, madbp_sim.hpp).
//        PassageControl::arbitrate's `asked`: a plan routes only robots that may claim a passage
//        its scenes' robots claim (plan_robot among 1024: 1.3 ms, was 7.2).
//        guidance.priority 4 (SceneBatch::priority): in a team larger than a scene, a scene's
//        robots give way in its guidance by priority_order, as the expert's robots do.
//        follower.filter_static_margin 0.005 (paper preset 0.01): the follower's filter lets a
//        robot through most gaps its route passes (kPassableClearance 0.102).
//        traffic.make_way: robots whose goals lie in a one-lane passage make way for robots
//        passing through, and of two such robots the one that would pass the other goes around
//        or both queue at the mouth it comes in by; a robot inside a long passage claims the mouth behind it;
//        waiting robots are routed to their waiting points (issue 46's maze).
//        traffic.queue_in_order: a robot behind one queueing at a passage's mouth queues too.
//        passage_traffic(): the guided expert takes the planner's turns in one-lane passages.
//        Queue places follow the free space where the line out of a mouth meets a wall; of two
//        robots coming in by one mouth to goals in a passage, the one going deeper goes first.
//        PassageControl::follow_order: the robots going one way through a passage, in a line
//        from the front; passage_traffic() has the expert plan each after the one ahead of it.
//        expert_traffic(): passage_traffic()'s default, the planner's turns with spare 0.1.
//        CrowdRoutes, traffic.crowd_weight, crowd_density and crowd_cell: in a team larger than a
//        scene with at least crowd_density (1) robots a square unit, robots are routed around the
//        crowds the others' routes make (issue 47; on by default since 2026-12-04).
//        traffic.crowd_time, crowd_time_from and crowd_time_weight: in a team of 512 robots or more
//        routes around crowds count a robot in a cell only about when it is due there.
//        traffic.crowd_detour (an option, off): no detour longer than this times the straight
//        way. DiffusionPlanner::last_crowd_targets().
//        traffic.pocket_order (the expert's default; off for the planner): a robot whose goal
//        would close off a pocket (a dead end) that another's route enters or leaves waits beside
//        it until that robot is through. follow_order: a robot going on to a goal in a passage
//        follows the robot ahead of it there that goes deeper.
//        MapFields::kGoalFieldBytes: at most 16 MB of goal fields (max_goal_fields()), so a
//        whole episode of 256 robots holds ~60 MB, not ~115 (issue 47).
//        A plan on several threads also routes the robots near where they head (near fields)
//        and encodes its scenes (map crops) on them, each thread with a route guide of its own
//        (ChunkWorker::guide), and a first plan makes its route fields several at once there
//        (RouteGuide::expect): the same windows, a smaller serial share (issue 47). Routes
//        around crowds take a straight way clear on the grid as open ground without a field (an
//        empty world's first plan of 1024 robots: 0.9 s, was 7.9).
//   0.3  PlannerConfig: every planner setting in one struct, its defaults written once.
//        PlannerConfig::tuned() (the default) and paper() (the paper's planner) presets.
//        planner_settings(): one table behind validate(), set(), --set and --list-settings.
//        DiffusionPlanner::settings replaces its public fields; sampler() resolves the sampler.
//        The kDefault* constants and planner_sample_steps are gone (PlannerConfig holds them).
//        PassageControl moves here (Section 8); PassageParams becomes TrafficConfig.
//        make_follower(planner); DecentralisedTeam moves here from the tool.
//        default_model_path(): $MADBP_MODEL, the install, the checkout.
//        detail::ddim_loop: one DDIM loop for the plain, guided and MADiff samplers.
//        velocity_context and priority_context removed; a checkpoint setting either is refused.
//   0.2  One FilmUNet, ContextEncoder and TrajectoryProcessor; one world-to-model encoder.
//        BatchNorm statistics in ParamStore::state; optimizer-state I/O moved to madbp_train.hpp.
//        The Local scene frame, route subgoals, ModelConfig::n_train_max (absent = as in 0.1).
//        Automatic neighbourhoods; plan_robot, one robot planning for itself.
//        The planner samples with guidance (kDefaultGuidance).
//        ModelConfig::velocity_context and priority_context: options, off in shipped models.
//        priority_values; Neighbour::id.
//        SamplerConfig::keep_right: robots that meet pass each other on the right.
//        SamplerConfig::validate checks every option on either sampling path (some were ignored).
//        DiffusionPlanner::take_turns: robots take turns in one-lane corridors, or go around.
//        route_goal takes ClosedCells; last_waiting, last_wait_points.
//        SamplerConfig::end_bend: a window that stops short of a goal within reach is bent to it.
//        SamplerConfig::warm_start: a plan starts from each robot's last window, shifted to now.
//        plan_robot takes the robot's clock (`step`) and warm-starts from its own last windows.
//        DiffusionPlanner::passage_replan: replan after 4 steps while robots may meet in a passage.
//        kDefaultKeepRight 500 (was 300), with the follower's lookahead 2.0.
//        DiffusionPlanner::line_start: a robot without a last window warm-starts from a line.
//        kDefaultSampleSteps 8, kDefaultWarmStart 4 (was 5 of 10): 4 network passes a plan.
//        MapFields' goal fields: a bucket queue on every other node (kGoalStride), 0.1 ms each.
//        DiffusionPlanner::small_plan_candidates: best of 2 windows for plans of <= 4 windows.
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
#if MADBP_VERSION_MAJOR != 0 || MADBP_VERSION_MINOR != 4
#error "madbp.hpp is release 0.4; the madbp_sim.hpp it includes is another release"
#endif

#include <Eigen/Dense>
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <fcntl.h>
#include <functional>
#include <limits>
#include <climits>
#include <map>
#include <memory>
#include <numeric>
#include <queue>
#include <sstream>
#include <stdexcept>
#include <string>
#include <sys/stat.h>
#include <unistd.h>
#include <variant>
#include <vector>
#ifdef _OPENMP
#include <omp.h>
#endif

namespace madbp {

// =============================================================================================
// Section 1. Neural-network core (SPEC 4)
// =============================================================================================

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
// its team in libgomp. `dynamic`: each thread takes the next i when done (items of uneven cost,
// or a thread slowed by another job); fn's results must then not depend on which thread runs i.
template <class F>
inline void parallel_for(int n, int threads, const F& fn, bool dynamic = false) {
#ifdef _OPENMP
    if (threads > 1 && dynamic) {
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
        for (int i = 0; i < n; ++i) fn(i, omp_get_thread_num());
        return;
    }
    if (threads > 1) {
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int i = 0; i < n; ++i) fn(i, omp_get_thread_num());
        return;
    }
#endif
    for (int i = 0; i < n; ++i) fn(i, 0);
}

// parallel_for of an fn that may throw (an exception must not leave an OpenMP region): a thread
// that failed runs none of its next items, and the first thread's failure is rethrown when all
// are done. `failed`: scratch, one slot a thread.
template <class F>
inline void parallel_for_rethrow(int n, int threads, std::vector<std::exception_ptr>& failed, const F& fn, bool dynamic = false) {
    failed.assign(std::max(1, threads), nullptr);
    parallel_for(n, threads, [&](int i, int t) {
        if (failed[t]) return;
        try {
            fn(i, t);
        } catch (...) {
            failed[t] = std::current_exception();
        }
    }, dynamic);
    for (const std::exception_ptr& e : failed)
        if (e) std::rethrow_exception(e);
}

// RouteGuide::run_ahead on set_num_threads' threads, and the fields a batch makes: one a thread
// (one thread: none ahead; two a thread were no faster and wait longer in memory: docs/speed.md,
// "Route work on the threads").
inline void run_on_threads(int count, const std::function<void(int)>& fn) {
    std::vector<std::exception_ptr> failed;
    parallel_for_rethrow(count, std::min(count, max_threads()), failed, [&](int j, int) { fn(j); }, /*dynamic*/ true);
}
inline int fields_ahead_batch() { return max_threads(); }

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

// Limits of a ParamStore and the parameter budget of checkpoint loaders. A store's offsets are
// int, so it holds at most kMaxStoreValues values; ParamStore::add refuses a tensor beyond that
// before allocating it (std::invalid_argument naming the tensor). While a ParamBudget is alive
// on a thread, add() also refuses (std::runtime_error) a tensor that would bring the values
// added since the budget began above its limit: loaders build a model from a checkpoint's
// metadata inside a budget of the values the file holds, so a configuration that implies more
// memory than the file's tensors fails with a message instead of allocating it.
constexpr long kMaxStoreValues = std::numeric_limits<int>::max();
namespace detail {
struct ParamBudgetState {
    long limit = -1, used = 0;  // limit < 0: no budget
    std::string source;
};
inline ParamBudgetState& param_budget() {
    thread_local ParamBudgetState state;
    return state;
}
// Counts `shape` against the store's limit (values already at `offset`) and any budget.
inline long charge_params(const std::string& name, const std::vector<int>& shape, long offset) {
    long n = 1;
    bool over = false;
    for (int d : shape) n = d == 0 ? 0 : n;
    for (int d : shape)
        if (n != 0) {
            if (n > kMaxStoreValues / d) over = true;
            else n *= d;
        }
    if (over || n > kMaxStoreValues - offset)
        throw std::invalid_argument("tensor '" + name + "': shape " + shape_string(shape) + " would bring the store past its limit kMaxStoreValues = " +
                                    std::to_string(kMaxStoreValues) + " values");
    ParamBudgetState& b = param_budget();
    if (b.limit >= 0 && n > b.limit - b.used)
        throw std::runtime_error(b.source + ": the architecture its metadata declares needs more values than the " + std::to_string(b.limit) +
                                 " its tensors hold (tensor '" + name + "' " + shape_string(shape) + " alone has " + std::to_string(n) +
                                 "): the metadata does not match the file");
    b.used += n;
    return n;
}
}  // namespace detail
struct ParamBudget {
    detail::ParamBudgetState saved;
    ParamBudget(long values, const std::string& source) : saved(detail::param_budget()) {
        detail::param_budget() = {std::max(0L, values), 0, source};
    }
    ~ParamBudget() { detail::param_budget() = saved; }
    ParamBudget(const ParamBudget&) = delete;
    ParamBudget& operator=(const ParamBudget&) = delete;
};

// value, grad (P): the trainable parameters of a model in one flat buffer; state (S): the
// tensors that are not trained (BatchNorm running statistics, normalisation limits), kept apart
// so that optimizers, EMA and gradient clipping see only weights and a forward pass in training
// mode (which updates running statistics) never writes the weights. Entries are named views;
// checkpoints hold both kinds under their names.
struct ParamStore {
    Vec value, grad, state;
    struct Entry {
        std::string name;
        int offset;              // into value (trainable) or state
        std::vector<int> shape;  // row-major, as in the checkpoint (see Conventions)
        bool trainable;          // false: state such as BatchNorm running statistics
        int numel() const { return (int)detail::shape_numel(shape); }
    };
    std::vector<Entry> entries;

    // Appends a tensor initialised now and returns its offset (into value, or into state when
    // not trainable). Names must be unique and must not start with "optim." (reserved for
    // optimizer state in checkpoints).
    int add(const std::string& name, std::vector<int> shape, Init init, Rng& rng, bool trainable = true) {
        MADBP_ASSERT(find(name) == nullptr);
        MADBP_ASSERT(name.rfind("optim.", 0) != 0 && !name.empty());
        MADBP_ASSERT(std::all_of(shape.begin(), shape.end(), [](int d) { return d >= 0; }));
        Vec& buf = trainable ? value : state;
        const int offset = (int)buf.size();
        const int n = (int)detail::charge_params(name, shape, offset);  // checks limits before allocating
        buf.conservativeResize(offset + n);
        if (trainable) {
            grad.conservativeResize(offset + n);
            grad.segment(offset, n).setZero();
        }
        for (int i = 0; i < n; ++i) {
            float v = 0;
            switch (init.kind) {
                case Init::Zeros: v = 0; break;
                case Init::Ones: v = 1; break;
                case Init::Uniform: v = (float)rng.uniform(-init.scale, init.scale); break;
                case Init::Normal: v = (float)(init.scale * rng.normal()); break;
            }
            buf[offset + i] = v;
        }
        entries.push_back({name, offset, std::move(shape), trainable});
        return offset;
    }
    const Entry* find(const std::string& name) const {
        for (auto& e : entries)
            if (e.name == name) return &e;
        return nullptr;
    }
    float* data(const Entry& e) { return (e.trainable ? value : state).data() + e.offset; }
    const float* data(const Entry& e) const { return (e.trainable ? value : state).data() + e.offset; }
    Eigen::Map<Mat> view(int offset, int rows, int cols) { return {value.data() + offset, rows, cols}; }
    Eigen::Map<const Mat> view(int offset, int rows, int cols) const { return {value.data() + offset, rows, cols}; }
    Eigen::Map<Mat> grad_view(int offset, int rows, int cols) { return {grad.data() + offset, rows, cols}; }
    Eigen::Map<const Mat> grad_view(int offset, int rows, int cols) const { return {grad.data() + offset, rows, cols}; }
    Eigen::Map<Vec> vec(int offset, int n) { return {value.data() + offset, n}; }
    Eigen::Map<const Vec> vec(int offset, int n) const { return {value.data() + offset, n}; }
    Eigen::Map<Vec> grad_vec(int offset, int n) { return {grad.data() + offset, n}; }
    Eigen::Map<Vec> state_vec(int offset, int n) { return {state.data() + offset, n}; }
    Eigen::Map<const Vec> state_vec(int offset, int n) const { return {state.data() + offset, n}; }
    void zero_grad() { grad.setZero(); }
    int size() const { return (int)value.size(); }  // trainable parameters
    long trainable_count() const { return (long)value.size(); }
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
        MADBP_ASSERT(k % 2 == 1 && k > 0);
        const float bound = 1.0f / std::sqrt((float)cin * (float)k);  // float product: no int overflow for any k
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
        const float bound = 1.0f / std::sqrt((float)cout * (float)k);  // PyTorch's fan_in for this layer
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
        auto rm = ps->state_vec(running_mean, C);
        auto rv = ps->state_vec(running_var, C);
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
        const float bound = 1.0f / std::sqrt((float)cin * (float)k * (float)k);
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
namespace detail {
inline double sinusoidal_frequency(int i, int dim) { return std::exp(-std::log(10000.0) * i / (dim / 2 - 1)); }
}  // namespace detail

inline void sinusoidal_embedding(const float* t, int N, int dim, Mat& y) {
    MADBP_ASSERT(dim % 2 == 0 && dim >= 4);
    const int half = dim / 2;
    y.resize(dim, N);
    for (int n = 0; n < N; ++n)
        for (int i = 0; i < half; ++i) {
            const double arg = t[n] * detail::sinusoidal_frequency(i, dim);
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
            const double f = detail::sinusoidal_frequency(i, dim), arg = t[n] * f;
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
            if (!e.trainable) continue;  // state lives in ps.state
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

// Exponential moving average of the weights: shadow = decay * shadow + (1 - decay) * value.
// The first update copies the weights. shadow (P) is the state to checkpoint; the store's
// state (running statistics) is not averaged: the live statistics go with the EMA weights.
struct Ema {
    float decay = 0.995f;
    Vec shadow;

    void update(const ParamStore& ps) {
        if (shadow.size() != ps.size()) {
            shadow = ps.value;
            return;
        }
        shadow = decay * shadow + (1 - decay) * ps.value;
    }
    void copy_to(ParamStore& ps) const {
        MADBP_ASSERT(shadow.size() == ps.size());
        ps.value = shadow;
    }
};

// =============================================================================================
// Section 2. Checkpoints: safetensors (SPEC 11)
// =============================================================================================
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
    // Float values in all tensors: the ParamBudget a loader builds the declared model in.
    long values() const {
        long n = 0;
        for (auto& t : tensors) n += (long)t.data.size();
        return n;
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

constexpr uint64_t kSafetensorsMaxHeader = 100000000;  // header JSON, bytes (the reference implementation's limit)
constexpr uint64_t kMaxCheckpointBytes = 1ull << 31;    // a checkpoint or training-state file, bytes (2 GiB)

namespace detail {
constexpr uint64_t kPayloadUnknown = ~0ull;

// Parses and validates the JSON header (`n` bytes at `header`) of a checkpoint whose payload
// is `payload` bytes, or kPayloadUnknown (a pipe: then `payload` becomes the bytes the header
// declares). Returns the metadata and the tensors in payload order with their shapes, data
// not read; `ends` gets each tensor's end offset. Throws std::runtime_error naming `source`.
inline SafeTensors parse_safetensors_header(const uint8_t* header, uint64_t n, uint64_t& payload, const std::string& source,
                                            std::vector<uint64_t>& ends) {
    using detail::JsonValue;
    auto fail = [&](const std::string& what) -> void { throw std::runtime_error(source + ": " + what); };
    if (!detail::valid_utf8(header, n)) fail("header is not valid UTF-8");
    if (n == 0 || header[0] != '{') fail("header does not start with '{'");
    detail::JsonParser parser((const char*)header, n, source);
    const JsonValue root = parser.parse_document();
    if (root.type != JsonValue::Object) fail("header is not a JSON object");

    SafeTensors st;
    st.source = source;
    const bool known = payload != kPayloadUnknown;
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
        if (known && end > payload) fail(where + ": data_offsets " + range + " run past the payload (" + std::to_string(payload) + " bytes)");
        if (!known && end > kMaxCheckpointBytes)
            fail(where + ": data_offsets " + range + " run past the limit kMaxCheckpointBytes = " + std::to_string(kMaxCheckpointBytes));
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
    if (!known) payload = expected;
    if (expected != payload)
        fail("tensors cover " + std::to_string(expected) + " bytes of a " + std::to_string(payload) + "-byte payload");
    std::vector<NamedTensor> ordered;  // payload order
    ends.clear();
    for (const Span& s : spans) {
        ordered.push_back(std::move(st.tensors[s.tensor]));
        ends.push_back(s.end);
    }
    st.tensors = std::move(ordered);
    return st;
}

// Checks that the values just read into `t` are finite.
inline void check_finite_tensor(const NamedTensor& t, const std::string& source) {
    for (size_t i = 0; i < t.data.size(); ++i)
        if (!std::isfinite(t.data[i]))
            throw std::runtime_error(source + ": tensor '" + t.name + "': element " + std::to_string(i) + " is " +
                                     (std::isnan(t.data[i]) ? "NaN" : "infinite"));
}
}  // namespace detail

// Parses and validates a whole safetensors file held in memory. Throws std::runtime_error
// naming `source` and the offending field on anything but a well-formed file of finite F32
// tensors whose offsets tile the payload exactly.
inline SafeTensors parse_safetensors(const uint8_t* data, size_t size, const std::string& source = "<memory>") {
    auto fail = [&](const std::string& what) -> void { throw std::runtime_error(source + ": " + what); };
    if (size < 8) fail("file is " + std::to_string(size) + " bytes, shorter than the 8-byte header size");
    uint64_t n = 0;
    for (int i = 7; i >= 0; --i) n = (n << 8) | data[i];
    if (n > kSafetensorsMaxHeader) fail("header size " + std::to_string(n) + " exceeds the 100 MB limit kSafetensorsMaxHeader");
    if (n > size - 8)
        fail("header size " + std::to_string(n) + " runs past the end of the file (" + std::to_string(size) + " bytes)");
    uint64_t payload = size - 8 - n;
    std::vector<uint64_t> ends;
    SafeTensors st = detail::parse_safetensors_header(data + 8, n, payload, source, ends);
    const uint8_t* base = data + 8 + n;
    for (size_t k = 0; k < st.tensors.size(); ++k) {
        NamedTensor& t = st.tensors[k];
        const size_t count = (size_t)detail::shape_numel(t.shape), begin = (size_t)(ends[k] - 4 * count);
        t.data.resize(count);
        for (size_t i = 0; i < count; ++i) t.data[i] = detail::load_f32_le(base + begin + 4 * i);
        detail::check_finite_tensor(t, source);
    }
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

// The bytes of `path` (a regular file or a pipe). A directory, a device (/dev/zero) or a file
// of more than `max_bytes` is refused before reading (std::runtime_error naming `limit`), one
// that does not start with `magic` (when given; `kind` names the format) after its first bytes.
inline std::vector<uint8_t> read_file(const std::string& path, uint64_t max_bytes = kMaxCheckpointBytes,
                                      const std::string& limit = "kMaxCheckpointBytes", const std::string& magic = "",
                                      const std::string& kind = "") {
    std::vector<uint8_t> bytes;
    detail::read_bounded(path, max_bytes, limit, bytes, magic, kind);
    return bytes;
}

inline void save_safetensors(const std::string& path, const std::vector<NamedTensor>& tensors,
                             const std::map<std::string, std::string>& metadata) {
    write_file_atomic(path, serialize_safetensors(tensors, metadata));
}

// Loads a checkpoint by its declared header, never slurping the file: the 8-byte size, the
// header (<= kSafetensorsMaxHeader), then each tensor's bytes straight into its data. Refuses a
// directory, a device (/dev/zero), a file over kMaxCheckpointBytes, and anything
// parse_safetensors refuses; std::runtime_error naming the path and the field.
inline SafeTensors load_safetensors(const std::string& path) {
    auto fail = [&](const std::string& what) -> void { throw std::runtime_error(path + ": " + what); };
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) detail::io_fail(path, "cannot open");
    struct FdCloser { int fd; ~FdCloser() { ::close(fd); } } closer{fd};
    struct stat sb;
    if (::fstat(fd, &sb) != 0) detail::io_fail(path, "cannot stat");
    if (S_ISDIR(sb.st_mode)) fail("is a directory, not a checkpoint file");
    if (!S_ISREG(sb.st_mode) && !S_ISFIFO(sb.st_mode)) fail("is a device, not a checkpoint file");
    const bool regular = S_ISREG(sb.st_mode);
    const uint64_t size = regular ? (uint64_t)sb.st_size : 0;
    if (regular && size > kMaxCheckpointBytes)
        fail(std::to_string(size) + " bytes exceed the limit kMaxCheckpointBytes = " + std::to_string(kMaxCheckpointBytes));
    if (regular && size < 8) fail("file is " + std::to_string(size) + " bytes, shorter than the 8-byte header size");
    auto read_exact = [&](void* dst, uint64_t n, const std::string& what) {
        uint8_t* p = (uint8_t*)dst;
        while (n > 0) {
            const ssize_t got = ::read(fd, p, (size_t)std::min<uint64_t>(n, 1u << 30));
            if (got < 0 && errno == EINTR) continue;
            if (got < 0) detail::io_fail(path, "read failed");
            if (got == 0) fail("file ends inside " + what + " (truncated)");
            p += got;
            n -= (uint64_t)got;
        }
    };
    uint8_t head[8];
    read_exact(head, 8, "the 8-byte header size");
    uint64_t n = 0;
    for (int i = 7; i >= 0; --i) n = (n << 8) | head[i];
    if (n > kSafetensorsMaxHeader) fail("header size " + std::to_string(n) + " exceeds the 100 MB limit kSafetensorsMaxHeader");
    if (regular && n > size - 8)
        fail("header size " + std::to_string(n) + " runs past the end of the file (" + std::to_string(size) + " bytes)");
    std::vector<uint8_t> header((size_t)n);
    read_exact(header.data(), n, "the header");
    uint64_t payload = regular ? size - 8 - n : detail::kPayloadUnknown;
    std::vector<uint64_t> ends;
    SafeTensors st = detail::parse_safetensors_header(header.data(), n, payload, path, ends);
    for (NamedTensor& t : st.tensors) {  // payload order: each tensor's bytes follow the last one's
        t.data.resize((size_t)detail::shape_numel(t.shape));
        read_exact(t.data.data(), 4 * (uint64_t)t.data.size(), "tensor '" + t.name + "'");
        detail::check_finite_tensor(t, path);
    }
    if (!regular) {
        uint8_t extra;
        if (::read(fd, &extra, 1) > 0) fail("more bytes follow the " + std::to_string(payload) + "-byte payload the header declares");
    }
    return st;
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
    for (auto& e : ps.entries) out.push_back(make_tensor(e.name, e.shape, ps.data(e)));
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
        std::copy(t.data.begin(), t.data.end(), ps.data(e));
    }
}

inline void save_params(const std::string& path, const ParamStore& ps, const std::map<std::string, std::string>& metadata) {
    save_safetensors(path, param_tensors(ps), metadata);
}

inline void load_params(const std::string& path, ParamStore& ps) { read_param_tensors(load_safetensors(path), ps); }

}  // namespace madbp

namespace madbp {

// =============================================================================================
// Section 3. Model inputs (SPEC 5): ModelConfig, SceneBatch, the world-to-model encoding
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
// Where a scene's coordinates start (issue 13). World: at the world's centre, the grid spanning
// the whole world (the paper's; a larger world is out of distribution). Local: at the centre of
// the scene's robots (scene_origin), the grid a crop of +-position_scale around it, so a scene
// looks the same anywhere in a world of any size.
enum class SceneFrame { World, Local };

// Limits of ModelConfig::validate beyond each field's range (docs/limits.md): the U-Net kernel,
// and the temporal attention's scores per agent (heads x horizon^2 floats of workspace).
constexpr int kMaxKernel = 255;
// A model's lengths in world units (position_scale, window_scale, local_extent, subgoal_distance)
// lie in [kMinModelLength, kMaxModelLength] (subgoal_distance may be 0: off); the shipped models
// use 0.28 to 2.4. A checkpoint outside (1e30, 1e-30) makes a planner that never succeeds.
constexpr double kMinModelLength = 1e-3, kMaxModelLength = 1e3;
constexpr long kMaxAttentionScores = 1L << 24;

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
    Prediction prediction = Prediction::X0;  // measured better than the paper's eps here (docs/experiments.md)
    SceneFrame frame = SceneFrame::World;        // metadata "frame" (absent in 0.1 checkpoints: world)
    float subgoal_distance = 0;        // > 0: a goal farther than this, or out of view, is given as a point this far
                                       // along the route around the map (route_goal; world units)
    int n_train_max = 0;               // the largest team in training (metadata train.n_train_max; 0 = unknown)

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
        auto length = [&](const char* f, double v, bool zero_ok) {
            if (!(v >= kMinModelLength && v <= kMaxModelLength) && !(zero_ok && v == 0))
                bad(f, number_text(v) + " is outside [kMinModelLength, kMaxModelLength] = [" + number_text(kMinModelLength) + ", " +
                           number_text(kMaxModelLength) + "] world units" + (zero_ok ? " (0: off)" : ""));
        };
        length("local_extent", local_extent, false);
        if (kernel < 1 || kernel % 2 == 0 || kernel > kMaxKernel)
            bad("kernel", std::to_string(kernel) + " must be odd and in [1, kMaxKernel = " + std::to_string(kMaxKernel) + "]");
        if ((long)heads * horizon * horizon > kMaxAttentionScores)
            bad("horizon/heads", "heads x horizon^2 = " + std::to_string((long)heads * horizon * horizon) +
                                     " attention scores per agent exceed the limit kMaxAttentionScores = " + std::to_string(kMaxAttentionScores));
        if (waypoint_stride < 1 || waypoint_stride > 16) bad("waypoint_stride", "must be in [1, 16]");
        if (diffusion_steps < 2 || diffusion_steps > 100000) bad("diffusion_steps", "must be in [2, 100000]");
        if (sample_steps < 1 || sample_steps > diffusion_steps) bad("sample_steps", "must be in [1, diffusion_steps]");
        length("position_scale", position_scale, false);
        length("window_scale", window_scale, false);
        length("subgoal_distance", subgoal_distance, true);
        if (n_train_max < 0 || n_train_max > n_max) bad("n_train_max", "must be in [0, n_max]");
    }
    std::map<std::string, std::string> to_metadata() const {
        std::string ch;
        for (size_t i = 0; i < channels.size(); ++i) ch += (i ? "," : "") + std::to_string(channels[i]);
        char scale[32];
        std::snprintf(scale, sizeof scale, "%.9g", position_scale);
        char wscale[32], lext[32], sub[32];
        std::snprintf(wscale, sizeof wscale, "%.9g", window_scale);
        std::snprintf(lext, sizeof lext, "%.9g", local_extent);
        std::snprintf(sub, sizeof sub, "%.9g", subgoal_distance);
        std::map<std::string, std::string> md = {{"model", "madbp"}, {"horizon", std::to_string(horizon)}, {"waypoint_stride", std::to_string(waypoint_stride)}, {"dim", std::to_string(dim)},
                {"heads", std::to_string(heads)}, {"n_max", std::to_string(n_max)}, {"grid", std::to_string(grid)},
                {"channels", ch}, {"kernel", std::to_string(kernel)}, {"diffusion_steps", std::to_string(diffusion_steps)},
                {"sample_steps", std::to_string(sample_steps)}, {"processor", processor == Processor::AAP ? "AAP" : "LE"},
                {"window", window == WindowMode::MW ? "MW" : "CT"}, {"position_scale", scale}, {"window_scale", wscale},
                {"prediction", prediction == Prediction::Eps ? "eps" : "x0"}, {"local_grid", std::to_string(local_grid)},
                {"local_extent", lext}, {"frame", frame == SceneFrame::World ? "world" : "local"}, {"subgoal_distance", sub}};
        if (n_train_max > 0) md["train.n_train_max"] = std::to_string(n_train_max);  // training writes it too
        return md;
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
                throw std::runtime_error(source + ": metadata field '" + k + "' is not an integer ('" + printable(s) + "')");
            return (int)v;
        };
        if (get("model") != "madbp") throw std::runtime_error(source + ": not an MA-DBP checkpoint (model = '" + printable(get("model")) + "')");
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
            if (pos == 0 || pos != item.size() || c.channels.size() >= 4)
                throw std::runtime_error(source + ": metadata field 'channels' is malformed or has more than 4 levels");
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
            if (s.empty() || end != s.c_str() + s.size())
                throw std::runtime_error(source + ": metadata field '" + k + "' is not a number ('" + printable(s) + "')");
            return v;
        };
        c.position_scale = real("position_scale");
        c.window_scale = real("window_scale");
        c.local_extent = real("local_extent");
        const std::string& pr = get("prediction");
        if (pr != "eps" && pr != "x0") throw std::runtime_error(source + ": metadata field 'prediction' must be eps or x0");
        c.prediction = pr == "eps" ? Prediction::Eps : Prediction::X0;
        // Fields of release 0.2; a 0.1 checkpoint has none of them and means the defaults.
        if (md.count("frame")) {
            const std::string& f = get("frame");
            if (f != "world" && f != "local") throw std::runtime_error(source + ": metadata field 'frame' must be world or local");
            c.frame = f == "world" ? SceneFrame::World : SceneFrame::Local;
        }
        if (md.count("subgoal_distance")) c.subgoal_distance = real("subgoal_distance");
        if (md.count("train.n_train_max")) c.n_train_max = integer("train.n_train_max");
        // Options of 0.2 removed in 0.3 (they did not help): 0, their default, reads as before; a
        // model trained with one needs inputs this release no longer gives it.
        for (const char* flag : {"velocity_context", "priority_context"}) {
            if (!md.count(flag)) continue;
            const std::string& v = get(flag);
            if (v == "1") throw std::runtime_error(source + ": metadata field '" + flag + "' = 1: the option was removed in release 0.3");
            if (v != "0") throw std::runtime_error(source + ": metadata field '" + flag + "' must be 0 or 1");
        }
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
    static constexpr int kPoseRows = 4;
    Mat pose;                       // (kPoseRows, A) normalised current position x, y and goal x, y, from the scene's origin
    Mat grid;                       // (1, G*G*B) occupancy grid per scene, column b*G*G + row*G + col
    Mat local;                      // (1, Gl*Gl*A) each agent's crop of the map (local_crop), when Gl > 0
    bool shared_grid = false;       // grid holds one map for every scene (planning only; encoded once)
    std::vector<Vec2> origin;       // (B) world position of each scene's frame (0 in the World frame)
    std::vector<float> goal_final;  // (A) 1: the goal is the agent's real goal; 0: a route subgoal (never pinned)
    std::vector<float> priority;    // (A) > 0: the guidance's push between two agents moves the higher one less (window_cost)
    std::vector<uint64_t> noise_seed;  // (B) or empty: scene b's sampling noise from its own stream (decentralised planning)

    int agents() const { return B * n; }
    // Agent a's position and goal in world units, decoded from pose.
    Vec2 position(int a, const ModelConfig& c) const {
        const Vec2& o = origin[a / n];
        return {o.x + pose(0, a) * (double)c.position_scale, o.y + pose(1, a) * (double)c.position_scale};
    }
    Vec2 goal(int a, const ModelConfig& c) const {
        const Vec2& o = origin[a / n];
        return {o.x + pose(2, a) * (double)c.position_scale, o.y + pose(3, a) * (double)c.position_scale};
    }
    int grid_scenes() const { return shared_grid ? 1 : B; }
    void resize(int B_, int n_, int G, int Gl = 0, bool shared = false) {
        B = B_;
        n = n_;
        shared_grid = shared;
        agent_mask.assign((size_t)B * n, 0.0f);
        slot.assign((size_t)B * n, 0);
        count.assign(B, 0);
        pose.setZero(kPoseRows, B * n);
        grid.setZero(1, (long)G * G * grid_scenes());
        local.setZero(1, (long)Gl * Gl * B * n);
        origin.assign(B, Vec2{0, 0});
        goal_final.assign((size_t)B * n, 1.0f);
        priority.assign((size_t)B * n, 1.0f);
        noise_seed.clear();
    }
    void resize(int B_, int n_, const ModelConfig& c, bool shared = false) { resize(B_, n_, c.grid, c.local_grid, shared); }
};

// ---------------------------------------------------------------------------------------------
// The world-to-model encoding: the one place where robots, goals and the map become a
// SceneBatch. The planner (DiffusionPlanner::plan_into) and the trainer (make_train_batch)
// both call these, so what the model sees in training is what it sees when planning.

// A scene's origin for the robots at positions pos(0) .. pos(m-1): the centre of their bounding
// box in the Local frame (so a scene and its translate encode alike), the world's centre in the
// World frame. Order-free: a robot planning alone finds the origin the team plan used.
template <class PositionOf>
Vec2 scene_origin(const ModelConfig& c, int m, PositionOf pos) {
    if (c.frame == SceneFrame::World || m <= 0) return {0, 0};
    Vec2 lo = pos(0), hi = lo;
    for (int i = 1; i < m; ++i) {
        const Vec2 p = pos(i);
        lo = {std::min(lo.x, p.x), std::min(lo.y, p.y)};
        hi = {std::max(hi.x, p.x), std::max(hi.y, p.y)};
    }
    return (lo + hi) * 0.5;
}

// Scene `scene`'s map as the model's occupancy grid: the whole world (World frame), or a crop of
// +-position_scale around batch.origin[scene] (Local frame; cells beyond the walls are occupied).
// Set the scene's origin first.
inline void encode_map(SceneBatch& batch, int scene, const WorldMap& map, const ModelConfig& c) {
    const long G2 = (long)c.grid * c.grid;
    if (c.frame == SceneFrame::Local) {
        local_crop(map, batch.origin[scene], c.grid, c.position_scale, batch.grid.data() + scene * G2);
        return;
    }
    const Grid g = occupancy_grid(map, c.grid);
    for (long j = 0; j < G2; ++j) batch.grid(0, scene * G2 + j) = g.cells[j];
}

// What the model is told to head for (the planner and the trainer both ask here). Without route
// subgoals (subgoal_distance = 0): the goal. With: the goal when it is within subgoal_distance D
// and in straight view; else a point D away in the direction of the route's next waypoint
// (RouteGuide::subgoal, at most kRouteLookahead ahead). Placing it D away, not at the waypoint,
// keeps the model's reading of a goal it has not reached: "keep going this way", as for any far
// goal, never "stop here" (a goal between the pinning reach and D is a real goal). A route that
// keeps out of `closed` (a robot going around a corridor, PassageControl) is given as subgoals
// even without subgoal_distance (D = kRouteLookahead then).
// (The MAPPO and MADiff baselines may be told the same, with their own D: madbp_train.hpp.)
constexpr double kRouteLookahead = 0.8;
// The subgoal D from pos towards `toward` (not at pos): "keep going this way", never "stop here".
inline RouteGoal subgoal_towards(Vec2 pos, Vec2 toward, double D) {
    const Vec2 d = toward - pos;
    return {pos + d * (D / norm(d)), false};
}
inline RouteGoal route_goal(RouteGuide& guide, double D, const WorldMap& map, Vec2 pos, Vec2 goal, ClosedCells closed = {}) {
    if (D <= 0 || (norm(goal - pos) <= D && guide.in_view(map, pos, goal, closed))) return {goal, true};
    const RouteGoal next = guide.subgoal(map, pos, goal, std::min(D, kRouteLookahead), closed);
    if (norm(next.goal - pos) < 1e-9) return {goal, true};  // no direction: the goal itself
    return subgoal_towards(pos, next.goal, D);
}
inline RouteGoal route_goal(RouteGuide& guide, const ModelConfig& c, const WorldMap& map, Vec2 pos, Vec2 goal,
                            ClosedCells closed = {}) {
    return route_goal(guide, c.subgoal_distance > 0 ? c.subgoal_distance : closed.any() ? kRouteLookahead : 0, map, pos, goal, closed);
}

// Agent column a (scene a / n, whose origin is set): active, with PE_agent slot `slot`, its
// position and goal normalised from the scene's origin, whether that goal is its real one
// (`final`; a subgoal's end is never pinned), and its own crop of the map (when the model has one).
inline void encode_agent(SceneBatch& batch, int a, int slot, Vec2 pos, Vec2 goal, const WorldMap& map, const ModelConfig& c,
                         bool final = true) {
    const Vec2 o = batch.origin[a / batch.n], p = pos - o, g = goal - o;
    batch.agent_mask[a] = 1;
    batch.slot[a] = slot;
    batch.goal_final[a] = final ? 1.0f : 0.0f;
    batch.pose.col(a).head<4>() << (float)(p.x / c.position_scale), (float)(p.y / c.position_scale), (float)(g.x / c.position_scale),
        (float)(g.y / c.position_scale);
    if (c.local_grid > 0) local_crop(map, pos, c.local_grid, c.local_extent, batch.local.data() + (long)a * c.local_grid * c.local_grid);
}

// About the distance a window covers at the expert's cruising pace (0.55 units for 15 steps).
inline float default_goal_reach(const ModelConfig& c) { return (float)(0.55 * (c.horizon - 1) * c.waypoint_stride / 15.0); }

// The goal-pinning rule: agent a's window ends at its goal when the goal is its real goal and
// within `reach` world units of it. Training pins that waypoint (to the demonstrated end), the
// sampler inpaints it with the goal, `*end` (normalised displacement units).
inline bool end_pinned(const SceneBatch& batch, int a, const ModelConfig& c, float reach, Eigen::Vector2f* end = nullptr) {
    if (batch.goal_final[a] == 0) return false;
    const Eigen::Vector2f to_goal = (batch.pose.col(a).segment<2>(2) - batch.pose.col(a).head<2>()) * c.position_scale;
    if (to_goal.norm() > reach) return false;
    if (end) *end = to_goal / c.window_scale;
    return true;
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

// =============================================================================================
// Section 4. Model parts (SPEC 5)
// =============================================================================================
// Model parts: each is a small struct with forward/backward over the model's layouts, built
// into a caller's ParamStore. MadbpModel composes ContextEncoder, StepEmbedding,
// TrajectoryProcessor and FilmUNet; MADiff (madbp_train.hpp) uses StepEmbedding and FilmUNet
// with agent attention.

// One U-Net level's block: x (cin, T*A) -> y (cout, T*A):
// Conv1d -> BatchNorm -> ReLU -> FiLM(cond) -> Conv1d -> BatchNorm -> ReLU.
// cond (Dc, A) gives gamma, beta (cout, A) through a Linear; BatchNorm counts active columns only.
struct ConvBlock {
    Conv1d conv1, conv2;
    BatchNorm1d bn1, bn2;
    ReLU relu1, relu2;
    Linear film;
    int cout = 0;
    Mat c1, n1, a1, f1, c2, n2;    // (cout, T*A) forward intermediates
    Mat gb;                        // (2*cout, A) FiLM output: gamma on top of beta
    Mat gamma, beta;               // (cout, A)
    Mat d_a, d_b;                  // (cout, T*A) backward scratch
    Mat d_gamma, d_beta, d_gb;     // (cout, A), (cout, A), (2*cout, A)
    Mat d_cond;                    // (Dc, A)

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

// Self-attention over the n agents of a scene at each time step, pre-LayerNorm, residual:
// x (C, T*A) agent-major (A = B*n) -> y (C, T*A) = x + MHA(LN(x)) with the agents of scene b at
// time t as queries and keys (no mask: the team is fixed). backward(x, T, B, n, dy, dx).
struct AgentAttention {
    LayerNorm ln;
    MultiHeadAttention att;
    Mat x_tm, z, a_tm, a;          // (C, T*A): x time-major, LN(x_tm), attention out time- and agent-major
    Mat d_tm, d_q, d_kv, d_z;      // (C, T*A) backward scratch

    AgentAttention() = default;
    AgentAttention(ParamStore& ps, const std::string& name, int C, int heads, Rng& rng)
        : ln(ps, name + ".ln", C, rng), att(ps, name + ".attn", C, heads, rng) {}
    void forward(const Mat& x, int T, int B, int n, Mat& y) {
        MADBP_ASSERT(x.cols() == (long)T * B * n);
        detail::agent_to_time_major(x, B, n, T, x_tm);
        ln.forward(x_tm, z);
        att.forward(z, n, z, n, B * T, nullptr, a_tm);
        detail::time_to_agent_major(a_tm, B, n, T, a);
        y = x + a;
    }
    void backward(const Mat& x, int T, int B, int n, const Mat& dy, Mat& dx) {
        detail::agent_to_time_major(dy, B, n, T, d_tm);
        att.backward(z, n, z, n, B * T, nullptr, d_tm, d_q, d_kv);
        d_q += d_kv;
        ln.backward(x_tm, d_q, d_z);
        detail::time_to_agent_major(d_z, B, n, T, dx);
        dx += dy;
    }
};

// The FiLM U-Net (SPEC 5): x (cin, H*A) -> y (cout, H*A), agent-major columns a*H + t. Level l
// runs at T_l = H / 2^l with widths[l] channels; every block is FiLM-conditioned on each agent's
// cond (Dc, A). With attention heads > 0 (MADiff), the agents of a scene attend to each other
// on every skip and at the bottleneck. set_agent_mask() makes BatchNorm count only active
// agents' columns (MA-DBP's padded teams); without it every column counts.
// Tensor names: <name>.down<l>, <name>.mid, <name>.up<l>, <name>.decoder, <attn>.skip<l>, <attn>.mid.
struct FilmUNet {
    std::vector<ConvBlock> down, up;       // per level
    ConvBlock mid;
    std::vector<AgentAttention> skip_attn; // per level, when attention
    AgentAttention mid_attn;
    std::vector<MaxPool1d> pool;
    std::vector<Upsample1d> upsample;
    Conv1d decoder;
    int H = 0, levels = 0;
    bool attention = false;
    std::vector<std::vector<float>> colmask;  // per level (T_l * A): active-agent columns; empty: all
    // Forward intermediates, per level l unless noted.
    std::vector<Mat> h;                    // (C_l, T_l*A) down block output
    std::vector<Mat> skip;                 // (C_l, T_l*A) h after agent attention (attention only)
    std::vector<Mat> pooled;               // (C_l, T_l/2*A)
    std::vector<Mat> up_buf;               // (C_l+1 or C_L, T_l*A) the level below, upsampled
    std::vector<Mat> cat;                  // (.. + C_l, T_l*A) [up_buf; skip]
    std::vector<Mat> up_out;               // (C_l, T_l*A) up block output
    Mat mid_h, mid_out;                    // (C_L, T_L*A) bottleneck before / after attention
    // Backward scratch.
    std::vector<Mat> d_skip;               // (C_l, T_l*A)
    Mat d_cur, d_cat, d_up, d_mid, d_pool, d_h, d_tmp;

    FilmUNet() = default;
    FilmUNet(ParamStore& ps, const std::string& name, const std::string& attn_name, int cin, int cout,
             const std::vector<int>& widths, int kernel, int cond_dim, int horizon, int attention_heads, Rng& rng)
        : H(horizon), levels((int)widths.size()), attention(attention_heads > 0) {
        const int L = levels;
        int c = cin;
        for (int l = 0; l < L; ++l) {
            down.emplace_back(ps, name + ".down" + std::to_string(l), c, widths[l], kernel, cond_dim, rng);
            if (attention) skip_attn.emplace_back(ps, attn_name + ".skip" + std::to_string(l), widths[l], attention_heads, rng);
            c = widths[l];
        }
        mid = ConvBlock(ps, name + ".mid", c, c, kernel, cond_dim, rng);
        if (attention) mid_attn = AgentAttention(ps, attn_name + ".mid", c, attention_heads, rng);
        up.resize(L);
        for (int l = L - 1; l >= 0; --l) {
            up[l] = ConvBlock(ps, name + ".up" + std::to_string(l), c + widths[l], widths[l], kernel, cond_dim, rng);
            c = widths[l];
        }
        decoder = Conv1d(ps, name + ".decoder", widths[0], cout, 1, rng);
        pool.resize(L);
        upsample.resize(L);
        for (auto* v : {&h, &skip, &pooled, &up_buf, &cat, &up_out, &d_skip}) v->resize(L);
    }
    void set_training(bool on) {
        for (auto& b : down) b.set_training(on);
        for (auto& b : up) b.set_training(on);
        mid.set_training(on);
    }
    // BatchNorm statistics over the columns of active agents only (agent_mask (A), 1 = active).
    void set_agent_mask(const std::vector<float>& agent_mask) {
        const int A = (int)agent_mask.size();
        colmask.resize(levels + 1);
        for (int l = 0; l <= levels; ++l) {
            const int T = H >> l;
            colmask[l].resize((size_t)T * A);
            for (int a = 0; a < A; ++a)
                for (int t = 0; t < T; ++t) colmask[l][(size_t)a * T + t] = agent_mask[a];
        }
    }

    // x (cin, H*A), cond (Dc, A) -> y (cout, H*A); B scenes of n agents (A = B*n; for attention).
    void forward(const Mat& x, const Mat& cond, int B, int n, Mat& y) {
        const int L = levels;
        for (int l = 0; l < L; ++l) {
            down[l].forward(down_input(x, l), H >> l, cond, mask(l), h[l]);
            if (attention) skip_attn[l].forward(h[l], H >> l, B, n, skip[l]);
            pool[l].forward(h[l], H >> l, pooled[l]);
        }
        mid.forward(pooled[L - 1], H >> L, cond, mask(L), mid_h);
        if (attention) mid_attn.forward(mid_h, H >> L, B, n, mid_out);
        for (int l = L - 1; l >= 0; --l) {
            upsample[l].forward(up_input(l), up_buf[l]);  // nearest x2, then the skip below it
            const Mat& s = skip_of(l);
            const long cu = up_buf[l].rows(), cs = s.rows();
            cat[l].resize(cu + cs, up_buf[l].cols());
            cat[l].topRows(cu) = up_buf[l];
            cat[l].bottomRows(cs) = s;
            up[l].forward(cat[l], H >> l, cond, mask(l), up_out[l]);
        }
        decoder.forward(up_out[0], H, y);
    }
    // Backward of the last forward: writes dx (cin, H*A), ADDS into dcond (Dc, A).
    void backward(const Mat& x, const Mat& cond, int B, int n, const Mat& dy, Mat& dx, Mat& dcond) {
        const int L = levels;
        decoder.backward(up_out[0], H, dy, d_cur);
        for (int l = 0; l < L; ++l) {
            up[l].backward(cat[l], H >> l, cond, mask(l), d_cur, d_cat, dcond);
            const long cu = up_input(l).rows(), cs = skip_of(l).rows();
            d_skip[l] = d_cat.bottomRows(cs);
            d_up = d_cat.topRows(cu);
            upsample[l].backward(up_input(l), d_up, d_cur);
        }
        const Mat* d_mid_h = &d_cur;
        if (attention) {
            mid_attn.backward(mid_h, H >> L, B, n, d_cur, d_mid);
            d_mid_h = &d_mid;
        }
        mid.backward(pooled[L - 1], H >> L, cond, mask(L), *d_mid_h, d_pool, dcond);
        for (int l = L - 1; l >= 0; --l) {
            pool[l].backward(h[l], H >> l, d_pool, d_h);
            if (attention) {
                skip_attn[l].backward(h[l], H >> l, B, n, d_skip[l], d_tmp);
                d_h += d_tmp;
            } else {
                d_h += d_skip[l];
            }
            down[l].backward(down_input(x, l), H >> l, cond, mask(l), d_h, l == 0 ? dx : d_pool, dcond);
        }
    }

private:
    const float* mask(int l) const { return colmask.empty() ? nullptr : colmask[l].data(); }
    const Mat& down_input(const Mat& x, int l) const { return l == 0 ? x : pooled[l - 1]; }
    const Mat& skip_of(int l) const { return attention ? skip[l] : h[l]; }
    const Mat& up_input(int l) const { return l == levels - 1 ? (attention ? mid_out : mid_h) : up_out[l + 1]; }
};

// Diffusion-step embedding (SPEC 5): k (B) -> tok (D, B) = Linear(Mish(Linear(sinusoidal(k)))),
// D -> 2D -> D. Tensor names <name>.l1, <name>.l2. backward(d_tok) adds the parameter gradients.
struct StepEmbedding {
    Linear l1, l2;
    Mish act;
    int dim = 0;
    std::vector<float> k;          // (B) the steps as floats
    Mat sin, h1, h1a;              // (D, B), (2D, B), (2D, B)
    Mat d_h1a, d_h1, d_sin;        // backward scratch

    StepEmbedding() = default;
    StepEmbedding(ParamStore& ps, const std::string& name, int D, Rng& rng)
        : l1(ps, name + ".l1", D, 2 * D, rng), l2(ps, name + ".l2", 2 * D, D, rng), dim(D) {}
    void forward(const int* steps, int B, Mat& tok) {
        k.resize(B);
        for (int b = 0; b < B; ++b) k[b] = (float)steps[b];
        sinusoidal_embedding(k.data(), B, dim, sin);
        l1.forward(sin, h1);
        act.forward(h1, h1a);
        l2.forward(h1a, tok);
    }
    void backward(const Mat& d_tok) {
        l2.backward(h1a, d_tok, d_h1a);
        act.backward(h1, d_h1a, d_h1);
        l1.backward(sin, d_h1, d_sin);
    }
};

// The context encoder (SPEC 5): the map's grid (a CNN to P image tokens), each agent's pose (an
// MLP) plus its own map crop (a small CNN), and the scene's agent count (an embedding), fused by
// attention of the pose tokens over all of them: batch -> ctx (D, A). With batch.shared_grid
// the map is encoded once for every scene (planning).
struct ContextEncoder {
    Conv2d g1, g2, g3;             // grid CNN: (1, G*G) -> (16, G/2) -> (32, G/4) -> (D, G/8 = P tokens)
    Conv2d l1, l2, l3;             // crop CNN: (1, Gl*Gl) -> (8, Gl/2) -> (16, Gl/4) -> (D, 1)
    ReLU r1, r2, r3, r4;
    Embedding pe_img, count_emb;
    Linear pose1, pose2;
    Mish pose_act;
    MultiHeadAttention fuse;
    LayerNorm ln;
    ModelConfig config;
    std::vector<int> img_ids, count_ids;   // (P*B), (B)
    std::vector<float> kv_mask;            // (Lk*B), Lk = P + n + 1 keys per scene
    Mat g1o, g1a, g2o, g2a;                // grid CNN intermediates
    Mat img, img_one, tmp;                 // (D, P*B) image tokens; (D, P) the shared map's; scratch
    Mat l1o, l1a, l2o, l2a, local_tok;     // crop CNN intermediates; (D, A) crop tokens
    Mat p1, p1a, pose_tok;                 // (D, A) pose MLP
    Mat count_tok;                         // (D, B)
    Mat kv, att, pre_ln;                   // (D, Lk*B) keys; (D, A) attention out, residual sum
    Mat d_pre, d_pose, d_kv, d_img, d_count;          // backward: (D, A), (D, A), (D, Lk*B), (D, P*B), (D, B)
    Mat d_g2a, d_g2o, d_g1a, d_g1o, d_grid;           // grid CNN
    Mat d_l1o, d_l1a, d_l2o, d_l2a, d_local;          // crop CNN
    Mat d_p1a, d_p1, d_posein;                        // pose MLP

    ContextEncoder() = default;
    ContextEncoder(ParamStore& ps, const ModelConfig& c, Rng& rng) : config(c) {
        const int D = c.dim;
        g1 = Conv2d(ps, "ctx.grid1", 1, 16, 3, 2, 1, rng);
        g2 = Conv2d(ps, "ctx.grid2", 16, 32, 3, 2, 1, rng);
        g3 = Conv2d(ps, "ctx.grid3", 32, D, 3, 2, 1, rng);
        pe_img = Embedding(ps, "ctx.pe_img", c.image_tokens(), D, rng);
        pose1 = Linear(ps, "ctx.pose1", SceneBatch::kPoseRows, D, rng);
        pose2 = Linear(ps, "ctx.pose2", D, D, rng);
        if (c.local_grid > 0) {
            l1 = Conv2d(ps, "ctx.local1", 1, 8, 3, 2, 1, rng);
            l2 = Conv2d(ps, "ctx.local2", 8, 16, 3, 2, 1, rng);
            l3 = Conv2d(ps, "ctx.local3", 16, D, c.local_grid / 4, 1, 0, rng);  // the whole 4x4-reduced crop -> one token
        }
        count_emb = Embedding(ps, "ctx.count", c.n_max + 1, D, rng);
        fuse = MultiHeadAttention(ps, "ctx.fuse", D, c.heads, rng);
        ln = LayerNorm(ps, "ctx.ln", D, rng);
    }

    void forward(const SceneBatch& batch, Mat& ctx) {
        const ModelConfig& c = config;
        const int B = batch.B, n = batch.n, G = c.grid, P = c.image_tokens();
        g1.forward(batch.grid, G, G, g1o);
        r1.forward(g1o, g1a);
        g2.forward(g1a, G / 2, G / 2, g2o);
        r2.forward(g2o, g2a);
        if (batch.shared_grid) {  // one map for every scene: encode it once, give each scene a copy
            g3.forward(g2a, G / 4, G / 4, img_one);
            img.resize(c.dim, (long)P * B);
            for (int b = 0; b < B; ++b) img.middleCols((long)b * P, P) = img_one;
        } else {
            g3.forward(g2a, G / 4, G / 4, img);
        }
        img_ids.resize((size_t)P * B);
        for (int j = 0; j < P * B; ++j) img_ids[j] = j % P;
        pe_img.forward(img_ids.data(), P * B, tmp);
        img += tmp;
        pose1.forward(batch.pose, p1);
        pose_act.forward(p1, p1a);
        pose2.forward(p1a, pose_tok);
        if (c.local_grid > 0) {  // each agent's own crop of the map, added to its pose token
            const int Gl = c.local_grid;
            l1.forward(batch.local, Gl, Gl, l1o);
            r3.forward(l1o, l1a);
            l2.forward(l1a, Gl / 2, Gl / 2, l2o);
            r4.forward(l2o, l2a);
            l3.forward(l2a, Gl / 4, Gl / 4, local_tok);
            pose_tok += local_tok;
        }
        count_ids.assign(batch.count.begin(), batch.count.end());
        count_emb.forward(count_ids.data(), B, count_tok);
        // Keys of scene b: its P image tokens, its n pose tokens (inactive masked), its count token.
        const int Lk = P + n + 1;
        kv.resize(c.dim, (long)Lk * B);
        kv_mask.resize((size_t)Lk * B);
        for (int b = 0; b < B; ++b) {
            const long o = (long)b * Lk;
            kv.middleCols(o, P) = img.middleCols((long)b * P, P);
            kv.middleCols(o + P, n) = pose_tok.middleCols((long)b * n, n);
            kv.col(o + P + n) = count_tok.col(b);
            for (int j = 0; j < P; ++j) kv_mask[o + j] = 1.0f;
            for (int i = 0; i < n; ++i) kv_mask[o + P + i] = batch.agent_mask[(size_t)b * n + i];
            kv_mask[o + P + n] = 1.0f;
        }
        fuse.forward(pose_tok, n, kv, Lk, B, kv_mask.data(), att);
        pre_ln = pose_tok + att;
        ln.forward(pre_ln, ctx);
    }

    // d_ctx (D, A) -> parameter gradients (one grid per scene: training batches).
    void backward(const SceneBatch& batch, const Mat& d_ctx) {
        const ModelConfig& c = config;
        const int B = batch.B, n = batch.n, G = c.grid, P = c.image_tokens(), Lk = P + n + 1;
        if (batch.shared_grid) throw std::logic_error("context backward: training needs one grid per scene (shared_grid is for planning)");
        ln.backward(pre_ln, d_ctx, d_pre);
        fuse.backward(pose_tok, n, kv, Lk, B, kv_mask.data(), d_pre, d_pose, d_kv);
        d_pose += d_pre;
        d_img.resize(c.dim, (long)P * B);
        d_count.resize(c.dim, B);
        for (int b = 0; b < B; ++b) {
            const long o = (long)b * Lk;
            d_img.middleCols((long)b * P, P) = d_kv.middleCols(o, P);
            d_pose.middleCols((long)b * n, n) += d_kv.middleCols(o + P, n);
            d_count.col(b) = d_kv.col(o + P + n);
        }
        count_emb.backward(count_ids.data(), B, d_count);
        pose2.backward(p1a, d_pose, d_p1a);
        pose_act.backward(p1, d_p1a, d_p1);
        pose1.backward(batch.pose, d_p1, d_posein);
        if (c.local_grid > 0) {
            const int Gl = c.local_grid;
            l3.backward(l2a, Gl / 4, Gl / 4, d_pose, d_l2a);
            r4.backward(l2o, d_l2a, d_l2o);
            l2.backward(l1a, Gl / 2, Gl / 2, d_l2o, d_l1a);
            r3.backward(l1o, d_l1a, d_l1o);
            l1.backward(batch.local, Gl, Gl, d_l1o, d_local);
        }
        pe_img.backward(img_ids.data(), P * B, d_img);
        g3.backward(g2a, G / 4, G / 4, d_img, d_g2a);
        r2.backward(g2o, d_g2a, d_g2o);
        g2.backward(g1a, G / 2, G / 2, d_g2o, d_g1a);
        r1.backward(g1o, d_g1a, d_g1o);
        g1.backward(batch.grid, G, G, d_g1o, d_grid);
    }
};

// The trajectory processor (SPEC 5): the noisy window x (2, H*A) -> out (D, H*A). A Linear of
// [displacement; current position], then (AAP) positional embeddings of agent slot and time,
// attention over time within each agent, attention over the agents at each time step (inactive
// agents masked as keys), each with residual + LayerNorm, and a residual MLP. LE (ablation):
// the Linear alone.
struct TrajectoryProcessor {
    Linear in_proj, mlp1, mlp2;
    Embedding pe_agent, pe_time;
    MultiHeadAttention time_attn, agent_attn;
    LayerNorm ln_time, ln_agent;
    Mish mlp_act;
    ModelConfig config;
    std::vector<int> slot_ids, time_ids;   // (H*A)
    std::vector<float> agent_key_mask;     // (H*A) time-major
    Mat in;                                // (4, H*A) [x; current position]
    Mat proj, pe, pos, att_t, sum_t, xt;   // (D, H*A) agent-major
    Mat xt_tm, att_a_tm;                   // (D, H*A) time-major
    Mat att_a, sum_a, xat, m2;             // (D, H*A)
    Mat m1, m1a;                           // (2D, H*A)
    Mat out;                               // (D, H*A) the result (LE: proj)
    Mat d_xat, d_m2, d_m1a, d_m1, d_sum_a, d_xt, d_tm, d_q, d_kv, d_sum_t, d_pos, d_x;  // backward scratch

    TrajectoryProcessor() = default;
    TrajectoryProcessor(ParamStore& ps, const ModelConfig& c, Rng& rng) : config(c) {
        const int D = c.dim;
        in_proj = Linear(ps, "aap.in_proj", 4, D, rng);
        if (c.processor == Processor::AAP) {
            pe_agent = Embedding(ps, "aap.pe_agent", c.n_max, D, rng);
            pe_time = Embedding(ps, "aap.pe_time", c.horizon, D, rng);
            time_attn = MultiHeadAttention(ps, "aap.time_attn", D, c.heads, rng);
            ln_time = LayerNorm(ps, "aap.ln_time", D, rng);
            agent_attn = MultiHeadAttention(ps, "aap.agent_attn", D, c.heads, rng);
            ln_agent = LayerNorm(ps, "aap.ln_agent", D, rng);
            mlp1 = Linear(ps, "aap.mlp1", D, 2 * D, rng);
            mlp2 = Linear(ps, "aap.mlp2", 2 * D, D, rng);
        }
    }

    void forward(const Mat& x, const SceneBatch& batch) {
        const int B = batch.B, n = batch.n, A = B * n, H = config.horizon;
        in.resize(4, (long)H * A);
        in.topRows(2) = x;
        for (int a = 0; a < A; ++a) in.block(2, (long)a * H, 2, H).colwise() = batch.pose.col(a).head<2>();
        in_proj.forward(in, proj);
        if (config.processor == Processor::LE) {
            out = proj;
            return;
        }
        slot_ids.resize((size_t)H * A);
        time_ids.resize((size_t)H * A);
        for (int a = 0; a < A; ++a)
            for (int t = 0; t < H; ++t) {
                slot_ids[(size_t)a * H + t] = batch.slot[a];
                time_ids[(size_t)a * H + t] = t;
            }
        pe_agent.forward(slot_ids.data(), H * A, pe);
        pos = proj + pe;
        pe_time.forward(time_ids.data(), H * A, pe);
        pos += pe;
        // Attention over time within each agent, residual + LayerNorm.
        time_attn.forward(pos, H, pos, H, A, nullptr, att_t);
        sum_t = pos + att_t;
        ln_time.forward(sum_t, xt);
        // Attention over agents at each time step (inactive agents masked as keys).
        detail::agent_to_time_major(xt, B, n, H, xt_tm);
        agent_key_mask.resize((size_t)H * A);
        for (int b = 0; b < B; ++b)
            for (int t = 0; t < H; ++t)
                for (int i = 0; i < n; ++i) agent_key_mask[((size_t)b * H + t) * n + i] = batch.agent_mask[(size_t)b * n + i];
        agent_attn.forward(xt_tm, n, xt_tm, n, B * H, agent_key_mask.data(), att_a_tm);
        detail::time_to_agent_major(att_a_tm, B, n, H, att_a);
        sum_a = xt + att_a;
        ln_agent.forward(sum_a, xat);
        // X~ = X_at + MLP(X_at).
        mlp1.forward(xat, m1);
        mlp_act.forward(m1, m1a);
        mlp2.forward(m1a, m2);
        out = xat + m2;
    }
    // d_out (D, H*A) -> parameter gradients (the window's own gradient is not needed).
    void backward(const Mat& d_out, const SceneBatch& batch) {
        const int B = batch.B, n = batch.n, A = B * n, H = config.horizon;
        if (config.processor == Processor::LE) {
            in_proj.backward(in, d_out, d_x);
            return;
        }
        mlp2.backward(m1a, d_out, d_m1a);
        mlp_act.backward(m1, d_m1a, d_m1);
        mlp1.backward(xat, d_m1, d_xat);
        d_xat += d_out;
        ln_agent.backward(sum_a, d_xat, d_sum_a);
        detail::agent_to_time_major(d_sum_a, B, n, H, d_tm);
        agent_attn.backward(xt_tm, n, xt_tm, n, B * H, agent_key_mask.data(), d_tm, d_q, d_kv);
        d_q += d_kv;
        detail::time_to_agent_major(d_q, B, n, H, d_xt);
        d_xt += d_sum_a;
        ln_time.backward(sum_t, d_xt, d_sum_t);
        time_attn.backward(pos, H, pos, H, A, nullptr, d_sum_t, d_q, d_kv);
        d_pos = d_sum_t + d_q + d_kv;
        pe_agent.backward(slot_ids.data(), H * A, d_pos);
        pe_time.backward(time_ids.data(), H * A, d_pos);
        in_proj.backward(in, d_pos, d_x);
    }
};

// =============================================================================================
// Section 5. The model (SPEC 5, 11): MadbpModel, save_model, load_model
// =============================================================================================
// The denoiser eps_theta(X^k, k, c) (or x0_theta with Prediction::X0): ContextEncoder ->
// ctx (D, A); cond = Mish(ctx + StepEmbedding(k)) (D, A); TrajectoryProcessor -> FilmUNet
// conditioned on cond. Not copyable (layers point into its ParamStore); movable; clone() copies.
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

    // An independent copy (same config, parameters, state and mode) with its own workspaces.
    MadbpModel clone() const {
        MadbpModel m(config);
        m.params->value = params->value;
        m.params->state = params->state;
        m.set_training(training_);
        return m;
    }
    long parameter_count() const { return params->trainable_count(); }
    // Training mode: BatchNorm uses (masked) batch statistics and updates its running ones.
    void set_training(bool on) {
        training_ = on;
        unet_.set_training(on);
    }
    bool training() const { return training_; }

    // Encodes the scene conditioning into ctx (D, A). Keeps `batch` (by reference) for denoise
    // and backward.
    void encode_context(const SceneBatch& batch) {
        check_batch(batch);
        batch_ = &batch;
        context_.forward(batch, ctx_);
        unet_.set_agent_mask(batch.agent_mask);  // constant while the batch is
    }

    // out (2, H*A) = the network's prediction (eps or x0) for x_noisy (2, H*A) at diffusion
    // step k (B, one per scene), given the last encoded context.
    void denoise(const Mat& x_noisy, const int* k, Mat& out) {
        MADBP_ASSERT(batch_ != nullptr);
        const SceneBatch& batch = *batch_;
        const int B = batch.B, n = batch.n, A = B * n;
        MADBP_ASSERT(x_noisy.rows() == 2 && x_noisy.cols() == (long)config.horizon * A);
        // The step embedding is added to each agent's context, then FiLM at every level.
        step_.forward(k, B, step_tok_);
        cond_pre_.resize(config.dim, A);
        for (int a = 0; a < A; ++a) cond_pre_.col(a) = ctx_.col(a) + step_tok_.col(a / n);
        cond_act_.forward(cond_pre_, cond_);
        processor_.forward(x_noisy, batch);
        unet_.forward(processor_.out, cond_, B, n, out);
    }

    // Backward of the last encode_context + denoise: ADDS every parameter's gradient.
    void backward(const Mat& d_out) {
        const SceneBatch& batch = *batch_;
        const int B = batch.B, n = batch.n, A = B * n;
        d_cond_.setZero(config.dim, A);
        unet_.backward(processor_.out, cond_, B, n, d_out, d_proc_, d_cond_);
        processor_.backward(d_proc_, batch);
        // cond = Mish(ctx + step_tok[scene]).
        cond_act_.backward(cond_pre_, d_cond_, d_pre_);
        d_tok_.setZero(config.dim, B);
        for (int a = 0; a < A; ++a) d_tok_.col(a / n) += d_pre_.col(a);
        step_.backward(d_tok_);
        context_.backward(batch, d_pre_);
    }

    const Mat& context() const { return ctx_; }

private:
    bool training_ = true;
    const SceneBatch* batch_ = nullptr;
    TrajectoryProcessor processor_;
    ContextEncoder context_;
    StepEmbedding step_;
    FilmUNet unet_;
    Mish cond_act_;
    Mat ctx_;                      // (D, A) encoded context
    Mat step_tok_, d_tok_;         // (D, B)
    Mat cond_pre_, cond_, d_cond_, d_pre_;  // (D, A)
    Mat d_proc_;                   // (D, H*A)

    // Parameters are created in this order (it fixes the initial weights for a seed).
    void build(uint64_t seed) {
        Rng rng(seed);
        ParamStore& ps = *params;
        const ModelConfig& c = config;
        processor_ = TrajectoryProcessor(ps, c, rng);
        context_ = ContextEncoder(ps, c, rng);
        step_ = StepEmbedding(ps, "step", c.dim, rng);
        unet_ = FilmUNet(ps, "unet", "", c.dim, 2, c.channels, c.kernel, c.dim, c.horizon, /*attention heads*/ 0, rng);
    }

    void check_batch(const SceneBatch& b) const {
        const long A = (long)b.B * b.n;
        if (b.B < 1 || b.n < 1) throw std::invalid_argument("scene batch: needs B >= 1 and n >= 1");
        if (b.n > config.n_max)
            throw std::invalid_argument("scene batch: " + std::to_string(b.n) + " agent slots exceed the model's n_max = " + std::to_string(config.n_max));
        if ((long)b.agent_mask.size() != A || (long)b.slot.size() != A || (long)b.count.size() != b.B || b.pose.rows() != SceneBatch::kPoseRows ||
            b.pose.cols() != A || b.grid.rows() != 1 || b.grid.cols() != (long)config.grid * config.grid * b.grid_scenes() ||
            b.local.cols() != (long)config.local_grid * config.local_grid * A || (long)b.origin.size() != b.B ||
            (long)b.goal_final.size() != A || (long)b.priority.size() != A || (!b.noise_seed.empty() && (long)b.noise_seed.size() != b.B))
            throw std::invalid_argument("scene batch: array sizes do not match B = " + std::to_string(b.B) + ", n = " + std::to_string(b.n));
        for (int s = 0; s < b.B; ++s)
            if (b.count[s] < 0 || b.count[s] > config.n_max)
                throw std::invalid_argument("scene batch: count " + std::to_string(b.count[s]) + " outside [0, n_max]");
        for (long a = 0; a < A; ++a)
            if (b.slot[a] < 0 || b.slot[a] >= config.n_max) throw std::invalid_argument("scene batch: slot outside [0, n_max)");
        if (!b.pose.allFinite()) throw std::invalid_argument("scene batch: pose (positions or goals) is not finite");
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
    const ParamBudget budget(st.values(), path);  // the declared config may need no more values than the file holds
    MadbpModel model(ModelConfig::from_metadata(st.metadata, path));
    read_param_tensors(st, *model.params);
    model.set_training(false);
    return model;
}

// The shipped default model, madbp-default.safetensors, wherever madbp was installed or checked
// out: the one lookup behind the tool's --model default (other front ends, e.g. Python, should
// follow the same order). The first existing file of, in order:
//   1 $MADBP_MODEL (set and non-empty): the model file itself; a missing file is an error rather
//     than a fall-through, so that a typo does not silently plan with another model
//   2 <dir of the running executable>/../share/madbp/models (Linux /proc/self/exe): an installed
//     or relocated tool uses the model installed beside it, not the tree it was built from;
//     then MADBP_MODEL_DIR (compile-time macro; the CMake target and madbp.pc define it), then
//     <dir of this header>/../share/madbp/models (installed headers; the header's path is known
//     only when it was included by an absolute path, as CMake does)
//   3 the checkout: ./models, then <dir of this header>/models
// Throws std::runtime_error naming every place tried when none exists. Prints nothing.
namespace detail {
constexpr const char* kDefaultModelFile = "madbp-default.safetensors";
inline bool is_regular_file(const std::string& path) {
    struct stat sb;
    return ::stat(path.c_str(), &sb) == 0 && S_ISREG(sb.st_mode);
}
// "" for a path without a directory part.
inline std::string dir_of(const std::string& path) {
    const size_t slash = path.find_last_of('/');
    return slash == std::string::npos ? "" : slash == 0 ? "/" : path.substr(0, slash);
}
// The running program's directory; "" where the platform does not say (no /proc).
inline std::string executable_dir() {
#ifdef __linux__
    char buf[PATH_MAX];
    const ssize_t n = ::readlink("/proc/self/exe", buf, sizeof buf - 1);
    if (n > 0) return dir_of(std::string(buf, (size_t)n));
#endif
    return "";
}
// For messages: a relative path with the current directory in front.
inline std::string absolute_for_message(const std::string& path) {
    char cwd[PATH_MAX];
    return !path.empty() && path[0] != '/' && ::getcwd(cwd, sizeof cwd) ? std::string(cwd) + "/" + path : path;
}
// Model directories of steps 2 and 3 of default_model_path, in order.
inline std::vector<std::string> default_model_dirs() {
    std::vector<std::string> dirs;
    const std::string exe = executable_dir();
    if (!exe.empty()) dirs.push_back(exe + "/../share/madbp/models");
#ifdef MADBP_MODEL_DIR
    dirs.push_back(MADBP_MODEL_DIR);
#endif
    // A relative __FILE__ is relative to the compiler's directory, not the program's: skipped.
    const std::string header_dir = __FILE__[0] == '/' ? dir_of(__FILE__) : "";
    if (!header_dir.empty()) dirs.push_back(header_dir + "/../share/madbp/models");
    dirs.push_back("models");
    if (!header_dir.empty()) dirs.push_back(header_dir + "/models");
    return dirs;
}
}  // namespace detail

inline std::string default_model_path() {
    const char* env = std::getenv("MADBP_MODEL");
    if (env && *env) {
        if (!detail::is_regular_file(env))
            throw std::runtime_error(std::string("MADBP_MODEL=") + env + ": no such model file (MADBP_MODEL names the file itself; unset it for the shipped model)");
        return env;
    }
    std::string tried;
    for (const std::string& dir : detail::default_model_dirs()) {
        const std::string path = dir + "/" + detail::kDefaultModelFile;
        if (detail::is_regular_file(path)) return path;
        tried += (tried.empty() ? "" : ", ") + detail::absolute_for_message(path);
    }
    throw std::runtime_error(std::string("default model: ") + detail::kDefaultModelFile + " not found (MADBP_MODEL not set; tried " + tried +
                             "); set MADBP_MODEL to the model file, or pass its path (madbp: --model FILE)");
}

// =============================================================================================
// Section 6. Diffusion (SPEC 6): cosine schedule, training-time noising, DDIM sampler with inpainting
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

namespace detail {
// One DDIM step's noise levels: from diffusion step k (of DDIM step s of S) to k_prev.
struct DdimLevels {
    int k = 0, k_prev = 0;
    double alpha_bar = 1;
    float sa = 1, s1a = 0, sap = 1, s1ap = 0;  // sqrt(alpha_bar), sqrt(1 - alpha_bar), and the same at k_prev
    DdimLevels(const NoiseSchedule& schedule, int s, int S)
        : k(schedule.ddim_step(s, S)), k_prev(schedule.ddim_step(s - 1, S)), alpha_bar(schedule.alpha_bar[k]) {
        const double ab_prev = schedule.alpha_bar[k_prev];
        sa = (float)std::sqrt(alpha_bar), s1a = (float)std::sqrt(1 - alpha_bar);
        sap = (float)std::sqrt(ab_prev), s1ap = (float)std::sqrt(1 - ab_prev);
    }
};

// The DDIM loop (eta = 0) of every sampler: the planner's plain and guided ones and MADiff's
// (madbp_train.hpp). For DDIM steps s = s_top .. 1 of S: x0_hat(levels, x0) writes the predicted
// clean sample for the current x (the network's, clipped, and steered where a sampler steers:
// guidance, classifier-free guidance); x moves to the next level with the noise that x0 implies;
// pin(x) re-imposes what is known (inpainting). x0 has x's shape (it may be the denoiser's output).
template <class PredictX0, class Pin>
void ddim_loop(const NoiseSchedule& schedule, int S, int s_top, Mat& x, Mat& x0, PredictX0&& x0_hat, Pin&& pin) {
    for (int s = s_top; s >= 1; --s) {
        const DdimLevels l(schedule, s, S);
        x0_hat(l, x0);
        MADBP_ASSERT(x0.size() == x.size());
        for (long j = 0; j < x.size(); ++j) {
            const float xj = x.data()[j], x0j = x0.data()[j];
            const float e = (xj - l.sa * x0j) / l.s1a;  // the noise consistent with the (clipped, steered) x0
            x.data()[j] = l.sap * x0j + l.s1ap * e;
        }
        pin(x);
    }
}
}  // namespace detail

// ---------------------------------------------------------------------------------------------
// Conflict-aware sampling (issue 12): a differentiable cost of a scene's windows (robots too
// close to each other, robots too close to the map, ends far from the goals) that guides every
// DDIM step through its gradient on x0_hat and picks the best of k candidate windows. Options
// of SamplerConfig, off by default.

// Largest SamplerConfig::candidates (the batch grows k-fold).
constexpr int kMaxCandidates = 64;

// A square grid of nodes over the world, (x, y) = (lo + col * cell, lo + row * cell), row-major
// from the lowest y, and bilinear interpolation of values given at its nodes.
struct NodeGrid {
    int nodes = 0;              // per side; 0 = not built
    double lo = 0, cell = 0;    // first node's coordinate on both axes; node spacing (world units)

    // Bilinear interpolation of `values` given at this grid's nodes, and its gradient.
    double interpolate(const std::vector<float>& values, double x, double y, double* gx = nullptr, double* gy = nullptr) const {
        MADBP_ASSERT(nodes >= 2 && values.size() == (size_t)nodes * nodes);
        const double u = (x - lo) / cell, v = (y - lo) / cell;
        const int col = std::clamp((int)std::floor(u), 0, nodes - 2), row = std::clamp((int)std::floor(v), 0, nodes - 2);
        const double fx = u - col, fy = v - row;
        const float* p = values.data() + (size_t)row * nodes + col;
        const double d00 = p[0], d10 = p[1], d01 = p[nodes], d11 = p[nodes + 1];
        if (gx) *gx = ((1 - fy) * (d10 - d00) + fy * (d11 - d01)) / cell;
        if (gy) *gy = ((1 - fx) * (d01 - d00) + fx * (d11 - d10)) / cell;
        return (1 - fy) * ((1 - fx) * d00 + fx * d10) + fy * ((1 - fx) * d01 + fx * d11);
    }
};

// The map's clearance (static_clearance: distance to the nearest obstacle or wall surface,
// world units, negative inside) sampled at the nodes of a square grid of spacing `cell` over the
// world and a border of `pad`, read with bilinear interpolation, which also gives the gradient
// (values continuous; the gradient jumps only across cell lines). Beyond the border a cell's
// plane is extended. At most kMaxNodes a side (a huge world gets coarser cells).
struct DistanceField : NodeGrid {
    static constexpr int kMaxNodes = 512;
    WorldMap map;                    // the map it was built from
    std::vector<float> d;       // (nodes * nodes) clearance at the nodes

    DistanceField() = default;
    explicit DistanceField(const WorldMap& m, double cell_wanted = 0.02, double pad = 0.2) { build(m, cell_wanted, pad); }
    void build(const WorldMap& m, double cell_wanted = 0.02, double pad = 0.2) {
        if (!(cell_wanted > 0) || !(pad >= 0) || !std::isfinite(cell_wanted + pad))
            throw std::invalid_argument("DistanceField: needs cell > 0 and pad >= 0");
        const double span = 2 * (m.half_size + pad);
        nodes = (int)std::min<double>(kMaxNodes, std::ceil(span / cell_wanted) + 1);
        cell = span / (nodes - 1);
        lo = -m.half_size - pad;
        map = m;
        d.resize((size_t)nodes * nodes);
        for (int row = 0; row < nodes; ++row)
            for (int col = 0; col < nodes; ++col) d[(size_t)row * nodes + col] = (float)static_clearance(m, {lo + col * cell, lo + row * cell});
    }
    bool built_for(const WorldMap& m) const { return nodes > 0 && m == map; }
    // Clearance at (x, y), world units; its gradient in *gx, *gy when given.
    double value(double x, double y, double* gx = nullptr, double* gy = nullptr) const { return interpolate(d, x, y, gx, gy); }
};

// What the window cost reads of the map: the clearance field, and the distance to each goal
// around the obstacles (a "goal field": Dijkstra over goal_grid, every kGoalStride-th node of the
// clearance field's each way, 8-connected, a step into a node closer than `radius` to the map
// costing kBlockedFactor times its length), read the same way. Goal fields are made by add_goals
// and kept for the map (at most max_goal_fields(); a new goal takes the place of a field the plan
// does not use).
struct MapFields {
    static constexpr int kMaxGoalFields = 256;
    // And at most this many bytes of them. A field is a float per goal-grid node, up to 264 KB in
    // a world of half-size 6.8 or more, and once every robot of a team of 256 sees its goal a
    // whole episode held 111-118 MB, 64 MB of it goal fields; with 16 MB (63 fields there) it holds
    // 59-61 MB, the robots past the cap keeping the straight-line goal term (docs/speed.md, "Goal
    // fields within 16 MB"). A constant-density team of 64 robots (fields of 131 KB) or any smaller
    // world keeps every field, as before.
    static constexpr size_t kGoalFieldBytes = size_t(16) << 20;
    static constexpr double kBlockedFactor = 20;
    // Goal fields on every other node (cell 0.04 in the standard world): a quarter of the nodes,
    // so a first plan after new goals costs about a warm plan more instead of two; the tuning suite
    // was level (docs/experiments.md, "Goal fields in buckets").
    static constexpr int kGoalStride = 2;
    struct GoalField {
        double x = 0, y = 0;        // the goal, world units (as decoded from a SceneBatch)
        std::vector<float> d;       // (goal_grid.nodes^2) distance to the goal
    };
    DistanceField clearance;
    NodeGrid goal_grid;             // the goal fields' nodes
    std::vector<GoalField> goals;

    // (Re)builds the clearance field, and forgets the goal fields, when the map differs from the last one.
    void set_map(const WorldMap& map) {
        if (clearance.built_for(map)) return;
        clearance.build(map);
        goal_grid.nodes = (clearance.nodes - 1 + kGoalStride - 1) / kGoalStride + 1;
        goal_grid.lo = clearance.lo;
        goal_grid.cell = clearance.cell * kGoalStride;
        goals.clear();
        used_.clear();
        steps_radius_ = -1;  // the step lengths are the old map's
    }
    // How many goal fields are kept on this map: kMaxGoalFields, fewer where that many would pass
    // kGoalFieldBytes.
    int max_goal_fields() const {
        const size_t field_bytes = (size_t)goal_grid.nodes * goal_grid.nodes * sizeof(float);
        return (int)std::clamp<size_t>(kGoalFieldBytes / std::max<size_t>(field_bytes, 1), 1, kMaxGoalFields);
    }
    // The clearance at goal-grid node (row, col): the clearance field's node there (its last
    // row or column where the goal grid reaches past it).
    float clearance_at_goal_node(int row, int col) const {
        const int N = clearance.nodes;
        return clearance.d[(size_t)std::min(row * kGoalStride, N - 1) * N + std::min(col * kGoalStride, N - 1)];
    }
    // The field of the goal at (x, y), matched within kGoalMatch: goals are decoded from a
    // SceneBatch, whose Local frame moves with the robots, so the same goal differs in the last bits.
    static constexpr double kGoalMatch = 1e-4;
    const GoalField* find(double x, double y) const {
        for (const GoalField& g : goals)
            if (std::abs(g.x - x) <= kGoalMatch && std::abs(g.y - y) <= kGoalMatch) return &g;
        return nullptr;
    }
    // Makes the goal fields of every active agent of `batch` that has none yet (real goals only:
    // a route subgoal is in straight view, SceneBatch::goal_final). With max_goal_fields() kept, a new
    // goal takes the place of a field this call's agents do not use; when all are in use, its agent
    // keeps the straight-line goal term (window_cost). Clearing the cache when full, as before
    // 2026-12-04, rebuilt every field every plan once more than kMaxGoalFields robots of a team saw
    // their goals (512 robots among obstacles: 0.6-1.4 s a plan; docs/speed.md).
    void add_goals(const SceneBatch& batch, const ModelConfig& c, double radius) {
        MADBP_ASSERT(clearance.nodes >= 2);
        ++call_;
        used_.resize(goals.size(), 0);
        auto wanted = [&](int a) { return batch.agent_mask[a] != 0 && batch.goal_final[a] != 0; };
        for (int a = 0; a < batch.agents(); ++a) {  // the fields this call uses stay
            if (!wanted(a)) continue;
            const Vec2 g = batch.goal(a, c);
            if (const GoalField* field = find(g.x, g.y)) used_[(size_t)(field - goals.data())] = call_;
        }
        const size_t cap = (size_t)max_goal_fields();
        size_t spare = 0;  // the next field to look at for one this call does not use
        for (int a = 0; a < batch.agents(); ++a) {
            if (!wanted(a)) continue;
            const Vec2 g = batch.goal(a, c);
            if (find(g.x, g.y)) continue;
            size_t slot = goals.size();
            if (slot >= cap) {
                while (spare < goals.size() && used_[spare] == call_) ++spare;
                if (spare == goals.size()) continue;  // every field in use: the straight-line term
                slot = spare;
            } else {
                goals.emplace_back();
                used_.push_back(0);
            }
            goals[slot].x = g.x, goals[slot].y = g.y;
            used_[slot] = call_;
            build_goal(goals[slot], radius);
        }
    }
    // Distance to goal field g's goal at (x, y), and its gradient.
    double goal_distance(const GoalField& g, double x, double y, double* gx = nullptr, double* gy = nullptr) const {
        return goal_grid.interpolate(g.d, x, y, gx, gy);
    }

private:
    std::vector<uint64_t> used_;  // (goals) the add_goals call that last used each field
    uint64_t call_ = 0;
    // Dijkstra's queue as buckets of one cell's width (Dial's algorithm), reused: bucket
    // band % size holds the (distance, node) entries of distance band `band` = floor(d / cell).
    std::vector<std::vector<std::pair<float, int>>> buckets_;
    // Per goal-grid node, the length of a straight and of a diagonal step into it, for steps_radius_.
    std::vector<double> into_straight_, into_diagonal_;
    double steps_radius_ = -1;

    // Dijkstra over the goal grid's nodes from the four around the goal. Every step is at least
    // one cell long, so the nodes of a distance band are final before the band is expanded, and
    // the buckets give a heap's order without its log factor (a goal field of the standard world
    // on every clearance node: 1.7-2.5 ms with a binary heap, 0.4-0.5 ms so; docs/speed.md).
    // Stale entries are skipped.
    void build_goal(GoalField& g, double radius) {
        const NodeGrid& f = goal_grid;
        const int N = f.nodes;
        const size_t nodes = (size_t)N * N;
        if (steps_radius_ != radius) {  // set_map forgets them with the map
            into_straight_.resize(nodes);
            into_diagonal_.resize(nodes);
            for (int row = 0; row < N; ++row)
                for (int col = 0; col < N; ++col) {
                    const double blocked = clearance_at_goal_node(row, col) < radius ? kBlockedFactor : 1.0;
                    into_straight_[(size_t)row * N + col] = 1.0 * f.cell * blocked;
                    into_diagonal_[(size_t)row * N + col] = std::sqrt(2.0) * f.cell * blocked;
                }
            steps_radius_ = radius;
        }
        g.d.assign(nodes, std::numeric_limits<float>::infinity());
        // A step spans at most kBlockedFactor * sqrt(2) cells, so at most that many bands (+2)
        // are open at once: a power of two of buckets at least as many.
        size_t nb = 1;
        while (nb < (size_t)std::ceil(kBlockedFactor * std::sqrt(2.0)) + 2) nb *= 2;
        buckets_.resize(nb);
        for (auto& b : buckets_) b.clear();
        const double per_cell = 1 / f.cell;
        long band = 0, pending = 0;
        auto relax = [&](float dist, int k, double step) {
            const float nd = (float)(dist + step);
            if (nd >= g.d[k]) return;
            g.d[k] = nd;
            const long b = std::max(band, (long)(nd * per_cell));  // never into a band already expanded
            buckets_[(size_t)b & (nb - 1)].push_back({nd, k});
            ++pending;
        };
        // Seed the four nodes around the goal with their straight-line distances.
        const int c0 = std::clamp((int)std::floor((g.x - f.lo) / f.cell), 0, N - 2), r0 = std::clamp((int)std::floor((g.y - f.lo) / f.cell), 0, N - 2);
        for (int dr = 0; dr <= 1; ++dr)
            for (int dc = 0; dc <= 1; ++dc) relax(0, (r0 + dr) * N + c0 + dc, std::hypot(f.lo + (c0 + dc) * f.cell - g.x, f.lo + (r0 + dr) * f.cell - g.y));
        const int straight[4] = {-N, -1, 1, N}, diagonal[4] = {-N - 1, -N + 1, N - 1, N + 1};
        for (; pending > 0; ++band) {
            std::vector<std::pair<float, int>>& bucket = buckets_[(size_t)band & (nb - 1)];
            for (size_t i = 0; i < bucket.size(); ++i) {  // by index: a rounding-short step may append to this band
                const auto [dist, k] = bucket[i];
                --pending;
                if (dist > g.d[k]) continue;
                const int row = k / N, col = k % N;
                if (row > 0 && row < N - 1 && col > 0 && col < N - 1) {  // all eight neighbours exist
                    for (int o : straight) relax(dist, k + o, into_straight_[(size_t)(k + o)]);
                    for (int o : diagonal) relax(dist, k + o, into_diagonal_[(size_t)(k + o)]);
                    continue;
                }
                for (int dr = -1; dr <= 1; ++dr)
                    for (int dc = -1; dc <= 1; ++dc) {
                        const int r2 = row + dr, c2 = col + dc;
                        if ((dr == 0 && dc == 0) || r2 < 0 || r2 >= N || c2 < 0 || c2 >= N) continue;
                        const int k2 = r2 * N + c2;
                        relax(dist, k2, dr && dc ? into_diagonal_[(size_t)k2] : into_straight_[(size_t)k2]);
                    }
            }
            bucket.clear();
        }
    }
};

// The cost of one scene's windows, world units. Waypoints of active agent a:
// P_a(t) = p_a + window_scale * x_a(t), t = 1 .. H-1 (t = 0 is the current position p_a):
//   agent_weight * sum over pairs a < b and t of max(0, 2 radius + agent_margin - |P_a(t) - P_b(t)|)^2
// + map_weight   * sum over a and t of max(0, radius + map_margin - clearance(P_a(t)))^2
// + goal_weight  * sum over a of dist(P_a(H-1), g_a)     (g_a: a's goal or route subgoal)
// where dist is the distance around the obstacles (MapFields' goal field) with `geodesic` and a
// goal field made for g_a (real goals only), else sqrt(|P - g|^2 + 0.01^2). Squared hinges, so the cost is smooth
// where they switch on. Every weight and margin >= 0.
struct WindowCost {
    float radius = 0.1f;         // robot radius, world units (WorldConfig::radius)
    float agent_margin = 0.05f;  // extra distance wanted between two robots' surfaces
    float map_margin = 0.03f;    // extra distance wanted between a robot's surface and the map
    float agent_weight = 100.f;
    float map_weight = 100.f;
    float goal_weight = 200.f;   // (the weights: tuned with guidance 0.004 on seeds 1000-1099, docs/experiments.md)
    bool geodesic = true;        // the goal term measures around the obstacles (goal fields)
};

// Relative speed (world units over two waypoints) below which the keep-right push fades in
// proportion: robots barely moving relative to each other have no side to pass on.
constexpr double kKeepRightFade = 0.05;

// The WindowCost of scene s's windows x (2, H*A) (normalised displacements, agent-major, as
// sample_windows writes them) in `batch`; the map comes from `fields` (set_map; goal fields from
// add_goals, else the goal term is straight-line). With `grad`
// (2, H*A), ADDS d cost / d x to the columns of scene s's active agents, t >= 1.
// With `grad` and keep_right > 0 it also adds the keep-right push (SamplerConfig::keep_right),
// which is not the gradient of any cost: for two waypoints within 2 radius + agent_margin of
// each other, h = that reach - their distance, and v = the pair's relative motion there (a's
// waypoints t+1 minus t-1, minus b's), a is pushed by keep_right * h along v turned right
// (unit, fading below kKeepRightFade), b by the opposite; in `grad` as minus those pushes. The
// returned cost does not change. Unequal SceneBatch::priority splits both pair terms of `grad`:
// a takes 2 p_b / (p_a + p_b) of its share, b 2 p_a / (p_a + p_b) (the higher gives way less;
// then not the cost's gradient either).
inline double window_cost(const SceneBatch& batch, int s, const Mat& x, const ModelConfig& c, const WindowCost& w,
                          const MapFields& fields, Mat* grad = nullptr, float keep_right = 0) {
    const DistanceField& field = fields.clearance;
    const int n = batch.n, H = c.horizon;
    const double ps = c.position_scale, ws = c.window_scale;
    MADBP_ASSERT(s >= 0 && s < batch.B && x.cols() == (long)H * batch.agents());
    MADBP_ASSERT(!grad || (grad->rows() == 2 && grad->cols() == x.cols()));
    auto P = [&](int a, int t, int k) {  // waypoint t of agent a, world units
        const Vec2& o = batch.origin[a / n];
        return (k ? o.y : o.x) + batch.pose(k, a) * ps + ws * x(k, (long)a * H + t);
    };
    auto add = [&](int a, int t, double dx, double dy) {  // d cost / d P -> d cost / d x
        (*grad)(0, (long)a * H + t) += (float)(ws * dx);
        (*grad)(1, (long)a * H + t) += (float)(ws * dy);
    };
    double cost = 0;
    const double reach = 2.0 * w.radius + w.agent_margin, keep = (double)w.radius + w.map_margin, smooth2 = 1e-4;
    for (int i = 0; i < n; ++i) {
        const int a = s * n + i;
        if (batch.agent_mask[a] == 0) continue;
        for (int j = i + 1; j < n; ++j) {  // robots too close to each other
            const int b = s * n + j;
            if (batch.agent_mask[b] == 0) continue;
            // The pair's pushes split by priority (2 pb / (pa + pb) of a's, equal: 1 each).
            const double pa = batch.priority[a], pb = batch.priority[b], share_a = 2 * pb / (pa + pb), share_b = 2 * pa / (pa + pb);
            for (int t = 1; t < H; ++t) {
                const double dx = P(a, t, 0) - P(b, t, 0), dy = P(a, t, 1) - P(b, t, 1), dist = std::sqrt(dx * dx + dy * dy);
                const double h = reach - dist;
                if (h <= 0) continue;
                cost += w.agent_weight * h * h;
                if (grad && dist > 1e-12) {
                    const double g = -2.0 * w.agent_weight * h / dist;  // d cost / d P_a = g * (P_a - P_b)
                    add(a, t, share_a * g * dx, share_a * g * dy);
                    add(b, t, -share_b * g * dx, -share_b * g * dy);
                }
                if (grad && keep_right > 0) {
                    // A head-on pair's push above is along the line between them, which can only
                    // stop both; a push to the right of their relative motion makes them pass.
                    const int t1 = std::min(t + 1, H - 1);
                    const double vx = P(a, t1, 0) - P(a, t - 1, 0) - (P(b, t1, 0) - P(b, t - 1, 0));
                    const double vy = P(a, t1, 1) - P(a, t - 1, 1) - (P(b, t1, 1) - P(b, t - 1, 1));
                    const double k = keep_right * h / std::max(std::sqrt(vx * vx + vy * vy), kKeepRightFade);
                    add(a, t, -share_a * k * vy, share_a * k * vx);  // a's push k (vy, -vx): v turned right
                    add(b, t, share_b * k * vy, -share_b * k * vx);
                }
            }
        }
        for (int t = 1; t < H; ++t) {  // robots too close to the map
            double gx = 0, gy = 0;
            const double h = keep - field.value(P(a, t, 0), P(a, t, 1), &gx, &gy);
            if (h <= 0) continue;
            cost += w.map_weight * h * h;
            if (grad) add(a, t, -2.0 * w.map_weight * h * gx, -2.0 * w.map_weight * h * gy);
        }
        // The window's end far from the goal.
        const Vec2 goal = batch.goal(a, c);
        const double goal_x = goal.x, goal_y = goal.y;
        const MapFields::GoalField* gf = w.geodesic && batch.goal_final[a] != 0 ? fields.find(goal_x, goal_y) : nullptr;
        if (gf) {
            double gx = 0, gy = 0;
            cost += w.goal_weight * fields.goal_distance(*gf, P(a, H - 1, 0), P(a, H - 1, 1), &gx, &gy);
            if (grad) add(a, H - 1, w.goal_weight * gx, w.goal_weight * gy);
            continue;
        }
        const double ex = P(a, H - 1, 0) - goal_x, ey = P(a, H - 1, 1) - goal_y;
        const double q = std::sqrt(ex * ex + ey * ey + smooth2);
        cost += w.goal_weight * q;
        if (grad) add(a, H - 1, w.goal_weight * ex / q, w.goal_weight * ey / q);
    }
    return cost;
}

namespace detail {
// dst sized for B scenes shaped like src's (agent slots, grid and crop sizes), its shared grid
// copied; every other value is left for copy_scene.
inline void size_like(const SceneBatch& src, int B, SceneBatch& dst) {
    const int n = src.n;
    const long G2 = src.grid.cols() / src.grid_scenes(), L = src.agents() ? src.local.cols() / src.agents() : 0;
    dst.B = B;
    dst.n = n;
    dst.shared_grid = src.shared_grid;
    dst.agent_mask.resize((size_t)B * n);
    dst.slot.resize((size_t)B * n);
    dst.count.resize(B);
    dst.pose.resize(src.pose.rows(), (long)B * n);
    dst.grid.resize(1, G2 * dst.grid_scenes());
    dst.local.resize(1, L * B * n);
    dst.origin.resize(B);
    dst.goal_final.resize((size_t)B * n);
    dst.priority.resize((size_t)B * n);
    dst.noise_seed.resize(src.noise_seed.empty() ? 0 : B);
    if (src.shared_grid) dst.grid = src.grid;
}
// Scene b of src as scene d of dst (sized by size_like), its noise seed included.
inline void copy_scene(const SceneBatch& src, int b, SceneBatch& dst, int d) {
    const int n = src.n;
    const long G2 = src.grid.cols() / src.grid_scenes(), L = src.agents() ? src.local.cols() / src.agents() : 0;
    dst.count[d] = src.count[b];
    dst.origin[d] = src.origin[b];
    if (!src.noise_seed.empty()) dst.noise_seed[d] = src.noise_seed[b];
    if (!src.shared_grid) dst.grid.middleCols((long)d * G2, G2) = src.grid.middleCols((long)b * G2, G2);
    for (int i = 0; i < n; ++i) {
        const int from = b * n + i, to = d * n + i;
        dst.agent_mask[to] = src.agent_mask[from];
        dst.slot[to] = src.slot[from];
        dst.goal_final[to] = src.goal_final[from];
        dst.priority[to] = src.priority[from];
        dst.pose.col(to) = src.pose.col(from);
        if (L) dst.local.middleCols((long)to * L, L) = src.local.middleCols((long)from * L, L);
    }
}
}  // namespace detail

// The scenes of `src` repeated k times into dst: scene b's copy j is scene b * k + j.
inline void repeat_scenes(const SceneBatch& src, int k, SceneBatch& dst) {
    detail::size_like(src, src.B * k, dst);
    for (int b = 0; b < src.B; ++b)
        for (int j = 0; j < k; ++j) {
            const int d = b * k + j;
            detail::copy_scene(src, b, dst, d);
            if (!src.noise_seed.empty()) dst.noise_seed[d] = src.noise_seed[b] + 0x9E3779B97F4A7C15ull * (uint64_t)j;  // candidates differ
        }
}

// Scenes first .. first + count - 1 of `src` as a batch of their own in dst.
inline void slice_scenes(const SceneBatch& src, int first, int count, SceneBatch& dst) {
    MADBP_ASSERT(first >= 0 && count >= 0 && first + count <= src.B);
    detail::size_like(src, count, dst);
    for (int d = 0; d < count; ++d) detail::copy_scene(src, first + d, dst, d);
}

// Workspaces of conflict-aware sampling, reused across draws (no heap allocation once sizes are
// steady), and after a draw what it chose: the cost of every candidate and the one kept.
struct ConflictWorkspace {
    MapFields fields;          // the map's clearance and goal fields: set_map(); goal fields made while sampling
    // When set, the map's fields are read from here, never changed, instead of from `fields`
    // (threads sampling parts of one plan share one set; its goal fields are made beforehand).
    const MapFields* shared_fields = nullptr;
    const MapFields& map_fields() const { return shared_fields ? *shared_fields : fields; }
    SceneBatch batch;          // the scenes repeated k times (repeat_scenes); unused when k = 1
    Mat x, out, grad;          // (2, H*A*k): every candidate's windows after the draw in x
    std::vector<int> steps;
    std::vector<double> cost;  // (B*k) final WindowCost of each candidate, scene b's candidate j at b*k + j
    std::vector<int> best;     // (B) the candidate kept for each scene: the first of the lowest cost
    // (Re)builds the map's fields when the map differs from the last one.
    void set_map(const WorldMap& map) { fields.set_map(map); }
};

// Sampling options (SPEC 6, paper Alg. 2) of sample_windows. Its defaults are plain DDIM, the
// paper's sampler; the planner makes its own from PlannerConfig (PlannerConfig::sampler_config).
struct SamplerConfig {
    int sample_steps = 10;       // S, DDIM steps (eta = 0), in [1, K]
    float x0_clip = 1.5f;        // x0_hat clipped to [-x0_clip, x0_clip] (normalised displacements; Diffuser's clip_denoised)
    bool goal_inpaint = true;    // pin the window's last waypoint to the goal when it is within reach
    float goal_reach = 0.55f;    // "within reach": distance to goal in world units at most this (see default_goal_reach)
    // Conflict-aware sampling (issue 12), off by default: with guidance = 0 and candidates = 1
    // the sampler is the plain DDIM below, bit for bit. Both read the map through a
    // ConflictWorkspace (sample_windows' last argument; DiffusionPlanner keeps one).
    float guidance = 0;          // W >= 0: every DDIM step moves each predicted waypoint of x0_hat by
                                 // -W * d cost / d waypoint (world units; cost: WindowCost)
    int candidates = 1;          // k in [1, kMaxCandidates]: windows drawn per scene in one batch; the lowest-cost one is kept
    WindowCost cost;             // the cost both use
    // With guidance > 0: robots whose waypoints come within 2 radius + agent_margin of each other
    // are also pushed apart sideways, each to the right of their relative motion (window_cost),
    // so a head-on pair passes instead of stopping nose to nose. Not a cost gradient; 0 = off.
    float keep_right = 0;
    // In [0, 1]: after the draw, a window whose end is pinned to the goal (goal_inpaint) and whose
    // waypoint H-2 is nearer that goal than the robot is has its free waypoints t = 1 .. H-2
    // moved by end_bend * t / (H-2) * (goal - waypoint H-2): it arrives instead of stopping short
    // and jumping to the goal at its last waypoint. A window that leaves its goal (a robot making
    // way) is kept. 0 = off (the planner's: PlannerConfig::sampler.end_bend).
    float end_bend = 0;
    // W >= 0: given warm windows (sample_windows' `warm`: DiffusionPlanner passes each robot's
    // last window, shifted to now), DDIM runs only its last W steps, starting from the
    // warm windows noised to that step's level (SDEdit) instead of from pure noise: a robot keeps
    // the way it chose (which side, who goes first) unless the model pulls it off, and a plan
    // costs W / S of the network evaluations. 0, or W >= S (every step) = off.
    int warm_start = 0;
    bool warm_starts() const { return warm_start > 0 && warm_start < sample_steps; }  // warm_start is on
    bool conflict_aware() const { return guidance != 0 || candidates != 1; }
    // Throws std::invalid_argument naming the first field out of range; K: the model's diffusion
    // steps. sample_windows calls it, whichever path the options take.
    void validate(int K) const {
        auto bad = [](const std::string& field, const std::string& rule, double v) {
            throw std::invalid_argument("sampler " + field + ": must be " + rule + " (got " + number_text(v) + ")");
        };
        if (sample_steps < 1 || sample_steps > K) bad("sample_steps", "in [1, " + std::to_string(K) + "]", sample_steps);
        if (!(x0_clip > 0) || !std::isfinite(x0_clip)) bad("x0_clip", "a finite number > 0", x0_clip);
        if (!(goal_reach >= 0) || !std::isfinite(goal_reach)) bad("goal_reach", "a finite number >= 0", goal_reach);
        if (!(guidance >= 0) || !std::isfinite(guidance)) bad("guidance", "a finite number >= 0", guidance);
        if (candidates < 1 || candidates > kMaxCandidates) bad("candidates", "in [1, kMaxCandidates = " + std::to_string(kMaxCandidates) + "]", candidates);
        if (!(keep_right >= 0) || !std::isfinite(keep_right)) bad("keep_right", "a finite number >= 0", keep_right);
        if (!(end_bend >= 0 && end_bend <= 1)) bad("end_bend", "in [0, 1]", end_bend);
        if (warm_start < 0) bad("warm_start", ">= 0", warm_start);
        const std::pair<const char*, float> weights[] = {{"cost.radius", cost.radius},           {"cost.agent_margin", cost.agent_margin},
                                                         {"cost.map_margin", cost.map_margin},   {"cost.agent_weight", cost.agent_weight},
                                                         {"cost.map_weight", cost.map_weight},   {"cost.goal_weight", cost.goal_weight}};
        for (const auto& [field, v] : weights)
            if (!(v >= 0) || !std::isfinite(v)) bad(field, "a finite number >= 0", v);
    }
};

namespace detail {
// The pinned waypoints re-imposed on windows x (2, H*A): every active agent's t = 0 at its
// position (zero displacement), its last waypoint at its goal when the goal is pinned
// (end_pinned, with goal inpainting on); inactive agents' windows zeroed.
inline void impose_pins(const SceneBatch& batch, const ModelConfig& c, const SamplerConfig& sc, Mat& x) {
    const int H = c.horizon;
    for (int a = 0; a < batch.agents(); ++a) {
        auto w = x.middleCols((long)a * H, H);
        if (batch.agent_mask[a] == 0) { w.setZero(); continue; }
        w.col(0).setZero();
        Eigen::Vector2f end;
        if (sc.goal_inpaint && end_pinned(batch, a, c, sc.goal_reach, &end)) w.col(H - 1).head<2>() = end;  // a fixed-size target: no vector loads past `end`
    }
}

// SamplerConfig::end_bend on drawn windows x (2, H*A). The model's windows near a goal often
// end 0.05-0.15 short of it, or stay put with others about, and only the inpainted last
// waypoint is at the goal; the tracker follows the first replan steps, so the robot never gets there.
inline void bend_to_pinned_ends(const SceneBatch& batch, const ModelConfig& c, const SamplerConfig& sc, Mat& x) {
    const int H = c.horizon;
    if (sc.end_bend <= 0 || !sc.goal_inpaint || H < 3) return;
    for (int a = 0; a < batch.agents(); ++a) {
        Eigen::Vector2f end;
        if (batch.agent_mask[a] == 0 || !end_pinned(batch, a, c, sc.goal_reach, &end)) continue;
        auto w = x.middleCols((long)a * H, H);
        const Eigen::Vector2f gap = end - w.col(H - 2).head<2>();
        if (gap.norm() >= end.norm()) continue;  // not heading for the goal (t = 0 is the robot, at 0)
        for (int t = 1; t <= H - 2; ++t) w.col(t).head<2>() += gap * (sc.end_bend * (float)t / (float)(H - 2));
    }
}

// The starting noise x (2, H*A) ~ N(0, I): from `rng`, or with batch.noise_seed each scene's
// columns from its own stream (so a scene draws the same noise in any batch).
inline void draw_noise(const SceneBatch& batch, int H, Rng& rng, Mat& x) {
    x.resize(2, (long)H * batch.agents());
    if (batch.noise_seed.empty()) {
        for (long j = 0; j < x.size(); ++j) x.data()[j] = (float)rng.normal();
        return;
    }
    MADBP_ASSERT((int)batch.noise_seed.size() == batch.B);
    const long per_scene = 2L * H * batch.n;
    for (int b = 0; b < batch.B; ++b) {
        Rng scene_rng(batch.noise_seed[b]);
        for (long j = 0; j < per_scene; ++j) x.data()[b * per_scene + j] = (float)scene_rng.normal();
    }
}

// The first DDIM step s of a draw: S from pure noise x, or with `warm` (2, H*B*n) and
// sc.warm_start > 0, warm_start from x = sqrt(ab) warm + sqrt(1 - ab) x at that step's level,
// each of the k candidates of scene b (x's scene b*k + j) from scene b's warm window.
inline int warm_from(const NoiseSchedule& schedule, const SamplerConfig& sc, const Mat* warm, long scene_cols, int k, Mat& x) {
    if (!warm || !sc.warm_starts()) return sc.sample_steps;
    if (warm->rows() != 2 || warm->cols() * k != x.cols()) throw std::invalid_argument("sampler: warm windows must be 2 x " + std::to_string(x.cols() / k) + " (2, H * agents), got " +
                                    std::to_string(warm->rows()) + " x " + std::to_string(warm->cols()));
    const double ab = schedule.alpha_bar[schedule.ddim_step(sc.warm_start, sc.sample_steps)];
    const float sa = (float)std::sqrt(ab), s1a = (float)std::sqrt(1 - ab);
    const long B = warm->cols() / scene_cols;
    for (long b = 0; b < B; ++b)
        for (int j = 0; j < k; ++j) {
            auto xs = x.middleCols((b * k + j) * scene_cols, scene_cols);
            xs = sa * warm->middleCols(b * scene_cols, scene_cols) + s1a * xs;
        }
    return sc.warm_start;
}

// The warm window (SamplerConfig::warm_start) of a robot at `pos` from its last window, made
// `elapsed` world steps ago (world waypoints for the steps 1, 2, ... after it was made): x's
// columns col .. col + H - 1 get, as normalised displacements from `pos`, 0 and then the last
// window's waypoints for the steps elapsed + t * stride (waypoint_now: its last past its end).
// False, x untouched, when there is no such window (elapsed outside [1, its length - 1]).
inline bool warm_window(const std::vector<Vec2>& last, long elapsed, Vec2 pos, const ModelConfig& c, Mat& x, long col) {
    if (elapsed < 1 || elapsed >= (long)last.size()) return false;
    x.col(col).setZero();
    for (int t = 1; t < c.horizon; ++t) {
        const Vec2 d = waypoint_now(last, (int)elapsed + t * c.waypoint_stride) - pos;
        x(0, col + t) = (float)(d.x / c.window_scale);
        x(1, col + t) = (float)(d.y / c.window_scale);
    }
    return true;
}

// The denoiser's clipped x0_hat for x at DDIM levels l (its eps turned into x0 for an eps model),
// every scene at step l.k: the plain sampler's prediction, which the guided one then steers.
template <class Denoiser>
void x0_prediction(Denoiser& model, const Mat& x, const DdimLevels& l, const SamplerConfig& sc, std::vector<int>& steps, Mat& x0) {
    std::fill(steps.begin(), steps.end(), l.k);
    model.denoise(x, steps.data(), x0);
    const bool eps_mode = model.config.prediction == Prediction::Eps;
    float* p = x0.data();
    for (long j = 0; j < x.size(); ++j) p[j] = std::clamp(eps_mode ? (x.data()[j] - l.s1a * p[j]) / l.sa : p[j], -sc.x0_clip, sc.x0_clip);
}

// sample_windows with SamplerConfig::guidance and candidates: the batch's scenes repeated k
// times (repeat_scenes) and denoised together; at every DDIM step the clipped x0_hat takes one
// gradient step on its WindowCost (scaled so that a waypoint moves -W * d cost / d waypoint
// world units), clipped again, and the DDIM update uses the guided x0_hat; pins as in plain
// sampling. Then each scene keeps its lowest-cost candidate: x (2, H*A) of `batch`.
template <class Denoiser>
void sample_conflict_aware(Denoiser& model, const NoiseSchedule& schedule, const SceneBatch& batch, const SamplerConfig& sc, Rng& rng,
                           Mat& x_best, ConflictWorkspace& cw, const Mat* warm) {
    const ModelConfig& c = model.config;
    const int H = c.horizon, B = batch.B, n = batch.n, S = sc.sample_steps, k = sc.candidates;
    const WindowCost& wc = sc.cost;
    if (wc.geodesic && wc.goal_weight > 0 && !cw.shared_fields) cw.fields.add_goals(batch, c, wc.radius);  // new goals only
    const MapFields& fields = cw.map_fields();
    if (k > 1) repeat_scenes(batch, k, cw.batch);
    const SceneBatch& rb = k > 1 ? cw.batch : batch;
    const int Bk = rb.B;
    model.encode_context(rb);
    Mat& x = cw.x;
    draw_noise(rb, H, rng, x);
    const int s_top = warm_from(schedule, sc, warm, (long)n * H, k, x);
    impose_pins(rb, c, sc, x);
    cw.steps.resize(Bk);
    // d x0 = -W / window_scale^2 * d cost / d x0 moves a waypoint by -W * d cost / d P (world units).
    const float step_size = (float)(sc.guidance / ((double)c.window_scale * c.window_scale));
    auto guided_x0 = [&](const DdimLevels& l, Mat& x0) {  // x0 is cw.out: window_cost reads it
        x0_prediction(model, x, l, sc, cw.steps, x0);
        if (sc.guidance > 0) {
            cw.grad.setZero(2, x.cols());
            for (int b = 0; b < Bk; ++b) window_cost(rb, b, x0, c, wc, fields, &cw.grad, sc.keep_right);
            float* p = x0.data();
            for (long j = 0; j < x.size(); ++j) p[j] = std::clamp(p[j] - step_size * cw.grad.data()[j], -sc.x0_clip, sc.x0_clip);
        }
    };
    ddim_loop(schedule, S, s_top, x, cw.out, guided_x0, [&](Mat& xs) { impose_pins(rb, c, sc, xs); });
    // Best of k: each scene keeps its first lowest-cost candidate.
    cw.cost.resize(Bk);
    cw.best.resize(B);
    for (int b = 0; b < Bk; ++b) cw.cost[b] = window_cost(rb, b, x, c, wc, fields);
    x_best.resize(2, (long)H * B * n);
    for (int b = 0; b < B; ++b) {
        int best = 0;
        for (int j = 1; j < k; ++j)
            if (cw.cost[(size_t)b * k + j] < cw.cost[(size_t)b * k + best]) best = j;
        cw.best[b] = best;
        x_best.middleCols((long)b * n * H, (long)n * H) = x.middleCols((long)(b * k + best) * n * H, (long)n * H);
    }
}
}  // namespace detail

// Draws windows for a batch of scenes with DDIM: x (2, H*A) starts as N(0, I); after every
// step the pinned waypoints are re-imposed and inactive agents are zeroed (paper Alg. 2).
// `model.encode_context(batch)` is called here. Output: normalised displacements. `out` is the
// denoiser's scratch (after a plain draw it holds the last step's clipped x0_hat).
// Denoiser: MadbpModel, or anything with `config`, encode_context(batch), denoise(x, k, out).
// With sc.conflict_aware() the draw is guided and/or best-of-k (detail::sample_conflict_aware)
// and needs `cw` with the map's distance field (ConflictWorkspace::set_map); all scenes of the
// batch share that map, as the planner's do. `out` is then untouched.
template <class Denoiser>
void sample_windows(Denoiser& model, const NoiseSchedule& schedule, const SceneBatch& batch, const SamplerConfig& sc,
                    Rng& rng, Mat& x, Mat& out, std::vector<int>& step_buf, ConflictWorkspace* cw = nullptr, const Mat* warm = nullptr) {
    sc.validate(schedule.K);
    if (sc.conflict_aware()) {
        if (!cw || cw->map_fields().clearance.nodes == 0)
            throw std::invalid_argument("sampler: guidance and candidates need a ConflictWorkspace holding the map's distance field (set_map)");
        detail::sample_conflict_aware(model, schedule, batch, sc, rng, x, *cw, warm);
        detail::bend_to_pinned_ends(batch, model.config, sc, x);
        return;
    }
    const ModelConfig& c = model.config;
    const int H = c.horizon, B = batch.B, S = sc.sample_steps;
    model.encode_context(batch);
    detail::draw_noise(batch, H, rng, x);
    const int s_top = detail::warm_from(schedule, sc, warm, (long)batch.n * H, 1, x);
    detail::impose_pins(batch, c, sc, x);
    step_buf.resize(B);
    detail::ddim_loop(schedule, S, s_top, x, out, [&](const detail::DdimLevels& l, Mat& x0) { detail::x0_prediction(model, x, l, sc, step_buf, x0); },
                      [&](Mat& xs) { detail::impose_pins(batch, c, sc, xs); });
    detail::bend_to_pinned_ends(batch, c, sc, x);
}

// =============================================================================================
// Section 7. Planner settings: PlannerConfig, its presets and its table
// =============================================================================================

// One-lane passages (Section 8): whether robots take turns there, and how the passages are found
// and queued. PassageControl reads the passage fields; the planner reads take_turns and
// passage_replan.
struct TrafficConfig {
    bool take_turns = true;        // robots that would meet head-on in a one-lane passage take turns (false: each heads for its goal)
    bool make_way = true;          // a robot parked in a passage leaves it ahead of a robot passing through (PassageControl)
    bool queue_in_order = true;    // a robot behind one queueing at a mouth queues too, though it would enter after the holder left
    bool pocket_order = false;     // a robot whose goal would close off a pocket (a dead end) others' routes enter waits beside it until they pass (the expert: true)
    int passage_replan = 4;        // while robots may meet in a passage, a plan asks to be replaced after this many steps (0: never)
    double one_lane_width = 0.47;  // passages narrower than this, wall to wall, are one-lane (on the grid: 0.45 always, 0.50 never)
    // A robot's centre fits where the clearance is >= this: RouteClearance::min, so a 0.25-wide
    // aisle (a MovingAI map's one-cell aisle at cell 0.25) leaves a 0.046 band, which the 0.036
    // cells always hold, and is taken in turns wherever it falls (0.12, before 0.4: a 0.01 band,
    // held at about a quarter of wall offsets; docs/experiments.md, "Aisles as passages").
    double free_clear = kPassableClearance;
    double lookahead = 1.2;        // a robot claims the first passage within this distance along its route
    double spare = 0;              // a claim from another mouth waits if it would enter before a holder is this far out
    double wait_back = 0.45;       // the nearest waiting robot waits this far out from its mouth,
    double queue_spacing = 0.3;    // each next one this much farther,
    double wait_side = 0.25;       // and this far to the right of the way in
    double min_length = 0.5;       // only passages whose mouths are this far apart (corridors, not doorways);
    double bypass = 1.0;           // one with a way around at most this much longer is avoidable:
    bool go_around = true;         // robots that would wait go around it (false: it is no passage)
    double spread = 0.3;           // and take its two sides in turn: each the side whose way, plus this per
                                   // robot already going that side, is shortest (0: all the shortest way)
    // Routes around crowds (CrowdRoutes), in a team larger than a scene, at least crowd_density
    // robots per square world unit, in a world larger than the training world: a coarse cell's
    // step costs 1 + crowd_weight x the robots routed through it per its free area (0: every robot
    // heads straight along its map route). Among obstacles at issue 47's density (1.4 a square
    // unit) 0.04 lifts 32 / 64 / 128 / 256 robots from .98 / .94 / .88 / .87 to 1.00 / .98 / .94 /
    // .93 (docs/evaluation.md, "Crowds at constant density"). Sparser teams (MovingAI maps with 32
    // robots: 0.09-0.5 a square unit) keep their map routes: there are no crowds to go around, and
    // the routes' small detours would change their plans for nothing.
    double crowd_weight = 0.04;
    double crowd_density = 1.0;    // robots per square world unit (the world's (2 half_size)^2) from which they act
    double crowd_cell = 0.6;       // the coarse cells' side, world units
    double crowd_detour = 0;       // > 0: a route around crowds longer than this times the straight way is not taken
    // In a team of crowd_time_from robots or more, a route counts in a cell only within about
    // crowd_time steps of when its robot is due there at cruise, and a cell costs 1 +
    // crowd_time_weight per robot due there per its free area. Counted wherever a route passes,
    // the demand in the middle grows with the world's side, and so do the detours of the long
    // trips an episode ends with: among obstacles, 1024 robots 16 of 20 counted wherever, 18 of
    // 20 in time, 512 robots in 9 % fewer steps; at 256 robots the two do not separate
    // (docs/experiments.md, "Routes in time from 512 robots").
    double crowd_time = 25;        // steps (0: routes count wherever they pass, in every team)
    int crowd_time_from = 512;     // robots
    double crowd_time_weight = 0.1;
};

// Everything a plan uses, each default written once, here: who plans with whom, the sampler, its
// guidance, the traffic conventions and the follower that executes the plans. The defaults are
// the tuned planner (PlannerConfig::tuned(), tuned on seeds 1000-1999; what each setting bought:
// docs/experiments.md); PlannerConfig::paper() is the paper's planner. planner_settings() lists
// every field with its range and meaning: validate(), set() and the tool's --set and
// --list-settings all read that one table.
struct PlannerConfig {
    struct Neighbourhood {
        // Robots per scene K: each robot's window comes from its own scene of itself and its K-1
        // nearest within sensing_radius (n scenes sampled as one batch), so the model never attends
        // over more robots than it saw in training; 0: the whole team in one scene (the paper's).
        // -1 (automatic): K = ceil(1.5 n_train_max) (n_max when unknown; at most n_max) when the
        // world is larger than the training world or the team larger than n_max, else one scene.
        int neighbours = -1;
        double sensing_radius = 0;  // world units; 0 (automatic): 2 position_scale, the training world's width
        // Neighbourhood scenes cover the team (the windows of each computed about once a plan):
        // an uncovered robot's scene (it and its K-1 nearest) keeps the windows of its first
        // `cover` robots not yet covered (all of them when the scene is the whole team). 0: a
        // scene per robot, keeping only that robot's window (every window computed K times).
        int cover = 3;
    } neighbourhood;
    // How a plan's scenes are sampled: in chunks of chunk_scenes, each chunk on one thread with
    // its own workspace (set_num_threads), so the workspace is bounded by the chunk, not the team.
    // The chunk size, not the thread count, fixes the arithmetic: plans are the same on any
    // number of threads.
    struct Workspace {
        int chunk_scenes = 4;  // smaller chunks were as fast or faster on one core (docs/speed.md)
        double max_mb = 1024;  // a plan whose workspace (planner_workspace_bytes) would exceed this is refused
    } workspace;
    struct Sampler {
        int sample_steps = 8;            // DDIM steps S, at most the model's own; 0: the model's own
        int warm_start = 4;              // run the last W of S steps from each robot's last window (0: off)
        bool line_start = true;          // a robot without a last window warm-starts from a straight line
        int candidates = 1;              // best of k windows per scene
        int small_plan_candidates = 2;   // at least this many for a plan of <= kSmallPlanWindows robot windows
        float end_bend = 1;              // bend a window that stops short of a goal within reach to arrive (0: off)
        bool goal_inpaint = SamplerConfig{}.goal_inpaint;  // pin the last waypoint to a goal within reach
        float goal_reach = -1;           // "within reach", world units; -1 (automatic): default_goal_reach
        float x0_clip = SamplerConfig{}.x0_clip;
    } sampler;
    struct Guidance {
        float weight = 0.004f;   // each DDIM step moves x0_hat's waypoints by -weight * d cost / d waypoint (0: plain DDIM)
        float keep_right = 500;  // robots meeting in the guided windows are pushed to the right of their relative motion
        // >= 1: in a team larger than a scene, each scene's robot of first priority (priority_order:
        // longest way when first seen) is pushed this many times less than its last (1: all alike).
        float priority = 4;
        WindowCost cost;         // the cost the guidance descends and best-of-k ranks
    } guidance;
    TrafficConfig traffic;
    FollowerConfig follower;     // how PlanFollower executes the plans (make_follower)

    // Today's planner, the default.
    static PlannerConfig tuned() { return PlannerConfig{}; }
    // The paper's planner: plain DDIM with goal inpainting in the model's own S steps from noise,
    // one window per scene, no guidance, keep-right, end bend or traffic rules; the SPEC 8
    // follower (no lookahead, no early replans, equal filter weights, SPEC 3.2's barrier rate).
    static PlannerConfig paper() {
        PlannerConfig p;
        p.neighbourhood.cover = 0;
        p.sampler.sample_steps = 0;
        p.sampler.warm_start = 0;
        p.sampler.line_start = false;
        p.sampler.small_plan_candidates = 1;
        p.sampler.end_bend = 0;
        p.guidance.weight = 0;
        p.guidance.keep_right = 0;
        p.guidance.priority = 1;
        p.traffic.take_turns = false;
        p.traffic.passage_replan = 0;
        p.traffic.crowd_weight = 0;
        p.follower.priority_weight = 1;
        p.follower.lookahead = 0;
        p.follower.replan_error = 0;
        p.follower.unjam = 0;
        p.follower.replan_every = 8;  // SPEC 8: half the shipped model's window
        p.follower.filter = SafetyFilterParams{};
        return p;
    }
    // A preset by name: "tuned" or "paper".
    static PlannerConfig preset(const std::string& name) {
        if (name == "tuned") return tuned();
        if (name == "paper") return paper();
        throw std::invalid_argument("planner preset '" + printable(name) + "': expected tuned or paper");
    }

    // Throws std::invalid_argument naming the first setting out of its range.
    inline void validate() const;
    // Sets one setting by its table name ("guidance.weight") from text ("0.004", "auto", "true").
    inline void set(const std::string& name, const std::string& value);
    // The sampler's options for `model`: automatic values resolved.
    SamplerConfig sampler_config(const ModelConfig& model) const {
        SamplerConfig sc;
        sc.sample_steps = sampler.sample_steps > 0 ? std::min(sampler.sample_steps, model.sample_steps) : model.sample_steps;
        sc.x0_clip = sampler.x0_clip;
        sc.goal_inpaint = sampler.goal_inpaint;
        sc.goal_reach = sampler.goal_reach >= 0 ? sampler.goal_reach : default_goal_reach(model);
        sc.guidance = guidance.weight;
        sc.candidates = sampler.candidates;
        sc.cost = guidance.cost;
        sc.keep_right = guidance.keep_right;
        sc.end_bend = sampler.end_bend;
        sc.warm_start = sampler.warm_start;
        return sc;
    }
};

// A plan of at most this many robot windows draws PlannerConfig::sampler.small_plan_candidates
// (2): a batch no larger than a team of 8 planned as one scene, whose plan time is the speed target.
constexpr int kSmallPlanWindows = 4;

// One row of the settings table: a PlannerConfig field, its name, range and meaning.
struct PlannerSetting {
    const char* name;          // group.field, as --set takes it
    double lo, hi;             // the range of a value (a bool: 0 and 1)
    const char* meaning;       // one line
    const char* automatic;     // what `automatic_value` stands for ("auto" in text), or nullptr
    double automatic_value;
    std::variant<int& (*)(PlannerConfig&), float& (*)(PlannerConfig&), double& (*)(PlannerConfig&), bool& (*)(PlannerConfig&)> field;

    double get(const PlannerConfig& c) const {
        return std::visit([&](auto f) { return (double)f(const_cast<PlannerConfig&>(c)); }, field);
    }
    bool is_bool() const { return std::holds_alternative<bool& (*)(PlannerConfig&)>(field); }
    bool is_integer() const { return std::holds_alternative<int& (*)(PlannerConfig&)>(field) || is_bool(); }
    bool allows(double v) const { return (automatic && v == automatic_value) || (v >= lo && v <= hi); }
    // "[lo, hi]", "0 or 1", plus "or auto".
    std::string range_text() const {
        std::string r = is_bool() ? "0 or 1" : "[" + number_text(lo) + ", " + number_text(hi) + "]";
        return automatic ? r + " or auto" : r;
    }
    std::string value_text(const PlannerConfig& c) const {
        const double v = get(c);
        return automatic && v == automatic_value ? std::string("auto") : number_text(v);
    }
};

// The table of every PlannerConfig setting (the order of the struct).
inline const std::vector<PlannerSetting>& planner_settings() {
    using C = PlannerConfig;
    static const std::vector<PlannerSetting> table = {
        {"neighbourhood.neighbours", 0, 1024, "robots per scene: each robot plans with its K-1 nearest; 0 = the whole team",
         "ceil(1.5 n_train_max) when the team or world is larger than in training, else the whole team", -1,
         +[](C& c) -> int& { return c.neighbourhood.neighbours; }},
        {"neighbourhood.sensing_radius", 1e-3, 1000, "neighbours farther than this (world units) are left out",
         "2 x the model's position_scale", 0, +[](C& c) -> double& { return c.neighbourhood.sensing_radius; }},
        {"neighbourhood.cover", 0, 1024, "windows kept per neighbourhood scene; scenes cover the team (0 = a scene per robot, its window only)", nullptr, 0,
         +[](C& c) -> int& { return c.neighbourhood.cover; }},
        {"workspace.chunk_scenes", 1, 1024, "scenes sampled together, on one thread with their own workspace", nullptr, 0,
         +[](C& c) -> int& { return c.workspace.chunk_scenes; }},
        {"workspace.max_mb", 1, 1e6, "a plan whose sampling workspace would exceed this (MB) is refused", nullptr, 0,
         +[](C& c) -> double& { return c.workspace.max_mb; }},
        {"sampler.sample_steps", 1, 1000, "DDIM steps S, at most the model's own (a model that samples in fewer keeps its own)",
         "the model's own S", 0, +[](C& c) -> int& { return c.sampler.sample_steps; }},
        {"sampler.warm_start", 0, 1000, "a plan runs the last W of the S steps from each robot's last window (0 = off)", nullptr, 0,
         +[](C& c) -> int& { return c.sampler.warm_start; }},
        {"sampler.line_start", 0, 1, "a robot without a last window starts from a straight line toward its goal", nullptr, 0,
         +[](C& c) -> bool& { return c.sampler.line_start; }},
        {"sampler.candidates", 1, kMaxCandidates, "windows drawn per scene; the lowest-cost one is kept", nullptr, 0,
         +[](C& c) -> int& { return c.sampler.candidates; }},
        {"sampler.small_plan_candidates", 1, kMaxCandidates, "at least this many for a plan of at most 4 robot windows", nullptr, 0,
         +[](C& c) -> int& { return c.sampler.small_plan_candidates; }},
        {"sampler.end_bend", 0, 1, "a window that stops short of a goal within reach is bent to arrive (0 = off)", nullptr, 0,
         +[](C& c) -> float& { return c.sampler.end_bend; }},
        {"sampler.goal_inpaint", 0, 1, "pin a window's last waypoint to its goal when the goal is within reach", nullptr, 0,
         +[](C& c) -> bool& { return c.sampler.goal_inpaint; }},
        {"sampler.goal_reach", 0, 100, "\"within reach\" for goal inpainting, world units", "0.55 (H-1) stride / 15, the model's window reach scaled (0.55 for the shipped model)",
         -1, +[](C& c) -> float& { return c.sampler.goal_reach; }},
        {"sampler.x0_clip", 1e-3, 100, "x0_hat is clipped to [-x0_clip, x0_clip] (normalised displacements)", nullptr, 0,
         +[](C& c) -> float& { return c.sampler.x0_clip; }},
        {"guidance.weight", 0, 1e6, "each DDIM step moves x0_hat's waypoints by -weight * d cost / d waypoint (0 = plain DDIM)", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.weight; }},
        {"guidance.keep_right", 0, 1e6, "robots meeting in the guided windows are pushed to the right of their relative motion", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.keep_right; }},
        {"guidance.priority", 1, 1e6, "in a team larger than a scene, each scene's first robot in priority is pushed this many times less than its last (1 = all alike)", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.priority; }},
        {"guidance.agent_weight", 0, 1e6, "cost weight of robots closer than 2 radius + agent_margin", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.agent_weight; }},
        {"guidance.map_weight", 0, 1e6, "cost weight of robots closer than radius + map_margin to the map", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.map_weight; }},
        {"guidance.goal_weight", 0, 1e6, "cost weight of a window's end distance to its goal or subgoal", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.goal_weight; }},
        {"guidance.agent_margin", 0, 10, "extra distance wanted between two robots' surfaces (world units)", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.agent_margin; }},
        {"guidance.map_margin", 0, 10, "extra distance wanted between a robot's surface and the map (world units)", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.map_margin; }},
        {"guidance.radius", 0, 10, "robot radius the cost assumes (world units)", nullptr, 0,
         +[](C& c) -> float& { return c.guidance.cost.radius; }},
        {"guidance.geodesic", 0, 1, "the goal term measures distance around obstacles", nullptr, 0,
         +[](C& c) -> bool& { return c.guidance.cost.geodesic; }},
        {"traffic.take_turns", 0, 1, "robots meeting head-on in a one-lane passage take turns", nullptr, 0,
         +[](C& c) -> bool& { return c.traffic.take_turns; }},
        {"traffic.make_way", 0, 1, "a robot whose goal is in a one-lane passage leaves it ahead of robots passing through", nullptr, 0,
         +[](C& c) -> bool& { return c.traffic.make_way; }},
        {"traffic.queue_in_order", 0, 1, "a robot behind one queueing at a passage's mouth queues too", nullptr, 0,
         +[](C& c) -> bool& { return c.traffic.queue_in_order; }},
        {"traffic.pocket_order", 0, 1, "a robot whose goal would close off a pocket (a dead end) that others' routes enter waits beside it until they pass", nullptr, 0,
         +[](C& c) -> bool& { return c.traffic.pocket_order; }},
        {"traffic.passage_replan", 0, 1000, "while robots may meet in a passage, replan after this many steps (0 = off)", nullptr, 0,
         +[](C& c) -> int& { return c.traffic.passage_replan; }},
        {"traffic.one_lane_width", 0, 100, "passages narrower than this, wall to wall, are one-lane", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.one_lane_width; }},
        {"traffic.free_clear", 0, 100, "a robot's centre fits where the clearance is at least this", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.free_clear; }},
        {"traffic.lookahead", 0, 100, "a robot claims the first passage within this distance along its route", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.lookahead; }},
        {"traffic.spare", 0, 100, "a claim from another mouth waits unless those inside are this far out", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.spare; }},
        {"traffic.wait_back", 0, 100, "the first waiting robot waits this far out from the mouth", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.wait_back; }},
        {"traffic.queue_spacing", 0, 100, "each next waiting robot this much farther", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.queue_spacing; }},
        {"traffic.wait_side", 0, 100, "waiting robots stand this far to the right of the way in", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.wait_side; }},
        {"traffic.min_length", 0, 100, "only passages whose mouths are this far apart count (corridors, not doorways)", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.min_length; }},
        {"traffic.bypass", 0, 100, "a passage with a way around at most this much longer is avoidable", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.bypass; }},
        {"traffic.go_around", 0, 1, "a robot that would wait at an avoidable passage goes around it", nullptr, 0,
         +[](C& c) -> bool& { return c.traffic.go_around; }},
        {"traffic.spread", 0, 100, "robots going around take its sides in turn: this much per robot already on a side", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.spread; }},
        {"traffic.crowd_weight", 0, 100, "in a team larger than a scene, at least traffic.crowd_density robots a square unit, in a world larger than training, robots route around crowds: a cell costs 1 + this per robot routed through it (0 = off)", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_weight; }},
        {"traffic.crowd_density", 0, 1000, "routes around crowds act only in a team of at least this many robots per square world unit", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_density; }},
        {"traffic.crowd_cell", 0.2, 100, "cell side of the grid routes around crowds are made on (world units)", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_cell; }},
        {"traffic.crowd_detour", 0, 100, "routes around crowds: a detour longer than this times the straight way is not taken (0 = any)", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_detour; }},
        {"traffic.crowd_time", 0, 1000, "in a team of traffic.crowd_time_from robots or more, routes around crowds count a robot in a cell only within this many steps of its time there (0 = whenever, in every team)", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_time; }},
        {"traffic.crowd_time_from", 1, 1000000, "teams of this many robots or more count routes around crowds in time (traffic.crowd_time)", nullptr, 0,
         +[](C& c) -> int& { return c.traffic.crowd_time_from; }},
        {"traffic.crowd_time_weight", 0, 100, "where routes around crowds count in time, a cell costs 1 + this per robot due there", nullptr, 0,
         +[](C& c) -> double& { return c.traffic.crowd_time_weight; }},
        {"follower.replan_every", 1, 1000, "steps executed per plan (m)", nullptr, 0,
         +[](C& c) -> int& { return c.follower.replan_every; }},
        {"follower.safety_filter", 0, 1, "the SPEC 3.2 safety filter runs after the tracker", nullptr, 0,
         +[](C& c) -> bool& { return c.follower.safety_filter; }},
        {"follower.priority_weight", 1, 1000, "safety-filter weight of the robot that goes first (1 = all equal)", nullptr, 0,
         +[](C& c) -> double& { return c.follower.priority_weight; }},
        {"follower.lookahead", 0, kMaxLookahead, "the tracker aims this many steps ahead of the plan's waypoint for now", nullptr, 0,
         +[](C& c) -> double& { return c.follower.lookahead; }},
        {"follower.replan_error", 0, 100, "replan early (after m/2 steps) when a robot is this far off its plan (0 = off)", nullptr, 0,
         +[](C& c) -> double& { return c.follower.replan_error; }},
        {"follower.unjam", 0, 1000, "a robot the filter holds this many steps, with no progress for twice as long, backs out (0 = off)", nullptr, 0,
         +[](C& c) -> int& { return c.follower.unjam; }},
        {"follower.unjam_near", 0, 10, "with unjam: a robot standing still with another this near, world units, counts as held (0 = off: only the filter holds)", nullptr, 0,
         +[](C& c) -> double& { return c.follower.unjam_near; }},
        {"follower.filter_rate", 0.01, 9.99, "the safety filter's barrier rate, 1/s (below 1/dt)", nullptr, 0,
         +[](C& c) -> double& { return c.follower.filter.rate; }},
        {"follower.filter_static_margin", 0, 1, "the safety filter's gap kept to obstacles and walls beyond touching, world units (routes pass cells 0.002 beyond)", nullptr, 0,
         +[](C& c) -> double& { return c.follower.filter.static_margin; }},
    };
    return table;
}

// The table's row named `name`, or nullptr.
inline const PlannerSetting* find_planner_setting(const std::string& name) {
    for (const PlannerSetting& s : planner_settings())
        if (name == s.name) return &s;
    return nullptr;
}

inline void PlannerConfig::validate() const {
    for (const PlannerSetting& s : planner_settings()) {
        const double v = s.get(*this);
        if (!s.allows(v))  // the message only on failure: no allocation while planning
            throw std::invalid_argument("planner setting " + std::string(s.name) + ": must be " + s.range_text() + " (got " + number_text(v) + ")");
    }
}

inline void PlannerConfig::set(const std::string& name, const std::string& text) {
    const PlannerSetting* s = find_planner_setting(name);
    if (!s) throw std::invalid_argument("planner setting '" + printable(name) + "': no such setting (madbp eval --list-settings lists them)");
    const std::string what = "planner setting " + name + ": ";
    double v = 0;
    if (s->automatic && text == "auto") {
        v = s->automatic_value;
    } else if (s->is_bool() && (text == "true" || text == "false")) {
        v = text == "true";
    } else {
        char* end = nullptr;
        errno = 0;
        v = std::strtod(text.c_str(), &end);
        if (text.empty() || end != text.c_str() + text.size() || !std::isfinite(v) || errno == ERANGE)
            throw std::invalid_argument(what + "expected a number, got '" + printable(text) + "'");
        if (s->is_integer() && v != std::floor(v)) throw std::invalid_argument(what + "expected a whole number, got '" + printable(text) + "'");
        // An automatic value is written "auto", never as its number: no silent sentinels.
        if (!(v >= s->lo && v <= s->hi)) throw std::invalid_argument(what + "must be " + s->range_text() + " (got " + printable(text) + ")");
    }
    std::visit([&](auto f) {
        auto& field = f(*this);
        field = (std::remove_reference_t<decltype(field)>)v;
    }, s->field);
}

// =============================================================================================
// Section 8. Traffic conventions: one-lane passages (PassageControl), crowds (CrowdRoutes)
// =============================================================================================

// One-lane passages (issue 12): corridors too narrow for two robots to pass side by side. Two
// robots that meet head-on in one cannot settle it within a planning window: the filter holds
// them nose to nose, or the last one through waits in the way and runs out of time. Fleets
// settle it as traffic control does, one direction at a time, and so does PassageControl: it
// finds the passages on a RouteGuide's grid and tells each robot of a team whether to go on, to
// wait beside the passage's mouth while a robot that entered from another mouth holds it, or
// (where the corridor has a short way around) to go around it.
//   - One-lane cell: a centre fits there (clearance >= free_clear) and some line through it, in
//     one of 8 directions, crosses the free space in less than one_lane_width - 2 free_clear
//     (no room for a second centre 2 radius + a margin away). Its key: the two obstacle groups
//     (detail::surface_groups: obstacles with no room for a centre between them are one, the
//     border one) at the ends of its shortest such line. A passage: an 8-connected set of cells
//     of one key with two mouths (the connected sets of free cells beside it, pockets aside) at
//     least min_length apart: a corridor, not a doorway, a corner, a dead end or a junction.
//     Keys keep the narrow gaps around a corridor's ends (a wall's end and a disc, a disc and
//     the border) from joining it into a junction. One with a way around
//     at most `bypass` longer is avoidable.
//   - A robot's claim: the first passage on its route (RouteGuide::route_cells) within
//     `lookahead`, how far along the route it starts (0: the robot is in it) and the mouth it
//     enters by (in it: the mouth nearest it other than the one its route leaves by).
//   - Of the claims on a passage, the nearest (then the one with less of it ahead, then the
//     lower id, then the lower index) holds it; the claims that enter by another mouth wait in
//     a queue at theirs: places wait_back out from the mouth's centre, then every
//     queue_spacing, each wait_side to the right of the way in (to the left, or on that line,
//     where there is no room), each taken by the robot nearest it of those left; where none of
//     the three fits near the mouth's free space (a maze's corners), the fitting cell near by
//     nearest the line, else the one whose walk from the mouth is about as long.
//     A robot in the passage that must wait backs out. At an avoidable passage a robot that
//     would wait outside it goes around instead (go_around): its route keeps out of the passage
//     (closed_to, ClosedCells) while the holders are in it, and robots going around the same
//     passage take its two sides in turn (spread; closed_to then also closes the other side).
//   - Goals in a passage (make_way): claims passing through come before those of robots whose
//     goal lies in it; such a robot in the holder's way queues at the mouth the holder leaves
//     by, ahead of it; of two such robots, the one that would pass the other goes around it
//     (closed_to: a plug of cells at the other) or, with no way around, both queue at the mouth
//     it comes in by; of two coming in by one mouth, the one ahead whose goal the other would
//     pass queues until it has.
//   - Queues keep their order (queue_in_order): at a passage with no way around, when a claim
//     from a mouth waits, every claim from that mouth waits, since none can pass the first.
//   - Goals that close off a pocket (pocket_order): a robot parked at its goal in a one-lane
//     place (the dead ends PassageControl does not count as passages) stands in the way of a
//     robot whose route goes past it into the space behind, or out of it, and in a dead end the
//     two cannot swap. A goal in a one-lane cell closes off a pocket for a route that comes
//     within two radii (2 free_clear) of it when, with that disc closed, the free cells on one
//     side of it, the route's end or its start, are all one-lane and cover less than a square
//     `bypass` wide (a dead end; in a wider pocket the parked robot steps aside), unless its
//     robot would arrive (route cells, one a step) wait_back after the route's robot is past.
//     Its robot, unless already waiting, waits (kWait) at the free cell nearest its goal by walk, within
//     lookahead + wait_side + free_clear of it and out of the pockets, that keeps
//     wait_side + free_clear from the goal, from those routes and from the spots given to
//     others: so a dead end fills from its far end (maze-32-32-4, seed 38 at cell 0.25).
// Memory: a few grids (one of them the walk lengths from a mouth, for queues; one of a byte a
// cell, the one-lane cells; with pocket_order two more of ints), plus two cell lists per avoidable passage (its sides); per call, the claims'
// route cells in their passages and a few cells per plug, and with pocket_order every travelling
// robot's whole route.
// Claims are made afresh at every call from positions, goals and ids alone, so robots that plan
// for themselves with the same information reach the same decision.
class PassageControl {
public:
    TrafficConfig params;  // the passage fields (take_turns and passage_replan are the planner's)
    struct Mouth {
        int passage = -1;
        Vec2 at;    // the centre of the mouth's cells
        Vec2 in;    // unit: from there into the passage
    };

    // For cell k of the guide's grid for `map`: passage(...)[k], the passage it belongs to, or -1;
    // mouth_of_cell()[k], the mouth it belongs to, or -1; mouths() lists them.
    const std::vector<int>& passage(RouteGuide& guide, const WorldMap& map) {
        const ClearanceGrid& grid = guide.grid(map);
        const double shape[] = {params.one_lane_width, params.free_clear, params.min_length, params.bypass, (double)params.go_around, grid.cell};
        if (!(map_ == map) || (int)passage_.size() != grid.n * grid.n || !std::equal(shape, shape + 6, made_with_)) {
            find_passages(grid, map);
            std::copy(shape, shape + 6, made_with_);
            cell_ = grid.cell;
        }
        return passage_;
    }
    const std::vector<int>& mouth_of_cell() const { return mouth_; }
    const std::vector<char>& avoidable() const { return avoidable_; }  // per passage: has a way around within `bypass`
    const std::vector<Mouth>& mouths() const { return mouths_; }

    // For robots i < n at pos[i] heading for goal[i] (at_goal[i]: arrived, claims nothing; ids[i]:
    // the robot's id, which breaks ties, or nullptr: the index does):
    // wait[i] = kWait and point[i] = where to wait; kGoAround (keep out of the passage
    // closed_to(i) on the way to goal[i]); or kGoOn (point[i] = goal[i]). Returns how many do not go on.
    // asked (nullptr: all): the robots whose turns the caller reads. Only the passages they claim
    // are decided, from every claim on them, so their turns are those of a call with all asked;
    // the others' may not be (a robot planning for itself among 1024 routes a few, not 1024).
    enum Turn : char { kGoOn = 0, kWait = 1, kGoAround = 2 };
    int arbitrate(RouteGuide& guide, const WorldMap& map, int n, const Vec2* pos, const Vec2* goal, const char* at_goal,
                  std::vector<char>& wait, std::vector<Vec2>& point, const int* ids = nullptr, const char* asked = nullptr) {
        int waiting = take_turns(guide, map, n, pos, goal, at_goal, wait, point, ids, asked);
        if (params.pocket_order) waiting += order_pockets(guide, map, n, pos, goal, at_goal, wait, point);
        return waiting;
    }
    // Whether the last arbitrate() saw claims on one passage from two of its mouths, or sent a
    // parked robot out ahead of a holder (robots that may meet in it), of the passages it decided.
    bool contested() const {
        if (made_way_) return true;
        for (size_t a = 0; a < claims_.size(); ++a)
            for (size_t b = 0; b < a; ++b)
                if (claims_[a].passage == claims_[b].passage && claims_[a].mouth != claims_[b].mouth) return true;
        return false;
    }
    // Who follows whom through a passage, from the last arbitrate() (its guide, `turn`, `pos` and `goal`):
    // ahead[i], the robot directly ahead of robot i in one line through its passage, or -1. A
    // line: the claims going on into (or through) a passage by one mouth, the one farthest in
    // first (robots in it by their distance from that mouth, then those outside by how near they
    // are), headed by the parked robots sent out ahead of them (make_way), the farthest first.
    // A robot follows one that goes on past `lookahead` and is in the passage or follows (one
    // outside a line can step aside; one about to arrive is better planned after the robots
    // that pass its goal, which it then makes way for, as the expert's priorities have it: the
    // corridor interaction scene). A robot parking in the passage follows the nearest robot
    // ahead of it, in by its mouth, that passes its goal, or no one. A robot going on
    // by another mouth than the holder's (it enters once the holder is `spare` out) follows the
    // holder. A planner that plans robots one after another (the guided expert) plans each after
    // the one it follows: planned first, a robot behind routes through the one ahead in a
    // one-lane aisle, which then cannot go on, and one coming in by the far mouth sends the
    // holder back out (docs/experiments.md, "The expert's line through an aisle").
    void follow_order(const RouteGuide& guide, const std::vector<char>& turn, const Vec2* pos, const Vec2* goal, std::vector<int>& ahead) const {
        ahead.assign(turn.size(), -1);
        auto depth = [&](const Claim& c) { return claim_depth(c, pos); };
        line_.clear();
        for (int k = 0; k < (int)claims_.size(); ++k)
            if (!claims_[k].parks && turn[claims_[k].robot] == kGoOn) line_.push_back(k);
        // By passage and mouth, then the farthest in first: each line from its head.
        std::sort(line_.begin(), line_.end(), [&](int a, int b) {
            const Claim &x = claims_[a], &y = claims_[b];
            if (x.passage != y.passage || x.mouth != y.mouth) return std::tie(x.passage, x.mouth) < std::tie(y.passage, y.mouth);
            return depth(x) != depth(y) ? depth(x) > depth(y) : x.robot < y.robot;
        });
        bool followed = false;  // the robot before in the line is followed
        for (size_t k = 0; k < line_.size(); ++k) {
            const Claim& c = claims_[line_[k]];
            const bool head = k == 0 || claims_[line_[k - 1]].passage != c.passage || claims_[line_[k - 1]].mouth != c.mouth;
            if (head) {  // it follows the robots sent out ahead of it, the nearest last
                for (int last = c.robot;;) {
                    int nearest = -1;
                    const double beyond = last == c.robot ? -1 : norm(pos[last] - pos[c.robot]);
                    for (const SentOut& o : sent_out_)
                        if (o.passage == c.passage && o.mouth == c.mouth && norm(pos[o.robot] - pos[c.robot]) > beyond &&
                            (nearest < 0 || norm(pos[o.robot] - pos[c.robot]) < norm(pos[nearest] - pos[c.robot])))
                            nearest = o.robot;
                    if (nearest < 0) break;
                    ahead[last] = nearest;
                    last = nearest;
                }
            } else if (followed) {
                ahead[c.robot] = claims_[line_[k - 1]].robot;
            }
            followed = !c.arrives && (c.entry == 0 || ahead[c.robot] >= 0);
        }
        for (int k : line_) {  // going on by another mouth than the holder's: after the holder
            const Claim& c = claims_[k];
            const int h = holder_[c.passage];
            if (ahead[c.robot] < 0 && h >= 0 && claims_[h].mouth != c.mouth) ahead[c.robot] = claims_[h].robot;
        }
        // Going on to a goal in the passage: after the nearest robot ahead of it there that passes
        // its goal (planned first, it routes through that robot, which then steps back to let it
        // by in a one-lane aisle, and the two creep: maze-32-32-4, seed 87 at cell 0.25).
        for (const Claim& c : claims_) {
            if (!c.parks || turn[c.robot] != kGoOn) continue;
            const Claim* next = nullptr;
            for (const Claim& d : claims_)
                if (d.robot != c.robot && d.passage == c.passage && d.mouth == c.mouth && turn[d.robot] == kGoOn && depth(d) > depth(c) &&
                    (!next || depth(d) < depth(*next)) && passes(guide.grid(), d, goal[d.robot], goal[c.robot]))
                    next = &d;
            ahead[c.robot] = next ? next->robot : -1;
        }
    }
    // The cells robot i of the last arbitrate() keeps out of (its passage's; none unless it goes around).
    ClosedCells closed_to(int i) const {
        if (i < 0 || i >= (int)around_.size() || around_[i] < 0) return {};
        if (around_side_[i] >= 0) return side_cells(around_[i], around_side_[i]);
        if (plug_of_[i] >= 0) return {nullptr, -1, plugs_[plug_of_[i]].key, &plugs_[plug_of_[i]].cells};
        return {&passage_, around_[i], closed_key_[around_[i]]};
    }

private:
    struct Claim {
        int robot = -1, passage = -1, mouth = -1;
        int entry = 0, exit = 0;  // route cells before the passage (0: in it) and before its last cell there
        bool parks = false;       // its goal lies in the passage (make_way)
        bool arrives = false;     // its route reaches its goal within `lookahead` (follow_order)
        int cells_begin = 0, cells_end = 0;  // claim_cells_[begin, end): its route's cells in the passage, ahead of it
    };
    WorldMap map_;
    double made_with_[6] = {};  // the parameters and cell the passages were found with
    double cell_ = 0;           // that cell, world units (follow_order)
    std::vector<int> passage_, mouth_, route_, losers_, behind_, queue_, around_, around_side_, going_;
    std::vector<Mouth> mouths_;
    std::vector<std::vector<int>> mouth_cells_;  // per mouth: its cells
    std::vector<Vec2> places_;                   // arbitrate: one queue's places
    std::vector<float> walk_;                    // queue_places: walk lengths from a mouth (walk_from)
    std::vector<int> walked_;                    // the cells walk_ holds
    std::vector<std::vector<Vec2>> queue_memo_;  // per mouth: its first queue places found so far (queue_places)
    double queue_memo_with_[3] = {-1, -1, -1};   // the queue parameters they were found with
    std::vector<char> avoidable_;    // per passage: it has a way around within `bypass`
    std::vector<uint64_t> closed_key_;  // per passage: ClosedCells::key of its cells
    std::vector<Box> box_;              // per passage: the box of its cells' centres (arbitrate's `asked`: who may claim it)
    std::vector<Claim> asked_claims_;   // arbitrate: the asked robots' claims, then made in robot order
    std::vector<char> relevant_;        // arbitrate: per passage, some asked robot claims it
    std::vector<int> relevant_list_;    // the same passages, listed
    std::vector<int> holder_;           // arbitrate: per passage, the claim that holds it (-1: none)
    std::vector<std::vector<int>> side_closed_;  // per avoidable passage p and side s, [2p + s]: the cells a robot going around on s keeps out of, sorted
    std::vector<Claim> claims_;
    std::vector<int> claim_cells_;  // arbitrate: the claims' route cells in their passages
    std::vector<std::pair<int, int>> parked_;   // arbitrate: (robot, passage): robots in a passage that holds their goal (make_way)
    std::vector<std::pair<int, int>> waiters_;  // arbitrate: (robot, mouth): who queues where at one passage
    bool made_way_ = false;         // arbitrate: some parked robot was sent out ahead of a holder
    struct SentOut {
        int robot, passage, mouth;  // a parked robot sent out ahead of the holder of `passage`, in by `mouth` (make_way)
    };
    std::vector<SentOut> sent_out_;  // arbitrate: follow_order's heads of lines
    // order_pockets: robots whose goals may close a way, the travelling robots' routes (robot b's
    // cells routes_[route_begin_[b], route_begin_[b + 1])), per grid cell the stamp of the last
    // flood that saw it and of the pockets marked for the robot being placed, a flood's cells, the
    // route points a waiting robot keeps clear of and the waiting spots taken.
    std::vector<char> one_lane_;  // per grid cell: one-lane (find_passages)
    std::vector<int> narrow_, routes_, route_begin_, seen_, pocket_, flood_;
    int seen_stamp_ = 0, pocket_stamp_ = 0;
    std::vector<Vec2> keep_clear_, spots_;
    mutable std::vector<int> line_;  // follow_order: the claims going on, in lines
    struct Plug {
        uint64_t key;
        std::vector<int> cells;  // sorted
    };
    std::vector<Plug> plugs_;       // arbitrate: the passage cells around robots parked in the way of another's goal
    std::vector<int> plug_of_;      // per robot: the plug it goes around (an index into plugs_), or -1

    // The passages' turns (arbitrate without pocket_order).
    int take_turns(RouteGuide& guide, const WorldMap& map, int n, const Vec2* pos, const Vec2* goal, const char* at_goal,
                   std::vector<char>& wait, std::vector<Vec2>& point, const int* ids, const char* asked) {
        const TrafficConfig& p = params;
        const double lengths[] = {p.one_lane_width, p.free_clear, p.lookahead, p.wait_back, p.queue_spacing, p.wait_side, p.min_length, p.bypass, p.spread, p.spare};
        for (double v : lengths)
            if (!(v >= 0) || !std::isfinite(v)) throw std::invalid_argument("traffic: every length must be a finite number >= 0 (got " + number_text(v) + ")");
        const std::vector<int>& cell_passage = passage(guide, map);
        const ClearanceGrid& grid = guide.grid();
        wait.assign(n, kGoOn);
        point.assign(goal, goal + n);
        around_.assign(n, -1);
        around_side_.assign(n, -1);
        plug_of_.assign(n, -1);
        plugs_.clear();
        claims_.clear();
        claim_cells_.clear();
        made_way_ = false;
        sent_out_.clear();
        holder_.assign(avoidable_.size(), -1);
        if (mouths_.empty()) return 0;
        // Robots in a passage whose goal lies in it too (make_way): they may stand in the way of
        // robots passing through.
        parked_.clear();
        if (p.make_way)
            for (int i = 0; i < n; ++i) {
                const int q = cell_passage[grid.index(pos[i])];
                if (q >= 0 && cell_passage[grid.index(goal[i])] == q) parked_.push_back({i, q});
            }
        const int max_cells = 2 + (int)std::ceil(p.lookahead / grid.cell);
        // Only passages an asked robot claims are decided, so only robots whose route may reach
        // one claim: a route's cells lie within (max_cells + 3) sqrt(2) cells of the robot (its
        // start cell within 2 cells, then one neighbour a step).
        const double reach = (max_cells + 3) * std::sqrt(2.0) * grid.cell;
        asked_claims_.clear();
        relevant_.assign(avoidable_.size(), asked ? 0 : 1);
        relevant_list_.clear();
        if (asked) {
            Claim c;
            for (int i = 0; i < n; ++i)
                if (asked[i] && !at_goal[i] && make_claim(guide, map, cell_passage, max_cells, i, pos, goal, c)) {
                    asked_claims_.push_back(c);
                    if (!relevant_[c.passage]) relevant_[c.passage] = 1, relevant_list_.push_back(c.passage);
                }
            for (auto [i, q] : parked_)  // an asked robot parked in a passage learns whether to make way
                if (asked[i] && !relevant_[q]) relevant_[q] = 1, relevant_list_.push_back(q);
        }
        size_t next_asked = 0;
        for (int i = 0; i < n; ++i) {
            if (asked && asked[i]) {  // its claim, in robot order
                if (next_asked < asked_claims_.size() && asked_claims_[next_asked].robot == i) claims_.push_back(asked_claims_[next_asked++]);
                continue;
            }
            if (at_goal[i]) continue;
            bool near = !asked;
            for (size_t q = 0; !near && q < relevant_list_.size(); ++q) near = box_distance(box_[relevant_list_[q]], pos[i]) <= reach;
            Claim c;
            if (near && make_claim(guide, map, cell_passage, max_cells, i, pos, goal, c) && relevant_[c.passage]) claims_.push_back(c);
        }
        // A claim from another mouth waits when it would enter before a claim from the holder's mouth
        // is `spare` out (route cells, as if both moved alike; the safety filter keeps them apart).
        const int clear_cells = (int)std::ceil(p.spare / grid.cell);
        int waiting = 0;
        for (size_t a = 0; a < claims_.size(); ++a) {
            bool seen = false;  // the first claim on each passage decides for all of its claims
            for (size_t b = 0; b < a; ++b) seen = seen || claims_[b].passage == claims_[a].passage;
            if (seen) continue;
            const Claim* lead = &claims_[a];
            for (size_t b = a + 1; b < claims_.size(); ++b)
                if (claims_[b].passage == lead->passage && before(ids, claims_[b], *lead)) lead = &claims_[b];
            holder_[lead->passage] = (int)(lead - claims_.data());
            losers_.clear();
            behind_.clear();
            for (size_t b = a; b < claims_.size(); ++b) {
                if (claims_[b].passage != lead->passage || claims_[b].mouth == lead->mouth) continue;
                bool meets = false;
                for (size_t h = a; h < claims_.size(); ++h)
                    meets = meets || (claims_[h].passage == lead->passage && claims_[h].mouth == lead->mouth &&
                                      claims_[b].entry <= claims_[h].exit + clear_cells);
                if (!meets) {
                    if (p.queue_in_order && !avoidable_[lead->passage]) behind_.push_back((int)b);
                    continue;
                }
                if (avoidable_[lead->passage] && claims_[b].entry > 0) {
                    wait[claims_[b].robot] = kGoAround;
                    around_[claims_[b].robot] = lead->passage;
                    ++waiting;
                } else {
                    losers_.push_back((int)b);
                }
            }
            // Queues keep their order (queue_in_order): a claim that would enter after the holder
            // leaves still queues when a claim from its mouth queues, since it cannot pass that
            // robot on its way in; going on, it pushes the queue into the mouth the holder leaves
            // by (maze-32-32-4's dead-end mouths, docs/experiments.md "Queues in order").
            for (int b : behind_) {
                bool queue = false;
                for (int l : losers_) queue = queue || claims_[l].mouth == claims_[b].mouth;
                if (queue) losers_.push_back(b);
            }
            if (p.spread > 0 && avoidable_[lead->passage]) spread_around(guide, map, lead->passage, pos, goal, ids);
            // Who queues at which mouth (waiters_: robot, mouth): the losers at theirs, then those
            // make_way sends out.
            waiters_.clear();
            for (int b : losers_) waiters_.push_back({claims_[b].robot, claims_[b].mouth});
            if (p.make_way) waiting += make_way(guide, map, *lead, a, pos, goal, wait);
            // The queue at each waiting mouth: its places from the mouth out, each to the robot
            // nearest it of those left (robots keep their places as they walk to them).
            for (int m = 0; m < (int)mouths_.size(); ++m) {
                if (mouths_[m].passage != lead->passage) continue;
                int queued = 0;
                for (auto [r, mouth] : waiters_) queued += mouth == m && !wait[r];
                if (queued == 0) continue;
                queue_places(grid, m, queued, places_);
                for (const Vec2 spot : places_) {
                    int best = -1;
                    for (auto [r, mouth] : waiters_)
                        if (mouth == m && !wait[r] && (best < 0 || norm(pos[r] - spot) < norm(pos[best] - spot))) best = r;
                    if (best < 0) break;
                    wait[best] = kWait;
                    point[best] = spot;
                    ++waiting;
                }
            }
        }
        return waiting;
    }
    // Goals that close off a pocket (pocket_order; see the class comment): robots going on
    // (wait[a] == kGoOn) whose goal, occupied, would close off a pocket another robot's route
    // enters or leaves wait beside it, out of the pocket and off those routes. Returns how many.
    int order_pockets(RouteGuide& guide, const WorldMap& map, int n, const Vec2* pos, const Vec2* goal, const char* at_goal,
                      std::vector<char>& wait, std::vector<Vec2>& point) {
        const ClearanceGrid& grid = guide.grid(map);
        const double block = 2 * params.free_clear;                // a centre this near a parked robot's touches it
        const double off = params.wait_side + params.free_clear;   // a waiting robot keeps this far from the routes it clears
        const double reach = params.lookahead + off;               // and waits this near its goal
        passage(guide, map);  // the one-lane cells
        narrow_.clear();
        for (int a = 0; a < n; ++a)  // no room to pass beside the goal: the only goals that may close a way
            if (wait[a] == kGoOn && one_lane_[grid.index(goal[a])]) narrow_.push_back(a);
        if (narrow_.empty()) return 0;
        // Every travelling robot's whole route, once.
        routes_.clear();
        route_begin_.assign(n + 1, 0);
        for (int b = 0; b < n; ++b) {
            route_begin_[b] = (int)routes_.size();
            if (at_goal[b]) continue;
            guide.route_cells(map, pos[b], goal[b], std::numeric_limits<int>::max(), route_);
            if (route_.size() >= 2) routes_.insert(routes_.end(), route_.begin(), route_.end());
        }
        route_begin_[n] = (int)routes_.size();
        if (seen_.size() != (size_t)grid.n * grid.n) seen_.assign((size_t)grid.n * grid.n, 0), pocket_.assign(seen_.size(), 0);
        const double side = params.bypass / grid.cell;
        const int pocket_cap = (int)std::ceil(side * side);  // cells of a square `bypass` wide
        const int spare_cells = (int)std::ceil(params.wait_back / grid.cell);
        int waiting = 0;
        spots_.clear();
        for (int a : narrow_) {
            ++pocket_stamp_;
            keep_clear_.clear();
            for (int b = 0; b < n; ++b) {
                const int* r = routes_.data() + route_begin_[b];
                const int len = route_begin_[b + 1] - route_begin_[b];
                if (b == a || len == 0 || norm(goal[b] - goal[a]) < block) continue;
                int past = -1;  // the last route cell within `block` of a's goal: b is past it there
                for (int k = 0; k < len; ++k)
                    if (norm(grid.centre(r[k]) - goal[a]) < block) past = k;
                // Robot a would arrive (a cell a step, as b moves) before b is past, or less than
                // wait_back after: it would park in b's way.
                const bool early = past >= 0 && route_begin_[a + 1] - route_begin_[a] <= past + spare_cells;
                // A dead end: the side of the goal the route goes into (or comes out of) holds,
                // with the goal's disc closed, only one-lane cells, fewer than pocket_cap.
                if (!early || !(is_pocket(grid, goal[a], block, r[len - 1], r[0], pocket_cap) || is_pocket(grid, goal[a], block, r[0], r[len - 1], pocket_cap)))
                    continue;
                for (int c : flood_) pocket_[c] = pocket_stamp_;
                for (int k = 0; k < len; ++k)
                    if (norm(grid.centre(r[k]) - goal[a]) < reach + off) keep_clear_.push_back(grid.centre(r[k]));
            }
            if (keep_clear_.empty()) continue;
            Vec2 spot;
            if (!waiting_spot(grid, goal[a], off, reach, spot)) continue;
            wait[a] = kWait, point[a] = spot, ++waiting;
            spots_.push_back(spot);
        }
        return waiting;
    }
    // Whether the free cells reached from cell `from` without coming within `block` of `centre`
    // number fewer than `cap`, are all one-lane and do not hold cell `to` (a dead end: then
    // flood_ holds them). In a wider pocket the parked robot can step aside for the other.
    bool is_pocket(const ClearanceGrid& grid, Vec2 centre, double block, int from, int to, int cap) {
        ++seen_stamp_;
        flood_.assign(1, from);
        seen_[from] = seen_stamp_;
        bool open = false;  // it reached `to`, a cell that is not one-lane, or `cap` cells
        for (size_t q = 0; q < flood_.size() && !open; ++q)
            detail::for_each_neighbour(grid.n, flood_[q], [&](int k2) {
                if (open || seen_[k2] == seen_stamp_) return;
                seen_[k2] = seen_stamp_;
                if (grid.clear[k2] < params.free_clear || norm(grid.centre(k2) - centre) < block) return;
                open = k2 == to || (int)flood_.size() >= cap || !one_lane_[k2];
                if (!open) flood_.push_back(k2);
            });
        return !open;
    }
    // The free cell nearest `goal` by walk (out of the pockets marked, within `reach` of it) that
    // is `off` from it, from every point of keep_clear_ and from the spots taken this call.
    bool waiting_spot(const ClearanceGrid& grid, Vec2 goal, double off, double reach, Vec2& spot) {
        ++seen_stamp_;
        const int start = grid.index(goal);
        flood_.assign(1, start);
        seen_[start] = seen_stamp_;
        auto fits = [&](Vec2 c) {
            if (norm(c - goal) < off) return false;
            for (Vec2 k : keep_clear_) if (norm(c - k) < off) return false;
            for (Vec2 k : spots_) if (norm(c - k) < 2 * off) return false;
            return true;
        };
        for (size_t q = 0; q < flood_.size(); ++q) {
            if (q > 0 && fits(grid.centre(flood_[q]))) return spot = grid.centre(flood_[q]), true;
            detail::for_each_neighbour(grid.n, flood_[q], [&](int k2) {
                if (seen_[k2] == seen_stamp_) return;
                seen_[k2] = seen_stamp_;
                if (grid.clear[k2] >= params.free_clear && pocket_[k2] != pocket_stamp_ && norm(grid.centre(k2) - goal) <= reach) flood_.push_back(k2);
            });
        }
        return false;
    }
    // How far in claim c's robot is: its distance from the mouth it enters by when in the passage,
    // else minus the route length to it (the lines of follow_order, from the farthest in).
    double claim_depth(const Claim& c, const Vec2* pos) const {
        return c.entry > 0 ? -c.entry * cell_ : norm(pos[c.robot] - mouths_[c.mouth].at);
    }
    // Robot i's claim (`c`): the first passage on its route within max_cells route cells, where
    // the route enters and leaves it, and the mouth it enters by; false when it claims none.
    bool make_claim(RouteGuide& guide, const WorldMap& map, const std::vector<int>& cell_passage, int max_cells, int i, const Vec2* pos, const Vec2* goal,
                    Claim& c) {
        guide.route_cells(map, pos[i], goal[i], max_cells, route_);
        c = Claim{};
        c.robot = i;
        for (int j = 0; j < (int)route_.size() && c.passage < 0; ++j)
            if (cell_passage[route_[j]] >= 0) c.passage = cell_passage[route_[j]], c.entry = j;
        if (c.passage < 0) return false;
        c.parks = params.make_way && cell_passage[guide.grid().index(goal[i])] == c.passage;
        c.arrives = (int)route_.size() < max_cells;
        if (c.parks && (int)route_.size() == max_cells)  // the whole way to its goal: who it passes there (make_way)
            guide.route_cells(map, pos[i], goal[i], std::numeric_limits<int>::max(), route_);
        c.exit = c.entry;
        while (c.exit + 1 < (int)route_.size() && cell_passage[route_[c.exit + 1]] == c.passage) ++c.exit;
        c.cells_begin = (int)claim_cells_.size();
        claim_cells_.insert(claim_cells_.end(), route_.begin() + std::max(c.entry, 1), route_.begin() + c.exit + 1);
        c.cells_end = (int)claim_cells_.size();
        c.mouth = c.entry > 0 ? mouth_[route_[c.entry - 1]] : -1;
        if (c.mouth < 0 || mouths_[c.mouth].passage != c.passage) {
            // In the passage (or entered beside a mouth): the nearest mouth but the one the route
            // leaves by; when the route ends in the passage (at a goal there, or past the
            // lookahead in a long one), the mouth it heads away from most (not the nearest: a
            // robot past a long corridor's middle has not come from the mouth ahead of it).
            const int leaves = c.exit + 1 < (int)route_.size() ? mouth_[route_[c.exit + 1]] : -1;
            const Vec2 end = guide.grid().centre(route_[c.exit]);
            const bool heading = leaves < 0 && norm(end - pos[i]) >= 2 * guide.grid().cell;
            auto away = [&](int m) { return heading ? norm(mouths_[m].at - end) - norm(mouths_[m].at - pos[i]) : -norm(mouths_[m].at - pos[i]); };
            c.mouth = -1;
            for (int m = 0; m < (int)mouths_.size(); ++m)
                if (mouths_[m].passage == c.passage && m != leaves && (c.mouth < 0 || away(m) > away(c.mouth))) c.mouth = m;
            if (c.mouth < 0) return false;
        }
        return true;
    }
    // Robots whose goals lie in a passage (parked_; make_way), for passage lead.passage, whose
    // claims start at claims_[first]:
    // - One that stands in the way of a holder passing through queues at the mouth the holder
    //   leaves by, ahead of it: backing out the other way would meet it head-on, and staying would
    //   hold them nose to nose.
    // - A claim that would pass one whose goal it would pass too (the two goals in the other's
    //   order) goes in by the other mouth where there is a way (kGoAround, around a plug of cells
    //   at the other); where there is none (the corridor is the only way, as in a maze) both
    //   queue at the mouth it comes in by, which it reaches first, so it enters first.
    // Adds to waiters_; returns how many go around.
    int make_way(RouteGuide& guide, const WorldMap& map, const Claim& lead, size_t first, const Vec2* pos, const Vec2* goal,
                 std::vector<char>& wait) {
        const ClearanceGrid& grid = guide.grid();
        auto queued = [&](int i) {
            return std::any_of(waiters_.begin(), waiters_.end(), [i](const std::pair<int, int>& w) { return w.first == i; });
        };
        auto queue = [&](int i, int m) {
            if (!queued(i)) waiters_.push_back({i, m}), made_way_ = true;
        };
        int around = 0;
        for (auto [i, q] : parked_) {
            if (lead.parks || i == lead.robot || q != lead.passage || queued(i) || !in_the_way(grid, lead, pos[i])) continue;
            int out = -1;  // the mouth ahead of the holder: not the one it came in by
            for (int m = 0; m < (int)mouths_.size(); ++m)
                if (mouths_[m].passage == lead.passage && m != lead.mouth && (out < 0 || norm(mouths_[m].at - pos[i]) < norm(mouths_[out].at - pos[i])))
                    out = m;
            if (out >= 0) queue(i, out), sent_out_.push_back({i, lead.passage, lead.mouth});
        }
        for (size_t b = first; b < claims_.size(); ++b) {
            const Claim& c = claims_[b];
            if (c.passage != lead.passage || !c.parks || queued(c.robot)) continue;
            for (auto [j, q] : parked_) {
                if (j == c.robot || q != c.passage || !passes(grid, c, goal[c.robot], pos[j]) ||
                    !passes(grid, c, goal[c.robot], goal[j]))
                    continue;
                const ClosedCells plug = plug_at(grid, c.passage, pos[j], pos[c.robot], goal[c.robot]);
                if (guide.walk_steps(map, pos[c.robot], goal[c.robot], plug) < RouteGuide::kRouteUnreachable) {
                    wait[c.robot] = kGoAround;
                    around_[c.robot] = c.passage;
                    plug_of_[c.robot] = (int)plugs_.size() - 1;
                    ++around;
                } else {
                    queue(c.robot, c.mouth);
                    queue(j, c.mouth);
                }
                break;
            }
            // Of two robots coming in by one mouth to goals in the passage, the one that would
            // pass the other's goal goes first: the other, ahead of it, queues until it has.
            // Else the one ahead parks in its way, and both back out (maze-32-32-4).
            for (size_t e = first; e < claims_.size() && !queued(c.robot); ++e) {
                const Claim& d = claims_[e];
                if (e != b && d.passage == c.passage && d.mouth == c.mouth && d.parks && !queued(d.robot) &&
                    passes(grid, c, goal[c.robot], goal[d.robot]) && (d.entry < c.entry || passes(grid, c, goal[c.robot], pos[d.robot])))
                    queue(d.robot, c.mouth);
            }
        }
        return around;
    }
    // Whether a robot at `at` stands in the way of claim c: within two radii (2 free_clear) of a
    // cell of its route in the passage, ahead of it.
    bool in_the_way(const ClearanceGrid& grid, const Claim& c, Vec2 at) const {
        for (int k = c.cells_begin; k < c.cells_end; ++k)
            if (norm(grid.centre(claim_cells_[k]) - at) < 2 * params.free_clear) return true;
        return false;
    }
    // Whether claim c's robot passes a robot at `at` on its way to `goal`: the cell of its route in
    // the passage nearest `at` is within two radii (2 free_clear) and before the goal's cell (a
    // robot beside or beyond the goal is not passed, so of two robots whose goals lie in one
    // corridor in the other's order, one passes the other, not both).
    bool passes(const ClearanceGrid& grid, const Claim& c, Vec2 goal, Vec2 at) const {
        const int goal_cell = grid.index(goal);
        int nearest = -1;
        double best = 2 * params.free_clear;
        for (int k = c.cells_begin; k < c.cells_end; ++k) {
            const double d = norm(grid.centre(claim_cells_[k]) - at);
            if (d < best) best = d, nearest = k;
            if (claim_cells_[k] == goal_cell) return nearest >= 0 && nearest < k;
        }
        return nearest >= 0;
    }
    // A new plug (plugs_.back()) for a robot going from `from` to `goal`: the cells of passage q
    // within two radii (2 free_clear) of the centre of the cell at `at`, but for the robot's own
    // cell and its goal's (goals may lie one map cell, 0.25, apart); its key names the cells.
    ClosedCells plug_at(const ClearanceGrid& grid, int q, Vec2 at, Vec2 from, Vec2 goal) {
        const int k0 = grid.index(at), reach = (int)std::ceil(2 * params.free_clear / grid.cell);
        const int start = grid.index(from), end = grid.index(goal);
        const Vec2 centre = grid.centre(k0);
        Plug plug{closed_key_[q] ^ (0xC2B2AE3D27D4EB4Full * (uint64_t)(k0 + 3)) ^ (0x165667B19E3779F9ull * (uint64_t)(start + 5)) ^
                      (0x27D4EB2F165667C5ull * (uint64_t)(end + 7)), {}};
        for (int row = std::max(0, k0 / grid.n - reach); row <= std::min(grid.n - 1, k0 / grid.n + reach); ++row)
            for (int col = std::max(0, k0 % grid.n - reach); col <= std::min(grid.n - 1, k0 % grid.n + reach); ++col) {
                const int k = row * grid.n + col;
                if (passage_[k] == q && k != start && k != end && norm(grid.centre(k) - centre) < 2 * params.free_clear) plug.cells.push_back(k);
            }
        plugs_.push_back(std::move(plug));
        return {nullptr, -1, plugs_.back().key, &plugs_.back().cells};
    }
    // The first `count` places of the queue at mouth m, nearest first (queue_places). Place k is
    // wait_back + k queue_spacing out from the mouth: right of the way in, left, or on it, the first
    // point that fits (clearance >= free_clear + 0.04, outside any passage) and is near by the
    // free cells (in straight view of the mouth's centre, or its walk from the mouth at most 1.5
    // times as long). Where none is (a mouth at a maze's corner, a wall or the border behind
    // it: the line runs into walls or another aisle), of the fitting cells at least 0.8
    // queue_spacing from the places before it, the one near by nearest the point on the line;
    // with none near by, the one whose walk from the mouth is nearest that distance (docs/design.md,
    // "Queue places"). Place k depends only on the map and the places before it, so each mouth's
    // places are kept (queue_memo_) until the passages or the queue's parameters change.
    void queue_places(const ClearanceGrid& grid, int m, int count, std::vector<Vec2>& places) {
        const double shape[3] = {params.wait_back, params.queue_spacing, params.wait_side};
        if (!std::equal(shape, shape + 3, queue_memo_with_)) queue_memo_.clear(), std::copy(shape, shape + 3, queue_memo_with_);
        queue_memo_.resize(mouths_.size());
        std::vector<Vec2>& memo = queue_memo_[m];
        if ((int)memo.size() < count) find_queue_places(grid, m, count, memo);
        places.assign(memo.begin(), memo.begin() + count);
    }
    void find_queue_places(const ClearanceGrid& grid, int m, int count, std::vector<Vec2>& places) {
        const TrafficConfig& p = params;
        const Mouth& mouth = mouths_[m];
        const double lim = grid.half - p.free_clear;
        auto fits = [&](Vec2 q) {
            return std::abs(q.x) <= lim && std::abs(q.y) <= lim && grid.clear[grid.index(q)] >= p.free_clear + 0.04 &&
                   passage_[grid.index(q)] < 0;
        };
        auto in_view = [&](Vec2 q) {  // over free cells outside passages, every half cell
            const int samples = 1 + (int)std::ceil(2 * norm(q - mouth.at) / grid.cell);
            for (int s = 0; s <= samples; ++s) {
                const int k = grid.index(mouth.at + (q - mouth.at) * ((double)s / samples));
                if (grid.clear[k] < p.free_clear || passage_[k] >= 0) return false;
            }
            return true;
        };
        const Vec2 right{mouth.in.y, -mouth.in.x};
        places.clear();
        double walked_to = -1;  // how far walk_ reaches from this mouth (-1: not walked yet)
        for (int k = 0; k < count; ++k) {
            const double distance = p.wait_back + k * p.queue_spacing;
            const Vec2 base = mouth.at - mouth.in * distance, preferred = base + right * p.wait_side;
            const double reach = 1.5 * (distance + p.wait_side) + 2;  // world units: the free room may begin farther out
            auto walk = [&](Vec2 q) {
                if (walked_to < reach) walk_from(grid, mouth_cells_[m], reach), walked_to = reach;
                return walk_[grid.index(q)];
            };
            auto apart = [&](Vec2 q) {  // from the places before it (straight ones always are)
                for (const Vec2 other : places)
                    if (norm(q - other) < 0.8 * p.queue_spacing) return false;
                return true;
            };
            bool placed = false;
            for (const Vec2 q : {preferred, base - right * p.wait_side, base}) {
                if (!fits(q) || !apart(q)) continue;
                const double w = in_view(q) ? 0 : walk(q);
                if (w >= 0 && w <= 1.5 * norm(q - mouth.at) + 2 * grid.cell) {
                    places.push_back(q);
                    placed = true;
                    break;
                }
            }
            if (placed) continue;
            walk(base);
            int nearest = -1, farther = -1;  // the cells near by nearest the line's point; the one walked about as far
            double nearest_off = 0, farther_gap = 0;
            for (int c : walked_) {
                const Vec2 q = grid.centre(c);
                if (!fits(q) || !apart(q)) continue;
                const double off = norm(q - base), gap = std::abs(walk_[c] - distance);
                if (walk_[c] <= 1.5 * norm(q - mouth.at) + 2 * grid.cell && (nearest < 0 || off < nearest_off)) nearest = c, nearest_off = off;
                if (farther < 0 || gap < farther_gap) farther = c, farther_gap = gap;
            }
            places.push_back(nearest >= 0 ? grid.centre(nearest) : farther >= 0 ? grid.centre(farther) : clamp_box(base, lim));
        }
    }
    // walk_[k] for the cells walked_ lists: the length of the shortest walk (8 directions) from
    // `from` to cell k over free cells outside passages, up to `reach`; the other cells hold -1.
    void walk_from(const ClearanceGrid& grid, const std::vector<int>& from, double reach) {
        const int n = grid.n;
        for (int k : walked_) walk_[k] = -1;
        walked_.clear();
        walk_.resize((size_t)n * n, -1.f);
        using Item = std::pair<float, int>;
        std::priority_queue<Item, std::vector<Item>, std::greater<Item>> open;
        for (int k : from) walk_[k] = 0, walked_.push_back(k), open.push({0.f, k});
        while (!open.empty()) {
            const auto [w, k] = open.top();
            open.pop();
            if (w > walk_[k]) continue;  // reached more cheaply since it was queued
            detail::for_each_neighbour(n, k, [&](int k2) {
                const float w2 = w + (float)(grid.cell * ((k2 / n != k / n && k2 % n != k % n) ? std::sqrt(2.0) : 1.0));
                if (w2 > reach || grid.clear[k2] < params.free_clear || passage_[k2] >= 0 || (walk_[k2] >= 0 && walk_[k2] <= w2)) return;
                if (walk_[k2] < 0) walked_.push_back(k2);
                walk_[k2] = w2;
                open.push({w2, k2});
            });
        }
    }

    // The cells a robot going around avoidable passage p on side s keeps out of (close_side).
    ClosedCells side_cells(int p, int s) const {
        return {nullptr, -1, closed_key_[p] ^ (0x9E3779B97F4A7C15ull * (uint64_t)(s + 1)), &side_closed_[2 * p + s]};
    }
    // Whether claim a comes before b on their passage: one passing through before one whose
    // goal lies in it (make_way; else a robot parked in a corridor holds it for good), then the
    // nearer (fewer route cells before it), then the one with less of it ahead, then the lower
    // id (robots without one, no ids or id < 0, after those with one), then the lower index. By
    // id, not index, a robot planning for itself (the others listed in another order) decides as
    // the team's plan does.
    static bool before(const int* ids, const Claim& a, const Claim& b) {
        if (a.parks != b.parks) return b.parks;
        if (a.entry != b.entry) return a.entry < b.entry;
        if (a.exit != b.exit) return a.exit < b.exit;
        auto rank = [&](const Claim& c) { return ids && ids[c.robot] >= 0 ? ids[c.robot] : std::numeric_limits<int>::max(); };
        return rank(a) != rank(b) ? rank(a) < rank(b) : a.robot < b.robot;
    }
    // Robots going around passage `id` (around_) take its two sides in turn, in before() order
    // (the nearest first): each the side whose way to its goal, plus `spread` per robot already
    // going that side, is shortest (ties: the shorter way, then side 0). Two robots queueing
    // through the same gap beside a corridor lose more than one going a little farther round.
    void spread_around(RouteGuide& guide, const WorldMap& map, int id, const Vec2* pos, const Vec2* goal, const int* ids) {
        going_.clear();
        for (int c = 0; c < (int)claims_.size(); ++c)
            if (around_[claims_[c].robot] == id) going_.push_back(c);
        std::sort(going_.begin(), going_.end(), [&](int a, int b) { return before(ids, claims_[a], claims_[b]); });
        int taking[2] = {0, 0};
        for (int c : going_) {
            const int r = claims_[c].robot;
            double cost[2];
            int steps[2];
            for (int s = 0; s < 2; ++s) {
                steps[s] = guide.walk_steps(map, pos[r], goal[r], side_cells(id, s));
                cost[s] = steps[s] * guide.cell + params.spread * taking[s];
            }
            int side = cost[1] < cost[0] || (cost[1] == cost[0] && steps[1] < steps[0]) ? 1 : 0;
            if (steps[side] >= RouteGuide::kRouteUnreachable) side = -1;  // neither side has a way: keep out of the passage only
            around_side_[r] = side;
            if (side >= 0) ++taking[side];
        }
    }
    // The cells a robot going around the passage of `cells` (mouths a, b) on side `side` keeps
    // out of (listed, sorted, in `closed`): the passage, and a band 3 cells wide from its middle
    // across the other side, through the wall there and the free space beyond, to the next
    // obstacle or the border. That side's way around crosses the band, so the robot's way takes
    // side `side`.
    void close_side(const ClearanceGrid& grid, const std::vector<int>& cells, const Mouth& a, const Mouth& b, int side, std::vector<int>& closed) const {
        const int n = grid.n;
        closed.assign(cells.begin(), cells.end());  // a list, not a grid: fine grids have many passages
        const Vec2 middle = (a.at + b.at) * 0.5, u = normalized(b.at - a.at);
        const Vec2 across = side == 0 ? Vec2{u.y, -u.x} : Vec2{-u.y, u.x};  // side 0 passes left of a -> b: close the right
        int start = cells[0];
        for (int c : cells)
            if (norm(grid.centre(c) - middle) < norm(grid.centre(start) - middle)) start = c;
        int phase = 0;  // 0: in the passage, 1: in the wall beside it, 2: in the free space beyond
        for (double t = 0;; t += 0.5 * grid.cell) {
            const Vec2 q = grid.centre(start) + across * t;
            if (std::abs(q.x) >= grid.half || std::abs(q.y) >= grid.half) break;
            const int k = grid.index(q);
            const bool blocked = grid.clear[k] < params.free_clear;
            if (phase == 0 && blocked) phase = 1;
            if (phase == 1 && !blocked) phase = 2;
            if (phase == 2 && blocked) break;
            closed.push_back(k);
            detail::for_each_neighbour(n, k, [&](int k2) { closed.push_back(k2); });
        }
        std::sort(closed.begin(), closed.end());
        closed.erase(std::unique(closed.begin(), closed.end()), closed.end());
    }
    // 8-connected flood from `seed` over the cells k with open(k) (not yet labelled): labels them
    // `id` and appends them to out.
    template <class Open>
    void flood(int n, int seed, Open open, std::vector<int>& label, int id, std::vector<int>& out) {
        queue_.assign(1, seed);
        label[seed] = id;
        for (size_t head = 0; head < queue_.size(); ++head) {
            out.push_back(queue_[head]);
            detail::for_each_neighbour(n, queue_[head], [&](int k2) {
                if (open(k2)) label[k2] = id, queue_.push_back(k2);
            });
        }
    }
    // Whether the free cells outside component `id` reached from `group` are all one-lane.
    bool pocket(const ClearanceGrid& grid, const std::vector<int>& one_lane, const std::vector<int>& component, int id,
                const std::vector<int>& group) {
        if (std::any_of(group.begin(), group.end(), [&](int g) { return one_lane[g] < 0; })) return false;  // the usual mouth
        const int n = grid.n;
        std::vector<char> seen((size_t)n * n, 0);
        queue_ = group;
        for (int g : group) seen[g] = 1;
        for (size_t head = 0; head < queue_.size(); ++head) {
            if (one_lane[queue_[head]] < 0) return false;
            detail::for_each_neighbour(n, queue_[head], [&](int k2) {
                if (seen[k2] || component[k2] == id || grid.clear[k2] < params.free_clear) return;
                seen[k2] = 1;
                queue_.push_back(k2);
            });
        }
        return true;
    }
    // Whether a walk of at most `steps` cells through free cells outside component `id` leads from
    // mouth `from` to another mouth of the same passage (mouths from `from` on are that passage's).
    bool way_around(const ClearanceGrid& grid, const std::vector<int>& component, int id, int from, int steps) {
        const int n = grid.n;
        std::vector<int> depth((size_t)n * n, -1);
        queue_.clear();
        for (int k = 0; k < n * n; ++k)
            if (mouth_[k] == from) depth[k] = 0, queue_.push_back(k);
        for (size_t head = 0; head < queue_.size(); ++head) {
            const int k = queue_[head];
            if (mouth_[k] > from) return true;
            if (depth[k] >= steps) continue;
            detail::for_each_neighbour(n, k, [&](int k2) {
                if (depth[k2] >= 0 || component[k2] == id || grid.clear[k2] < params.free_clear) return;
                depth[k2] = depth[k] + 1;
                queue_.push_back(k2);
            });
        }
        return false;
    }
    void find_passages(const ClearanceGrid& grid, const WorldMap& map) {
        const int n = grid.n;
        const double chord_max = params.one_lane_width - 2 * params.free_clear, step = 0.5 * grid.cell;
        auto fits = [&](Vec2 q) {
            if (std::abs(q.x) >= grid.half || std::abs(q.y) >= grid.half) return false;
            return grid.clear[grid.index(q)] >= params.free_clear;
        };
        // One-lane cells, keyed by the two obstacle groups their shortest chord ends at: a
        // corridor's cells all end at its two walls, so a narrow gap between a wall's end and a
        // disc nearby, or a disc and the border, does not join it into a junction.
        const std::vector<int> surface_group = detail::surface_groups(map, 2 * params.free_clear);
        const int groups = 1 + *std::max_element(surface_group.begin(), surface_group.end());
        std::vector<int> one_lane((size_t)n * n, -1);  // the key of a one-lane cell (< (kMaxObstacles + 1)^2), else -1
        for (int k = 0; k < n * n; ++k) {
            if (grid.clear[k] < params.free_clear) continue;
            const Vec2 c = grid.centre(k);
            double shortest = chord_max;
            Vec2 ends[2];
            for (int d = 0; d < 8; ++d) {
                const double angle = d * 0.39269908169872414;  // pi / 8
                const Vec2 u{std::cos(angle), std::sin(angle)};
                double chord = 0;
                Vec2 end[2];
                for (int side = 0; side < 2 && chord < shortest; ++side) {
                    const Vec2 way = side ? u : u * -1.0;
                    double s = step;
                    for (; chord < shortest && fits(c + way * s); s += step) chord += step;
                    end[side] = c + way * s;
                }
                if (chord < shortest) shortest = chord, ends[0] = end[0], ends[1] = end[1];
            }
            if (shortest >= chord_max) continue;
            const int a = surface_group[detail::nearest_surface(map, ends[0])], b = surface_group[detail::nearest_surface(map, ends[1])];
            one_lane[k] = std::min(a, b) * groups + std::max(a, b);
        }
        one_lane_.resize((size_t)n * n);
        for (size_t k = 0; k < one_lane.size(); ++k) one_lane_[k] = one_lane[k] >= 0;
        passage_.assign((size_t)n * n, -1);
        mouth_.assign((size_t)n * n, -1);
        mouths_.clear();
        mouth_cells_.clear();
        queue_memo_.clear();
        avoidable_.clear();
        closed_key_.clear();
        box_.clear();
        side_closed_.clear();
        std::vector<int> component((size_t)n * n, -1), cells, group;
        int passages = 0, components = 0;
        for (int k = 0; k < n * n; ++k) {
            if (one_lane[k] < 0 || component[k] != -1) continue;
            cells.clear();
            const int id = components++;
            flood(n, k, [&](int k2) { return one_lane[k2] == one_lane[k] && component[k2] == -1; }, component, id, cells);
            // Its mouths: free cells beside it (other one-lane cells too), not yet another
            // passage's, grouped by connection; a pocket (a sliver beside a wall's end, from which
            // no free cell outside a one-lane region is reached without crossing the passage) is
            // no mouth.
            std::vector<int> beside;
            for (int c : cells)
                detail::for_each_neighbour(n, c, [&](int k2) {
                    if (grid.clear[k2] >= params.free_clear && component[k2] != id && mouth_[k2] == -1)
                        mouth_[k2] = -3, beside.push_back(k2);  // -3: beside, ungrouped
                });
            const size_t first_mouth = mouths_.size();
            for (int b : beside) {
                if (mouth_[b] != -3) continue;
                group.clear();
                flood(n, b, [&](int k2) { return mouth_[k2] == -3; }, mouth_, (int)mouths_.size(), group);
                if (pocket(grid, one_lane, component, id, group)) {
                    for (int g : group) mouth_[g] = -1;
                    continue;
                }
                Mouth m;
                m.passage = passages;
                Vec2 inner;
                int inner_count = 0;
                for (int g : group) {
                    m.at += grid.centre(g);
                    for (int c : cells)
                        if (std::abs(c / n - g / n) <= 1 && std::abs(c % n - g % n) <= 1) inner += grid.centre(c), ++inner_count;
                }
                m.at = m.at / (double)group.size();
                m.in = normalized(inner / (double)std::max(1, inner_count) - m.at);
                mouths_.push_back(m);
                mouth_cells_.push_back(group);
            }
            // A corner or a dead end (one mouth) is no passage; nor is a junction (three or more),
            // a doorway (mouths less than min_length apart), or without go_around one with a way
            // around at most `bypass` longer.
            double length = 0;
            for (size_t m = first_mouth + 1; m < mouths_.size(); ++m) length = std::max(length, norm(mouths_[m].at - mouths_[first_mouth].at));
            const bool corridor = mouths_.size() - first_mouth == 2 && length >= params.min_length;
            const bool avoidable = corridor && way_around(grid, component, id, (int)first_mouth, (int)std::ceil((length + params.bypass) / grid.cell));
            if (!corridor || (avoidable && !params.go_around)) {
                for (int b : beside) mouth_[b] = -1;
                mouths_.resize(first_mouth);
                mouth_cells_.resize(first_mouth);
                continue;
            }
            avoidable_.push_back(avoidable);
            uint64_t key = 1469598103934665603ull;  // FNV-1a of the cells: the same key means the same cells
            Box box{grid.centre(cells[0]), grid.centre(cells[0])};
            for (int c : cells) {
                passage_[c] = passages;
                key = (key ^ (uint64_t)c) * 1099511628211ull;
                const Vec2 q = grid.centre(c);
                box = {{std::min(box.lo.x, q.x), std::min(box.lo.y, q.y)}, {std::max(box.hi.x, q.x), std::max(box.hi.y, q.y)}};
            }
            box_.push_back(box);
            closed_key_.push_back(key | 1);  // never 0 (no cells)
            side_closed_.resize(2 * (passages + 1));
            if (avoidable)
                for (int side = 0; side < 2; ++side)
                    close_side(grid, cells, mouths_[first_mouth], mouths_[first_mouth + 1], side, side_closed_[2 * passages + side]);
            ++passages;
        }
        map_ = map;
    }
};

// The expert's turns: the planner's (TrafficConfig), but a claim from another mouth waits until
// those inside are 0.1 out (`spare`; the planner's 0). The expert's robots track grid plans with
// lag, so one coming in planned to enter as another leaves met it nose to nose in the mouth
// (maze-32-32-4, seed 0 at cell 0.3 with 32 robots; docs/experiments.md, "The expert's line
// through an aisle").
inline TrafficConfig expert_traffic() {
    TrafficConfig traffic = PlannerConfig{}.traffic;
    traffic.spare = 0.1;
    traffic.pocket_order = true;
    return traffic;
}

// The guided expert's traffic rule with the planner's conventions (ExpertTraffic, madbp_sim.hpp
// Section 12): before each of its plans, PassageControl with `traffic` decides who holds each
// one-lane passage, and the expert plans a robot that waits to its queue place and one that goes
// around out of the passage's cells, both after the others, and a robot going on through a
// passage right after the one ahead of it there (follow_order). Without it, two robots meeting
// head-on in a maze's one-cell aisle, or one parked at its goal in another's way, hold each other
// for good (issue 46). Use: GuidedExpert expert(map, ExpertParams{}, passage_traffic());
// traffic.take_turns false: no rule (each robot heads for its goal). Each call makes a rule with
// its own state (the passages found, scratch arrays): give each expert its own.
inline ExpertTraffic passage_traffic(const TrafficConfig& traffic = expert_traffic()) {
    if (!traffic.take_turns) return nullptr;
    struct State {
        PassageControl control;
        std::vector<Vec2> pos, goal, point;
        std::vector<char> at_goal, turn;
        std::vector<int> ids, ahead;
    };
    auto state = std::make_shared<State>();
    state->control.params = traffic;
    return [state](const World& world, RouteGuide& guide, std::vector<ExpertHeading>& heading) {
        State& s = *state;
        const auto& ag = world.agents();
        const int n = (int)ag.size();
        s.pos.resize(n), s.goal.resize(n), s.at_goal.resize(n), s.ids.resize(n);
        for (int i = 0; i < n; ++i) {
            s.pos[i] = ag[i].pos, s.goal[i] = ag[i].goal, s.ids[i] = ag[i].id;
            s.at_goal[i] = world.at_goal(ag[i]);
        }
        s.control.arbitrate(guide, world.map(), n, s.pos.data(), s.goal.data(), s.at_goal.data(), s.turn, s.point, s.ids.data());
        s.control.follow_order(guide, s.turn, s.pos.data(), s.goal.data(), s.ahead);
        for (int i = 0; i < n; ++i) {
            if (s.turn[i] == PassageControl::kWait) heading[i] = ExpertHeading{s.point[i], {}, true};
            if (s.turn[i] == PassageControl::kGoAround) heading[i] = ExpertHeading{s.goal[i], s.control.closed_to(i), true};
            heading[i].after = s.ahead[i];
        }
    };
}

// Routes around crowds (issue 47). In a team larger than a scene, the straight ways between
// random starts and goals cross most near the world's centre; at constant density the robots
// that meet there grow with the world's side, and at 128 robots among obstacles they stand in
// crowds of 15-20 for 100-250 steps (docs/experiments.md, "Where crowds of 128 knot"). Traffic
// planning spreads them: CrowdRoutes routes each robot over a coarse grid of cells `crowd_cell`
// wide whose step into a cell costs its length times 1 + crowd_weight x the robots already
// routed through it per its free area, so a robot whose straight way runs
// through a crowded middle goes around it when that costs less. Robots are routed one at a time,
// in index order, each against the routes before it, and again every kCrowdReroute steps (or when
// pushed off their route or given a new goal), each against everyone else's as they stand then.
// Only on open ground and for a way of kCrowdMinWay cells or more: a robot whose map route winds
// (open_ground), or that is near its goal, keeps its map route. Parked robots are not counted:
// every route must end among them, and counting them sent robots near their goals on detours.
//   - Coarse cells: each has a point (the free fine cell, clearance >= preferred, nearest its
//     centre) and an area (its share of fine cells a robot's centre fits in); a step between two
//     cells is allowed when the segment between their points crosses only cells with the
//     preferred clearance (RouteGuide::straight).
//   - Following: a robot heads for the point of the route cell kCrowdAhead cells past the one
//     nearest it, then for its goal once that is the goal's cell; when the route, as made, strays
//     less than a cell from the straight way to the goal, for the goal itself (so the route
//     changes nothing where there is no crowd to go around).
// In a team of crowd_time_from robots or more (with crowd_time W > 0) a route counts in a cell
// only about when its robot is due there, at weight crowd_time_weight: the
// demand is kept per time bin of W steps (kCrowdBins of them, from now), a route's cell adding to
// the bin of the step its robot reaches it at cruise (ExpertParams::cell a step along the route's
// points) and the bins either side, and a step of the search into a cell reads the bin of the
// time it arrives. So routes that cross a middle cell at different times leave each other
// straight, as the expert's reservations do, and only robots due together spread.
// Memory: a few floats a coarse cell (at most kCrowdMaxSide^2, times kCrowdBins with crowd_time)
// and each robot's route cells.
class CrowdRoutes {
public:
    static constexpr int kCrowdMaxSide = 96;   // coarse cells a side (a huge world gets larger cells)
    static constexpr int kCrowdReroute = 40;   // steps a route is kept before it is made again
    static constexpr int kCrowdAhead = 2;      // a robot heads this many route cells past its own
    static constexpr int kCrowdMinWay = 4;     // a robot fewer cells than this from its goal heads for it
    static constexpr int kCrowdBins = 16;      // time bins of crowd_time steps each (later arrivals count in the last)

    // Where each of the n robots heads (target[i]: goal[i] where its route goes straight there).
    void update(RouteGuide& guide, const WorldMap& map, const TrafficConfig& p, int n, const Vec2* pos, const Vec2* goal,
                const char* at_goal, const int* ids, long step, std::vector<Vec2>& target) {
        const bool in_time = p.crowd_time > 0 && n >= p.crowd_time_from;
        const double weight = in_time ? p.crowd_time_weight : p.crowd_weight;
        set_map(guide, map, p, in_time ? p.crowd_time : 0);
        target.assign(goal, goal + n);
        // Forget robots gone (without allocating: plans in a steady state allocate nothing); then
        // the demand of every remaining route from where its robot is.
        present_.assign(ids, ids + n);
        std::sort(present_.begin(), present_.end());
        for (auto it = routes_.begin(); it != routes_.end();)
            it = std::binary_search(present_.begin(), present_.end(), it->first) ? std::next(it) : routes_.erase(it);
        std::fill(demand_.begin(), demand_.end(), 0.f);
        index_.assign(n, -1);
        for (int i = 0; i < n; ++i) {
            if (at_goal[i]) continue;
            auto it = routes_.find(ids[i]);
            if (it == routes_.end()) continue;
            Route& r = it->second;
            index_[i] = progress(r, pos[i]);
            if (index_[i] >= 0) add(r, index_[i], pos[i], +1);
        }
        // The routes made again (stale_), those of them on coarse cells whose straight way is
        // clear on the grid (straight_: open ground without a field; the route then costs at most
        // its chebyshev cells + 2, under open_ground's bound), and the goals of the others, whose
        // fields open_ground reads and the guide may make ahead (RouteGuide::expect). An empty
        // world's first plan of 1024 robots made a whole-grid wavefront per robot without
        // straight_ (docs/speed.md).
        stale_.assign(n, 0);
        straight_.assign(n, 0);
        walk_goals_.clear();
        for (int i = 0; i < n; ++i) {
            if (at_goal[i]) continue;
            const Route& r = routes_[ids[i]];
            stale_[i] = index_[i] < 0 || !(r.goal == goal[i]) || step < r.made || step - r.made >= kCrowdReroute;
            if (!stale_[i] || !routes_on_cells(pos[i], goal[i])) continue;
            straight_[i] = guide.straight(map, pos[i], goal[i]);
            if (!straight_[i]) walk_goals_.push_back(goal[i]);
        }
        const RouteGuide::Expecting expecting = guide.expect(map, walk_goals_, detail::fields_ahead_batch());
        for (int i = 0; i < n; ++i) {
            if (at_goal[i]) continue;
            Route& r = routes_[ids[i]];
            if (stale_[i]) {
                if (index_[i] >= 0) add(r, index_[i], pos[i], -1);
                if (routes_on_cells(pos[i], goal[i]) && (straight_[i] || open_ground(guide, map, pos[i], goal[i]))) {
                    const double way = route(r, pos[i], goal[i], weight);
                    if (p.crowd_detour > 0 && way > p.crowd_detour * norm(goal[i] - pos[i]) + cell_) route(r, pos[i], goal[i], 0);
                }
                else r.cells.assign(1, cell_of(goal[i]));  // near, or a winding way: its map route, as without crowds
                r.goal = goal[i], r.made = step, r.straight = along_straight_way(r, pos[i], goal[i]);
                index_[i] = 0;
                add(r, 0, pos[i], +1);
            }
            if (!r.straight && index_[i] + kCrowdAhead < (int)r.cells.size() - 1) target[i] = point_[r.cells[index_[i] + kCrowdAhead]];
        }
    }

private:
    struct Route {
        Vec2 goal;
        long made = 0;
        bool straight = true;    // it keeps within a cell of the straight way to the goal: the robot heads for the goal
        std::vector<int> cells;  // coarse cells from the robot's to its goal's
    };
    WorldMap map_;
    int side_ = 0;
    double lo_ = 0, cell_ = 1;
    std::vector<Vec2> point_;      // per coarse cell: where a route through it passes
    std::vector<float> area_;      // per coarse cell: the share of it a robot's centre fits in (0: none)
    std::vector<uint8_t> links_;   // per coarse cell: bit d, the step to neighbour d (kDr, kDc) is clear
    std::vector<float> demand_;    // per time bin and coarse cell (bin * side^2 + cell): routes through it
    int bins_ = 1;                 // time bins: 1 (routes count whenever) or kCrowdBins
    double bin_steps_ = 0;         // steps a time bin spans (crowd_time in time; 0: one bin for all time)
    double step_length_ = ExpertParams{}.cell;  // world units a robot covers a step at cruise
    std::map<int, Route> routes_;  // by robot id
    std::vector<int> index_;       // per robot of this call: its place on its route (-1: none)
    std::vector<char> stale_;      // per robot of this call: its route is made again
    std::vector<char> straight_;   // and its straight way is clear on the grid (open ground)
    std::vector<Vec2> walk_goals_;  // the goals of the stale routes that walk the map's route, in order
    std::vector<int> present_;     // this call's ids, sorted
    std::vector<double> cost_;     // Dijkstra's scratch: costs, way lengths, the cell each came from, the heap
    std::vector<double> way_;
    std::vector<int> from_;
    std::vector<std::pair<double, int>> heap_;
    static constexpr int kDr[8] = {-1, -1, -1, 0, 0, 1, 1, 1}, kDc[8] = {-1, 0, 1, -1, 1, -1, 0, 1};

    // A route from a to goal is made on the coarse cells only when the goal is this far (and the
    // ground open, open_ground, which walks the guide's field): else the map's route is kept.
    bool routes_on_cells(Vec2 a, Vec2 goal) const { return norm(goal - a) > kCrowdMinWay * cell_; }
    int cell_of(Vec2 q) const {
        const int col = std::clamp((int)std::floor((q.x - lo_) / cell_), 0, side_ - 1);
        const int row = std::clamp((int)std::floor((q.y - lo_) / cell_), 0, side_ - 1);
        return row * side_ + col;
    }
    Vec2 centre(int k) const { return {lo_ + (k % side_ + 0.5) * cell_, lo_ + (k / side_ + 0.5) * cell_}; }

    void set_map(RouteGuide& guide, const WorldMap& map, const TrafficConfig& p, double bin_steps) {
        const double h = map.half_size;
        // The cells fit the world, so cell_ is crowd_cell rounded: compare the side, not the cell
        // (comparing cell_ with crowd_cell remade every route every plan where 2h / crowd_cell
        // is not a whole number).
        const int side = std::max(1, (int)std::ceil(2 * h / std::max(p.crowd_cell, 2 * h / kCrowdMaxSide) - 1e-9));
        if (side == side_ && map == map_ && bin_steps == bin_steps_) return;
        map_ = map;
        bin_steps_ = bin_steps;
        bins_ = bin_steps_ > 0 ? kCrowdBins : 1;
        side_ = side;
        cell_ = 2 * h / side_;
        lo_ = -h;
        routes_.clear();
        const int cells = side_ * side_;
        point_.assign(cells, Vec2{});
        area_.assign(cells, 0.f);
        links_.assign(cells, 0);
        demand_.assign((size_t)cells * bins_, 0.f);
        const ClearanceGrid& g = guide.grid(map);
        std::vector<int> fits(cells, 0), all(cells, 0);
        std::vector<double> best(cells, std::numeric_limits<double>::infinity());
        for (int k = 0; k < g.n * g.n; ++k) {
            const Vec2 c = g.centre(k);
            const int q = cell_of(c);
            ++all[q];
            if (g.clear[k] >= p.free_clear) ++fits[q];
            const double d = norm(c - centre(q));
            if (g.clear[k] >= guide.clear && d < best[q]) best[q] = d, point_[q] = c;
        }
        for (int q = 0; q < cells; ++q) area_[q] = std::isfinite(best[q]) && all[q] > 0 ? (float)fits[q] / all[q] : 0.f;
        for (int q = 0; q < cells; ++q) {
            if (area_[q] == 0) continue;
            const int r = q / side_, c = q % side_;
            for (int d = 0; d < 8; ++d) {
                const int r2 = r + kDr[d], c2 = c + kDc[d];
                if (r2 < 0 || r2 >= side_ || c2 < 0 || c2 >= side_) continue;
                const int q2 = r2 * side_ + c2;
                if (area_[q2] > 0 && guide.straight(map, point_[q], point_[q2])) links_[q] |= (uint8_t)(1u << d);
            }
        }
    }
    // The map route from a to goal is at most kCrowdOpenRatio times the straight way (both in
    // the grid's 8-direction moves; a narrow cell costs more): a crowd there can be gone around.
    // A winding way (a maze, rooms, a one-lane passage) keeps its map route and PassageControl's
    // turns: the coarse cells may miss a one-cell door that the map route goes through.
    static constexpr double kCrowdOpenRatio = 1.3;
    bool open_ground(RouteGuide& guide, const WorldMap& map, Vec2 a, Vec2 goal) const {
        const ClearanceGrid& g = guide.grid(map);
        const int steps = guide.route_steps(map, a, goal);
        const double chebyshev = std::max(std::fabs(goal.x - a.x), std::fabs(goal.y - a.y)) / g.cell;
        return steps < RouteGuide::kRouteUnreachable && steps <= kCrowdOpenRatio * chebyshev + 2 + guide.narrow_cost;  // a robot may stand in one narrow cell
    }
    // The time bin a robot that has come `way` world units along its route is in (bins_: beyond
    // them; add() counts those in the last bin, the search reads nothing there).
    int bin_of(double way) const {
        if (bins_ == 1) return 0;
        return (int)std::min<double>(bins_, std::floor(way / step_length_ / bin_steps_));
    }
    // Adds `sign` to the demand of r's cells from index `from` on, for its robot at q: with time
    // bins, each cell in the bin of its arrival and the bins either side.
    void add(const Route& r, int from, Vec2 q, float sign) {
        const size_t cells = (size_t)side_ * side_;
        double way = 0;
        for (size_t k = (size_t)from; k < r.cells.size(); ++k) {
            way += norm(point_[r.cells[k]] - q), q = point_[r.cells[k]];
            const int b = bin_of(way);
            for (int bb = std::max(0, b - 1); bb <= std::min(bins_ - 1, b + 1); ++bb) demand_[bb * cells + r.cells[k]] += sign;
        }
    }
    // The index of r's cell whose centre is nearest q, or -1 when q strayed more than a cell and
    // a half from all of them (the route is made again).
    int progress(const Route& r, Vec2 q) const {
        int best = -1;
        double best_d = 1.5 * cell_;
        for (int k = 0; k < (int)r.cells.size(); ++k) {
            const double d = norm(q - centre(r.cells[k]));
            if (d <= best_d) best_d = d, best = k;
        }
        return best;
    }
    // Dijkstra over the coarse cells from a's to goal's: a step costs its length times
    // 1 + weight x demand / area of the cell stepped into (an area below a quarter counts a quarter).
    // Returns the route's length through its cells' points (0 when there is no coarse way).
    double route(Route& r, Vec2 a, Vec2 goal, double weight) {
        const int cells = side_ * side_, start = cell_of(a), end = cell_of(goal);
        cost_.assign(cells, std::numeric_limits<double>::infinity());
        way_.assign(cells, 0.0);
        from_.assign(cells, -1);
        const auto later = std::greater<std::pair<double, int>>();  // a min-heap
        heap_.assign(1, {0.0, start});
        cost_[start] = 0;
        while (!heap_.empty()) {
            std::pop_heap(heap_.begin(), heap_.end(), later);
            const auto [d, q] = heap_.back();
            heap_.pop_back();
            if (d > cost_[q]) continue;
            if (q == end) break;
            const int row = q / side_, col = q % side_;
            for (int k = 0; k < 8; ++k) {
                if (!(links_[q] >> k & 1u) && q != start) continue;  // the start cell's point may not be where the robot is
                const int r2 = row + kDr[k], c2 = col + kDc[k];
                if (r2 < 0 || r2 >= side_ || c2 < 0 || c2 >= side_) continue;
                const int q2 = r2 * side_ + c2;
                if (area_[q2] == 0) continue;
                const double length = norm(point_[q2] - (q == start ? a : point_[q]));
                const int b = bin_of(way_[q] + length);
                const float demand = b < bins_ ? demand_[(size_t)b * cells + q2] : 0.f;
                const double step = length * (1 + weight * demand / std::max(area_[q2], 0.25f));
                if (d + step < cost_[q2]) {
                    cost_[q2] = d + step, way_[q2] = way_[q] + length, from_[q2] = q;
                    heap_.push_back({d + step, q2});
                    std::push_heap(heap_.begin(), heap_.end(), later);
                }
            }
        }
        r.cells.clear();
        if (!std::isfinite(cost_[end])) {  // no coarse way: the goal's own cell, so the robot heads straight for it
            r.cells.push_back(end);
            return 0;
        }
        for (int q = end; q >= 0; q = from_[q]) r.cells.push_back(q);
        std::reverse(r.cells.begin(), r.cells.end());
        return way_[end];
    }
    // Route r from q keeps within a cell of the straight way to the goal all along. Decided when
    // the route is made, not every plan: a robot whose heading flipped between its goal and its
    // route's next point from plan to plan stood between two discs for 290 steps.
    bool along_straight_way(const Route& r, Vec2 q, Vec2 goal) const {
        const Vec2 d = goal - q;
        const double len2 = std::max(dot(d, d), 1e-12);
        for (int k : r.cells) {
            const Vec2 c = point_[k];
            const double t = std::clamp(dot(c - q, d) / len2, 0.0, 1.0);
            if (norm(q + d * t - c) > cell_) return false;
        }
        return true;
    }
};

// =============================================================================================
// Section 9. Moving-window planner (SPEC 8): DiffusionPlanner, make_follower, DecentralisedTeam
// =============================================================================================

// Bytes a plan's sampling needs (PlannerConfig::workspace.max_mb checks it before allocating):
// the scenes' inputs and windows, (scenes x K robot slots, linear in the team), plus per thread
// the network's activations for one chunk of chunk_scenes scenes, each drawn `candidates`
// times. The activations per robot slot are an upper estimate, measured for the shipped model
// (docs/limits.md); the planner's other memory (routes, map fields) is not counted.
inline double planner_workspace_bytes(const ModelConfig& c, int scenes, int K, int candidates, int chunk_scenes, int threads) {
    const double H = c.horizon, G2 = (double)c.grid * c.grid, Gl2 = (double)c.local_grid * c.local_grid;
    double width = c.dim;
    for (int ch : c.channels) width += ch;
    // One robot slot's inputs (pose, mask, its map crop) and windows (x, warm, decoded), and a scene's grid.
    const double slot_inputs = 4.0 * (8 + Gl2 + 4 * 2 * H), scene_inputs = 4.0 * G2;
    const double all = (double)scenes * (K * slot_inputs + scene_inputs);
    // A chunk's activations per robot slot: the processor's and U-Net's feature maps (about
    // kActivationFloats floats per unit of width per waypoint), the map crop's convolutions,
    // the attention scores; per scene, the map's convolutions.
    constexpr double kActivationFloats = 40;
    const double slot_activations = 4.0 * (kActivationFloats * width * H + 16 * Gl2 + 2.0 * c.heads * H * H),
                 scene_activations = 4.0 * 16 * G2;
    const int chunk = std::min(chunk_scenes, std::max(scenes, 1));
    const double per_thread = (double)chunk * candidates * (K * (slot_activations + slot_inputs) + scene_activations + scene_inputs);
    return all + std::max(threads, 1) * per_thread;
}

// Plans a window for every present agent of a World with one shared model. Plug it into a
// PlanFollower (madbp_sim.hpp) to execute the first m waypoints and replan:
//   madbp::DiffusionPlanner planner(madbp::load_model("models/madbp-default.safetensors"));
//   madbp::PlanFollower follower = madbp::make_follower(planner);
// A robot that plans for itself (decentralised) calls plan_robot with what it knows instead.
// A planner remembers its last plan (PlannerConfig::sampler.warm_start): use one per world.
// Every setting is in `settings` (PlannerConfig, Section 7); change them between plans freely.
class DiffusionPlanner {
public:
    // Another robot as one robot knows it: position and goal as received from it.
    struct Neighbour {
        Vec2 pos, goal;
        int id = -1;  // breaks ties in taking turns (take_turns: the lower id goes first, -1 after any id)
    };
    PlannerConfig settings;
    int last_plan_candidates() const { return last_k_; }  // candidates per scene the last plan drew
    // What the last plan (or plan_robot) asks: traffic.passage_replan while robots of its scenes
    // may meet in a passage, else 0 (Plan::replan_after).
    int replan_after() const {
        const TrafficConfig& t = settings.traffic;
        if (t.passage_replan <= 0 || !t.take_turns) return 0;
        bool waits = false;
        for (size_t i = 0; i < waiting_.size(); ++i) waits = waits || (in_scene_[i] && waiting_[i] == PassageControl::kWait);
        return waits || passages_.contested() ? t.passage_replan : 0;
    }

    explicit DiffusionPlanner(MadbpModel model, uint64_t seed = 0, PlannerConfig planner_settings = PlannerConfig::tuned())
        : settings(std::move(planner_settings)), model_(std::move(model)), schedule_(model_.config.diffusion_steps), rng_(seed) {
        model_.set_training(false);
        guide_.run_ahead = detail::run_on_threads;  // a first plan's fields, on the threads
    }
    const ModelConfig& config() const { return model_.config; }
    MadbpModel& model() { return model_; }
    // The sampler options a plan uses now (settings resolved for this model).
    SamplerConfig sampler() const { return settings.sampler_config(model_.config); }
    const SceneBatch& last_scene_batch() const { return batch_; }  // what the model saw in the last plan
    // The agent column of last_scene_batch() whose window robot i (the world's agent i) got in the
    // last plan() (scene a / n, slot a % n).
    int last_window_agent(int i) const { return window_col_.at((size_t)i); }
    const ConflictWorkspace& last_candidates() const { return conflict_; }  // costs and choices of the last conflict-aware plan
    const PassageControl& passages() const { return passages_; }            // the one-lane passages of the last plan's map
    // Per robot of the last plan (take_turns): PassageControl::kWait, waits to take its turn
    // through a one-lane passage, at last_wait_points()[i]; kGoAround, goes around one; kGoOn.
    const std::vector<char>& last_waiting() const { return waiting_; }
    const std::vector<Vec2>& last_wait_points() const { return wait_point_; }
    const std::vector<Vec2>& last_crowd_targets() const { return crowd_target_; }  // traffic.crowd_weight: where each robot headed (empty: none)
    void reseed(uint64_t seed) { rng_.reseed(seed); }

    // Robots per scene (at most) when planning a team of n in a world of half-size `half_size`,
    // by the rule of `neighbours`; neighbourhood planning when this is < n or the world is larger
    // than the training world.
    int neighbourhood(int n, double half_size) const {
        const ModelConfig& c = model_.config;
        const int K = neighbourhood_size();
        const int neighbours = settings.neighbourhood.neighbours;
        if (neighbours == 0) return n;
        if (neighbours < 0 && half_size <= c.position_scale * (1 + 1e-9) && n <= c.n_max) return n;  // the training world: one scene
        return std::min(K, n);
    }
    // K, the robots of a neighbourhood scene: `neighbours`, or when automatic ceil(1.5 n_train_max)
    // (n_max when n_train_max is unknown), at most n_max.
    int neighbourhood_size() const {
        const ModelConfig& c = model_.config;
        const int neighbours = settings.neighbourhood.neighbours;
        if (neighbours < -1)
            throw std::invalid_argument("planner setting neighbourhood.neighbours: must be [0, 1024] or auto (got " + std::to_string(neighbours) + ")");
        if (neighbours >= 0) return neighbours;  // 0: the whole team
        return std::min(c.n_train_max > 0 ? (3 * c.n_train_max + 1) / 2 : c.n_max, c.n_max);
    }

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
        const int n = world.size();
        out.ids.resize(n);
        out.waypoints.resize(n);
        if (n == 0) { out.plan_ms = 0; return; }
        for (const Agent& a : world.agents())
            if (!std::isfinite(a.pos.x + a.pos.y + a.goal.x + a.goal.y))  // the message only on failure: no allocation
                throw std::invalid_argument("planner: agent " + std::to_string(a.id) + " has a non-finite position or goal");
        const int K = neighbourhood(n, world.map().half_size);
        // Neighbourhood scenes unless one scene of the whole team was asked for or chosen.
        const bool local = settings.neighbourhood.neighbours != 0 && (K < n || world.map().half_size > model_.config.position_scale * (1 + 1e-9));
        const SceneRule rule = !local ? SceneRule::Whole : settings.neighbourhood.cover > 0 ? SceneRule::Cover : SceneRule::PerRobot;
        pos_.resize(n);
        goal_.resize(n);
        ids_.resize(n);
        at_goal_.resize(n);
        for (int i = 0; i < n; ++i) {
            const Agent& a = world.agents()[i];
            pos_[i] = a.pos, goal_[i] = a.goal, ids_[i] = a.id, at_goal_[i] = world.at_goal(a);
        }
        now_ = world.t();
        // Routes around crowds where the team is larger than a scene, dense enough to crowd, and
        // the world larger than the training world's (where ways are long enough to meet in crowds).
        const double side = 2 * world.map().half_size;
        if (settings.traffic.crowd_weight > 0 && K < n && n >= settings.traffic.crowd_density * side * side &&
            world.map().half_size > model_.config.position_scale * (1 + 1e-9))
            crowds_.update(guide_, world.map(), settings.traffic, n, pos_.data(), goal_.data(), at_goal_.data(), ids_.data(), now_, crowd_target_);
        else
            crowd_target_.clear();
        plan_scenes(world.map(), n, K, rule, n);
        for (int i = 0; i < n; ++i) {
            out.ids[i] = ids_[i];
            decode_window(window_col_[i], pos_[i], out.waypoints[i]);
        }
        last_ids_.assign(ids_.begin(), ids_.end());  // what the next plan starts from (warm_start)
        last_windows_.resize(n);
        for (int i = 0; i < n; ++i) last_windows_[i] = out.waypoints[i];
        last_t_ = now_;
        out.replan_after = replan_after();
        out.plan_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    }

    // Decentralised use: one robot plans its own window from what it can know, its position and
    // goal, the other robots' positions and goals as received from them, and the map: its own
    // scene of itself and its K-1 nearest. `id` seeds the draw (use the robot's id): with the
    // same planner seed, and `others` in the world's agent order, a first plan_robot's window
    // equals the one a first plan() (or one with warm_start 0) gives this robot under
    // neighbourhood planning with a scene per robot (neighbourhood.cover = 0; K = neighbourhood
    // size of an automatic or set `neighbours`; the whole team when neighbours = 0).
    // The ids (the robot's own `id`, and Neighbour::id) break ties in taking turns, so give the
    // ids the team's plan() sees for the same turns.
    // `step`: the robot's clock in world steps (dt each), for warm starts (SamplerConfig::warm_start):
    // the plan starts from this planner's last plan_robot windows (its own and the neighbours' it
    // drew then, by id) when that plan was made at an earlier step; a robot of the scene without
    // an id or a window there starts from a line (line_start), or, without line_start, the whole
    // scene draws cold; with step -1 (the default) every robot has no window.
    // Use one planner per robot, as one per world.
    void plan_robot(const WorldMap& map, int id, Vec2 pos, Vec2 goal, const std::vector<Neighbour>& others, std::vector<Vec2>& window,
                    long step = -1) {
        if (step < -1) throw std::invalid_argument("planner: plan_robot's step must be >= 0, or -1 for a cold draw (got " + std::to_string(step) + ")");
        const int n = 1 + (int)others.size();
        for (int i = 0; i < n; ++i) {
            const Vec2 p = i ? others[i - 1].pos : pos, g = i ? others[i - 1].goal : goal;
            if (!std::isfinite(p.x + p.y + g.x + g.y))
                throw std::invalid_argument(i ? "planner: neighbour " + std::to_string(i - 1) + " has a non-finite position or goal"
                                              : std::string("planner: the robot's position or goal is not finite"));
        }
        const int K = settings.neighbourhood.neighbours == 0 ? n : std::min(neighbourhood_size(), n);
        pos_.resize(n);
        goal_.resize(n);
        ids_.resize(n);
        at_goal_.resize(n);
        pos_[0] = pos, goal_[0] = goal, ids_[0] = id;
        for (int i = 1; i < n; ++i)
            pos_[i] = others[i - 1].pos, goal_[i] = others[i - 1].goal, ids_[i] = others[i - 1].id;
        for (int i = 0; i < n; ++i) at_goal_[i] = WorldConfig{}.reached(pos_[i], goal_[i]);
        now_ = step;
        crowd_target_.clear();  // a robot alone routes straight along its map route
        plan_scenes(map, n, std::min(K, n), SceneRule::PerRobot, /*seeds: the robot alone*/ 1);
        // The scene's windows, the robot's (slot 0) and its neighbours': the next plan_robot starts from them.
        const int m = batch_.count[0];
        last_ids_.resize(m);
        last_windows_.resize(m);
        for (int k = 0; k < m; ++k) {
            last_ids_[k] = ids_[scene_robots_[k]];
            decode_window(k, pos_[scene_robots_[k]], last_windows_[k]);
        }
        last_t_ = step;
        window.assign(last_windows_[0].begin(), last_windows_[0].end());
    }

private:
    MadbpModel model_;
    NoiseSchedule schedule_;
    Rng rng_;
    SceneBatch batch_;
    WorldMap grid_map_;
    bool grid_valid_ = false;
    Mat x_, eps_;
    std::vector<int> steps_, members_, ids_, order_;
    std::map<int, std::pair<Vec2, double>> first_seen_;  // by id: the goal and its distance when first seen (set_priorities)
    std::vector<double> priority_key_;                   // set_priorities: a scene's robots' keys
    // The scenes of a plan (choose_scenes): scene b holds robots scene_robots_[b*K .. b*K + m)
    // (-1 after them), nearest to its seed scene_seed_[b] first; robot i's window is column
    // window_col_[i] of x_ (-1: none).
    std::vector<int> scene_robots_, scene_seed_, window_col_;
    std::vector<char> in_scene_;  // per robot: in some scene of the plan (its route_ is set)
    std::vector<int> near_robots_, far_robots_;  // route_robots: the robots routed on near fields, and the others
    std::vector<Vec2> walk_goals_;                // route_robots: the goals whose fields may be made ahead
    // One thread's share of a plan's sampling (sample_scenes): a chunk of scenes and its workspace.
    struct ChunkWorker {
        std::unique_ptr<MadbpModel> copy;  // thread 0 uses the planner's model; the others a copy, its parameters synced every plan
        SceneBatch batch;
        Mat x, out, warm;
        std::vector<int> steps;
        ConflictWorkspace cw;  // reads the planner's map fields (shared_fields)
        Rng rng;
        std::unique_ptr<RouteGuide> guide;  // route_robots' near routes (thread 0 uses the planner's)
    };
    std::vector<ChunkWorker> workers_;
    std::vector<std::exception_ptr> failed_;  // per thread: what stopped its chunks
    std::vector<Vec2> pos_, goal_;   // the robots planned for (ego first for plan_robot)
    std::vector<char> at_goal_;
    std::vector<RouteGoal> route_;   // what each is told to head for (route_goal)
    PassageControl passages_;        // traffic.take_turns: the one-lane passages
    CrowdRoutes crowds_;             // traffic.crowd_weight: routes around crowds
    std::vector<Vec2> crowd_target_;  // where each robot heads instead of its goal (empty: none)
    std::vector<char> waiting_;      // robots told to wait, and where
    std::vector<Vec2> wait_point_;
    RouteGuide guide_;               // route subgoals (ModelConfig::subgoal_distance)
    ConflictWorkspace conflict_;     // guidance and best-of-k (SamplerConfig::guidance, candidates)
    // SamplerConfig::warm_start: the last plan's robots and windows, made at the world's step
    // last_t_ (-1: none); now_, this plan's step (plan_robot's `step`). One world (or robot) per
    // planner: a clock that went back draws cold, but two worlds planned in turn would mix.
    std::vector<int> last_ids_;
    std::vector<std::vector<Vec2>> last_windows_;
    long last_t_ = -1, now_ = -1;
    int last_k_ = 1;  // last_plan_candidates
    Mat warm_;  // (2, H * scenes * K) the warm windows

    // Which scenes a plan samples: the whole team in one; a scene per robot (each keeps its
    // robot's window); or scenes that cover the team (PlannerConfig::neighbourhood.cover).
    enum class SceneRule { Whole, PerRobot, Cover };

    // Plans the scenes of at most K robots over pos_/goal_ (n robots) that `rule` makes for the
    // first `seeds` robots (choose_scenes). x_ holds the windows, scene b's robot k at column b * K + k.
    void plan_scenes(const WorldMap& map, int n, int K, SceneRule rule, int seeds) {
        const ModelConfig& c = model_.config;
        const bool local = rule != SceneRule::Whole;
        if (K > c.n_max)
            throw std::invalid_argument("planner: " + std::to_string(K) + " agents per scene exceed the model's n_max = " + std::to_string(c.n_max) +
                                        (local ? "" : "; larger teams need neighbourhood planning (neighbours = K <= n_max, --neighbours K)"));
        settings.validate();
        SamplerConfig sc = settings.sampler_config(c);
        sc.validate(schedule_.K);
        const double radius = settings.neighbourhood.sensing_radius > 0 ? settings.neighbourhood.sensing_radius : 2.0 * c.position_scale;
        choose_scenes(n, K, rule, seeds, radius);
        const int scenes = (int)scene_seed_.size();
        // Only the scenes' robots are told where to head (plan_robot: its scene's, not its team's).
        in_scene_.assign(n, 0);
        for (int r : scene_robots_)
            if (r >= 0) in_scene_[r] = 1;
        // Small plans draw small_plan_candidates. The team's robot windows: a scene per robot
        // (local; plan_robot's one scene stands for its team's n), or one scene of them all.
        if ((local ? n : 1) * std::min(K, n) <= kSmallPlanWindows) sc.candidates = std::max(sc.candidates, settings.sampler.small_plan_candidates);
        const double bytes = planner_workspace_bytes(c, scenes, K, sc.candidates, settings.workspace.chunk_scenes, sample_threads(scenes));
        if (bytes > settings.workspace.max_mb * 1e6)  // before anything of this size is allocated
            throw std::invalid_argument("planner setting workspace.max_mb: a plan of " + std::to_string(n) + " robots (" + std::to_string(scenes) + " scenes of " +
                                        std::to_string(K) + ") needs " + number_text(std::ceil(bytes / 1e6)) + " MB of workspace, over the limit " +
                                        number_text(settings.workspace.max_mb) + " MB (raise it, or lower workspace.chunk_scenes)");
        const bool shared = c.frame == SceneFrame::World;  // one grid for every scene
        if (batch_.B != scenes || batch_.n != K || batch_.shared_grid != shared) {  // new buffers, grid redrawn
            batch_.resize(scenes, K, c, shared);
            grid_valid_ = false;
        }
        if (shared) update_grid(map);
        waiting_.assign(n, PassageControl::kGoOn);
        if (settings.traffic.take_turns) {
            passages_.params = settings.traffic;
            passages_.arbitrate(guide_, map, n, pos_.data(), goal_.data(), at_goal_.data(), waiting_, wait_point_, ids_.data(), in_scene_.data());
        }
        route_robots(map, n, sample_threads(scenes));
        // Each neighbourhood scene draws its own noise, seeded by the plan and its seed robot's id.
        const uint64_t plan_seed = local ? rng_.next_u64() : 0;
        if (local) batch_.noise_seed.resize(scenes);
        else batch_.noise_seed.clear();
        // Warm when every robot of every scene has a last window to start from, or a line (line_start).
        const bool line_start = settings.sampler.line_start;
        bool warm = sc.warm_starts() && ((last_t_ >= 0 && now_ > last_t_) || line_start);
        if (warm) warm_.setZero(2, (long)c.horizon * scenes * K);
        for (int b = 0; b < scenes; ++b) {
            const int* robots = scene_robots_.data() + (size_t)b * K;
            int m = 0;
            while (m < K && robots[m] >= 0) ++m;
            if (local) batch_.noise_seed[b] = plan_seed ^ (0x9E3779B97F4A7C15ull * (uint64_t)(ids_[scene_seed_[b]] + 1));
            batch_.origin[b] = scene_origin(c, m, [&](int k) { return pos_[robots[k]]; });
            for (int k = 0; k < m && warm; ++k)
                if (!warm_from_last(robots[k], b * K + k)) {
                    if (line_start) line_window(robots[k], b * K + k);
                    else warm = false;
                }
            batch_.count[b] = m;
            set_priorities(b, m, robots, /*crowd*/ K < n);
        }
        // The scenes' maps and robots, on the sampling threads (each scene writes its own columns).
        detail::parallel_for_rethrow(scenes, sample_threads(scenes), failed_, [&](int b, int) {
            const int* robots = scene_robots_.data() + (size_t)b * K;
            if (!shared) encode_map(batch_, b, map, c);
            for (int k = 0; k < K; ++k) {
                const int a = b * K + k;
                if (k >= batch_.count[b]) {  // an empty slot
                    batch_.agent_mask[a] = 0;
                    batch_.slot[a] = k;
                    batch_.goal_final[a] = 1;
                    batch_.pose.col(a).setZero();
                    continue;
                }
                const int i = robots[k];
                encode_agent(batch_, a, /*slot*/ k, pos_[i], route_[i].goal, map, c, route_[i].final);
            }
        });
        if (first_seen_.size() > 2 * (size_t)n + 64)  // robots gone: keep the keys of this plan's (bounded memory)
            for (auto it = first_seen_.begin(); it != first_seen_.end();)
                it = std::find(ids_.begin(), ids_.end(), it->first) == ids_.end() ? first_seen_.erase(it) : std::next(it);
        last_k_ = sc.candidates;
        if (sc.conflict_aware()) conflict_.set_map(map);  // the distance field, once per map
        sample_scenes(sc, warm);
    }

    // Scene b's robots' SceneBatch::priority (guidance.priority) in a team larger than a scene
    // (`crowd`): priority_order's rule, the key the distance to the goal when the robot was first
    // seen heading there. A team planned in one scene shares the way alike: in the 50 tuning
    // cells (pairs and fours) priorities cost pace (docs/experiments.md, "Priorities in crowds").
    void set_priorities(int b, int m, const int* robots, bool crowd) {
        const float first = settings.guidance.priority;
        const int K = batch_.n;
        for (int k = 0; k < K; ++k) batch_.priority[(size_t)b * K + k] = 1;
        if (first == 1 || !crowd) return;
        priority_key_.resize(m);
        for (int k = 0; k < m; ++k) {
            const int i = robots[k];
            auto seen = first_seen_.find(ids_[i]);
            if (seen == first_seen_.end() || !(seen->second.first == goal_[i]))
                seen = first_seen_.insert_or_assign(ids_[i], std::make_pair(goal_[i], norm(goal_[i] - pos_[i]))).first;
            priority_key_[k] = seen->second.second;
        }
        priority_order(m, [&](int k) { return at_goal_[robots[k]] != 0; }, [&](int k) { return priority_key_[k]; }, [&](int k) { return ids_[robots[k]]; }, order_);
        for (int rank = 0; rank < m; ++rank) batch_.priority[(size_t)b * K + order_[rank]] = (float)priority_weight_of(rank, m, first);
    }

    // Robot b's neighbourhood into members_[0, m), returns m: b and its K-1 nearest (nearest
    // first, ties by index) within `radius`.
    int nearest_robots(int b, int n, int K, double radius) {
        members_.resize(n);
        for (int i = 0; i < n; ++i) members_[i] = i;
        const Vec2 pb = pos_[b];
        auto dist = [&](int i) { const Vec2 d = pos_[i] - pb; return i == b ? -1.0 : dot(d, d); };
        int m = std::min(K, n);
        std::partial_sort(members_.begin(), members_.begin() + m, members_.end(),
                          [&](int i, int j) { return dist(i) < dist(j) || (dist(i) == dist(j) && i < j); });
        while (m > 1 && dist(members_[m - 1]) > radius * radius) --m;
        return m;
    }

    // The scenes of SceneRule `rule` for robots 0 .. seeds-1 (scene_robots_, scene_seed_,
    // window_col_). Cover: robots in order, each not yet covered seeds a scene of its
    // neighbourhood, which keeps the windows of its first `cover` robots not yet covered (the
    // seed first; every robot when the scene holds the whole team).
    void choose_scenes(int n, int K, SceneRule rule, int seeds, double radius) {
        scene_robots_.clear();
        scene_seed_.clear();
        window_col_.assign(n, -1);
        auto add_scene = [&](int seed, int m) {
            const int b = (int)scene_seed_.size();
            scene_seed_.push_back(seed);
            scene_robots_.insert(scene_robots_.end(), members_.begin(), members_.begin() + m);
            scene_robots_.resize((size_t)(b + 1) * K, -1);
            return b;
        };
        if (rule == SceneRule::Whole) {
            members_.resize(n);
            for (int i = 0; i < n; ++i) members_[i] = window_col_[i] = i;
            add_scene(0, n);
            return;
        }
        const int cover = settings.neighbourhood.cover;
        for (int s = 0; s < seeds; ++s) {
            if (rule == SceneRule::Cover && window_col_[s] >= 0) continue;
            const int m = nearest_robots(s, n, K, radius);
            const int b = add_scene(s, m);
            if (rule == SceneRule::PerRobot) {
                window_col_[s] = b * K;
                continue;
            }
            for (int k = 0; k < m; ++k)
                if (window_col_[members_[k]] < 0 && (k < cover || m == n)) window_col_[members_[k]] = b * K + k;
        }
    }

    // Each scene robot's route_goal (route_), on `threads` threads at most. A waiting robot is
    // routed to its waiting point like to a goal: one that makes way may have the length of a
    // corridor to go. A robot routed around a crowd (traffic.crowd_weight) heads for its route's
    // next point as for a subgoal: that far along the way there, never to stop at it.
    // A robot within near_reach of where it heads walks a near field, which reads no cached field
    // (RouteGuide::walks_near): those are routed on the threads, each with a guide of its own
    // (thread 0 the planner's; ChunkWorker::guide), which walks the same routes. The others walk
    // the planner's guide's cached fields, in turn.
    void route_robots(const WorldMap& map, int n, int threads) {
        const ModelConfig& c = model_.config;
        route_.resize(n);
        near_robots_.clear();
        auto head_of = [&](int i) {
            if (waiting_[i] == PassageControl::kWait) return wait_point_[i];
            return around_crowd(i) ? crowd_target_[i] : goal_[i];
        };
        auto route = [&](RouteGuide& guide, int i) {
            route_[i] = route_goal(guide, c, map, pos_[i], head_of(i), waiting_[i] == PassageControl::kGoAround ? passages_.closed_to(i) : ClosedCells{});
            if (around_crowd(i) && norm(route_[i].goal - pos_[i]) > 1e-9)
                route_[i] = subgoal_towards(pos_[i], route_[i].goal, c.subgoal_distance > 0 ? c.subgoal_distance : kRouteLookahead);
        };
        // The robots routed on the planner's guide, and the goals of those whose walks may make
        // fields (route subgoals, no cells closed, the straight way not clear on the grid), which
        // the guide may make ahead (RouteGuide::expect).
        far_robots_.clear();
        walk_goals_.clear();
        for (int i = 0; i < n; ++i) {
            if (!in_scene_[i]) continue;
            if (guide_.walks_near(pos_[i], head_of(i))) {
                near_robots_.push_back(i);
                continue;
            }
            far_robots_.push_back(i);
            if (c.subgoal_distance > 0 && waiting_[i] != PassageControl::kGoAround && !guide_.straight(map, pos_[i], head_of(i)))
                walk_goals_.push_back(head_of(i));
        }
        {
            const RouteGuide::Expecting expecting = guide_.expect(map, walk_goals_, detail::fields_ahead_batch());
            for (int i : far_robots_) route(guide_, i);
        }
        if (near_robots_.empty()) return;
        if ((int)workers_.size() < threads) workers_.resize(threads);
        for (int t = 1; t < threads; ++t)
            if (!workers_[t].guide) workers_[t].guide = std::make_unique<RouteGuide>(guide_.settings_only());
        detail::parallel_for_rethrow((int)near_robots_.size(), threads, failed_, [&](int j, int t) {
            route(t == 0 ? guide_ : *workers_[t].guide, near_robots_[j]);
        }, /*dynamic: a robot's route is the same on any thread*/ true);
    }
    bool around_crowd(int i) const {
        return !crowd_target_.empty() && waiting_[i] == PassageControl::kGoOn && !(crowd_target_[i] == goal_[i]);
    }

    // Threads the sampling of `scenes` scenes uses: one per chunk, at most set_num_threads'.
    int sample_threads(int scenes) const {
        const int chunk = settings.workspace.chunk_scenes;
        return std::max(1, std::min(detail::max_threads(), (scenes + chunk - 1) / chunk));
    }

    // Samples batch_'s scenes into x_. A plan of one chunk samples the batch itself; a larger one
    // in chunks of workspace.chunk_scenes scenes, on sample_threads() threads, each chunk drawn
    // whole on one thread (its noise is its scenes', batch_.noise_seed), so the windows do not
    // depend on the thread count.
    void sample_scenes(const SamplerConfig& sc, bool warm) {
        const ModelConfig& c = model_.config;
        const int B = batch_.B, K = batch_.n, chunk = settings.workspace.chunk_scenes, chunks = (B + chunk - 1) / chunk;
        if (chunks <= 1) {
            sample_windows(model_, schedule_, batch_, sc, rng_, x_, eps_, steps_, &conflict_, warm ? &warm_ : nullptr);
            return;
        }
        MADBP_ASSERT(!batch_.noise_seed.empty());  // neighbourhood scenes: the only plans of several scenes
        // The goal fields, made once for every chunk (the chunks only read the fields).
        if (sc.conflict_aware() && sc.cost.geodesic && sc.cost.goal_weight > 0) conflict_.fields.add_goals(batch_, c, sc.cost.radius);
        const int threads = sample_threads(B), k = sc.candidates;
        if ((int)workers_.size() < threads) workers_.resize(threads);
        for (int t = 0; t < threads; ++t) {
            ChunkWorker& w = workers_[t];
            if (t > 0 && !w.copy) w.copy = std::make_unique<MadbpModel>(model_.clone());
            if (t > 0) {  // the planner's model may have been changed since the last plan
                w.copy->params->value = model_.params->value;
                w.copy->params->state = model_.params->state;
            }
            w.cw.shared_fields = &conflict_.fields;
        }
        const long cols = (long)c.horizon * K;  // one scene's window columns
        x_.resize(2, cols * B);
        conflict_.cost.resize((size_t)B * k);
        conflict_.best.resize(B);
        detail::parallel_for_rethrow(chunks, threads, failed_, [&](int i, int t) {
            ChunkWorker& w = workers_[t];
            MadbpModel& model = t == 0 ? model_ : *w.copy;
            const int first = i * chunk, count = std::min(chunk, B - first);
            slice_scenes(batch_, first, count, w.batch);
            if (warm) w.warm = warm_.middleCols(first * cols, count * cols);
            sample_windows(model, schedule_, w.batch, sc, w.rng, w.x, w.out, w.steps, &w.cw, warm ? &w.warm : nullptr);
            x_.middleCols(first * cols, count * cols) = w.x;
            if (sc.conflict_aware()) {
                std::copy(w.cw.cost.begin(), w.cw.cost.end(), conflict_.cost.begin() + (size_t)first * k);
                std::copy(w.cw.best.begin(), w.cw.best.end(), conflict_.best.begin() + first);
            }
        }, /*dynamic: a chunk's windows are the same on any thread*/ true);
    }

    // Agent a's columns of warm_ from robot i's last window (detail::warm_window); false without one.
    bool warm_from_last(int i, int a) {
        const int id = ids_[i];
        if (id < 0) return false;
        const size_t n = last_ids_.size();
        const size_t j = (size_t)i < n && last_ids_[i] == id ? (size_t)i : std::find(last_ids_.begin(), last_ids_.end(), id) - last_ids_.begin();
        return j < n && detail::warm_window(last_windows_[j], now_ - last_t_, pos_[i], model_.config, warm_, (long)a * model_.config.horizon);
    }

    // Agent a's columns of warm_ as a straight line from robot i toward route_[i] (line_start):
    // waypoint t at t / (H - 1) of a window's reach (window_scale) along it, or at the goal if
    // that is nearer and final.
    void line_window(int i, int a) {
        const ModelConfig& c = model_.config;
        const Vec2 d = route_[i].goal - pos_[i];
        const double dist = norm(d);
        const long col = (long)a * c.horizon;
        warm_.middleCols(col, c.horizon).setZero();
        if (dist < 1e-9) return;
        const double reach = route_[i].final ? std::min(1.0, dist / c.window_scale) : 1.0;  // normalised
        for (int t = 1; t < c.horizon; ++t) {
            const double r = reach * t / (c.horizon - 1);
            warm_(0, col + t) = (float)(r * d.x / dist);
            warm_(1, col + t) = (float)(r * d.y / dist);
        }
    }

    // Column `col` of x_ as waypoints from p0 (world units), interpolated to every world step.
    void decode_window(long col, Vec2 p0, std::vector<Vec2>& w) const {
        const ModelConfig& c = model_.config;
        const int H = c.horizon, stride = c.waypoint_stride;
        w.resize((size_t)(H - 1) * stride);
        auto at = [&](int t) { return p0 + Vec2{x_(0, col * H + t) * (double)c.window_scale, x_(1, col * H + t) * (double)c.window_scale}; };
        for (int t = 1; t < H; ++t)
            for (int s = 1; s <= stride; ++s)  // linear between sampled waypoints t-1 and t
                w[(size_t)(t - 1) * stride + s - 1] = at(t - 1) + (at(t) - at(t - 1)) * ((double)s / stride);
    }

    // Rasterizes the map only when it changed since the last plan.
    void update_grid(const WorldMap& map) {
        if (grid_valid_ && map == grid_map_) return;
        encode_map(batch_, 0, map, model_.config);
        grid_map_ = map;
        grid_valid_ = true;
    }
};

// A PlanFollower (madbp_sim.hpp) that executes `planner`'s plans with its settings.follower.
// The follower keeps a reference: the planner must outlive it.
inline PlanFollower make_follower(DiffusionPlanner& planner) {
    return PlanFollower([&planner](const World& w) { return planner.plan(w); }, planner.settings.follower);
}

// A team whose robots plan for themselves: each has its own planner (the same seed and settings)
// and calls plan_robot with every other robot's position, goal and id, as if received
// from it, and its clock (the world's step). Robots may join and leave. Plan::plan_ms is per
// robot: the team's plans run one after another here, each robot's on its own computer there.
class DecentralisedTeam {
public:
    DecentralisedTeam(std::shared_ptr<const MadbpModel> model, PlannerConfig settings, uint64_t seed)
        : model_(std::move(model)), settings_(std::move(settings)), seed_(seed) {}
    Plan plan(const World& world) {
        const auto t0 = std::chrono::steady_clock::now();
        const auto& agents = world.agents();
        const int n = (int)agents.size();
        Plan out;
        out.ids.resize(n);
        out.waypoints.resize(n);
        for (int i = 0; i < n; ++i) {
            const Agent& me = agents[i];
            others_.clear();
            for (int j = 0; j < n; ++j)
                if (j != i) others_.push_back({agents[j].pos, agents[j].goal, agents[j].id});
            auto& planner = robots_[me.id];
            if (!planner) planner = std::make_unique<DiffusionPlanner>(model_->clone(), seed_, settings_);
            planner->plan_robot(world.map(), me.id, me.pos, me.goal, others_, out.waypoints[i], world.t());
            out.ids[i] = me.id;
            // The team replans when the first robot asks to (one waits at a passage in its scene).
            const int after = planner->replan_after();
            if (after > 0 && (out.replan_after == 0 || after < out.replan_after)) out.replan_after = after;
        }
        out.plan_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / std::max(n, 1);
        return out;
    }

private:
    std::shared_ptr<const MadbpModel> model_;
    PlannerConfig settings_;
    uint64_t seed_;
    std::map<int, std::unique_ptr<DiffusionPlanner>> robots_;  // by id
    std::vector<DiffusionPlanner::Neighbour> others_;
};

}  // namespace madbp

#endif  // MADBP_HPP
