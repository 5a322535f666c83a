// The doctest runner; every tests/test_*.cpp is linked into one binary (build/run_tests).
#define DOCTEST_CONFIG_IMPLEMENT_WITH_MAIN
#include <doctest/doctest.h>

// Heap-allocation counting for the no-allocation tests (one definition per program).
#include "alloc_counter.hpp"
