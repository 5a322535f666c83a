// methods_nn.hpp - the learned methods and the training subcommands of the `madbp` tool:
// `eval --method madbp`, `collect`, `train`. Included by madbp.cpp.
#pragma once
#include <chrono>
#include <map>
#include <memory>
#include <mutex>

#include "madbp_train.hpp"
#include "methods_mappo.hpp"

namespace madbp_cli {


// Options of the diffusion planner, shared by eval, render and demo.
struct PlannerOptions {
    std::string model_path;
    int sample_steps = 0;      // 0: the model's default
    bool goal_inpaint = true;
    double goal_reach = -1;    // < 0: the model's default_goal_reach
    int neighbours = -1;       // DiffusionPlanner::neighbours (-1: automatic)
    double sensing_radius = 0; // DiffusionPlanner::sensing_radius (0: 2 x the model's position_scale)
    double guidance = madbp::kDefaultGuidance;  // SamplerConfig::guidance (0: off)
    int candidates = 1;        // SamplerConfig::candidates (1: off)
    int small_plan_candidates = madbp::kDefaultSmallPlanCandidates;  // DiffusionPlanner::small_plan_candidates (1: off)
    double keep_right = madbp::kDefaultKeepRight;  // SamplerConfig::keep_right (0: off)
    double end_bend = madbp::kDefaultEndBend;  // SamplerConfig::end_bend (0: off)
    madbp::WindowCost cost;    // SamplerConfig::cost
    double priority_weight = madbp::FollowerConfig{}.priority_weight;  // 1: the filter weighs robots equally
    double lookahead = madbp::FollowerConfig{}.lookahead;  // 0: track the waypoint planned for this step
    double filter_rate = madbp::FollowerConfig{}.filter.rate;  // the safety filter's barrier rate, 1/s
    bool take_turns = true;    // DiffusionPlanner::take_turns (one-lane passages)
    madbp::PassageParams passage;  // which passages, who waits where, when they go, going around
    int passage_replan = madbp::kDefaultPassageReplan;  // DiffusionPlanner::passage_replan (0: off)
    double replan_error = madbp::FollowerConfig{}.replan_error;  // 0: replan only every m steps
    int warm_start = madbp::kDefaultWarmStart;  // SamplerConfig::warm_start (0: off)
    bool line_start = madbp::kDefaultLineStart;  // DiffusionPlanner::line_start
    bool decentralised = false;  // each robot plans for itself (DiffusionPlanner::plan_robot), a planner each
};
// "A,M,G": the agent, map and goal weights of the window cost.
inline void read_cost_weights(const std::string& s, madbp::WindowCost& w) {
    if (s.empty()) return;
    float v[3];
    char tail = 0;
    if (std::sscanf(s.c_str(), "%f,%f,%f%c", &v[0], &v[1], &v[2], &tail) != 3)
        throw std::invalid_argument("--cost-weights: expected three numbers AGENT,MAP,GOAL like 100,100,200, got '" + s + "'");
    for (float x : v)
        if (!(x >= 0) || !std::isfinite(x)) throw std::invalid_argument("--cost-weights: weights must be finite and >= 0 (got '" + s + "')");
    w.agent_weight = v[0];
    w.map_weight = v[1];
    w.goal_weight = v[2];
}
inline PlannerOptions read_planner_options(Args& a) {
    PlannerOptions o;
    o.model_path = a.str("--model", kDefaultModel);
    o.sample_steps = (int)a.integer("--sample-steps", 0, 0, 1000);
    o.goal_inpaint = !a.flag("--no-goal-inpaint");
    o.goal_reach = a.real("--goal-reach", -1, 0, 100);  // a negative value is an error, not the default
    o.neighbours = (int)a.integer("--neighbours", -1, -1, 1024);
    o.sensing_radius = a.real("--sensing-radius", 0, 0, 1000);
    o.guidance = a.real("--guidance", madbp::kDefaultGuidance, 0, 1e6);
    o.candidates = (int)a.integer("--candidates", 1, 1, madbp::kMaxCandidates);
    o.small_plan_candidates = (int)a.integer("--small-plan-candidates", o.small_plan_candidates, 1, madbp::kMaxCandidates);
    o.keep_right = a.real("--keep-right", madbp::kDefaultKeepRight, 0, 1e6);
    o.end_bend = a.real("--end-bend", o.end_bend, 0, 1);
    read_cost_weights(a.str("--cost-weights", ""), o.cost);
    o.cost.agent_margin = (float)a.real("--cost-margin", o.cost.agent_margin, 0, 10);
    o.priority_weight = a.real("--priority-weight", o.priority_weight, 1, 1000);
    o.lookahead = a.real("--lookahead", o.lookahead, 0, madbp::kMaxLookahead);
    o.filter_rate = a.real("--filter-rate", o.filter_rate, 0.01, 9.99);  // < 1/dt (PlanFollower checks it against the world's dt)
    o.take_turns = a.integer("--take-turns", o.take_turns ? 1 : 0, 0, 1) != 0;
    madbp::PassageParams& p = o.passage;
    p.one_lane_width = a.real("--one-lane-width", p.one_lane_width, 0, 100);
    p.go_around = a.integer("--go-around", p.go_around ? 1 : 0, 0, 1) != 0;
    p.spread = a.real("--spread", p.spread, 0, 100);
    p.wait_back = a.real("--wait-back", p.wait_back, 0, 100);
    p.wait_side = a.real("--wait-side", p.wait_side, 0, 100);
    p.queue_spacing = a.real("--queue-spacing", p.queue_spacing, 0, 100);
    p.spare = a.real("--spare", p.spare, 0, 100);
    o.passage_replan = (int)a.integer("--passage-replan", o.passage_replan, 0, 1000);
    o.replan_error = a.real("--replan-error", o.replan_error, 0, 100);
    o.warm_start = (int)a.integer("--warm-start", o.warm_start, 0, 1000);
    o.line_start = a.integer("--line-start", o.line_start ? 1 : 0, 0, 1) != 0;
    o.decentralised = a.flag("--decentralised");
    return o;
}

// A planner on a copy of `model` (planners keep workspaces, so episodes running in parallel must
// not share one) with the options' sampler and passage settings.
inline std::unique_ptr<madbp::DiffusionPlanner> make_planner(const madbp::MadbpModel& model, const PlannerOptions& o, uint64_t seed) {
    auto planner = std::make_unique<madbp::DiffusionPlanner>(model.clone(), seed);
    if (o.sample_steps > 0) planner->sampler.sample_steps = o.sample_steps;
    planner->sampler.goal_inpaint = o.goal_inpaint;
    if (o.goal_reach >= 0) planner->sampler.goal_reach = (float)o.goal_reach;
    planner->neighbours = o.neighbours;
    planner->sensing_radius = o.sensing_radius;
    planner->sampler.guidance = (float)o.guidance;
    planner->sampler.candidates = o.candidates;
    planner->small_plan_candidates = o.small_plan_candidates;
    planner->sampler.keep_right = (float)o.keep_right;
    planner->sampler.end_bend = (float)o.end_bend;
    planner->sampler.cost = o.cost;
    planner->sampler.warm_start = o.warm_start;
    planner->line_start = o.line_start;
    planner->take_turns = o.take_turns;
    planner->passages.params = o.passage;
    planner->passage_replan = o.passage_replan;
    return planner;
}

// A team whose robots plan for themselves (eval --decentralised): each has its own planner
// (same seed, as the README's robot loop) and calls plan_robot with every other robot's position,
// goal, velocity and id, as if received from it, and its clock (the world's step). plan_ms is
// per robot: the team's plans run one after another here, each robot's on its own computer there.
class DecentralisedTeam {
public:
    DecentralisedTeam(std::shared_ptr<const madbp::MadbpModel> model, PlannerOptions o, uint64_t seed)
        : model_(std::move(model)), options_(std::move(o)), seed_(seed) {}
    madbp::Plan plan(const madbp::World& world) {
        const auto t0 = std::chrono::steady_clock::now();
        const auto& agents = world.agents();
        const int n = (int)agents.size();
        madbp::Plan out;
        out.ids.resize(n);
        out.waypoints.resize(n);
        for (int i = 0; i < n; ++i) {
            const madbp::Agent& me = agents[i];
            others_.clear();
            for (int j = 0; j < n; ++j)
                if (j != i) others_.push_back({agents[j].pos, agents[j].goal, agents[j].vel, agents[j].id});
            auto& planner = robots_[me.id];
            if (!planner) planner = make_planner(*model_, options_, seed_);
            planner->plan_robot(world.map(), me.id, me.pos, me.goal, others_, out.waypoints[i], me.vel, world.t());
            out.ids[i] = me.id;
            // The team replans when the first robot asks to (one waits at a passage in its scene).
            const int after = planner->replan_after();
            if (after > 0 && (out.replan_after == 0 || after < out.replan_after)) out.replan_after = after;
        }
        // What one robot pays: the team's plans ran one after another on this core.
        out.plan_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / std::max(n, 1);
        return out;
    }

private:
    std::shared_ptr<const madbp::MadbpModel> model_;
    PlannerOptions options_;
    uint64_t seed_;
    std::map<int, std::unique_ptr<madbp::DiffusionPlanner>> robots_;  // by id: robots may join and leave
    std::vector<madbp::DiffusionPlanner::Neighbour> others_;
};

// The planner policy of one episode: one planner for the team (plan), or one per robot
// (--decentralised, plan_robot).
inline madbp::PolicyFactory planner_factory(std::shared_ptr<const madbp::MadbpModel> model, const PlannerOptions& o, const MethodSetup& s) {
    if (o.sample_steps > model->config.diffusion_steps)
        throw std::invalid_argument("--sample-steps: must be <= the model's diffusion steps (" + std::to_string(model->config.diffusion_steps) + ")");
    madbp::FollowerConfig fc;
    fc.safety_filter = s.filter;
    fc.replan_every = s.replan;
    fc.priority_weight = o.priority_weight;
    fc.lookahead = o.lookahead;
    fc.filter.rate = o.filter_rate;
    fc.replan_error = o.replan_error;
    return [model, fc, o](const madbp::World&, uint64_t seed) -> std::unique_ptr<madbp::Policy> {
        if (o.decentralised)
            return std::make_unique<madbp::PlanFollower>(
                [team = std::make_shared<DecentralisedTeam>(model, o, seed)](const madbp::World& w) { return team->plan(w); }, fc);
        return std::make_unique<madbp::PlanFollower>(
            [planner = std::shared_ptr<madbp::DiffusionPlanner>(make_planner(*model, o, seed))](const madbp::World& w) { return planner->plan(w); }, fc);
    };
}

// Loads the model once for every episode of a cell.
inline MethodSpec madbp_method(const PlannerOptions& o, const MethodSetup& s) {
    // One thread per plan (SPEC 9 measures one core); eval --threads runs episodes in parallel.
    madbp::set_num_threads(1);
    auto shared = std::make_shared<const madbp::MadbpModel>(madbp::load_model(o.model_path));
    MethodSpec spec;
    spec.n_train = shared->config.n_train_max > 0 ? shared->config.n_train_max : -1;
    spec.factory = planner_factory(shared, o, s);
    return spec;
}

inline void register_nn_methods(std::vector<Method>& m) {
    m.push_back({"madbp",
                 "MA-DBP diffusion planner + tracker (+ safety filter) (SPEC 5-8); --model FILE\n"
                 "                    (default models/madbp-default.safetensors), --sample-steps S (DDIM\n"
                 "                    steps; default 8, or the model's own if fewer),\n"
                 "                    --no-goal-inpaint, --goal-reach R (world units; default 0.55),\n"
                 "                    --neighbours K (each robot plans with its K-1 nearest; 0 = whole team;\n"
                 "                    default: K = the model's n_train_max when the team or the world is larger\n"
                 "                    than in training, else the whole team), --sensing-radius R (neighbours\n"
                 "                    farther than R are left out; default 2 x the model's position scale, 2.4),\n"
                 "                    conflict-aware sampling (issue 12): --guidance W (each DDIM step moves\n"
                 "                    x0_hat's waypoints by -W * d cost / d waypoint; default 0.004, 0 = off), --candidates K\n"
                 "                    (best of K windows per scene; default 1), --small-plan-candidates K (at least K for\n"
                 "                    a plan of at most 4 robot windows: one scene of <= 4 robots; default 2, 1 = off),\n"
                 "                    --cost-weights A,M,G (robot-robot, robot-map,\n"
                 "                    goal; default 100,100,200), --cost-margin M (robot-robot, default 0.05),\n"
                 "                    --keep-right K (robots meeting in the guided windows are also pushed to the\n"
                 "                    right of their relative motion, so they pass; default 500, 0 = off),\n"
                 "                    --end-bend B (a window heading for a goal within reach is bent to arrive\n"
                 "                    there, not stop short; in [0, 1], default 1, 0 = off), --warm-start W (a plan\n"
                 "                    runs the last W of the S DDIM steps from each robot's last window, noised to\n"
                 "                    that level, instead of all S from noise; default 4, 0 = off), --line-start 0|1\n"
                 "                    (a robot with no last window, e.g. in a first plan, starts from a straight line\n"
                 "                    toward its goal or route subgoal instead, so it too runs W steps; default 1),\n"
                 "                    --priority-weight W (safety-filter weight of the robot that goes first, as the\n"
                 "                    expert's; default 4; 1 = all equal), --lookahead L (the tracker aims L steps\n"
                 "                    ahead of the plan's waypoint for now; default 2.0, 0 = SPEC 8's),\n"
                 "                    --filter-rate R (the safety filter's barrier rate, 1/s, below 1/dt; default 4,\n"
                 "                    2.5 = SPEC 3.2's and the expert's), --replan-error E (replan early, after m/2\n"
                 "                    steps at least, when a robot is more than E from its plan's waypoint for now;\n"
                 "                    default 0.15, 0 = only every m steps),\n"
                 "                    --take-turns 0|1 (robots meeting head-on in a one-lane corridor take turns,\n"
                 "                    one waiting beside its mouth; default 1), --go-around 0|1 (where the corridor\n"
                 "                    has a way around at most 1.0 longer, the one that would wait goes around it;\n"
                 "                    default 1), --spread S (robots going around one take its two sides in turn:\n"
                 "                    each the side whose way, plus S per robot already going that side, is\n"
                 "                    shortest; default 0.3, 0 = all the shortest way), --one-lane-width W (passages\n"
                 "                    narrower than W wall to wall are one-lane; default 0.47), --wait-back D,\n"
                 "                    --queue-spacing D, --wait-side D (the first waiting robot waits D out from the\n"
                 "                    mouth, each next D farther, D to the right; defaults 0.45, 0.3, 0.25), --spare D\n"
                 "                    (one from the other mouth waits unless it would enter after those inside are D\n"
                 "                    out; default 0), --passage-replan N (while robots may meet in a passage, replan\n"
                 "                    after N steps, so the waiting go when it is clear; default 4, 0 = off), --decentralised\n"
                 "                    (each robot plans for itself with plan_robot, its own planner and what the\n"
                 "                    others tell it: positions, goals, velocities, ids; warm-started like the team's)",
                 [](Args& a, const MethodSetup& s) { return madbp_method(read_planner_options(a), s); }});
}

// ---------------------------------------------------------------------------------------------
// --scenarios: "NAME:FRACTION,..." (all:F = F split evenly among every scenario); "" = none.
inline std::vector<std::pair<std::string, double>> parse_scenario_mix(const std::string& list) {
    std::vector<std::pair<std::string, double>> mix;
    if (list.empty()) return mix;
    for (const std::string& item : split(list, "--scenarios")) {
        const size_t colon = item.find(':');
        const std::string name = item.substr(0, colon), frac = colon == std::string::npos ? "" : item.substr(colon + 1);
        size_t pos = 0;
        double f = -1;
        try { f = std::stod(frac, &pos); } catch (...) { pos = 0; }
        if (frac.empty() || pos != frac.size() || !(f >= 0 && f <= 1))
            throw std::invalid_argument("--scenarios: expected NAME:FRACTION with a fraction in [0, 1], got '" + item + "'");
        const auto& names = madbp::interaction_scenarios();
        if (name == "all") {
            for (const std::string& n : names) mix.push_back({n, f / names.size()});
        } else if (std::find(names.begin(), names.end(), name) != names.end()) {
            mix.push_back({name, f});
        } else {
            throw std::invalid_argument("--scenarios: unknown scenario '" + name + "' (expected all, swap, cross, gap, corridor, parked or circle)");
        }
    }
    double total = 0;
    for (auto& m : mix) total += m.second;
    if (total > 1 + 1e-9) throw std::invalid_argument("--scenarios: fractions sum to " + std::to_string(total) + ", more than 1");
    return mix;
}

// --maps LIST (default empty,obstacles,barrier); an unknown name fails here, before any work.
inline std::vector<std::string> read_maps(Args& a) {
    std::vector<std::string> maps;
    for (const std::string& m : split(a.str("--maps", "empty,obstacles,barrier"), "--maps")) {
        madbp::Rng probe(0);
        madbp::make_map(m, probe);
        maps.push_back(m);
    }
    return maps;
}

inline int cmd_collect(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp collect - record demonstrations for training (SPEC 7)\n"
            "  --demonstrator D  expert (default) or mappo with --model FILE ({n} in FILE = team size)\n"
            "  --maps LIST       maps (default empty,obstacles,barrier)\n"
            "  --n-train-max N   teams of 1..N agents (default 4)\n"
            "  --episodes E      episodes per (map, n) cell (default 500)\n"
            "  --keep-failures   also keep episodes the demonstrator failed\n"
            "  --scenarios LIST  interaction scenes mixed into every cell of n <= 4, as NAME:FRACTION items\n"
            "                    (swap, cross, gap, corridor, parked, circle; all:F splits F evenly among\n"
            "                    them), e.g. all:0.5 or swap:0.2,corridor:0.1; default none (random spawns)\n"
            "  --threads T       parallel episodes (default 2)\n"
            "  --seed S          base seed (default 0)\n"
            "  --out FILE        dataset file (default demos.bin)\n"
            "  --json            print a JSON summary\n");
        return 0;
    }
    madbp::CollectConfig c;
    std::string dem = a.str("--demonstrator", "expert");
    c.maps = read_maps(a);
    c.n_train_max = (int)a.integer("--n-train-max", 4, 1, 64);
    c.scenarios = parse_scenario_mix(a.str("--scenarios", ""));
    c.episodes = (int)a.integer("--episodes", 500, 1, 10000000);
    c.successful_only = !a.flag("--keep-failures");
    c.threads = (int)a.integer("--threads", 2, 1, 256);
    c.seed = (uint64_t)a.integer("--seed", 0, 0);
    std::string out = a.str("--out", "demos.bin");
    std::string model = a.str("--model", "");
    bool json = a.flag("--json");
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", out}});
    if (dem != "expert" && dem != "mappo") throw std::invalid_argument("--demonstrator: unknown demonstrator '" + dem + "' (expected expert or mappo)");
    if (dem == "mappo" && model.empty())
        throw std::invalid_argument("--model: --demonstrator mappo needs a policy file, e.g. 'models/mappo/empty-{n}.safetensors' ({n} = team size)");
    auto t0 = std::chrono::steady_clock::now();
    c.progress = progress_line("collect");
    madbp::DemoSet set = madbp::collect_demonstrations(c, dem == "mappo" ? madbp::mappo_demonstrator(model) : madbp::expert_demonstrator(),
                                                       dem == "mappo" ? "mappo:" + model : dem);
    double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    madbp::save_demos(out, set);
    long steps = 0;
    for (auto& d : set.episodes) steps += d.steps;
    const long asked = (long)c.maps.size() * c.n_train_max * c.episodes;
    if (json)
        std::printf("%s\n", Json().add("out", out).add("demonstrator", dem).add("episodes", (long)set.episodes.size())
                                .add("asked", asked).add("steps", steps).add("seconds", secs).line().c_str());
    else
        std::printf("collect: kept %zu of %ld episodes (%ld steps) from '%s' in %.1f s -> %s\n", set.episodes.size(), asked, steps,
                    dem.c_str(), secs, out.c_str());
    return 0;
}

inline int cmd_train(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp train - train the MA-DBP denoiser on demonstrations (SPEC 7)\n"
            "  --data FILE        dataset from `madbp collect` (default demos.bin)\n"
            "  --out FILE         model file (default model.safetensors); training state goes to\n"
            "                     FILE.train, loss curves to FILE.csv and FILE.svg\n"
            "  --resume           continue from FILE.train\n"
            "  --steps N          optimizer steps (default 20000)\n"
            "  --batch B          windows per step (default 64)\n"
            "  --lr X             Adam learning rate (default 3e-4)\n"
            "  --n-train-max N    curriculum end (default 4)\n"
            "  --curriculum-end F fraction of training at which n_curr reaches N (default 0.5)\n"
            "  --weights a,b,c,d  loss weights noise,boundary,temporal,collision (default .85,.025,.025,.1)\n"
            "  --horizon H --dim D --heads K --channels C1,C2 --kernel K --n-max N --grid G\n"
            "  --processor AAP|LE --window MW|CT --prediction x0|eps --local-grid G (0: off)\n"
            "  --window-scale W --waypoint-stride K   model configuration (SPEC 5; defaults in docs/design.md;\n"
            "                     window scale default min(2.4, 0.6 (H-1) stride / 15))\n"
            "  --frame world|local  scene coordinates: from the world's centre (paper) or from each scene's\n"
            "                     centre with a grid cropped around it, for any world size (default local)\n"
            "  --subgoal D        a goal farther than D world units, or out of view, is shown D away in the\n"
            "                     direction of the route around the map; 0 = off (default 1.5)\n"
            "  --velocity         each robot's current velocity in its context (issue 12; default off)\n"
            "  --priority         each robot's place in the guided expert's priority order in its context\n"
            "                     (who gives way; issue 12; default off)\n"
            "  --checkpoint-every N (default 1000)   --seed S (default 0)\n"
            "  --threads T        data-parallel replicas (default 2); results depend on T, not on the machine\n"
            "  --json             print the final losses as JSON\n");
        return 0;
    }
    std::string data = a.str("--data", "demos.bin");
    madbp::TrainConfig tc;
    tc.out = a.str("--out", "model.safetensors");
    tc.resume = a.flag("--resume");
    tc.steps = a.integer("--steps", 20000, 1, 100000000);
    tc.batch = (int)a.integer("--batch", 64, 1, 100000);
    tc.lr = (float)a.real("--lr", 3e-4, 1e-7, 1);
    tc.n_train_max = (int)a.integer("--n-train-max", 4, 1, 1024);
    tc.curriculum_end = (float)a.real("--curriculum-end", 0.5, 0, 1);
    tc.checkpoint_every = a.integer("--checkpoint-every", 1000, 1);
    tc.seed = (uint64_t)a.integer("--seed", 0, 0);
    if (a.has("--weights")) {
        const std::vector<double> w = a.reals("--weights", "", 0, 1e6);
        if (w.size() != 4 || w[0] + w[1] + w[2] + w[3] <= 0)
            throw std::invalid_argument("--weights: expected four numbers >= 0, not all 0, like .85,.025,.025,.1, got '" +
                                        madbp::printable(a.str("--weights", "")) + "'");
        for (int i = 0; i < 4; ++i) tc.loss_weights[i] = (float)w[i];
    }
    madbp::ModelConfig mc;
    mc.horizon = (int)a.integer("--horizon", mc.horizon, 2, 4096);
    mc.dim = (int)a.integer("--dim", mc.dim, 4, 4096);
    mc.heads = (int)a.integer("--heads", mc.heads, 1, 64);
    mc.kernel = (int)a.integer("--kernel", mc.kernel, 1, 31);
    mc.n_max = (int)a.integer("--n-max", mc.n_max, 1, 1024);
    mc.grid = (int)a.integer("--grid", mc.grid, 8, 1024);
    std::string ch = a.str("--channels", "");
    if (!ch.empty()) {
        mc.channels.clear();
        for (long c : a.integers("--channels", ch, 1, 1024)) mc.channels.push_back((int)c);
    }
    mc.local_grid = (int)a.integer("--local-grid", mc.local_grid, 0, 256);
    mc.waypoint_stride = (int)a.integer("--waypoint-stride", mc.waypoint_stride, 1, 16);
    // Default: 0.6 world units per 15 steps of window (the top speed's reach), capped at 2.4 (a
    // complete trajectory crosses the world at most once), so H = 8, 32 and CT windows of ~100
    // steps get displacements of order 1, as H = 16 does with 0.6.
    const double span = (double)(mc.horizon - 1) * mc.waypoint_stride;
    mc.window_scale = (float)a.real("--window-scale", std::min(2.4, 0.6 * span / 15.0), 1e-3, 100);
    std::string pred = a.str("--prediction", "x0");
    if (pred != "x0" && pred != "eps") throw std::invalid_argument("--prediction: expected x0 or eps, got '" + pred + "'");
    mc.prediction = pred == "x0" ? madbp::Prediction::X0 : madbp::Prediction::Eps;
    std::string proc = a.str("--processor", "AAP"), win = a.str("--window", "MW");
    if (proc != "AAP" && proc != "LE") throw std::invalid_argument("--processor: expected AAP or LE, got '" + proc + "'");
    if (win != "MW" && win != "CT") throw std::invalid_argument("--window: expected MW or CT, got '" + win + "'");
    mc.processor = proc == "AAP" ? madbp::Processor::AAP : madbp::Processor::LE;
    mc.window = win == "MW" ? madbp::WindowMode::MW : madbp::WindowMode::CT;
    std::string frame = a.str("--frame", "local");
    if (frame != "world" && frame != "local") throw std::invalid_argument("--frame: expected world or local, got '" + frame + "'");
    mc.frame = frame == "local" ? madbp::SceneFrame::Local : madbp::SceneFrame::World;
    mc.subgoal_distance = (float)a.real("--subgoal", 1.5, 0, 100);
    mc.velocity_context = a.flag("--velocity");
    mc.priority_context = a.flag("--priority");
    mc.n_train_max = std::min(tc.n_train_max, mc.n_max);
    int threads = (int)a.integer("--threads", 2, 1, 256);
    bool json = a.flag("--json");
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", tc.out}}, {".train", ".csv", ".svg"});
    mc.validate();
    tc.threads = threads;
    madbp::set_num_threads(threads);
    madbp::DemoSet demos = load_training_data(data, mc.n_max);
    madbp::MadbpModel model(mc, tc.seed);
    if (!json) std::printf("train: %zu episodes from '%s', model with %ld parameters\n", demos.episodes.size(), demos.demonstrator.c_str(), model.parameter_count());
    tc.progress = progress_line("train");
    madbp::TrainReport r = madbp::train(demos, model, tc);
    write_curve_svg(tc.out + ".svg", r.curve, {"train_total", "val_total"}, "MA-DBP training loss", true);
    if (json)
        std::printf("%s\n", Json().add("out", tc.out).add("steps", r.steps).add("seconds", r.seconds).add("train_loss", r.last_train.total)
                                .add("val_loss", r.last_val.total).add("val_noise", r.last_val.noise).line().c_str());
    else
        std::printf("train: %ld steps in %.1f s; last train loss %.4f, validation loss %.4f (noise %.4f) -> %s\n", r.steps, r.seconds,
                    r.last_train.total, r.last_val.total, r.last_val.noise, tc.out.c_str());
    return 0;
}

inline int cmd_dagger(Args& a) {
    if (a.flag("--help")) {
        std::printf(
            "madbp dagger - on-policy data aggregation (issue 12): roll the model out, label the states it\n"
            "               visits with what the guided expert does from them, fine-tune on the labels\n"
            "               of every round so far plus as many expert windows; repeat\n"
            "  --model FILE       the model to start from (default models/madbp-default.safetensors)\n"
            "  --data FILE        the expert demonstrations it was trained on (default demos.bin)\n"
            "  --out FILE         final model (default dagger.safetensors); round R writes FILE.round-R.labels.bin\n"
            "                     and FILE.round-R.safetensors (+ .train, .csv); the log is FILE.dagger.csv\n"
            "  --resume           continue an interrupted run from its files\n"
            "  --rounds R         rounds (default 3); the log's round R+1 is the final model's evaluation\n"
            "  --episodes E       rollouts per (map, team size) cell and round (default 40)\n"
            "  --maps LIST        (default empty,obstacles,barrier)   --n-train-max N (teams 1..N, default 4)\n"
            "  --scenarios LIST   interaction scenes in the rollouts, as for collect (default all:0.3)\n"
            "  --label-every K    label every K-th visited state (default 2)\n"
            "  --base-ratio X     expert windows per label window in each fine-tune (default 1)\n"
            "  --steps N          fine-tune steps per round (default 3000)   --batch B (default 64)\n"
            "  --lr X             fine-tune learning rate (default 1e-4)\n"
            "  --seed S           seed of the rollouts (round R: S + R x 10^7) and the fine-tunes (default 50000000)\n"
            "  --threads T        parallel rollouts and training replicas (default 2)\n"
            "  planner options of the rollouts as for `eval --method madbp` (--guidance W, --candidates K, ...)\n");
        return 0;
    }
    PlannerOptions o = read_planner_options(a);
    std::string data = a.str("--data", "demos.bin");
    madbp::DaggerConfig c;
    c.train.out = a.str("--out", "dagger.safetensors");
    c.train.resume = a.flag("--resume");
    c.rounds = (int)a.integer("--rounds", 3, 1, 1000);
    c.rollouts.episodes = (int)a.integer("--episodes", 40, 1, 1000000);
    c.rollouts.maps = read_maps(a);
    c.rollouts.n_train_max = (int)a.integer("--n-train-max", 4, 1, 64);
    c.rollouts.scenarios = parse_scenario_mix(a.str("--scenarios", "all:0.3"));
    c.label_every = (int)a.integer("--label-every", 2, 1, 1000);
    c.base_ratio = a.real("--base-ratio", 1, 0, 1e6);
    c.train.steps = a.integer("--steps", 3000, 1, 100000000);
    c.train.batch = (int)a.integer("--batch", 64, 1, 100000);
    c.train.lr = (float)a.real("--lr", 1e-4, 1e-7, 1);
    c.train.n_train_max = c.rollouts.n_train_max;
    c.train.curriculum_end = 0;  // a fine-tune: every team size from the first step
    c.train.ema_start = 0;
    const uint64_t seed = (uint64_t)a.integer("--seed", (long)madbp::kDaggerDefaultSeed, 0);
    c.rollouts.seed = seed;
    c.train.seed = seed;
    const int threads = (int)a.integer("--threads", 2, 1, 256);
    a.finish();
    const auto locks = claim_outputs(a, {{"--out", c.train.out}}, {".train", ".csv", ".dagger.csv"});
    c.rollouts.threads = threads;
    c.train.threads = threads;
    madbp::set_num_threads(1);
    madbp::MadbpModel model = madbp::load_model(o.model_path);
    if (c.train.n_train_max > model.config.n_max) throw std::invalid_argument("--n-train-max: exceeds the model's n_max");
    madbp::DemoSet base = load_training_data(data, model.config.n_max);
    c.rollouts.progress = progress_line("dagger rollouts");
    c.train.progress = progress_line("dagger fine-tune");
    c.on_round = [&](const madbp::DaggerRound& r) {
        const bool last = r.round == c.rounds + 1;
        if (last)
            std::printf("dagger: after round %d: success %.3f +- %.3f over %d rollouts, %.2f collisions/episode (%.0f s)\n", c.rounds, r.success,
                        r.success_se, r.episodes, r.collisions, r.seconds);
        else
            std::printf("dagger: round %d: the model going in: success %.3f +- %.3f over %d rollouts, %.2f collisions/episode; %ld labels; "
                        "fine-tuned on %ld episodes (%.0f s)\n", r.round, r.success, r.success_se, r.episodes, r.collisions, r.labels,
                        r.train_episodes, r.seconds);
        std::fflush(stdout);
    };
    const MethodSetup setup;
    madbp::dagger(base, model, c, [&](const madbp::MadbpModel& m) {
        return planner_factory(std::make_shared<const madbp::MadbpModel>(m.clone()), o, setup);
    });
    std::printf("dagger: %d rounds -> %s (log %s.dagger.csv)\n", c.rounds, c.train.out.c_str(), c.train.out.c_str());
    return 0;
}

}  // namespace madbp_cli
