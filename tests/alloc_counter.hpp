// alloc_counter.hpp - counts heap allocations while a flag is set (tests and benchmarks).
// Replaces malloc & co. and operator new/delete: include it in exactly ONE translation unit of
// a program. Use: g_allocs = 0; g_count_allocs = true; ...work...; g_count_allocs = false;
#pragma once
#include <cerrno>
#include <cstddef>
#include <new>

#include "alloc_counter_api.hpp"

// Eigen allocates with malloc, the standard library with operator new, so both are counted.

std::atomic<bool> g_count_allocs{false};
std::atomic<long> g_allocs{0};

#if MADBP_TEST_COUNT_ALLOCS
extern "C" {
void* __libc_malloc(size_t);
void* __libc_calloc(size_t, size_t);
void* __libc_realloc(void*, size_t);
void* __libc_memalign(size_t, size_t);
void __libc_free(void*);

static inline void note_alloc() {
    if (g_count_allocs.load(std::memory_order_relaxed)) g_allocs.fetch_add(1, std::memory_order_relaxed);
}
void* malloc(size_t n) {
    note_alloc();
    return __libc_malloc(n);
}
void* calloc(size_t n, size_t m) {
    note_alloc();
    return __libc_calloc(n, m);
}
void* realloc(void* p, size_t n) {
    note_alloc();
    return __libc_realloc(p, n);
}
void* memalign(size_t a, size_t n) {
    note_alloc();
    return __libc_memalign(a, n);
}
void* aligned_alloc(size_t a, size_t n) {
    note_alloc();
    return __libc_memalign(a, n);
}
int posix_memalign(void** out, size_t a, size_t n) {
    note_alloc();
    void* p = __libc_memalign(a, n);
    if (!p) return ENOMEM;
    *out = p;
    return 0;
}
void free(void* p) { __libc_free(p); }
}

void* operator new(size_t n) {
    note_alloc();
    void* p = __libc_malloc(n ? n : 1);
    if (!p) throw std::bad_alloc();
    return p;
}
void* operator new[](size_t n) { return operator new(n); }
void operator delete(void* p) noexcept { __libc_free(p); }
void operator delete[](void* p) noexcept { __libc_free(p); }
void operator delete(void* p, size_t) noexcept { __libc_free(p); }
void operator delete[](void* p, size_t) noexcept { __libc_free(p); }
#endif

