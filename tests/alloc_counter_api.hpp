// alloc_counter_api.hpp - the counters of alloc_counter.hpp, for any translation unit.
// MADBP_TEST_COUNT_ALLOCS is 0 under AddressSanitizer (which owns malloc): nothing is counted.
#pragma once
#include <atomic>

#if defined(__SANITIZE_ADDRESS__)
#define MADBP_TEST_COUNT_ALLOCS 0
#elif defined(__has_feature)
#if __has_feature(address_sanitizer)
#define MADBP_TEST_COUNT_ALLOCS 0
#endif
#endif
#ifndef MADBP_TEST_COUNT_ALLOCS
#define MADBP_TEST_COUNT_ALLOCS 1
#endif

extern std::atomic<bool> g_count_allocs;  // count while true
extern std::atomic<long> g_allocs;        // allocations counted so far

// Heap allocations made while fn() runs.
template <class F>
long count_allocs(F&& fn) {
    g_allocs = 0;
    g_count_allocs = true;
    fn();
    g_count_allocs = false;
    return g_allocs.load();
}
