// After set-up, a DCA step allocates nothing: count every operator new in this binary.
#include <gtest/gtest.h>

#include <atomic>
#include <cstdlib>
#include <new>

#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

static std::atomic<long> g_allocs{0};
void* operator new(std::size_t n) {
  ++g_allocs;
  if (void* p = std::malloc(n ? n : 1)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return operator new(n); }
void* operator new(std::size_t n, std::align_val_t al) {
  ++g_allocs;
  if (void* p = std::aligned_alloc(static_cast<std::size_t>(al), (n + static_cast<std::size_t>(al) - 1) & ~(static_cast<std::size_t>(al) - 1))) return p;
  throw std::bad_alloc();
}
void operator delete(void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::align_val_t) noexcept { std::free(p); }
void operator delete(void* p, std::size_t, std::align_val_t) noexcept { std::free(p); }

namespace haptree {
namespace {

TEST(Allocation, ForwardDynamicsAndIntegrationAllocateNothing) {
  for (const char* scene : {"chain", "random_tree", "protein_like"}) {
    SceneOptions o;
    o.n = 300;
    o.seed = 2;
    o.mixed_joints = std::string(scene) == "random_tree";
    o.free_root = o.mixed_joints;
    auto model = make_scene(scene, o);
    State st(*model);
    Data d(*model);
    forward_dynamics(*model, d, st);   // warm-up
    const long before = g_allocs.load();
    for (int i = 0; i < 5; ++i) {
      forward_dynamics(*model, d, st);
      integrate(*model, st.q, st.qd, d.qdd, 1e-3);
    }
    EXPECT_EQ(g_allocs.load() - before, 0) << scene;
  }
}

}  // namespace
}  // namespace haptree
