// PlannerConfig: one table of settings, its presets, validate() and set() (madbp.hpp Section 7).
#include <doctest/doctest.h>

#include <set>

#include "madbp.hpp"
#include "tiny_model.hpp"

using namespace madbp;

TEST_CASE("settings: the table names every field once, in groups, and its values round-trip through set()") {
    std::set<std::string> names;
    const PlannerConfig tuned = PlannerConfig::tuned();
    for (const PlannerSetting& s : planner_settings()) {
        CHECK(names.insert(s.name).second);
        const std::string name = s.name, group = name.substr(0, name.find('.'));
        CHECK((group == "neighbourhood" || group == "workspace" || group == "sampler" || group == "guidance" || group == "traffic" || group == "follower"));
        CHECK(find_planner_setting(name) == &s);
        CHECK(s.allows(s.get(tuned)));  // both presets are valid
        CHECK(s.allows(s.get(PlannerConfig::paper())));
        // Writing a setting's own text back changes nothing; writing another value changes only it.
        PlannerConfig c = tuned;
        c.set(name, s.value_text(tuned));
        CHECK(s.get(c) == s.get(tuned));
        const double other = s.get(tuned) == s.hi ? s.lo : s.hi;
        c.set(name, number_text(other));
        CHECK(s.get(c) == doctest::Approx(other));
        for (const PlannerSetting& t : planner_settings())
            if (&t != &s) CHECK(t.get(c) == t.get(tuned));
        CHECK_THROWS_WITH_AS(c.set(name, "nan"), doctest::Contains(("planner setting " + name + ": expected").c_str()), std::invalid_argument);
        if (!s.is_bool()) {  // one past the range is refused by set() and validate(), naming the setting
            CHECK_THROWS_WITH_AS(c.set(name, number_text(s.hi * 2 + 1)), doctest::Contains(("planner setting " + name + ": must be").c_str()), std::invalid_argument);
            PlannerConfig bad = tuned;
            std::visit([&](auto f) { f(bad) = (std::remove_reference_t<decltype(f(bad))>)(s.hi * 2 + 1); }, s.field);
            CHECK_THROWS_WITH_AS(bad.validate(), doctest::Contains(name.c_str()), std::invalid_argument);
        }
    }
    CHECK(names.size() == planner_settings().size());
    // An automatic value is "auto", not its number.
    PlannerConfig c;
    for (const char* name : {"neighbourhood.neighbours", "neighbourhood.sensing_radius", "sampler.sample_steps", "sampler.goal_reach"}) {
        const PlannerSetting* s = find_planner_setting(name);
        REQUIRE(s);
        REQUIRE(s->automatic);
        CHECK_THROWS_WITH_AS(c.set(name, number_text(s->automatic_value)), doctest::Contains("or auto"), std::invalid_argument);
        c.set(name, "auto");
        CHECK(s->get(c) == s->automatic_value);
    }
    CHECK_THROWS_WITH_AS(PlannerConfig().set("sampler.nope", "1"), doctest::Contains("no such setting"), std::invalid_argument);
    CHECK_THROWS_WITH_AS(PlannerConfig::preset("fast"), doctest::Contains("expected tuned or paper"), std::invalid_argument);
}

TEST_CASE("settings: the presets: tuned is the default; paper is plain DDIM with inpainting and the SPEC 8 follower") {
    const PlannerConfig t = PlannerConfig::tuned(), p = PlannerConfig::paper(), d;
    CHECK(t.traffic.crowd_weight == 0.04);  // routes around crowds: the tuned planner's, from 1 robot a square unit
    CHECK(t.traffic.crowd_density == 1);
    CHECK(t.traffic.crowd_time_from == 512);  // and routes counted in time from 512 robots
    CHECK(t.traffic.crowd_time == 25);
    CHECK(t.traffic.crowd_time_weight == 0.1);
    CHECK(p.traffic.crowd_weight == 0);     // not the paper's
    for (const PlannerSetting& s : planner_settings()) CHECK(s.get(t) == s.get(d));
    // The tuned values, written once as member initializers (docs/experiments.md says what each bought).
    CHECK(t.guidance.weight == 0.004f);
    CHECK(t.guidance.keep_right == 500.f);
    CHECK(t.guidance.priority == 4.f);
    CHECK(t.sampler.end_bend == 1.f);
    CHECK(t.sampler.sample_steps == 8);
    CHECK(t.sampler.warm_start == 4);
    CHECK(t.sampler.line_start);
    CHECK(t.sampler.small_plan_candidates == 2);
    CHECK(t.traffic.take_turns);
    CHECK(t.traffic.passage_replan == 4);
    CHECK(t.follower.lookahead == 2.0);
    CHECK(t.follower.priority_weight == 4);
    CHECK(t.follower.filter.rate == 4);
    CHECK(t.follower.filter.static_margin == 0.005);
    CHECK(t.neighbourhood.cover == 3);
    CHECK(t.follower.replan_every == 4);  // a quarter of the shipped window
    // The paper's planner.
    CHECK(p.neighbourhood.cover == 0);  // a scene per robot where neighbourhoods are used
    CHECK(p.guidance.weight == 0);
    CHECK(p.guidance.keep_right == 0);
    CHECK(p.guidance.priority == 1);
    CHECK(p.sampler.end_bend == 0);
    CHECK(p.sampler.warm_start == 0);
    CHECK(!p.sampler.line_start);
    CHECK(p.sampler.candidates == 1);
    CHECK(p.sampler.small_plan_candidates == 1);
    CHECK(p.sampler.goal_inpaint);
    CHECK(!p.traffic.take_turns);
    CHECK(p.follower.lookahead == 0);
    CHECK(p.follower.priority_weight == 1);
    CHECK(p.follower.replan_error == 0);
    CHECK(p.follower.replan_every == 8);  // SPEC 8: m = H/2 of the shipped window
    CHECK(p.follower.filter.rate == SafetyFilterParams{}.rate);
    CHECK(p.follower.filter.static_margin == SafetyFilterParams{}.static_margin);
    // Resolved for a model: automatic values become the model's.
    ModelConfig c = tiny_config();  // its own S is 5
    SamplerConfig ts = t.sampler_config(c), ps = p.sampler_config(c);
    CHECK(ts.sample_steps == 5);  // at most the model's own
    CHECK(ps.sample_steps == 5);
    CHECK(ts.goal_reach == default_goal_reach(c));
    CHECK(!ps.conflict_aware());  // the plain DDIM path
    CHECK(ts.conflict_aware());
    c.sample_steps = 10;
    CHECK(t.sampler_config(c).sample_steps == 8);
    CHECK(p.sampler_config(c).sample_steps == 10);
}

TEST_CASE("settings: a planner with the paper preset plans with plain DDIM: no candidates, no turns, no early replans") {
    const ModelConfig c = tiny_config();
    DiffusionPlanner paper(MadbpModel(c, 1), 3, PlannerConfig::paper()), tuned(MadbpModel(c, 1), 3);
    const World w = make_random_world("barrier", 2, 5);
    paper.plan(w);
    tuned.plan(w);
    CHECK(paper.last_plan_candidates() == 1);
    CHECK(tuned.last_plan_candidates() == 2);
    CHECK(paper.replan_after() == 0);
    // A bad setting is refused when planning, naming it.
    paper.settings.sampler.candidates = 0;
    CHECK_THROWS_WITH_AS(paper.plan(w), doctest::Contains("sampler.candidates"), std::invalid_argument);
    // make_follower executes with settings.follower.
    tuned.settings.follower.replan_every = 3;
    World run = w;
    PlanFollower follower = make_follower(tuned);
    for (int k = 0; k < 7; ++k) run.step(follower.act(run));
    CHECK(run.t() == 7);
}
