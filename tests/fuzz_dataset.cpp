// libFuzzer target for the dataset reader (`make fuzz`): parse_demos must either return a
// valid dataset or throw std::runtime_error, never crash, hang, read out of bounds (ASan +
// UBSan are on) or allocate beyond what the input's size allows. A dataset that parses must
// pass validate_demos and survive a demos_bytes / parse_demos round trip byte for byte.
#include "madbp_train.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    madbp::DemoSet set;
    try {
        set = madbp::parse_demos(data, size, "fuzz");
    } catch (const std::runtime_error&) {
        return 0;  // rejected with a message: the expected outcome for most inputs
    }
    madbp::validate_demos(set);  // must not throw: parse_demos validated it
    const std::vector<uint8_t> bytes = madbp::demos_bytes(set);
    if (bytes.size() != size || std::memcmp(bytes.data(), data, size) != 0) __builtin_trap();
    const madbp::DemoSet again = madbp::parse_demos(bytes.data(), bytes.size(), "fuzz-roundtrip");
    if (madbp::demos_bytes(again) != bytes) __builtin_trap();
    return 0;
}
