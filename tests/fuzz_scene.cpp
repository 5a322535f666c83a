// libFuzzer target for the scene parser (`make fuzz`): parse_scene must either return a scene
// or throw std::invalid_argument, never crash, hang or read out of bounds (ASan + UBSan are
// on). A scene that parses must make a world (make_world does not throw) and survive a
// scene_text / parse_scene round trip unchanged, so the writer and reader agree.
#include "madbp_sim.hpp"

#include <string>

static bool same(const madbp::Scene& a, const madbp::Scene& b) {
    if (!(a.map.half_size == b.map.half_size) || a.map.discs.size() != b.map.discs.size() ||
        a.map.boxes.size() != b.map.boxes.size() || a.starts != b.starts || a.goals != b.goals)
        return false;
    for (size_t i = 0; i < a.map.discs.size(); ++i)
        if (!(a.map.discs[i].c == b.map.discs[i].c) || a.map.discs[i].r != b.map.discs[i].r) return false;
    for (size_t i = 0; i < a.map.boxes.size(); ++i)
        if (!(a.map.boxes[i].lo == b.map.boxes[i].lo) || !(a.map.boxes[i].hi == b.map.boxes[i].hi)) return false;
    return true;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string text((const char*)data, size);
    madbp::Scene scene;
    try {
        scene = madbp::parse_scene(text, "fuzz");
    } catch (const std::invalid_argument&) {
        return 0;  // rejected with a message: the expected outcome for most inputs
    }
    const madbp::World world = madbp::make_world(scene);  // must not throw: the parser checked everything
    const madbp::Scene again = madbp::parse_scene(madbp::scene_text(world), "fuzz-roundtrip");
    if (!same(scene, again)) __builtin_trap();
    return 0;
}
