// The shipped model's lookup (madbp::default_model_path, madbp.hpp section 5) and the tool's
// --model default built on it (madbp_cli::model_option). Run from the repository root, as
// `make test` and ctest do.
#include <doctest/doctest.h>

#include <cstdlib>
#include <fstream>
#include <sys/stat.h>
#include <unistd.h>

#include "methods.hpp"

namespace {

const char* const kCheckoutModel = "models/madbp-default.safetensors";

// Sets (value) or unsets (nullptr) MADBP_MODEL for a scope; restores what it was.
struct ScopedModelEnv {
    bool had = false;
    std::string old;
    explicit ScopedModelEnv(const char* value) {
        if (const char* v = std::getenv("MADBP_MODEL")) had = true, old = v;
        if (value) ::setenv("MADBP_MODEL", value, 1);
        else ::unsetenv("MADBP_MODEL");
    }
    ~ScopedModelEnv() {
        if (had) ::setenv("MADBP_MODEL", old.c_str(), 1);
        else ::unsetenv("MADBP_MODEL");
    }
};

// The same file (device and inode) under either name; false when either is missing.
bool same_file(const std::string& a, const std::string& b) {
    struct stat sa, sb;
    return ::stat(a.c_str(), &sa) == 0 && ::stat(b.c_str(), &sb) == 0 && sa.st_dev == sb.st_dev && sa.st_ino == sb.st_ino;
}

// default_model_path fails with a runtime_error whose message contains `part`.
void check_lookup_error(const std::string& part) {
    CHECK_THROWS_WITH_AS(madbp::default_model_path(), doctest::Contains(part.c_str()), std::runtime_error);
}

}  // namespace

TEST_CASE("default_model_path: MADBP_MODEL first; a missing MADBP_MODEL file is an error naming it") {
    REQUIRE(same_file(kCheckoutModel, kCheckoutModel));  // run from the repository root
    char tmpl[] = "/tmp/madbp-model-XXXXXX";
    const int fd = ::mkstemp(tmpl);
    REQUIRE(fd >= 0);
    ::close(fd);
    const std::string copy = tmpl;
    std::ofstream(copy, std::ios::binary) << std::ifstream(kCheckoutModel, std::ios::binary).rdbuf();
    {
        ScopedModelEnv env(copy.c_str());
        CHECK(madbp::default_model_path() == copy);
        CHECK(madbp::load_model(madbp::default_model_path()).parameter_count() > 0);  // a copy of the real model
    }
    ::unlink(copy.c_str());
    {
        ScopedModelEnv env(copy.c_str());  // now gone: an error, not the next place
        check_lookup_error("MADBP_MODEL=" + copy);
    }
}

TEST_CASE("default_model_path: without MADBP_MODEL, the checkout's model from the repository root") {
    for (const char* value : {(const char*)nullptr, ""}) {  // unset, or set but empty
        ScopedModelEnv env(value);
        CHECK(same_file(madbp::default_model_path(), kCheckoutModel));
    }
}

TEST_CASE("default_model_path: from a directory without models/, the build's model directory or an error listing the places") {
    char buf[4096];
    REQUIRE(::getcwd(buf, sizeof buf) != nullptr);
    const std::string root = buf;
    char tmpl[] = "/tmp/madbp-cwd-XXXXXX";
    REQUIRE(::mkdtemp(tmpl) != nullptr);
    ScopedModelEnv env(nullptr);
    REQUIRE(::chdir(tmpl) == 0);
#ifdef MADBP_MODEL_DIR
    // The CMake target defines it (the source tree's models/ in a build tree).
    CHECK(same_file(madbp::default_model_path(), root + "/" + kCheckoutModel));
#else
    // The Makefile build: no macro and a relative header path, so only ./models and the
    // executable's ../share/madbp/models are left, and neither exists.
    check_lookup_error("MADBP_MODEL not set");
    check_lookup_error("/../share/madbp/models/madbp-default.safetensors");
    check_lookup_error(std::string(tmpl) + "/" + kCheckoutModel);  // ./models, named in full
    check_lookup_error("--model FILE");
#endif
    REQUIRE(::chdir(root.c_str()) == 0);
    ::rmdir(tmpl);
}

TEST_CASE("madbp tool: --model's default is looked up only when --model is not given") {
    ScopedModelEnv env("/nonexistent/madbp-model.safetensors");  // the lookup fails, if made
    madbp_cli::Args given({"--model", "mine.safetensors"});
    CHECK(madbp_cli::model_option(given) == "mine.safetensors");
    given.finish();  // --model was read
    madbp_cli::Args absent(std::vector<std::string>{});
    CHECK_THROWS_WITH_AS(madbp_cli::model_option(absent), doctest::Contains("MADBP_MODEL"), std::runtime_error);
}
