// Tests of MAPPO (madbp_train.hpp, SPEC 3.3): GAE and the clipped objective against
// hand-computed values, the Gaussian and network gradients against central differences, the
// lidar on a hand-placed scene, a short one-agent training run that must learn, checkpoints
// (round trip, exact resume, determinism) and clear errors on bad input.
#include <doctest/doctest.h>

#include <cstdio>

#include "madbp_train.hpp"

using namespace madbp;

namespace {

std::string temp_path(const std::string& name) { return "/tmp/madbp_test_mappo_" + std::to_string(::getpid()) + "_" + name; }

void remove_outputs(const std::string& out) {
    for (const char* ext : {"", ".train", ".csv", ".svg"}) std::remove((out + ext).c_str());
}

// A tiny, fast configuration: few worlds, few iterations.
MappoConfig tiny_config(const std::string& map, int agents, long iterations) {
    MappoConfig c;
    c.map = map;
    c.agents = agents;
    c.iterations = iterations;
    c.worlds = 4;
    c.hidden = 16;
    return c;
}

double mean_success(const MappoNet& net, const std::string& map, int agents, int episodes) {
    EvalConfig ec;
    ec.map = map;
    ec.agents = agents;
    ec.episodes = episodes;
    ec.seed = 1000;
    return evaluate(ec, [&](const World&, uint64_t) { return std::unique_ptr<Policy>(new MappoPolicy(net.clone())); }).success;
}

}  // namespace

TEST_CASE("mappo: GAE matches a hand-computed stream with a terminal step") {
    // gamma 0.9, lambda 0.8; step 1 ends an episode by success (nothing follows it).
    const float reward[3] = {1, 0, 2}, value[3] = {0.5f, 0.4f, 0.3f};
    const uint8_t terminal[3] = {0, 1, 0};
    float adv[3], ret[3];
    gae(reward, value, terminal, /*last_value=*/1.0f, 3, 1, 0.9f, 0.8f, adv, ret);
    // t=2: 2 + 0.9*1.0 - 0.3 = 2.6.  t=1: 0 - 0.4 (terminal).  t=0: 1 + 0.9*0.4 - 0.5 + 0.72*(-0.4).
    CHECK(adv[2] == doctest::Approx(2.6));
    CHECK(adv[1] == doctest::Approx(-0.4));
    CHECK(adv[0] == doctest::Approx(0.572));
    CHECK(ret[0] == doctest::Approx(1.072));
    CHECK(ret[1] == doctest::Approx(0.0).epsilon(1e-6));
    CHECK(ret[2] == doctest::Approx(2.9));
    // A stride walks an interleaved buffer (the rollout's layout) to the same result.
    const float r2[6] = {1, 9, 0, 9, 2, 9}, v2[6] = {0.5f, 9, 0.4f, 9, 0.3f, 9};
    const uint8_t t2[6] = {0, 0, 1, 0, 0, 0};
    float a2[6], R2[6];
    gae(r2, v2, t2, 1.0f, 3, 2, 0.9f, 0.8f, a2, R2);
    CHECK(a2[0] == doctest::Approx(adv[0]));
    CHECK(a2[4] == doctest::Approx(adv[2]));
}

TEST_CASE("mappo: clipped surrogate matches hand-computed values and its gradient") {
    // ratios 1.5, 1.5, 0.5, 0.5, 1.1 against advantages +1, -1, +2, -2, +3, clip 0.2:
    // terms -min(rA, clip(r)A) = -1.2 (clipped), +1.5, -1.0, +1.6 (clipped), -3.3.
    Vec old = Vec::Zero(5), adv(5), logp(5), d;
    logp << std::log(1.5f), std::log(1.5f), std::log(0.5f), std::log(0.5f), std::log(1.1f);
    adv << 1, -1, 2, -2, 3;
    double clip_fraction = 0;
    const double loss = clipped_surrogate(logp, old, adv, 0.2f, d, &clip_fraction);
    CHECK(loss == doctest::Approx(-2.4 / 5));
    CHECK(clip_fraction == doctest::Approx(0.4));
    CHECK(d[0] == 0.0f);
    CHECK(d[1] == doctest::Approx(1.5 / 5));
    CHECK(d[2] == doctest::Approx(-1.0 / 5));
    CHECK(d[3] == 0.0f);
    CHECK(d[4] == doctest::Approx(-3.3 / 5));
    // Central differences agree away from the kinks.
    for (int s = 0; s < 5; ++s) {
        Vec lp = logp, lm = logp, dd;
        lp[s] += 1e-3f;
        lm[s] -= 1e-3f;
        const double fd = (clipped_surrogate(lp, old, adv, 0.2f, dd) - clipped_surrogate(lm, old, adv, 0.2f, dd)) / 2e-3;
        CHECK(fd == doctest::Approx(d[s]).epsilon(2e-3).scale(1));
    }
}

TEST_CASE("mappo: Gaussian log-probability and entropy: values and gradients") {
    const float a[2] = {0.3f, -0.7f}, mu[2] = {0.1f, -0.2f}, ls[2] = {-0.4f, 0.25f};
    float dmu[2], dls[2];
    const float lp = gaussian_log_prob(a, mu, ls, dmu, dls);
    double expect = 0;
    for (int k = 0; k < 2; ++k) {
        const double s = std::exp((double)ls[k]), z = (a[k] - mu[k]) / s;
        expect += -0.5 * z * z - ls[k] - 0.5 * std::log(2 * M_PI);
    }
    CHECK(lp == doctest::Approx(expect).epsilon(1e-6));
    const double h = 1e-3;
    for (int k = 0; k < 2; ++k) {
        float mp[2] = {mu[0], mu[1]}, mm[2] = {mu[0], mu[1]}, sp[2] = {ls[0], ls[1]}, sm[2] = {ls[0], ls[1]};
        mp[k] += (float)h, mm[k] -= (float)h, sp[k] += (float)h, sm[k] -= (float)h;
        CHECK(dmu[k] == doctest::Approx((gaussian_log_prob(a, mp, ls) - gaussian_log_prob(a, mm, ls)) / (2 * h)).epsilon(2e-3));
        CHECK(dls[k] == doctest::Approx((gaussian_log_prob(a, mu, sp) - gaussian_log_prob(a, mu, sm)) / (2 * h)).epsilon(2e-3));
        CHECK((gaussian_entropy(sp) - gaussian_entropy(sm)) / (2 * h) == doctest::Approx(1.0).epsilon(1e-3));
    }
    CHECK(gaussian_entropy(ls) == doctest::Approx(1 + std::log(2 * M_PI) + ls[0] + ls[1]).epsilon(1e-6));
}

TEST_CASE("mappo: actor and critic backward through the full PPO loss match central differences") {
    MappoNetConfig nc;
    nc.agents = 2;
    nc.hidden = 8;
    MappoNet net(nc, 3);
    Rng rng(5);
    // Make the actor's last layer non-trivial (it starts 100x small).
    for (int k = 0; k < net.params->size(); ++k) net.params->value[k] += (float)(0.1 * rng.normal());
    const int N = 6;
    PpoBatch b;
    b.obs.resize(kMappoObs, N);
    b.critic_in.resize(kMappoObs * 2, N);
    b.act.resize(2, N);
    for (int k = 0; k < b.obs.size(); ++k) b.obs.data()[k] = (float)rng.normal();
    for (int k = 0; k < b.critic_in.size(); ++k) b.critic_in.data()[k] = (float)rng.normal();
    for (int k = 0; k < b.act.size(); ++k) b.act.data()[k] = (float)rng.normal();
    b.adv.resize(N), b.ret.resize(N), b.logp_old.resize(N);
    // Old log-probabilities near the current ones: ratios in [0.9, 1.1], away from the clip kinks.
    Mat mean;
    net.actor.forward(b.obs, mean);
    const Eigen::Vector2f ls = net.log_std_value();
    for (int s = 0; s < N; ++s) {
        b.logp_old[s] = gaussian_log_prob(&b.act(0, s), &mean(0, s), ls.data()) + (float)rng.uniform(-0.08, 0.08);
        b.adv[s] = (float)rng.normal();
        b.ret[s] = (float)rng.normal();
    }
    PpoCoefficients k;
    k.ent_coef = 0.05f;  // large enough for its gradient to show
    PpoWorkspace ws;
    auto total = [&](const PpoTerms& t) { return t.policy + k.vf_coef * t.value - k.ent_coef * t.entropy; };
    net.params->zero_grad();
    ppo_loss(net, b, k, ws);
    const Vec grad = net.params->grad;
    // Every 7th parameter, and both entries of the learned log-std.
    std::vector<int> checked;
    for (int p = 0; p < net.params->size(); p += 7) checked.push_back(p);
    checked.push_back(net.log_std);
    checked.push_back(net.log_std + 1);
    CHECK(checked.size() > 50);
    for (int p : checked) {
        const float keep = net.params->value[p], h = 2e-3f;
        net.params->value[p] = keep + h;
        const double up = total(ppo_loss(net, b, k, ws));
        net.params->value[p] = keep - h;
        const double down = total(ppo_loss(net, b, k, ws));
        net.params->value[p] = keep;
        CHECK_MESSAGE(grad[p] == doctest::Approx((up - down) / (2 * h)).epsilon(0.03).scale(2e-3), "parameter ", p);
    }
}

TEST_CASE("mappo: observations and lidar on a hand-placed scene") {
    // Agent A at (0.3, 0.95): a disc obstacle 0.2 to its right (surface at 0.1), the top wall
    // 0.25 above, agent B 0.25 to its left (surface at 0.15). B sees a box 0.25 below it.
    WorldMap map;
    map.discs.push_back({{0.5, 0.95}, 0.1});
    map.boxes.push_back({{-1.2, 0.6}, {0.1, 0.7}});
    World world(map);
    world.add_agent({0.3, 0.95}, {-0.5, -0.5});
    world.add_agent({0.05, 0.95}, {0.5, -0.5});
    world.set_state(0, {0.3, 0.95}, {0.2, -0.1});
    float obs[kMappoObs];
    mappo_observe(world, 0, obs);
    CHECK(obs[0] == doctest::Approx(0.3));
    CHECK(obs[1] == doctest::Approx(0.95));
    CHECK(obs[2] == doctest::Approx(0.2));
    CHECK(obs[3] == doctest::Approx(-0.1));
    CHECK(obs[4] == doctest::Approx(0.8));   // p - goal
    CHECK(obs[5] == doctest::Approx(1.45));
    const float* lidar = obs + 6;
    CHECK(lidar[0] == doctest::Approx(0.35 - 0.1));   // +x: the disc obstacle
    CHECK(lidar[3] == doctest::Approx(0.35 - 0.25));  // +y: the top wall
    CHECK(lidar[6] == doctest::Approx(0.35 - 0.15));  // -x: agent B's disc
    CHECK(lidar[9] == 0.0f);                          // -y: nothing within range reads 0
    for (int k = 0; k < kLidarRays; ++k) CHECK((lidar[k] >= 0 && lidar[k] <= kLidarRange + 1e-6));
    mappo_observe(world, 1, obs);
    CHECK(obs[6 + 9] == doctest::Approx(0.35 - 0.25));  // B, -y: the box top at y = 0.7
    CHECK(obs[6 + 0] == doctest::Approx(0.35 - 0.15));  // B, +x: agent A
    // A diagonal ray against the disc: from (0.3, 0.95) at 30 degrees the ray passes the disc
    // centre (0.5, 0.95) at perpendicular distance 0.2 * sin(30) = 0.1 = r: a tangent hit.
    const double tangent = lidar_distance(world, 0, {std::cos(M_PI / 6), std::sin(M_PI / 6)});
    CHECK(tangent == doctest::Approx(0.2 * std::cos(M_PI / 6)).epsilon(1e-3));
    // Another lidar (a policy's own, from its file): 4 rays of range 0.2 see the disc and B
    // but not the wall 0.25 above; readings are scaled by the range.
    const MappoObservation four{4, 0.2};
    float obs4[6 + 4];
    mappo_observe(world, 0, obs4, four);
    CHECK(obs4[6 + 0] == doctest::Approx(0.2 - 0.1));
    CHECK(obs4[6 + 1] == 0.0f);
    CHECK(obs4[6 + 2] == doctest::Approx(0.2 - 0.15));
    CHECK(mappo_obs_scale(6, four) == doctest::Approx(5.0));
    Mat all(four.size(), 2);
    mappo_observe_all(world, all, 0, four);
    CHECK(all(6, 0) == doctest::Approx((0.2 - 0.1) * 5));
    CHECK(four.layout() == "pos2,vel2,pos-goal2,lidar4@0.2(range-distance)");
    CHECK(MappoObservation{}.layout() == "pos2,vel2,pos-goal2,lidar12@0.35(range-distance)");  // the shipped files' layout
    // From inside an obstacle a ray reads the full range.
    CHECK(detail::ray_disc({0.5, 0.95}, {1, 0}, {0.5, 0.95}, 0.1) == 0.0);
    CHECK(detail::ray_box({0, 0.65}, {0, 1}, map.boxes[0]) == 0.0);
}

TEST_CASE("mappo: rewards per agent and step (shaping, contacts, time, team success, at goal)") {
    MappoRewards r;
    r.at_goal = 0.2f;
    World world{WorldMap{}};
    world.add_agent({0, 0}, {0, 0.05});        // within the goal tolerance (0.1)
    world.add_agent({0.5, 0.5}, {-0.5, -0.5});
    CHECK(mappo_reward(r, world, 0, 0.15, 0.05, 0) == doctest::Approx(1.0 * (0.15 - 0.05) - 0.01 + 0.2));
    CHECK(mappo_reward(r, world, 1, 1.5, std::sqrt(2.0), 2) == doctest::Approx(1.0 * (1.5 - std::sqrt(2.0)) - 0.1 * 2 - 0.01));
    r.at_goal = 0;
    CHECK(mappo_reward(r, world, 0, 0.15, 0.05, 0) == doctest::Approx(0.1 - 0.01));
    // A team all at its goals on a step succeeds: every agent gets the bonus.
    World alone{WorldMap{}};
    alone.add_agent({0, 0}, {0, 0.05});
    alone.step({{0, 0}});
    REQUIRE(alone.metrics().success);
    CHECK(mappo_reward(r, alone, 0, 0.05, 0.05, 0) == doctest::Approx(-0.01 + 5.0));
}

TEST_CASE("mappo: the route distance and the route goal go around the barrier, through its gap") {
    Rng rng(3);
    const WorldMap map = make_map("barrier", rng);
    REQUIRE(map.boxes.size() == 2);
    const double gap_x = map.boxes[0].hi.x + 0.25;  // the gap's centre (width 0.5)
    const Vec2 goal{0.8, 0.6};
    const RouteDistance route(map, goal);
    // In open view of the goal: never below the straight distance, and at most 8.3 % and a cell
    // above it (8-connected steps: an octile distance, at most 1.082 times the straight one).
    for (Vec2 p : {Vec2{0.8, 0.6}, Vec2{0.3, 0.9}, Vec2{-0.9, 0.3}, Vec2{0.8, 0.2}}) {
        CHECK(route(p) >= norm(p - goal) - 1e-9);
        CHECK(route(p) <= 1.083 * norm(p - goal) + 0.06);
    }
    // Across the wall: the way through the gap, within 6 % of its length.
    const Vec2 p{0.8, -0.6}, mouth{gap_x, 0};
    const double through_gap = norm(p - mouth) + norm(mouth - goal);
    CHECK(route(p) == doctest::Approx(through_gap).epsilon(0.06));
    CHECK(route(p) > norm(p - goal) + 0.1);
    // Moving along the wall toward the gap shortens it; a step changes it by about the step.
    const double toward = gap_x < 0.8 ? -0.04 : 0.04;
    CHECK(route({0.8 + toward, -0.2}) < route({0.8, -0.2}));
    CHECK(std::fabs(route({0.81, -0.6}) - route({0.8, -0.6})) < 0.03);
    // Inside the wall (no robot fits): the straight distance.
    CHECK(route({gap_x + 0.6, 0}) == doctest::Approx(norm(Vec2{gap_x + 0.6, 0} - goal)));
    // An observation with a route goal: the point 1.5 ahead on the way through the gap.
    World world(map);
    world.add_agent(p, goal);
    const MappoObservation ob{kLidarRays, kLidarRange, 1.5};
    RouteGuide guide;
    float obs[kMappoObs];
    mappo_observe(world, 0, obs, ob, &guide);
    const Vec2 ahead = p - Vec2{obs[4], obs[5]};
    CHECK(norm(ahead - p) == doctest::Approx(1.5).epsilon(1e-4));
    CHECK((ahead.x - p.x) * (gap_x - p.x) > 0);  // toward the gap, not straight at the goal
    CHECK_THROWS_WITH_AS(mappo_observe(world, 0, obs, ob), doctest::Contains("needs a RouteGuide"), std::invalid_argument);
    CHECK(ob.layout() == "pos2,vel2,pos-routegoal2@1.5,lidar12@0.35(range-distance)");
    CHECK(MappoObservation::from_layout(ob.layout(), "f", "mappo.obs").route_goal == 1.5);
    // The shipped files' layout reads back as the defaults; near misses are refused by name.
    const MappoObservation old = MappoObservation::from_layout("pos2,vel2,pos-goal2,lidar12@0.35(range-distance)", "f", "mappo.obs");
    CHECK((old.rays == kLidarRays && old.range == kLidarRange && old.route_goal == 0));
    for (const char* bad : {"pos2,vel2,pos-routegoal2@1.50,lidar12@0.35(range-distance)", "pos2,vel2,pos-routegoal2@0,lidar12@0.35(range-distance)",
                            "pos2,vel2,pos-routegoal2@nan,lidar12@0.35(range-distance)", "pos2,vel2,pos-routegoal2@11,lidar12@0.35(range-distance)",
                            "pos2,vel2,pos-goal2,lidar12@0.35(range-distance)x", "pos2,vel2,pos-goal2,lidar99999999999@0.35(range-distance)",
                            "pos2,vel2,pos-goal2,lidar12@0.35"})
        CHECK_THROWS_WITH_AS(MappoObservation::from_layout(bad, "f", "mappo.obs"), doctest::Contains("f: __metadata__['mappo.obs']"),
                             std::runtime_error);
    // A length the layout's 6 digits would round is refused: the file must give back what trained.
    CHECK_THROWS_WITH_AS((MappoObservation{12, 0.1234567}.check("obs")), doctest::Contains("obs.range"), std::invalid_argument);
    CHECK_THROWS_WITH_AS((MappoObservation{12, 0.35, 1.2345678}.check("obs")), doctest::Contains("obs.route_goal"), std::invalid_argument);
}

TEST_CASE("mappo: a few seconds of one-agent training on the empty map learn to reach the goal [slow]") {
    MappoConfig c;
    c.map = "empty";
    c.agents = 1;
    c.iterations = 30;  // 96 000 world steps, about 2 s
    MappoNetConfig nc;
    nc.agents = 1;
    nc.hidden = c.hidden;
    const double before = mean_success(MappoNet(nc, c.seed), "empty", 1, 50);
    MappoNet trained(nc);
    MappoReport rep = train_mappo(c, &trained);
    const double after = mean_success(trained, "empty", 1, 50);
    MESSAGE("one-agent success ", before, " -> ", after, " (", rep.seconds, " s)");
    CHECK(before <= 0.1);
    CHECK(after >= 0.8);  // the stated margin: from <= .1 to >= .8
    const int ret = rep.curve.column("episode_return");
    CHECK(rep.curve.rows.back()[ret] > rep.curve.rows.front()[ret] + 1.0);
}

TEST_CASE("mappo: checkpoints round-trip; resume is exact; runs are deterministic") {
    const std::string out = temp_path("rt.safetensors");
    remove_outputs(out);
    MappoConfig c = tiny_config("obstacles", 2, 4);
    c.out = out;
    c.checkpoint_every = 2;
    c.obs = {16, 0.6, 1.5};  // a policy's own observation travels in its file
    c.rewards.route = true;  // route fields are made for every fresh world, resumed or not
    MappoNet full(MappoNetConfig{});
    train_mappo(c, &full);
    MappoNet loaded = load_mappo(out);
    CHECK(loaded.config.agents == 2);
    CHECK(loaded.config.hidden == 16);
    CHECK(loaded.config.obs.rays == 16);
    CHECK(loaded.config.obs.range == 0.6);
    CHECK(loaded.config.obs.route_goal == 1.5);
    CHECK(loaded.params->value == full.params->value);
    SafeTensors st = load_safetensors(out);
    CHECK(st.meta("mappo.map") == "obstacles");
    CHECK(st.meta("mappo.iteration") == "4");
    CHECK(st.find("optim.adam.m") == nullptr);  // the policy file carries no optimizer state
    // The same world gives the same actions from the saved and the in-memory policy.
    World w1 = make_random_world("obstacles", 2, 7), w2 = w1;
    MappoPolicy p1(full.clone()), p2(std::move(loaded));
    for (int t = 0; t < 10; ++t) {
        auto u1 = p1.act(w1), u2 = p2.act(w2);
        REQUIRE(u1.size() == 2);
        CHECK((u1[0] == u2[0] && u1[1] == u2[1]));
        w1.step(u1), w2.step(u2);
    }
    // Stopped after 2 iterations, then resumed to 4: the same parameters as straight through.
    const std::string out2 = temp_path("resume.safetensors");
    remove_outputs(out2);
    MappoConfig k = c;
    k.out = out2;
    k.keep_going = [](long it) { return it < 2; };
    train_mappo(k);
    CHECK(load_safetensors(out2 + ".train").meta("mappo.iteration") == "2");
    k.keep_going = nullptr;
    k.resume = true;
    MappoNet resumed(MappoNetConfig{});
    MappoReport rr = train_mappo(k, &resumed);
    CHECK(rr.iterations == 4);
    CHECK(rr.curve.rows.size() == 4);
    CHECK(resumed.params->value == full.params->value);
    // Thread count does not change the result.
    MappoConfig two = c;
    two.out = "";
    two.threads = 2;
    MappoNet parallel(MappoNetConfig{});
    train_mappo(two, &parallel);
    CHECK(parallel.params->value == full.params->value);
    // The same with VMAS's observation and straight shaping (the empty and obstacle policies).
    MappoConfig plain = tiny_config("obstacles", 2, 2);
    MappoNet one_thread(MappoNetConfig{}), two_threads(MappoNetConfig{});
    train_mappo(plain, &one_thread);
    plain.threads = 2;
    train_mappo(plain, &two_threads);
    CHECK(one_thread.params->value == two_threads.params->value);
    set_num_threads(1);
    remove_outputs(out);
    remove_outputs(out2);
}

TEST_CASE("mappo: bad input raises clear errors") {
    MappoNetConfig nc;
    nc.agents = 3;
    nc.hidden = 8;
    MappoPolicy policy{MappoNet(nc)};
    World two = make_random_world("empty", 2, 0);
    CHECK_THROWS_WITH_AS(policy.act(two), doctest::Contains("trained for 3 agents, the world has 2"), std::invalid_argument);
    // A foreign checkpoint (parameters of another model) is refused by name.
    const std::string foreign = temp_path("foreign.safetensors");
    ParamStore ps;
    Rng rng(0);
    Linear fc(ps, "fc", 2, 3, rng);
    save_params(foreign, ps, {{"step", "1"}});
    CHECK_THROWS_WITH_AS(load_mappo(foreign), doctest::Contains("not a MAPPO policy"), std::runtime_error);
    // A MAPPO file whose metadata disagrees with its tensors.
    MappoNet net(nc);
    auto md = net.metadata();
    md["mappo.agents"] = "4";
    save_params(foreign, *net.params, md);
    CHECK_THROWS_WITH_AS(load_mappo(foreign), doctest::Contains("critic.fc1.weight"), std::runtime_error);
    md["mappo.agents"] = "three";
    save_params(foreign, *net.params, md);
    CHECK_THROWS_WITH_AS(load_mappo(foreign), doctest::Contains("mappo.agents"), std::runtime_error);
    md = net.metadata();
    for (const char* layout : {"pos2,vel2,pos-goal2,lidar0@0.35(range-distance)", "pos2,vel2,pos-goal2,lidar12@0.350(range-distance)",
                               "pos2,vel2,lidar12@0.35", ""}) {
        md["mappo.obs"] = layout;
        save_params(foreign, *net.params, md);
        CHECK_THROWS_WITH_AS(load_mappo(foreign), doctest::Contains("observation layout"), std::runtime_error);
    }
    md = net.metadata();
    md["mappo.obs"] = "pos2,vel2,pos-goal2,lidar24@1(range-distance)";  // a valid layout, not these tensors'
    save_params(foreign, *net.params, md);
    CHECK_THROWS_WITH_AS(load_mappo(foreign), doctest::Contains("does not match the file"), std::runtime_error);
    std::remove(foreign.c_str());
    CHECK_THROWS_AS(load_mappo(temp_path("missing.safetensors")), std::runtime_error);
    MappoConfig c = tiny_config("moon", 2, 1);
    CHECK_THROWS_WITH_AS(train_mappo(c), doctest::Contains("unknown map name 'moon'"), std::invalid_argument);
    c = tiny_config("empty", 0, 1);
    CHECK_THROWS_WITH_AS(train_mappo(c), doctest::Contains("agents"), std::invalid_argument);
    c = tiny_config("empty", 2, 1);
    c.obs.rays = 0;
    CHECK_THROWS_WITH_AS(train_mappo(c), doctest::Contains("obs.rays"), std::invalid_argument);
    c.obs = {12, 0};
    CHECK_THROWS_WITH_AS(train_mappo(c), doctest::Contains("obs.range"), std::invalid_argument);
    c.obs = {12, 0.35, -1};
    CHECK_THROWS_WITH_AS(train_mappo(c), doctest::Contains("obs.route_goal"), std::invalid_argument);
    c = tiny_config("empty", 2, 1);
    c.resume = true;
    c.out = temp_path("never-written.safetensors");
    CHECK_THROWS_AS(train_mappo(c), std::runtime_error);
}

TEST_CASE("mappo: demonstrations from MAPPO policies, one per team size through {n}") {
    const std::string pattern = temp_path("demo-{n}.safetensors");
    for (int n = 1; n <= 2; ++n) {
        MappoConfig c = tiny_config("empty", n, 1);
        c.out = temp_path("demo-" + std::to_string(n) + ".safetensors");
        train_mappo(c);
    }
    CollectConfig cc;
    cc.maps = {"empty"};
    cc.n_train_max = 2;
    cc.episodes = 2;
    cc.successful_only = false;
    DemoSet set = collect_demonstrations(cc, mappo_demonstrator(pattern), "mappo:" + pattern);
    REQUIRE(set.episodes.size() == 4);
    CHECK(set.episodes[0].agents == 1);
    CHECK(set.episodes[3].agents == 2);
    CHECK(set.episodes[3].steps > 0);
    // One fixed policy cannot record the other team size.
    CHECK_THROWS_WITH(collect_demonstrations(cc, mappo_demonstrator(temp_path("demo-2.safetensors")), "mappo"),
                      doctest::Contains("trained for 2 agents"));
    cc.n_train_max = 3;  // no policy for n = 3
    CHECK_THROWS_WITH(collect_demonstrations(cc, mappo_demonstrator(pattern), "mappo"), doctest::Contains("demo-3.safetensors"));
    for (int n = 1; n <= 2; ++n) remove_outputs(temp_path("demo-" + std::to_string(n) + ".safetensors"));
}
