// Tests of the controllers (SPEC 3.1, 3.2, 3.5, 3.6), plans and their execution, episodes,
// evaluation and rendering.
#include <doctest/doctest.h>

#include "madbp_sim.hpp"

using namespace madbp;

// f(u) = |u|^2 + w max(0, a + b.u)^2, the CLF-QP objective with the slack eliminated.
static double clf_cost(double a, Vec2 b, double w, Vec2 u) {
    double c = std::max(0.0, a + dot(b, u));
    return dot(u, u) + w * c * c;
}

TEST_CASE("CLF-QP: the closed-form / active-set answer matches brute force over a fine grid") {
    Rng rng(7);
    int on_boundary = 0, inside = 0, zero = 0;
    for (int trial = 0; trial < 300; ++trial) {
        double a = rng.uniform(-1, 3) * (trial % 3 == 0 ? 10 : 1);
        Vec2 b{rng.uniform(-2, 2), rng.uniform(-2, 2)};
        if (trial % 7 == 0) b.x = 0;  // degenerate direction
        double w = trial % 2 ? 100 : rng.uniform(0.5, 50);
        Vec2 u = clf_qp_solve(a, b, w);
        REQUIRE(std::fabs(u.x) <= 1.0);
        REQUIRE(std::fabs(u.y) <= 1.0);
        // Brute force on a 0.005 grid, then refine around the best cell on a 1e-4 grid.
        Vec2 best{0, 0};
        double best_f = clf_cost(a, b, w, best);
        for (int i = -200; i <= 200; ++i)
            for (int j = -200; j <= 200; ++j) {
                Vec2 c{i * 0.005, j * 0.005};
                double f = clf_cost(a, b, w, c);
                if (f < best_f) { best_f = f; best = c; }
            }
        Vec2 coarse = best;
        for (int i = -50; i <= 50; ++i)
            for (int j = -50; j <= 50; ++j) {
                Vec2 c = clamp_box(coarse + Vec2{i * 1e-4, j * 1e-4}, 1.0);
                double f = clf_cost(a, b, w, c);
                if (f < best_f) { best_f = f; best = c; }
            }
        double f_qp = clf_cost(a, b, w, u);
        CHECK(f_qp <= best_f + 1e-9);
        // f is 2-strongly convex, so |u - u*|^2 <= f(best) - f(u*): the grid point pins u down.
        CHECK(dot(u - best, u - best) <= best_f - f_qp + 1e-9);
        if (norm(u) == 0) zero++;
        else if (std::fabs(u.x) == 1.0 || std::fabs(u.y) == 1.0) on_boundary++;
        else inside++;
    }
    // The trials exercise all three cases of the solver.
    CHECK(zero > 10);
    CHECK(on_boundary > 10);
    CHECK(inside > 10);
}

TEST_CASE("CLF-QP: tuned constants bring a lone agent home; VMAS's do not within 100 steps") {
    int tuned = 0, vmas = 0;
    ClfQpParams v;
    v.c_ev = 0.5;
    v.c_vv = 1.0;
    v.eps = 0.2;
    v.drag_in_lfv = false;
    for (int seed = 0; seed < 20; ++seed) {
        World w1 = make_random_world("empty", 1, seed), w2 = w1;
        ClfQp tuned_policy, vmas_policy(v);
        tuned += run_episode(w1, tuned_policy).success;
        vmas += run_episode(w2, vmas_policy).success;
    }
    CHECK(tuned == 20);
    CHECK(vmas == 0);
}

TEST_CASE("StepModel is the world's contact-free step, exactly") {
    World w;
    int id = w.add_agent({0, 0}, {0.5, 0.5});
    w.set_state(id, {0.1, -0.2}, {0.3, -0.1});
    StepModel m(w.config());
    CHECK(m.pv == doctest::Approx(0.075));
    CHECK(m.pu == doctest::Approx(0.0075));
    CHECK(m.vv == doctest::Approx(0.75));
    CHECK(m.vu == doctest::Approx(0.1));
    Vec2 u{0.6, -0.9};
    Vec2 p = w.agent(id).pos + w.agent(id).vel * m.pv + u * m.pu, v = w.agent(id).vel * m.vv + u * m.vu;
    w.step({u});
    CHECK(w.agent(id).pos.x == doctest::Approx(p.x).epsilon(1e-12));
    CHECK(w.agent(id).pos.y == doctest::Approx(p.y).epsilon(1e-12));
    CHECK(w.agent(id).vel.x == doctest::Approx(v.x).epsilon(1e-12));
}

TEST_CASE("tracker: follows a straight line at 0.3 units/s with a small error") {
    World w;
    int id = w.add_agent({-0.9, -0.5}, {0.9, 0.5});
    StepModel m(w.config());
    TrackerParams tp;
    double worst = 0;
    for (int t = 0; t < 50; ++t) {
        auto ref = [&](int k) { return Vec2{-0.9 + 0.03 * k, -0.5}; };
        const Agent& a = w.agent(id);
        w.step({track_waypoint(a.pos, a.vel, ref(t + 1), m.steady_velocity({0.03, 0}), m, tp)});
        if (t >= 20) worst = std::max(worst, norm(w.agent(id).pos - ref(t + 1)));
        if (t == 3) CHECK(norm(w.agent(id).pos - ref(t + 1)) > 0.03);  // from rest it lags (force limit)
    }
    CHECK(worst < 0.002);  // then catches up and holds the line
    CHECK(m.steady_velocity({0.03, 0}).x == doctest::Approx(0.32));
}

TEST_CASE("LinePlanner: straight waypoints toward the goal, stopping there") {
    World w;
    w.add_agent({0, 0}, {0.1, 0});
    LinePlanner lp;
    lp.horizon = 6;
    lp.speed = 0.3;
    Plan p = lp(w);
    REQUIRE(p.waypoints.size() == 1);
    REQUIRE(p.waypoints[0].size() == 6);
    CHECK(p.waypoints[0][0].x == doctest::Approx(0.03));
    CHECK(p.waypoints[0][2].x == doctest::Approx(0.09));
    CHECK(p.waypoints[0][3].x == doctest::Approx(0.1));
    CHECK(p.waypoints[0][5].x == doctest::Approx(0.1));
    CHECK(p.waypoints[0][5].y == 0.0);
}

// Eight agents on a circle, each heading for the antipode: the densest classic crossing.
static World crowded_circle(int n = 8, double radius = 0.8) {
    World w;
    for (int i = 0; i < n; ++i) {
        double a = 2 * M_PI * i / n;
        w.add_agent({radius * std::cos(a), radius * std::sin(a)}, {-radius * std::cos(a), -radius * std::sin(a)});
    }
    return w;
}

TEST_CASE("safety filter: agents never overlap in a crowded crossing (and do without it)") {
    for (bool filter : {true, false}) {
        World w = crowded_circle();
        FollowerConfig fc;
        fc.safety_filter = filter;
        PlanFollower follower(LinePlanner{}, fc);
        double closest = 1e9;
        while (!w.done()) {
            w.step(follower.act(w));
            for (int i = 0; i < w.size(); ++i)
                for (int j = i + 1; j < w.size(); ++j) closest = std::min(closest, norm(w.agents()[i].pos - w.agents()[j].pos));
        }
        if (filter) {
            CHECK(w.metrics().agent_collisions == 0);
            CHECK(closest >= 0.2);
        } else {
            CHECK(w.metrics().agent_collisions > 0);
        }
    }
    // Random nominal actions pushing agents at each other, obstacles and walls, with SPEC 3.2's
    // barrier rate and the plan follower's faster one.
    for (int seed = 0; seed < 20; ++seed) {
        World w = make_random_world("obstacles", 8, seed);
        Rng rng(seed);
        SafetyFilterParams sp = seed % 2 ? follower_filter() : SafetyFilterParams{};
        for (int t = 0; t < 100; ++t) {
            std::vector<Vec2> nominal;
            for (const Agent& a : w.agents()) {
                Vec2 toward_centre = normalized(Vec2{0, 0} - a.pos) * 1.5;
                nominal.push_back(toward_centre + Vec2{rng.uniform(-1, 1), rng.uniform(-1, 1)});
            }
            w.step(safety_filter(w, nominal, sp));
        }
        CHECK(w.metrics().agent_collisions == 0);
        CHECK(w.metrics().obstacle_collisions == 0);
    }
}

TEST_CASE("safety filter: leaves safe nominal actions alone and never steers toward goals") {
    World w;
    w.add_agent({-0.5, 0}, {0.5, 0});
    w.add_agent({0.5, 0.5}, {-0.5, -0.5});
    std::vector<Vec2> nominal{{0.3, -0.2}, {-0.1, 0.4}};
    auto out = safety_filter(w, nominal, SafetyFilterParams{});
    CHECK(out[0].x == doctest::Approx(0.3));
    CHECK(out[1].y == doctest::Approx(0.4));
    // A "stay here" plan: the team holds position and never reaches its goals.
    for (const char* map : {"empty", "obstacles", "barrier"})
        for (int seed = 0; seed < 10; ++seed) {
            World world = make_random_world(map, 6, seed);
            std::vector<Vec2> starts;
            for (const Agent& a : world.agents()) starts.push_back(a.pos);
            Planner stay = [](const World& wd) {
                Plan p;
                for (const Agent& a : wd.agents()) {
                    p.ids.push_back(a.id);
                    p.waypoints.push_back(std::vector<Vec2>(16, a.pos));
                }
                return p;
            };
            PlanFollower follower(stay);
            int reached = 0;
            while (!world.done()) {
                world.step(follower.act(world));
                for (const Agent& a : world.agents()) reached += world.at_goal(a);
            }
            CHECK(reached == 0);
            CHECK_FALSE(world.metrics().success);
            for (int i = 0; i < world.size(); ++i) CHECK(norm(world.agents()[i].pos - starts[i]) < 0.05);
        }
}

TEST_CASE("PlanFollower: replans every m steps and on joins and leaves; bad plans are errors") {
    World w = make_random_world("empty", 3, 1);
    FollowerConfig fc;
    fc.replan_every = 4;
    int calls = 0;
    PlanFollower f([&](const World& wd) { calls++; return LinePlanner{}(wd); }, fc);
    for (int t = 0; t < 10; ++t) w.step(f.act(w));
    CHECK(calls == 3);  // steps 0, 4, 8
    w.add_agent({0.9, -0.9}, {-0.9, 0.9});
    w.step(f.act(w));
    CHECK(calls == 4);
    w.remove_agent(0);
    w.step(f.act(w));
    CHECK(calls == 5);
    CHECK(f.plans() == 5);
    CHECK(f.plan().ids.size() == 3);

    auto bad = [&](std::function<void(Plan&)> spoil) {
        World wd = make_random_world("empty", 2, 0);
        PlanFollower pf([spoil](const World& x) { Plan p = LinePlanner{}(x); spoil(p); return p; });
        return pf.act(wd);
    };
    CHECK_THROWS_WITH_AS(bad([](Plan& p) { p.ids[1] = p.ids[0]; }), doctest::Contains("duplicate agent id"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(bad([](Plan& p) { p.ids.pop_back(); p.waypoints.pop_back(); }), doctest::Contains("covers 1 of 2"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(bad([](Plan& p) { p.waypoints[0][3].y = NAN; }), doctest::Contains("not finite"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(bad([](Plan& p) { p.ids[0] = 99; }), doctest::Contains("not in the world"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(bad([](Plan& p) { p.waypoints[1].clear(); }), doctest::Contains("no waypoints"), std::invalid_argument);
    FollowerConfig zero;
    zero.replan_every = 0;
    CHECK_THROWS_AS(PlanFollower(LinePlanner{}, zero), std::invalid_argument);
}

TEST_CASE("PlanFollower: a plan's replan_after brings the next plan forward; 0 leaves replan_every") {
    const World world = make_random_world("empty", 2, 1);
    for (int after : {0, 3}) {
        FollowerConfig fc;
        fc.replan_every = 8;
        fc.replan_error = 0;
        std::vector<long> planned_at;
        PlanFollower follower([&](const World& w) { planned_at.push_back(w.t()); Plan p = LinePlanner{}(w); p.replan_after = after; return p; }, fc);
        World w = world;
        for (int t = 0; t < 10; ++t) w.step(follower.act(w));
        CHECK(planned_at == (after ? std::vector<long>{0, 3, 6, 9} : std::vector<long>{0, 8}));
    }
}

TEST_CASE("PlanFollower: replans early when a robot is farther than replan_error from its plan's waypoint for now") {
    CHECK(FollowerConfig{}.replan_error == 0.15);
    // Plans that put every waypoint 0.5 to the side of where each robot is when planned: no robot
    // can be there after one step (it moves <= 0.036 a step), so each is 0.46+ off its plan.
    auto count_plans = [](double replan_error, bool reachable) {
        World w = make_random_world("empty", 2, 3);
        int calls = 0;
        FollowerConfig fc;
        fc.replan_every = 8;
        fc.replan_error = replan_error;
        PlanFollower f(
            [&](const World& wd) {
                calls++;
                Plan p = LinePlanner{}(wd);
                if (!reachable)
                    for (size_t i = 0; i < p.ids.size(); ++i)
                        for (Vec2& q : p.waypoints[i]) q = wd.agents()[i].pos + Vec2{0, 0.5};
                return p;
            },
            fc);
        for (int t = 0; t < 10; ++t) w.step(f.act(w));
        return calls;
    };
    CHECK(count_plans(0, false) == 2);     // steps 0 and 8 only
    CHECK(count_plans(0.15, false) == 3);  // off the plan at every step: a plan every 4 steps (half of m), 0, 4, 8
    CHECK(count_plans(0.5, false) == 2);   // 0.46-0.5 off: within the bound, no early plan
    CHECK(count_plans(0.15, true) == 2);   // a plan it can follow: every m steps, as with 0
    for (double bad : {-0.1, (double)NAN}) {
        FollowerConfig fc;
        fc.replan_error = bad;
        CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, fc), doctest::Contains("replan_error"), std::invalid_argument);
    }
}

TEST_CASE("PlanFollower: filter priorities break a symmetric standoff as the expert's do") {
    // Two robots nose to nose in the open, each driving at the other: with equal weights the
    // filter bends both actions alike; with priority_weight the one that goes first (farther
    // from its goal; the lower id on a tie) keeps more of its action.
    World w;
    w.add_agent({-0.12, 0}, {0.9, 0});   // 1.02 from its goal: goes first
    w.add_agent({0.12, 0.01}, {-0.8, 0.01});
    FollowerConfig equal;
    equal.priority_weight = 1;
    PlanFollower a(LinePlanner{}, equal), b(LinePlanner{}, FollowerConfig{});
    CHECK(FollowerConfig{}.priority_weight == 4);
    CHECK(a.filter_weights(w).empty());
    const std::vector<double> weights = b.filter_weights(w);
    REQUIRE(weights.size() == 2);
    CHECK(weights[0] == 4);
    CHECK(weights[1] == 1);
    PlanFollower nominal(LinePlanner{}, [] { FollowerConfig f; f.safety_filter = false; return f; }());
    const std::vector<Vec2> u0 = nominal.act(w), ue = a.act(w), up = b.act(w);
    const double bend_e0 = norm(ue[0] - u0[0]), bend_e1 = norm(ue[1] - u0[1]);
    const double bend_p0 = norm(up[0] - u0[0]), bend_p1 = norm(up[1] - u0[1]);
    MESSAGE("bends, equal: " << bend_e0 << " " << bend_e1 << "; priorities: " << bend_p0 << " " << bend_p1);
    REQUIRE(bend_e0 + bend_e1 > 0.05);  // the filter is active here
    CHECK(std::fabs(bend_e0 - bend_e1) < 0.3 * (bend_e0 + bend_e1));
    CHECK(bend_p0 < 0.5 * bend_p1);
    // A robot at its goal gives way to one still travelling; the order is kept from first sight.
    w.set_state(0, {0.9, 0}, {0, 0});
    const std::vector<double> later = b.filter_weights(w);
    CHECK(later[0] == 1);
    CHECK(later[1] == 4);
    FollowerConfig bad;
    bad.priority_weight = 0.5;
    CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, bad), doctest::Contains("priority_weight"), std::invalid_argument);
    bad.priority_weight = NAN;
    CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, bad), doctest::Contains("priority_weight"), std::invalid_argument);
}

// Two robots at x = -/+ `half_gap`, each with its goal 0.9 beyond the other, followed for 80
// steps: the widest gap between them from step `from` on (the unjam tests); no collisions.
static double widest_gap_after(double half_gap, Planner planner, const FollowerConfig& fc, int from) {
    World w;
    w.add_agent({-half_gap, 0}, {0.9, 0});
    w.add_agent({half_gap, 0}, {-0.9, 0});
    PlanFollower f(std::move(planner), fc);
    double widest = 0;
    for (int t = 0; t < 80; ++t) {
        w.step(f.act(w));
        if (t >= from) widest = std::max(widest, norm(w.agents()[0].pos - w.agents()[1].pos));
    }
    CHECK(w.metrics().collisions() == 0);
    return widest;
}

TEST_CASE("PlanFollower: unjam backs a robot out of a standoff the filter holds for good") {
    // Two robots nose to nose, each driving straight at the other with equal filter weights: the
    // filter stops both, and without unjam they stand there for good. With unjam, once each has
    // been held `unjam` steps and come no nearer its goal for twice as long, it backs out.
    auto widest_after = [](int unjam, int from) {
        FollowerConfig fc;
        fc.priority_weight = 1;
        fc.unjam = unjam;
        return widest_gap_after(0.12, LinePlanner{}, fc, from);
    };
    CHECK(FollowerConfig{}.unjam == 15);
    const double held = widest_after(0, 20), backed = widest_after(15, 20);
    MESSAGE("widest gap after step 20: " << held << " without unjam, " << backed << " with");
    CHECK(held < 0.245);    // stopped at the filter's distance, 0.23
    CHECK(backed > 0.35);   // backed out
    FollowerConfig bad;
    bad.unjam = -1;
    CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, bad), doctest::Contains("unjam"), std::invalid_argument);
}

TEST_CASE("PlanFollower: unjam_near backs out robots whose windows stand still in a knot") {
    // Two robots 0.25 apart, each with its goal behind the other, and a planner whose windows
    // keep every robot where it is (as the sampler's do in a knot among discs): the filter holds
    // no one, so only a robot standing still beside another counting as held backs them out.
    auto widest_after = [](double unjam_near, int from) {
        FollowerConfig fc;
        fc.unjam_near = unjam_near;
        auto stand_still = [](const World& world) {
            Plan p;
            for (const Agent& a : world.agents()) p.ids.push_back(a.id), p.waypoints.push_back(std::vector<Vec2>(16, a.pos));
            return p;
        };
        return widest_gap_after(0.125, stand_still, fc, from);
    };
    CHECK(FollowerConfig{}.unjam_near == 0);  // off: it loses knots at 128 robots (docs/experiments.md)
    const double still = widest_after(0, 20), backed = widest_after(0.35, 20);
    MESSAGE("widest gap after step 20: " << still << " without unjam_near, " << backed << " with");
    CHECK(still < 0.26);    // never moved
    CHECK(backed > 0.35);   // backed out
    FollowerConfig bad;
    bad.unjam_near = -0.1;
    CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, bad), doctest::Contains("unjam_near"), std::invalid_argument);
}

TEST_CASE("PlanFollower: lookahead aims between later waypoints; in steady tracking the robot runs that far ahead") {
    // One robot at rest, a plan along +x at half its top speed: waypoint k (0-based, the
    // position after step k + 1) at 0.02 (k + 1).
    World w;
    w.add_agent({0, 0}, {1, 0});
    auto along_x = [](const World&) {
        Plan p;
        p.ids = {0};
        p.waypoints.resize(1);
        for (int k = 0; k < 15; ++k) p.waypoints[0].push_back({0.02 * (k + 1), 0});
        return p;
    };
    const StepModel model(w.config());
    auto follower = [&](double lookahead) {
        FollowerConfig fc;
        fc.lookahead = lookahead;
        fc.replan_every = 100;  // one plan: the window runs out after 15 steps
        return PlanFollower(along_x, fc);
    };
    CHECK(FollowerConfig{}.lookahead == 2.0);
    const Vec2 v_ref = model.steady_velocity({0.02, 0});
    PlanFollower now = follower(0), ahead = follower(1.5), past_end = follower(100);
    CHECK(norm(now.act(w)[0] - track_waypoint({0, 0}, {0, 0}, {0.02, 0}, v_ref, model, TrackerParams{})) < 1e-12);
    // 1.5 steps ahead: halfway between waypoints 1 and 2, at 0.05.
    CHECK(norm(ahead.act(w)[0] - track_waypoint({0, 0}, {0, 0}, {0.05, 0}, v_ref, model, TrackerParams{})) < 1e-12);
    // Past the window's end: its last waypoint, at rest.
    CHECK(norm(past_end.act(w)[0] - track_waypoint({0, 0}, {0, 0}, {0.30, 0}, {0, 0}, model, TrackerParams{})) < 1e-12);
    // Closed loop: the robot accelerates at full force at first (both alike), then tracks. With
    // lookahead 0 it ends on the waypoint planned for now; with 1.5 more than a step ahead of it.
    auto ahead_of_plan = [&](double lookahead) {
        World wl;
        wl.add_agent({0, 0}, {1, 0});
        PlanFollower f = follower(lookahead);
        for (int t = 0; t < 12; ++t) wl.step(f.act(wl));
        return wl.agents()[0].pos.x - 0.02 * 12;
    };
    const double on0 = ahead_of_plan(0), on15 = ahead_of_plan(1.5);
    MESSAGE("ahead of the plan after 12 steps: " << on0 << " (lookahead 0), " << on15 << " (1.5)");
    CHECK(std::fabs(on0) < 0.002);
    CHECK(on15 > 0.02);
    for (double bad : {-0.5, (double)NAN, 2 * kMaxLookahead}) {
        FollowerConfig fc;
        fc.lookahead = bad;
        CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, fc), doctest::Contains("lookahead"), std::invalid_argument);
    }
}

TEST_CASE("PlanFollower: its filter's faster barrier lets robots close in sooner, never overlap; bad rates are refused") {
    CHECK(FollowerConfig{}.filter.rate == 4);
    CHECK(SafetyFilterParams{}.rate == 2.5);  // SPEC 3.2's, the expert's and the straight line's
    // Two robots head-on at top speed, 0.02 apart sideways so that they can slide past.
    auto head_on = [](double rate, double& closest) {
        World w;
        w.add_agent({-0.8, 0.01}, {0.8, 0.01});
        w.add_agent({0.8, -0.01}, {-0.8, -0.01});
        FollowerConfig fc;
        fc.filter.rate = rate;
        LinePlanner line;
        line.speed = 0.4;
        PlanFollower f(line, fc);
        closest = 1e9;
        int first_near = -1;  // the step at which their gap first falls below 0.05
        while (!w.done()) {
            w.step(f.act(w));
            const double d = norm(w.agents()[0].pos - w.agents()[1].pos);
            closest = std::min(closest, d);
            if (first_near < 0 && d < 0.25) first_near = w.t();
        }
        CHECK(w.metrics().agent_collisions == 0);
        return first_near;
    };
    double closest_spec = 0, closest_follower = 0;
    const int near_spec = head_on(2.5, closest_spec), near_follower = head_on(FollowerConfig{}.filter.rate, closest_follower);
    MESSAGE("gap below 0.05 at step " << near_spec << " (rate 2.5), " << near_follower << " (4); closest " << closest_spec << ", " << closest_follower);
    CHECK(near_follower > 0);
    CHECK(near_follower < near_spec);
    CHECK(closest_follower >= 0.2);
    for (double bad : {0.0, -1.0, (double)NAN}) {
        FollowerConfig fc;
        fc.filter.rate = bad;
        CHECK_THROWS_WITH_AS(PlanFollower(LinePlanner{}, fc), doctest::Contains("filter.rate"), std::invalid_argument);
    }
    // Checked against the world's step: at rate x dt >= 1 one step could close the whole gap.
    FollowerConfig fast;
    fast.filter.rate = 10;
    PlanFollower too_fast(LinePlanner{}, fast);
    World w = crowded_circle(2);
    CHECK_THROWS_WITH_AS(too_fast.act(w), doctest::Contains("filter.rate"), std::invalid_argument);
    fast.safety_filter = false;  // without the filter the rate is not used
    CHECK_NOTHROW(PlanFollower(LinePlanner{}, fast).act(w));
}

TEST_CASE("PlanFollower: its filter lets a robot through a gap on its route that SPEC's margin closes") {
    // One number says where a robot's centre may go for routes and passages; the follower's
    // filter keeps a little more, SPEC's filter more still.
    CHECK(RouteClearance{}.min == kPassableClearance);
    CHECK(RouteGuide{}.min_clear == kPassableClearance);
    CHECK(ExpertParams{}.min_clear == kPassableClearance);
    const double follower_clear = WorldConfig{}.radius + FollowerConfig{}.filter.static_margin;
    CHECK(follower_clear >= kPassableClearance);
    CHECK(follower_clear < WorldConfig{}.radius + SafetyFilterParams{}.static_margin);
    CHECK(SafetyFilterParams{}.static_margin == 0.01);  // SPEC 3.2's, the expert's and the straight line's
    // Two discs whose gap keeps 0.107 at its narrowest: passable for a route (>= 0.102) and the
    // follower (0.105), not for a filter keeping 0.01 beyond touching (0.11).
    const double throat = 0.107;
    WorldMap map;
    for (double side : {1.0, -1.0}) {  // walled off up to the world's edges: no way around
        map.discs.push_back({{0, side * (throat + 0.1)}, 0.1});
        map.boxes.push_back({{-0.02, side > 0 ? throat + 0.1 : -1.2}, {0.02, side > 0 ? 1.2 : -(throat + 0.1)}});
    }
    RouteGuide guide;
    const RouteGoal sub = guide.subgoal(map, {-0.6, 0}, {0.6, 0}, 0.9);
    CHECK(sub.goal.x > 0.1);  // the route goes through the gap
    CHECK(std::abs(sub.goal.y) < 0.05);
    auto through = [&](double static_margin) {
        World w(map);
        w.add_agent({-0.6, 0}, {0.6, 0});
        FollowerConfig fc;
        fc.filter.static_margin = static_margin;
        PlanFollower f(LinePlanner{}, fc);
        while (!w.done()) w.step(f.act(w));
        CHECK(w.metrics().collisions() == 0);
        return w.metrics().success;
    };
    CHECK(through(FollowerConfig{}.filter.static_margin));
    CHECK_FALSE(through(SafetyFilterParams{}.static_margin));  // frozen at the gap's mouth
}

TEST_CASE("wavefront: steps around a wall, unreachable behind a closed one") {
    WorldMap m;
    m.boxes.push_back({{-1.2, -0.05}, {0.6, 0.05}});  // gap from 0.6 to 1.2 on the right
    ClearanceGrid g(m, 0.1);
    REQUIRE(g.n == 24);
    std::vector<int> steps = wavefront(g, g.index({-0.8, 0.6}), 0.13);
    int below = steps[g.index({-0.8, -0.6})];
    // Straight through the wall would be 12 steps; around the end it is much longer.
    CHECK(below > 25);
    CHECK(steps[g.index({-0.8, 0.6})] == 0);
    CHECK(steps[g.index({-0.8, 0.0})] == -1);  // inside the wall
    WorldMap closed;
    closed.boxes.push_back({{-1.2, -0.05}, {1.2, 0.05}});
    ClearanceGrid gc(closed, 0.1);
    CHECK(wavefront(gc, gc.index({0, 0.6}), 0.13)[gc.index({0, -0.6})] == -1);
}

TEST_CASE("guided expert: solves random problems on every map with few collisions, deterministically") {
    struct Cell { const char* map; int n; };
    for (Cell c : {Cell{"empty", 6}, Cell{"obstacles", 4}, Cell{"barrier", 4}}) {
        int wins = 0;
        long collisions = 0;
        for (int seed = 0; seed < 8; ++seed) {
            World w = make_random_world(c.map, c.n, 500 + seed);
            GuidedExpert expert(w.map());
            EpisodeResult r = run_episode(w, expert);
            wins += r.success;
            collisions += r.collisions();
        }
        INFO(c.map << " n=" << c.n);
        CHECK(wins >= 7);
        CHECK(collisions <= 2);
    }
    World a = make_random_world("barrier", 3, 3), b = a;
    GuidedExpert ea(a.map()), eb(b.map());
    EpisodeResult ra = run_episode(a, ea), rb = run_episode(b, eb);
    CHECK(ra.steps == rb.steps);
    CHECK(a.agents()[2].pos.x == b.agents()[2].pos.x);
}

TEST_CASE("guided expert: a four-robot swap through a gap, and a team that changes mid-episode") {
    const char* text =
        "madbp-scene 1\n"
        "box -1.2 -0.05 -0.25 0.05\n"
        "box 0.25 -0.05 1.2 0.05\n"
        "agent -0.6 0.6 0.6 -0.6\n"
        "agent 0.6 -0.6 -0.6 0.6\n"
        "agent 0.6 0.6 -0.6 -0.6\n"
        "agent -0.6 -0.6 0.6 0.6\n";
    World w = make_world(parse_scene(text));
    GuidedExpert expert(w.map());
    EpisodeResult r = run_episode(w, expert);
    CHECK(r.success);
    CHECK(r.collisions() == 0);
    // Join at step 10, leave at step 20: success is judged on the agents present.
    World d = make_random_world("obstacles", 3, 4);
    GuidedExpert ed(d.map());
    EpisodeResult rd = run_episode(d, ed, false, [](World& x) {
        if (x.t() == 10) x.add_agent({0.0, -1.0}, {0.0, 1.0});
        if (x.t() == 20) x.remove_agent(0);
    });
    CHECK(rd.success);
    CHECK(rd.agents == 3);
    CHECK(d.index_of(3) >= 0);
    CHECK(rd.steps > 20);
}

TEST_CASE("evaluate: episode i uses seed S+i; success, its standard error, steps") {
    EvalConfig c;
    c.map = "empty";
    c.agents = 3;
    c.episodes = 4;
    c.seed = 10;
    int made = 0;
    std::vector<uint64_t> seeds;
    EvalResult r = evaluate(c, [&](const World&, uint64_t seed) {
        made++;
        seeds.push_back(seed);
        return std::make_unique<ClfQp>();
    });
    CHECK(made == 4);
    std::sort(seeds.begin(), seeds.end());
    CHECK(seeds == std::vector<uint64_t>{10, 11, 12, 13});
    int wins = 0;
    double steps = 0;
    for (int e = 0; e < 4; ++e) {
        World w = make_random_world("empty", 3, 10 + e);
        ClfQp p;
        EpisodeResult one = run_episode(w, p);
        CHECK(one.steps == r.runs[e].steps);
        wins += one.success;
        steps += one.success ? one.steps : 0;
    }
    CHECK(r.success == doctest::Approx(wins / 4.0));
    CHECK(r.success_se == doctest::Approx(std::sqrt(r.success * (1 - r.success) / 4)));
    if (wins) CHECK(r.steps == doctest::Approx(steps / wins));
    c.map = "swamp";
    CHECK_THROWS_AS(evaluate(c, [](const World&, uint64_t) { return std::make_unique<ClfQp>(); }), std::invalid_argument);
    c.map = "empty";
    c.episodes = 0;
    CHECK_THROWS_AS(evaluate(c, [](const World&, uint64_t) { return std::make_unique<ClfQp>(); }), std::invalid_argument);
}

TEST_CASE("evaluate: failed_seeds lists the seeds of the failed episodes, in order") {
    struct Still : Policy {
        std::vector<Vec2> act(const World& w) override { return std::vector<Vec2>(w.size()); }
    };
    EvalConfig c;
    c.agents = 1;
    c.episodes = 6;
    c.seed = 20;
    c.threads = 2;  // episodes finish out of order; the list is still by seed
    // CLF-QP brings one robot home in an empty world; a robot that stands still does not.
    EvalResult r = evaluate(c, [](const World&, uint64_t seed) -> std::unique_ptr<Policy> {
        if (seed % 3 == 0) return std::make_unique<Still>();
        return std::make_unique<ClfQp>();
    });
    CHECK(r.failed_seeds == std::vector<uint64_t>{21, 24});
    CHECK(r.success == doctest::Approx(4.0 / 6));
    for (int e = 0; e < c.episodes; ++e) CHECK(r.runs[e].success == ((c.seed + e) % 3 != 0));
}

TEST_CASE("render: static and animated SVG hold the map, goals, tracks and collisions") {
    World w = make_random_world("obstacles", 3, 2);
    FollowerConfig fc;
    fc.safety_filter = false;
    PlanFollower f(LinePlanner{}, fc);
    EpisodeResult r = run_episode(w, f, true);
    REQUIRE(r.log.frames.size() == (size_t)w.t() + 1);
    auto count = [](const std::string& s, const std::string& what) {
        size_t k = 0;
        for (size_t pos = s.find(what); pos != std::string::npos; pos = s.find(what, pos + 1)) k++;
        return k;
    };
    SvgOptions opt;
    opt.title = "a <title> & more";
    std::string svg = render_svg(r.log, opt);
    CHECK(svg.rfind("<svg", 0) == 0);
    CHECK(count(svg, "<polyline") == 3);
    CHECK(count(svg, "stroke-dasharray") == 3);     // goals
    CHECK(count(svg, "<circle") == 5 + 3 + 6);      // obstacles, goals, start and end discs
    CHECK(count(svg, "stroke=\"red\"") == (size_t)r.collisions());
    CHECK(svg.find("&lt;title> &amp; more") != std::string::npos);
    opt.animate = true;
    std::string anim = render_svg(r.log, opt);
    CHECK(count(anim, "<animate ") == 9);
    CHECK(anim.find("repeatCount=\"indefinite\"") != std::string::npos);
}
