// libFuzzer target for the MovingAI import (`make fuzz`): the input is a .map text, a NUL byte,
// then a .scen text; its first byte picks the robots (1-4) and the cell (0.2, 0.25, 0.3).
// movingai_scene must either return a scene or throw std::invalid_argument, never crash, hang
// or read out of bounds (ASan + UBSan are on); a scene it returns must pass parse_scene (the
// scene file rules) and come back unchanged through scene_text.
#include "madbp_sim.hpp"

#include <string>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size < 1) return 0;
    const std::string text((const char*)data + 1, size - 1);
    const size_t nul = text.find('\0');
    if (nul == std::string::npos) return 0;
    const int agents = 1 + data[0] % 4;
    const double cell = 0.2 + 0.05 * (data[0] / 4 % 3);
    madbp::Scene scene;
    try {
        scene = madbp::movingai_scene(text.substr(0, nul), "f.map", text.substr(nul + 1), "f.scen", agents, cell);
    } catch (const std::invalid_argument&) {
        return 0;  // rejected with a message: the expected outcome for most inputs
    }
    const madbp::Scene again = madbp::parse_scene(madbp::scene_text(scene), "fuzz-roundtrip");  // must not throw
    if (!(again.map == scene.map) || again.starts != scene.starts || again.goals != scene.goals) __builtin_trap();
    return 0;
}
