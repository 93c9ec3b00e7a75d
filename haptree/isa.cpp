#include "haptree/isa.hpp"

#include <atomic>
#include <cstdio>
#include <cstdlib>

namespace haptree::isa {

namespace {

bool cpu_has(Level l) {
#if HAPTREE_ISA_X86
  __builtin_cpu_init();
  // The runtime (libgcc / compiler-rt) checks the OS's XSAVE state for AVX / AVX-512 too. GCC knows
  // the levels by name; clang (before 18) only the features: the ones that tell a level apart (every
  // CPU with AVX2, FMA and BMI2 has the rest of x86-64-v3: LZCNT, MOVBE, F16C).
  switch (l) {
    case Level::generic: return true;
#if defined(__clang__)
    case Level::avx2:
      return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") && __builtin_cpu_supports("bmi") &&
             __builtin_cpu_supports("bmi2");
    case Level::avx512:
      return cpu_has(Level::avx2) && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
             __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq") &&
             __builtin_cpu_supports("avx512cd");
#else
    case Level::avx2: return __builtin_cpu_supports("x86-64-v3");
    case Level::avx512: return __builtin_cpu_supports("x86-64-v4");
#endif
  }
  return false;
#else
  return l == Level::generic;
#endif
}

Level from_env() {
  const Level top = best();
  const char* v = std::getenv("HAPTREE_ISA");
  if (!v || !*v || std::string_view(v) == "auto") return top;
  const std::optional<Level> l = parse(v);
  if (!l) {
    std::fprintf(stderr, "haptree: HAPTREE_ISA='%s' is not generic, avx2, avx512 or auto; using %s\n", v,
                 name(top));
    return top;
  }
  return *l < top ? *l : top;
}

std::atomic<int>& current() {
  static std::atomic<int> level{static_cast<int>(from_env())};
  return level;
}

}  // namespace

const char* name(Level l) {
  switch (l) {
    case Level::generic: return "generic";
    case Level::avx2: return "avx2";
    case Level::avx512: return "avx512";
  }
  return "?";
}

std::optional<Level> parse(std::string_view s) {
  for (Level l : {Level::generic, Level::avx2, Level::avx512})
    if (s == name(l)) return l;
  return std::nullopt;
}

bool supported(Level l) {
  static const bool has[3] = {cpu_has(Level::generic), cpu_has(Level::avx2), cpu_has(Level::avx512)};
  return has[static_cast<int>(l)];
}

Level best() {
  return supported(Level::avx512) ? Level::avx512 : supported(Level::avx2) ? Level::avx2 : Level::generic;
}

Level active() { return static_cast<Level>(current().load(std::memory_order_relaxed)); }

bool set_active(Level l) {
  if (!supported(l)) return false;
  current().store(static_cast<int>(l), std::memory_order_relaxed);
  return true;
}

}  // namespace haptree::isa
