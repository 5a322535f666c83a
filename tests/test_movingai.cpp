// Tests of the MovingAI benchmark import (movingai_scene), of seeded scenario rows for a map
// without .scen files (random_movingai_scenario, `madbp convert --random-scen`) and of a scene's
// default step limit (scene_step_limit): issue 46.
#include "cli_common.hpp"      // read_convert_options
#include "limits_helpers.hpp"  // error_of, TempDir

namespace {
// 6 x 5, every terrain character; one-cell aisle 'S' at column 3 of row 2 joins rows 1 and 3.
const std::string kMap =
    "type octile\n"
    "height 5\n"
    "width 6\n"
    "map\n"
    "@@@@@@\n"
    ".G..T@\n"
    "@@@S@@\n"
    "....W@\n"
    "@@@@@@\n";
const std::string kScen =
    "version 1\n"
    "0\tt.map\t6\t5\t0\t1\t0\t3\t6.82842712\n"
    "0\tt.map\t6\t5\t0\t3\t1\t1\t5.82842712\n";

// The message movingai_scene throws for these texts, or "" when it accepts them.
std::string refusal(const std::string& map, const std::string& scen, int agents = 2, double cell = 0.3, int offset = 0) {
    return error_of([&] { movingai_scene(map, "t.map", scen, "t.scen", agents, cell, offset); });
}
std::string replaced(std::string s, const std::string& from, const std::string& to) {
    const size_t at = s.find(from);
    REQUIRE(at != std::string::npos);
    return s.replace(at, from.size(), to);
}
bool starts_with(const std::string& s, const std::string& prefix) { return s.rfind(prefix, 0) == 0; }
}  // namespace

TEST_CASE("movingai: a hand-written map and scenario convert, cell for cell, and round-trip") {
    const Scene scene = movingai_scene(kMap, "dir/t.map", kScen, "t.scen", 2);
    // Tight fit: 6 cells of 0.3 across, the 5 rows centred, the margin above and below blocked.
    CHECK(scene.map.half_size == doctest::Approx(0.9));
    const char* rows[] = {"@@@@@@", ".G..T@", "@@@S@@", "....W@", "@@@@@@"};
    for (int r = 0; r < 5; ++r)
        for (int c = 0; c < 6; ++c) {
            const Vec2 p{-0.9 + (c + 0.5) * 0.3, 0.75 - (r + 0.5) * 0.3};
            const bool blocked = std::string("@OTW").find(rows[r][c]) != std::string::npos;
            CAPTURE(r);
            CAPTURE(c);
            CHECK(inside_obstacle(scene.map, p) == blocked);
            if (!blocked) CHECK(static_clearance(scene.map, p) == doctest::Approx(0.15));  // half a cell to a neighbour or wall
        }
    CHECK(inside_obstacle(scene.map, {0, 0.85}));   // margin above the map
    CHECK(inside_obstacle(scene.map, {0, -0.85}));  // and below
    // Runs merged: row 0, rows 1-3 columns 4-5 (one box), row 2 columns 0-2, row 4; two margins.
    CHECK(scene.map.boxes.size() == 6);
    REQUIRE(scene.starts.size() == 2);
    CHECK(scene.starts[0].x == doctest::Approx(-0.75));
    CHECK(scene.starts[0].y == doctest::Approx(0.3));
    CHECK(scene.goals[0].y == doctest::Approx(-0.3));
    CHECK(scene.starts[1].x == doctest::Approx(-0.75));  // row 1 starts on row 0's goal: allowed
    CHECK(scene.goals[1].x == doctest::Approx(-0.45));
    CHECK(scene.goals[1].y == doctest::Approx(0.3));

    const std::string text = scene_text(scene);
    CHECK(text.find("# MovingAI map dir/t.map (6 x 5 cells of 0.3), scenario t.scen rows 0..1") != std::string::npos);
    CHECK(text.find("# agent 1: scenario row 1 (line 3): start (0, 3) goal (1, 1)") != std::string::npos);
    const Scene again = parse_scene(text, "round-trip");
    CHECK(again.map == scene.map);
    CHECK(again.starts == scene.starts);
    CHECK(again.goals == scene.goals);
    CHECK(again.comments.empty());
    CHECK(scene_text(again) == text.substr(0, 14) + text.substr(text.find("world ")));  // comments are all that is lost

    // From files: the same scene; errors name the path.
    TempDir dir;
    write_file_atomic(dir.file("t.map"), kMap);
    write_file_atomic(dir.file("t.scen"), kScen);
    const Scene loaded = load_movingai_scene(dir.file("t.map"), dir.file("t.scen"), 2);
    CHECK(loaded.map == scene.map);
    CHECK(loaded.starts == scene.starts);
    CHECK(error_of([&] { load_movingai_scene(dir.file("t.map"), dir.file("t.scen"), 3); }) ==
          dir.file("t.scen") + ":3: has 2 scenario rows; offset 0 + 3 agents needs 3");
    CHECK(starts_with(error_of([&] { load_movingai_scene(dir.file("none.map"), dir.file("t.scen"), 2); }), dir.file("none.map") + ": cannot open"));

    // --offset: robot 0 takes row 1; a square map has no margin boxes.
    const Scene one = movingai_scene(kMap, "t.map", kScen, "t.scen", 1, 0.3, 1);
    CHECK(one.goals[0].x == doctest::Approx(-0.45));
    const Scene square = movingai_scene("type octile\nheight 2\nwidth 2\nmap\n..\n.@\n", "s.map",
                                        "version 1\n0\ts.map\t2\t2\t0\t0\t1\t0\t1\n", "s.scen", 1);
    CHECK(square.map.boxes.size() == 1);
    CHECK(square.map.half_size == doctest::Approx(0.3));
}

TEST_CASE("movingai: malformed maps and scenarios are refused with file:line") {
    CHECK(refusal(kMap, kScen) == "");
    // The map.
    CHECK(starts_with(refusal(replaced(kMap, "octile", "tile"), kScen), "t.map:1: map type 'tile'"));
    CHECK(starts_with(refusal(replaced(kMap, "height 5", "height five"), kScen), "t.map:2: height: 'five' is not an integer"));
    CHECK(starts_with(refusal(replaced(kMap, "width 6\n", "width 6\nwidth 6\n"), kScen), "t.map:4: 'width' given twice"));
    CHECK(starts_with(refusal(replaced(kMap, "type octile\n", ""), kScen), "t.map:3: 'map' before the header"));
    CHECK(starts_with(refusal(replaced(kMap, "map\n", "mop\n"), kScen), "t.map:4: unexpected header line 'mop'"));
    CHECK(starts_with(refusal(replaced(kMap, "@@@S@@", "@@S@@"), kScen), "t.map:7: row 2 has 5 characters, the header says width 6"));
    CHECK(starts_with(refusal(replaced(kMap, "@@@S@@", "@@@X@@"), kScen), "t.map:7: unknown terrain 'X' in column 3"));
    CHECK(starts_with(refusal(replaced(kMap, "....W@\n@@@@@@\n", "....W@\n"), kScen), "t.map:8: the map has 4 rows, its header says height 5"));
    CHECK(starts_with(refusal(kMap + "@@@@@@\n", kScen), "t.map:10: more rows than the header's height 5"));
    std::string crlf;
    for (char c : kMap) crlf += c == '\n' ? std::string("\r\n") : std::string(1, c);
    CHECK(refusal(crlf, kScen) == "");  // Windows line ends are fine
    // The scenario.
    CHECK(starts_with(refusal(kMap, replaced(kScen, "version 1", "version 2")), "t.scen:1: expected the header 'version 1'"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t6.82842712", "")), "t.scen:2: expected 9 tab-separated fields"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t1\t1\t5.8", "\tone\t1\t5.8")), "t.scen:3: goal x: 'one' is not an integer"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t5.82842712", "\tfar")), "t.scen:3: optimal length: 'far' is not a number"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t6\t5\t0\t1", "\t6\t6\t0\t1")), "t.scen:2: map size 6 x 6 differs from the map's 6 x 5"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "0\tt.map\t6\t5\t0\t3", "0\tmaps/u.map\t6\t5\t0\t3")), "t.scen:3: the row is for map 'maps/u.map', not t.map"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t0\t1\t0\t3", "\t6\t1\t0\t3")), "t.scen:2: start (6, 1) is outside the 6 x 5 map"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t0\t1\t0\t3", "\t0\t1\t4\t3")), "t.scen:2: goal (4, 3) is on a blocked cell 'W'"));
    CHECK(starts_with(refusal(kMap, kScen, 2, 0.3, 1), "t.scen:3: has 2 scenario rows; offset 1 + 2 agents needs 3"));
    CHECK(starts_with(refusal(kMap, replaced(kScen, "\t0\t3\t1\t1", "\t0\t1\t1\t1")), "t.scen:3: start (0, 1) overlaps the start of scenario row 0 (line 2)"));
    CHECK(starts_with(refusal(kMap, kScen, 2, 0.15), "t.scen:2: start (0, 1) is closer than a robot's radius"));
    // Sizes: a world over kMaxHalfSize, more boxes than kMaxObstacles.
    const std::string wide = "type octile\nheight 1\nwidth 1000\nmap\n" + std::string(1000, '.') + "\n";
    CHECK(starts_with(refusal(wide, "version 1\n0\tt.map\t1000\t1\t0\t0\t1\t0\t1\n", 1), "t.map: 1000 cells of 0.3 make a world of half-size 150"));
    std::string checker = "type octile\nheight 100\nwidth 100\nmap\n";
    for (int r = 0; r < 100; ++r) {
        for (int c = 0; c < 100; ++c) checker += (r + c) % 2 ? '@' : '.';
        checker += '\n';
    }
    CHECK(starts_with(refusal(checker, "version 1\n0\tt.map\t100\t100\t0\t0\t2\t0\t2\n", 1),
                      "t.map: its blocked cells need 5000 boxes (row runs merged), over the limit kMaxObstacles = 4096"));
}

TEST_CASE("step limit: a scene's default follows its longest route and is never below the old default") {
    // A 13 x 13 serpentine: free rows 0, 2, ..., 12 joined by one-cell gaps at alternate ends, so
    // robot 0 (row 0 to row 12, both at column 0) crosses the map 6 times: >= 6 x 12 cells of 0.3
    // in x, 600 steps at cruise 0.036 a step.
    std::string map = "type octile\nheight 13\nwidth 13\nmap\n";
    for (int r = 0; r < 13; ++r) {
        std::string row(13, r % 2 ? '@' : '.');
        if (r % 4 == 1) row[12] = '.';
        if (r % 4 == 3) row[0] = '.';
        map += row + "\n";
    }
    const Scene maze = movingai_scene(map, "maze.map",
                                      "version 1\n0\tmaze.map\t13\t13\t0\t0\t0\t12\t90\n"
                                      "0\tmaze.map\t13\t13\t2\t12\t4\t12\t2\n",
                                      "maze.scen", 2);
    const int old_default = default_max_steps(maze.map.half_size);
    const int limit = scene_step_limit(maze);
    CHECK(old_default == 163);
    CHECK(limit >= 2 * 600);
    CHECK(limit <= 2 * 700 + 100);  // 6 x 12 + 12 cells at most (diagonals only help), some rounding
    CHECK(limit > 5 * old_default);

    // Short routes keep the old default, in the standard world and a large one.
    Scene open;
    open.map.half_size = 1.2;
    open.starts = {{-0.5, 0}, {0.5, 0.5}};
    open.goals = {{0.5, 0}, {0.5, -0.5}};
    CHECK(scene_step_limit(open) == 100);
    open.map.half_size = 10;
    CHECK(scene_step_limit(open) == default_max_steps(10));
    // A wall from the top down to y = -2.7 between start and goal: the route goes round its
    // end, 5.3 down, 0.4 across under it (the wall and a robot radius either side), 5.3 up: 11
    // units along the axes (moves in 8 directions at 0.036 a step), against 1 unit straight.
    Scene wall;
    wall.map.half_size = 3;
    wall.map.boxes.push_back({{-0.1, -2.7}, {0.1, 3}});
    wall.starts = {{-0.5, 2.5}};
    wall.goals = {{0.5, 2.5}};
    const int around = scene_step_limit(wall);
    CHECK(around >= 2 * (11.0 - 0.3) / 0.036);
    CHECK(around <= 2 * (11.0 + 0.3) / 0.036);
}

namespace {
// 9 x 6: a left room (columns 0-3) and a right room (5-8) split by a wall at column 4, except
// two cells that touch only at a corner (rows 4 and 5: no corner cutting, so they do not join
// the rooms), and a lone cell at (8, 5) walled in.
const std::string kRooms =
    "type octile\n"
    "height 6\n"
    "width 9\n"
    "map\n"
    "....@....\n"
    "....@....\n"
    "....@....\n"
    "....@....\n"
    "@@@@.@@@@\n"
    "@@@@@.@@.\n";
// The component of a cell in kRooms: 0 left room, 1 right room, -1 any other cell.
int room_of(long col, long row) { return row < 4 && col < 4 ? 0 : row < 4 && col > 4 ? 1 : -1; }
}  // namespace

TEST_CASE("movingai: octile path lengths take 8 directions and never cut a corner") {
    const MovingAiMap open = parse_movingai_map("type octile\nheight 5\nwidth 5\nmap\n.....\n.....\n.....\n.....\n.....\n", "e.map");
    CHECK(movingai_path_length(open, 0, 0, 4, 2) == doctest::Approx(2 + 2 * std::sqrt(2.0)));
    CHECK(movingai_path_length(open, 3, 3, 3, 3) == 0);
    // Around a blocked centre: the diagonal past its corner is not a move, so 4, not 2 sqrt 2.
    const MovingAiMap ring = parse_movingai_map("type octile\nheight 3\nwidth 3\nmap\n...\n.@.\n...\n", "r.map");
    CHECK(movingai_path_length(ring, 0, 0, 2, 2) == doctest::Approx(4));
    CHECK(movingai_path_length(ring, 0, 0, 1, 1) == -1);  // blocked goal
    const MovingAiMap rooms = parse_movingai_map(kRooms, "rooms.map");
    CHECK(movingai_path_length(rooms, 0, 0, 5, 0) == -1);  // across the wall
    CHECK(movingai_path_length(rooms, 4, 4, 5, 5) == -1);  // corner to corner
    CHECK(movingai_path_length(rooms, 0, 0, 3, 3) == doctest::Approx(3 * std::sqrt(2.0)));
}

TEST_CASE("movingai: seeded random scenario rows, in one component, distinct, parsed back from their .scen text") {
    const MovingAiMap map = parse_movingai_map(kRooms, "dir/rooms.map");
    const std::vector<MovingAiScenarioRow> rows = random_movingai_scenario(map, 20, 7);
    REQUIRE(rows.size() == 20);
    std::set<std::pair<long, long>> starts, goals;
    for (const MovingAiScenarioRow& r : rows) {
        CAPTURE(r.start_x);
        CAPTURE(r.start_y);
        CAPTURE(r.goal_x);
        CAPTURE(r.goal_y);
        CHECK(r.map_name == "rooms.map");
        CHECK(r.map_width == 9);
        CHECK(r.map_height == 6);
        CHECK(r.line == 0);
        CHECK(room_of(r.start_x, r.start_y) >= 0);  // never the corner cells or the lone cell
        CHECK(room_of(r.start_x, r.start_y) == room_of(r.goal_x, r.goal_y));
        CHECK((r.start_x != r.goal_x || r.start_y != r.goal_y));
        CHECK(r.optimal_length == doctest::Approx(movingai_path_length(map, r.start_x, r.start_y, r.goal_x, r.goal_y)));
        CHECK(r.optimal_length > 0);
        CHECK(r.bucket == (long)std::floor(r.optimal_length / 4));
        starts.insert({r.start_x, r.start_y});
        goals.insert({r.goal_x, r.goal_y});
    }
    CHECK(starts.size() == 20);
    CHECK(goals.size() == 20);
    // The same seed, the same rows; another seed, other rows.
    const std::vector<MovingAiScenarioRow> again = random_movingai_scenario(map, 20, 7), other = random_movingai_scenario(map, 20, 8);
    const std::string text = movingai_scenario_text(rows);
    CHECK(movingai_scenario_text(again) == text);
    CHECK(movingai_scenario_text(other) != text);
    // Every usable cell: 32 room cells, each a start once and a goal once (or fewer, never more).
    CHECK(contains(error_of([&] { random_movingai_scenario(map, 33, 0); }), "dir/rooms.map: drew only "));

    // The .scen text: version 1, 9 tab-separated fields, read back by the scenario parser.
    CHECK(starts_with(text, "version 1\n"));
    const std::vector<MovingAiScenarioRow> read = parse_movingai_scenario(text, "rooms.scen", map);
    REQUIRE(read.size() == rows.size());
    for (size_t i = 0; i < rows.size(); ++i) {
        CHECK(read[i].line == i + 2);
        CHECK(read[i].bucket == rows[i].bucket);
        CHECK(read[i].map_name == rows[i].map_name);
        CHECK((read[i].start_x == rows[i].start_x && read[i].start_y == rows[i].start_y));
        CHECK((read[i].goal_x == rows[i].goal_x && read[i].goal_y == rows[i].goal_y));
        CHECK(read[i].optimal_length == doctest::Approx(rows[i].optimal_length).epsilon(1e-8));
    }
    // Drawn rows and their written file make one scene; drawn rows are named by index, not line.
    TempDir dir;
    write_file_atomic(dir.file("rooms.map"), kRooms);
    write_file_atomic(dir.file("rooms.scen"), text);
    const Scene drawn = movingai_scene(map, rows, "random, seed 7", 20);
    const Scene loaded = load_movingai_scene(dir.file("rooms.map"), dir.file("rooms.scen"), 20);
    CHECK(drawn.map == loaded.map);
    CHECK(drawn.starts == loaded.starts);
    CHECK(drawn.goals == loaded.goals);
    CHECK(contains(scene_text(drawn), "# agent 0: scenario row 0: start ("));
    CHECK(load_movingai_map(dir.file("rooms.map")).blocked == map.blocked);
    std::vector<MovingAiScenarioRow> bad = rows;
    bad[3].goal_x = 4, bad[3].goal_y = 0;
    CHECK(starts_with(error_of([&] { movingai_scene(map, bad, "random, seed 7", 20); }), "random, seed 7 row 3: goal (4, 0) is on a blocked cell '@'"));
    CHECK(error_of([&] { movingai_scene(map, rows, "random, seed 7", 21); }) == "random, seed 7: has 20 scenario rows; offset 0 + 21 agents needs 21");
}

TEST_CASE("movingai: a map with no two connected passable cells, or a bad count, is refused naming it") {
    const std::string corners = "type octile\nheight 2\nwidth 2\nmap\n.@\n@.\n";
    CHECK(error_of([&] { random_movingai_scenario(parse_movingai_map(corners, "maps/corners.map"), 1, 0); }) ==
          "maps/corners.map: no two passable cells are connected (octile moves, no corner cutting); "
          "a random scenario needs a start and a goal in one component");
    const std::string walls = "type octile\nheight 1\nwidth 3\nmap\n@@@\n";
    CHECK(starts_with(error_of([&] { random_movingai_scenario(parse_movingai_map(walls, "w.map"), 1, 0); }), "w.map: no two passable cells"));
    const MovingAiMap two = parse_movingai_map("type octile\nheight 1\nwidth 2\nmap\n..\n", "two.map");
    CHECK(random_movingai_scenario(two, 2, 0).size() == 2);  // a swap: 0 -> 1 and 1 -> 0
    CHECK(starts_with(error_of([&] { random_movingai_scenario(two, 3, 0); }), "two.map: drew only 2 of count = 3 scenario rows"));
    CHECK(starts_with(error_of([&] { random_movingai_scenario(two, 0, 0); }), "count: 0 is out of range [1, kMaxSceneAgents = 1024]"));
    std::vector<MovingAiScenarioRow> tabbed = random_movingai_scenario(two, 1, 0);
    tabbed[0].map_name = "a\tb.map";
    CHECK(starts_with(error_of([&] { movingai_scenario_text(tabbed); }), "map name: 'a\\x09b.map' holds a tab or line break"));
}

TEST_CASE("convert: --random-scen and --scen are alternatives; --offset and --write-scen belong to one each") {
    auto options_error = [](std::vector<std::string> args) {
        return error_of([&] {
            madbp_cli::Args a(args);
            madbp_cli::read_convert_options(a);
        });
    };
    const std::vector<std::string> base = {"--movingai", "m.map", "--agents", "4", "--out", "m.scene"};
    auto with = [&](std::vector<std::string> more) {
        more.insert(more.begin(), base.begin(), base.end());
        return more;
    };
    CHECK(options_error(with({"--scen", "m.scen", "--offset", "8"})) == "");
    CHECK(options_error(with({"--random-scen", "--seed", "5", "--write-scen", "m.scen"})) == "");
    CHECK(options_error(with({"--random-scen"})) == "");  // seed 0
    CHECK(options_error(with({"--random-scen", "--scen", "m.scen"})) == "--random-scen: give --scen FILE or --random-scen, not both");
    CHECK(starts_with(options_error(with({"--random-scen", "--offset", "0"})), "--offset: has no meaning with --random-scen"));
    CHECK(starts_with(options_error(with({"--scen", "m.scen", "--seed", "3"})), "--seed: picks the rows of --random-scen"));
    CHECK(starts_with(options_error(with({"--scen", "m.scen", "--write-scen", "x.scen"})), "--write-scen: saves the rows of --random-scen"));
    CHECK(starts_with(options_error(with({"--random-scen", "--write-scen", "m.scene"})), "--write-scen: is the same file as --out"));
    CHECK(starts_with(options_error(base), "needs --movingai MAP.map, --scen FILE.scen or --random-scen"));
    CHECK(options_error(with({"--random-scen", "--seed", "-1"})) == "--seed: -1 is out of range [0, 1099511627776]");
    madbp_cli::Args a(with({"--random-scen", "--seed", "12"}));
    const madbp_cli::ConvertOptions o = madbp_cli::read_convert_options(a);
    CHECK(o.random_scen);
    CHECK(o.seed == 12);
    CHECK(o.agents == 4);
}
