// Counts every operator new in the test binary that includes this header (include it from exactly
// one .cpp per binary: it replaces the global allocation functions). Tests read
// haptree::testing::allocation_count() before and after a hot path and expect no change.
#pragma once

#include <atomic>
#include <cstdlib>
#include <new>

namespace haptree::testing {
inline std::atomic<long> g_allocation_count{0};
inline long allocation_count() { return g_allocation_count.load(); }
}  // namespace haptree::testing

// GCC 12 flags free() in a replaced operator delete as mismatched; the pairing is ours
// (malloc/aligned_alloc ↔ free).
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void* operator new(std::size_t n) {
  ++haptree::testing::g_allocation_count;
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return operator new(n); }
void* operator new(std::size_t n, std::align_val_t al) {
  ++haptree::testing::g_allocation_count;
  const std::size_t a = static_cast<std::size_t>(al);
  if (void* p = std::aligned_alloc(a, (n + a - 1) & ~(a - 1))) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n, std::align_val_t al) { return operator new(n, al); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }
#pragma GCC diagnostic pop
