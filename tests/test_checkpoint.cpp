// Tests of safetensors checkpoints (madbp.hpp, SPEC section 11): bit-exact round trips, the
// byte layout Python's safetensors expects, atomic writes, and a clear std::runtime_error for
// every kind of bad file (truncated, inconsistent offsets or shapes, NaN payloads, random bytes).
#include "madbp_train.hpp"  // optimizer-state checkpoints live with training
#include "limits_helpers.hpp"  // TempDir, contains

#include <doctest/doctest.h>

#include <cstdlib>
#include <dirent.h>

using madbp::Mat;
using madbp::NamedTensor;
using madbp::ParamStore;
using madbp::Rng;

namespace {

// A small model's parameters: two layers and BatchNorm statistics.
struct TinyModel {
    std::unique_ptr<ParamStore> ps = std::make_unique<ParamStore>();
    madbp::Linear fc;
    madbp::BatchNorm1d bn;
    explicit TinyModel(uint64_t seed) {
        Rng rng(seed);
        fc = madbp::Linear(*ps, "fc", 3, 2, rng);
        bn = madbp::BatchNorm1d(*ps, "bn", 2, rng);
    }
};

// safetensors bytes from a header text and a payload.
std::vector<uint8_t> craft(const std::string& header, const std::vector<float>& payload = {}) {
    std::vector<uint8_t> out(8 + header.size() + 4 * payload.size());
    for (int i = 0; i < 8; ++i) out[i] = (uint8_t)((uint64_t)header.size() >> (8 * i));
    std::memcpy(out.data() + 8, header.data(), header.size());
    if (!payload.empty()) std::memcpy(out.data() + 8 + header.size(), payload.data(), 4 * payload.size());
    return out;
}

// The runtime_error message parsing `bytes` raises ("" when it parses).
std::string error_of(const std::vector<uint8_t>& bytes) {
    try {
        madbp::parse_safetensors(bytes.data(), bytes.size(), "bad.safetensors");
    } catch (const std::runtime_error& e) {
        return e.what();
    }
    return "";
}


}  // namespace

TEST_CASE("checkpoint: parameters round-trip bit-exactly, metadata too") {
    TempDir dir;
    TinyModel a(1), b(2);
    // Awkward values: negative zero, a denormal, the largest float, tiny and huge magnitudes.
    a.ps->value[0] = -0.0f;
    a.ps->value[1] = std::numeric_limits<float>::denorm_min();
    a.ps->value[2] = std::numeric_limits<float>::max();
    a.ps->value[3] = -1e-38f;
    const std::map<std::string, std::string> meta = {{"config", "{\"D\": 64}"}, {"step", "1200"}, {"note", "\xc3\xa9t\xc3\xa9 \"q\"\n"}};
    const std::string path = dir.file("model.safetensors");
    madbp::save_params(path, *a.ps, meta);
    madbp::load_params(path, *b.ps);
    REQUIRE(b.ps->size() == a.ps->size());
    CHECK(std::memcmp(a.ps->value.data(), b.ps->value.data(), 4 * a.ps->size()) == 0);
    const madbp::SafeTensors st = madbp::load_safetensors(path);
    CHECK(st.metadata == meta);
    CHECK(st.tensors.size() == a.ps->entries.size());
    CHECK(st.at("fc.weight").shape == std::vector<int>{3, 2});
    CHECK(st.at("bn.running_var").data == std::vector<float>{1, 1});
}

TEST_CASE("checkpoint: the file is valid safetensors (u64 LE length, JSON header, raw F32)") {
    TempDir dir;
    Rng rng(0);
    ParamStore ps;
    madbp::Linear fc(ps, "fc", 3, 2, rng);
    for (int i = 0; i < ps.size(); ++i) ps.value[i] = 0.5f * i;
    const std::string path = dir.file("m.safetensors");
    madbp::save_params(path, ps, {{"step", "7"}});
    const std::vector<uint8_t> bytes = madbp::read_file(path);
    uint64_t n = 0;
    for (int i = 7; i >= 0; --i) n = (n << 8) | bytes[i];
    REQUIRE(8 + n <= bytes.size());
    CHECK((8 + n) % 8 == 0);  // payload aligned, header padded with spaces
    const std::string header(bytes.begin() + 8, bytes.begin() + 8 + n);
    CHECK(header[0] == '{');
    CHECK(contains(header, "\"__metadata__\":{\"step\":\"7\"}"));
    CHECK(contains(header, "\"fc.weight\":{\"dtype\":\"F32\",\"shape\":[3,2],\"data_offsets\":[0,24]}"));
    CHECK(contains(header, "\"fc.bias\":{\"dtype\":\"F32\",\"shape\":[2],\"data_offsets\":[24,32]}"));
    CHECK(header.find_last_not_of(' ') == header.rfind('}'));
    REQUIRE(bytes.size() == 8 + n + 32);
    for (int i = 0; i < 8; ++i) {  // raw little-endian float32 in the store's order
        float f;
        std::memcpy(&f, bytes.data() + 8 + n + 4 * i, 4);
        CHECK(f == 0.5f * i);
    }
    // Row-major {in, out} of the weight: numpy's x @ W + b equals the layer's output.
    Mat x(3, 1), y;
    x << 1, -2, 3;
    fc.forward(x, y);
    for (int o = 0; o < 2; ++o) {
        float acc = ps.value[6 + o];
        for (int i = 0; i < 3; ++i) acc += x(i) * ps.value[i * 2 + o];  // W_file[i][o]
        CHECK(y(o) == doctest::Approx(acc));
    }
}

TEST_CASE("checkpoint: scalars, empty tensors and files without tensors round-trip") {
    const std::vector<NamedTensor> tensors = {{"scalar", {}, {3.5f}}, {"empty", {0, 4}, {}}, {"v", {2}, {1, 2}}};
    const auto bytes = madbp::serialize_safetensors(tensors, {});
    const madbp::SafeTensors st = madbp::parse_safetensors(bytes.data(), bytes.size());
    REQUIRE(st.tensors.size() == 3);
    CHECK(st.at("scalar").data == std::vector<float>{3.5f});
    CHECK(st.at("scalar").shape.empty());
    CHECK(st.at("empty").shape == std::vector<int>{0, 4});
    CHECK(st.at("v").data == std::vector<float>{1, 2});
    const auto none = madbp::serialize_safetensors({}, {});
    CHECK(madbp::parse_safetensors(none.data(), none.size()).tensors.empty());
}

TEST_CASE("checkpoint: the atomic write leaves no temporary file and replaces the old file whole") {
    TempDir dir;
    TinyModel a(1), b(2);
    const std::string path = dir.file("model.safetensors");
    madbp::save_params(path, *a.ps, {});
    madbp::save_params(path, *b.ps, {});  // overwrite
    CHECK(dir.files() == std::vector<std::string>{"model.safetensors"});
    TinyModel c(3);
    madbp::load_params(path, *c.ps);
    CHECK(std::memcmp(c.ps->value.data(), b.ps->value.data(), 4 * b.ps->size()) == 0);
    // A value the reader would refuse is refused before the file is touched.
    b.ps->value[0] = NAN;
    CHECK_THROWS_AS(madbp::save_params(path, *b.ps, {}), std::invalid_argument);
    madbp::load_params(path, *c.ps);
    CHECK(dir.files() == std::vector<std::string>{"model.safetensors"});
    // An unwritable place fails with the path in the message and leaves nothing.
    try {
        madbp::save_params(dir.file("missing/model.safetensors"), *a.ps, {});
        FAIL("no error");
    } catch (const std::runtime_error& e) {
        CHECK(contains(e.what(), "missing/model.safetensors: cannot create"));
    }
    CHECK(dir.files().size() == 1);
}

TEST_CASE("checkpoint: load_params names the tensor and both shapes on a mismatch") {
    TempDir dir;
    Rng rng(0);
    ParamStore small, wide, extra;
    madbp::Linear a(small, "fc", 3, 2, rng), b(wide, "fc", 3, 4, rng), c(extra, "fc", 3, 2, rng), d(extra, "head", 2, 1, rng);
    const std::string path = dir.file("small.safetensors");
    madbp::save_params(path, small, {});
    try {
        madbp::load_params(path, wide);
        FAIL("no error");
    } catch (const std::runtime_error& e) {
        INFO(e.what());
        CHECK(contains(e.what(), path));
        CHECK(contains(e.what(), "'fc.weight'"));
        CHECK(contains(e.what(), "[3, 2]"));
        CHECK(contains(e.what(), "[3, 4]"));
    }
    try {  // the model has a tensor the file lacks
        madbp::load_params(path, extra);
        FAIL("no error");
    } catch (const std::runtime_error& e) {
        CHECK(contains(e.what(), "'head.weight' is missing"));
    }
    const std::string path2 = dir.file("extra.safetensors");
    madbp::save_params(path2, extra, {});
    try {  // the file has a tensor the model lacks
        madbp::load_params(path2, small);
        FAIL("no error");
    } catch (const std::runtime_error& e) {
        CHECK(contains(e.what(), "'head.weight' is not a parameter"));
    }
    CHECK_THROWS_WITH_AS(madbp::load_params(dir.file("nope.safetensors"), small), doctest::Contains("nope.safetensors: cannot open"),
                         std::runtime_error);
}

TEST_CASE("checkpoint: every truncation of a valid file raises a clear error") {
    TinyModel a(1);
    const auto bytes = madbp::serialize_safetensors(madbp::param_tensors(*a.ps), {{"step", "3"}});
    for (size_t n = 0; n < bytes.size(); ++n) {
        const std::vector<uint8_t> cut(bytes.begin(), bytes.begin() + n);
        const std::string err = error_of(cut);
        INFO("truncated to " << n << " bytes");
        CHECK(contains(err, "bad.safetensors: "));
    }
    CHECK(contains(error_of({1, 2, 3}), "shorter than the 8-byte header size"));
    CHECK(contains(error_of(std::vector<uint8_t>(bytes.begin(), bytes.end() - 4)), "payload"));
}

TEST_CASE("checkpoint: inconsistent headers each raise an error naming the field") {
    const std::vector<float> six = {1, 2, 3, 4, 5, 6};
    auto tensor = [](const std::string& name, const std::string& shape, const std::string& offsets) {
        return "\"" + name + "\":{\"dtype\":\"F32\",\"shape\":" + shape + ",\"data_offsets\":" + offsets + "}";
    };
    struct Case { std::string header, expect; };
    const std::vector<Case> cases = {
        {"{" + tensor("a", "[2,3]", "[0,24]") + "}", ""},  // the valid baseline
        {"{" + tensor("a", "[2,3]", "[0,20]") + "}", "'a': shape [2, 3] of F32 needs 24 bytes but data_offsets [0, 20] hold 20"},
        {"{" + tensor("a", "[3,3]", "[0,24]") + "}", "shape [3, 3]"},
        {"{" + tensor("a", "[2,3]", "[4,28]") + "}", "run past the payload"},
        {"{" + tensor("a", "[2,3]", "[24,0]") + "}", "end before they begin"},
        {"{" + tensor("a", "[2]", "[0,8]") + "," + tensor("b", "[2]", "[12,20]") + "}", "(gap)"},
        {"{" + tensor("a", "[3]", "[0,12]") + "," + tensor("b", "[3]", "[8,20]") + "}", "(overlap)"},
        {"{" + tensor("a", "[2]", "[0,8]") + "}", "cover 8 bytes of a 24-byte payload"},
        {"{" + tensor("a", "[2,3]", "[0,24]") + "," + tensor("a", "[0]", "[24,24]") + "}", "duplicate key 'a'"},
        {"{\"a\":{\"dtype\":\"F16\",\"shape\":[2,6],\"data_offsets\":[0,24]}}", "dtype 'F16' is not supported"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[2,3]}}", "needs dtype, shape and data_offsets"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[6],\"data_offsets\":[0,24],\"x\":1}}", "unknown field 'x'"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[-6],\"data_offsets\":[0,24]}}", "shape[0] = -6 is not a non-negative integer"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[6.0],\"data_offsets\":[0,24]}}", "shape[0] = 6.0"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[6],\"data_offsets\":[0,\"24\"]}}", "data_offsets[1] is not a number"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[6],\"data_offsets\":[0]}}", "data_offsets is not [begin, end]"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[4294967296,4294967296],\"data_offsets\":[0,24]}}", "shape[0] is too large"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[2147483647,2147483647,2147483647],\"data_offsets\":[0,24]}}", "too many"},
        {"{\"__metadata__\":{\"k\":1}," + tensor("a", "[6]", "[0,24]") + "}", "__metadata__['k'] is not a string"},
        {"{\"__metadata__\":[]," + tensor("a", "[6]", "[0,24]") + "}", "__metadata__ is not an object"},
        {"{\"\":{\"dtype\":\"F32\",\"shape\":[6],\"data_offsets\":[0,24]}}", "empty tensor name"},
        {" {" + tensor("a", "[6]", "[0,24]") + "}", "does not start with '{'"},
        {"[]", "does not start with '{'"},
        {"{" + tensor("a", "[6]", "[0,24]") + "} x", "unexpected text after the header object"},
        {"{" + tensor("a", "[6]", "[0,24]") + ",}", "expected a string key"},
        {"{\"a\":[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]}", "nesting deeper than 16"},
        {"{\"a\\x\":1}", "unknown escape"},
        {"{\"a\\ud800\":1}", "high surrogate without its pair"},
        {"{\"a\":tru}", "unexpected character"},
        {"{\"a\":{\"dtype\":\"F32\",\"shape\":[6],\"data_offsets\":[0,24]}", "expected '}'"},
        {"{\"a\xff\":1}", "not valid UTF-8"},
    };
    for (const Case& c : cases) {
        const std::string err = error_of(craft(c.header, six));
        INFO("header: " << c.header);
        INFO("error: " << err);
        if (c.expect.empty()) {
            CHECK(err.empty());
        } else {
            CHECK(contains(err, "bad.safetensors: "));
            CHECK(contains(err, c.expect));
        }
    }
    // The header size itself: past the end of the file, and past the 100 MB limit.
    std::vector<uint8_t> lying = craft("{}");
    lying[0] = 200;
    CHECK(contains(error_of(lying), "header size 200 runs past the end of the file (10 bytes)"));
    lying[7] = 1;
    CHECK(contains(error_of(lying), "exceeds the 100 MB limit"));
}

TEST_CASE("checkpoint: NaN and infinite payload values are refused, naming tensor and element") {
    const std::string header = "{\"w\":{\"dtype\":\"F32\",\"shape\":[3],\"data_offsets\":[0,12]}}";
    CHECK(contains(error_of(craft(header, {1, NAN, 2})), "tensor 'w': element 1 is NaN"));
    CHECK(contains(error_of(craft(header, {1, 2, -INFINITY})), "tensor 'w': element 2 is infinite"));
    CHECK(error_of(craft(header, {1, 2, 3})).empty());
}

TEST_CASE("checkpoint: random bytes and random corruptions raise runtime_error, never crash") {
    Rng rng(99);
    for (int trial = 0; trial < 2000; ++trial) {
        std::vector<uint8_t> bytes(rng.uniform_int(64));
        for (auto& b : bytes) b = (uint8_t)rng.uniform_int(256);
        CHECK_FALSE(error_of(bytes).empty());
    }
    TinyModel a(5);
    const auto good = madbp::serialize_safetensors(madbp::param_tensors(*a.ps), {{"k", "v"}});
    int parsed = 0;
    for (int trial = 0; trial < 2000; ++trial) {  // flip 1-3 bytes anywhere
        std::vector<uint8_t> bytes = good;
        for (int k = 0, n = 1 + rng.uniform_int(3); k < n; ++k) bytes[rng.uniform_int((int)bytes.size())] ^= (uint8_t)(1 + rng.uniform_int(255));
        try {
            madbp::parse_safetensors(bytes.data(), bytes.size(), "x");
            ++parsed;  // e.g. a payload change that stays finite
        } catch (const std::runtime_error&) {
        }
    }
    CHECK(parsed < 2000);
}

TEST_CASE("checkpoint: training state (params, Adam, EMA, RNG) resumes bit-exactly") {
    // Trains a small regression model; a run interrupted at step 10 and resumed from its
    // checkpoint must match the uninterrupted run bit for bit.
    struct Run {
        std::unique_ptr<ParamStore> ps = std::make_unique<ParamStore>();
        madbp::Linear fc1, fc2;
        madbp::Tanh act;
        madbp::Adam adam;
        madbp::Ema ema;
        Rng data_rng{17};
        Run() {
            Rng init(3);
            fc1 = madbp::Linear(*ps, "fc1", 2, 8, init);
            fc2 = madbp::Linear(*ps, "fc2", 8, 1, init);
            adam.lr = 1e-2f;
            ema.decay = 0.9f;
        }
        void step() {
            Mat x(2, 16), t(1, 16), h, a, y, dy, da, dh, dx;
            for (int n = 0; n < 16; ++n) {
                x(0, n) = (float)data_rng.uniform(-1, 1);
                x(1, n) = (float)data_rng.uniform(-1, 1);
                t(0, n) = x(0, n) * x(1, n);
            }
            fc1.forward(x, h);
            act.forward(h, a);
            fc2.forward(a, y);
            dy = 2 * (y - t) / 16;
            ps->zero_grad();
            fc2.backward(a, dy, da);
            act.backward(h, da, dh);
            fc1.backward(x, dh, dx);
            madbp::clip_grad_norm(*ps, 1.0f);
            adam.update(*ps);
            ema.update(*ps);
        }
    };
    TempDir dir;
    const std::string path = dir.file("train.safetensors");
    Run straight;
    for (int i = 0; i < 20; ++i) straight.step();

    Run first;
    for (int i = 0; i < 10; ++i) first.step();
    std::vector<NamedTensor> tensors = madbp::param_tensors(*first.ps);
    std::map<std::string, std::string> meta = {{"step", "10"}};
    madbp::append_adam(first.adam, tensors, meta);
    madbp::append_ema(first.ema, tensors, meta);
    madbp::append_rng(first.data_rng, "rng.data", meta);
    madbp::save_safetensors(path, tensors, meta);

    Run resumed;
    const madbp::SafeTensors st = madbp::load_safetensors(path);
    madbp::read_param_tensors(st, *resumed.ps);  // ignores the optim.* tensors
    madbp::read_adam(st, resumed.ps->size(), resumed.adam);
    madbp::read_ema(st, resumed.ps->size(), resumed.ema);
    madbp::read_rng(st, "rng.data", resumed.data_rng);
    CHECK(resumed.adam.step == 10);
    CHECK(resumed.ema.decay == 0.9f);
    for (int i = 0; i < 10; ++i) resumed.step();
    CHECK(std::memcmp(straight.ps->value.data(), resumed.ps->value.data(), 4 * straight.ps->size()) == 0);
    CHECK(std::memcmp(straight.ema.shadow.data(), resumed.ema.shadow.data(), 4 * straight.ps->size()) == 0);
    CHECK(straight.data_rng.next_u64() == resumed.data_rng.next_u64());

    // Damaged training state is reported by field.
    std::map<std::string, std::string> bad = meta;
    bad["optim.adam.step"] = "ten";
    madbp::save_safetensors(path, tensors, bad);
    CHECK_THROWS_WITH_AS(madbp::read_adam(madbp::load_safetensors(path), resumed.ps->size(), resumed.adam),
                         doctest::Contains("optim.adam.step"), std::runtime_error);
    bad = meta;
    bad["rng.data"] = "1 2 3";
    madbp::save_safetensors(path, tensors, bad);
    CHECK_THROWS_WITH_AS(madbp::read_rng(madbp::load_safetensors(path), "rng.data", resumed.data_rng), doctest::Contains("rng.data"),
                         std::runtime_error);
    CHECK_THROWS_WITH_AS(madbp::read_adam(madbp::load_safetensors(path), resumed.ps->size() + 1, resumed.adam),
                         doctest::Contains("'optim.adam.m' has shape"), std::runtime_error);
}

TEST_CASE("checkpoint: serialize refuses names and data it could not read back") {
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"", {1}, {1}}}, {}), std::invalid_argument);
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"__metadata__", {1}, {1}}}, {}), std::invalid_argument);
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"a", {1}, {1}}, {"a", {1}, {1}}}, {}), std::invalid_argument);
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"a", {2}, {1}}}, {}), std::invalid_argument);
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"a\xff", {1}, {1}}}, {}), std::invalid_argument);
    CHECK_THROWS_AS(madbp::serialize_safetensors({{"a", {1}, {INFINITY}}}, {}), std::invalid_argument);
    // Control characters and non-ASCII in names survive the JSON escape.
    const std::vector<NamedTensor> odd = {{"tab\there \"q\" \\ \xe2\x82\xac", {1}, {2}}};
    const auto bytes = madbp::serialize_safetensors(odd, {{"\x01", "\x1f"}});
    const madbp::SafeTensors st = madbp::parse_safetensors(bytes.data(), bytes.size());
    CHECK(st.tensors[0].name == odd[0].name);
    CHECK(st.meta("\x01") == "\x1f");
}
