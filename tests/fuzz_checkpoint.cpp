// libFuzzer target for the checkpoint reader (`make fuzz`): parse_safetensors must either
// return a valid checkpoint or throw std::runtime_error, never crash, hang or read out of
// bounds (ASan + UBSan are on). A file that parses must survive a serialise/parse round trip
// unchanged, so the writer and reader agree on everything the reader accepts.
#include "madbp.hpp"

#include <cstring>

static bool same(const madbp::SafeTensors& a, const madbp::SafeTensors& b) {
    if (a.metadata != b.metadata || a.tensors.size() != b.tensors.size()) return false;
    for (size_t i = 0; i < a.tensors.size(); ++i) {
        const madbp::NamedTensor &x = a.tensors[i], &y = b.tensors[i];
        if (x.name != y.name || x.shape != y.shape || x.data.size() != y.data.size()) return false;
        if (!x.data.empty() && std::memcmp(x.data.data(), y.data.data(), 4 * x.data.size()) != 0) return false;
    }
    return true;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    madbp::SafeTensors st;
    try {
        st = madbp::parse_safetensors(data, size, "fuzz");
    } catch (const std::runtime_error&) {
        return 0;  // rejected with a message: the expected outcome for most inputs
    }
    const std::vector<uint8_t> bytes = madbp::serialize_safetensors(st.tensors, st.metadata);
    const madbp::SafeTensors again = madbp::parse_safetensors(bytes.data(), bytes.size(), "fuzz-roundtrip");
    if (!same(st, again)) __builtin_trap();
    return 0;
}
