/// @file
/// Run-time choice of the vectorised kernels' instruction set. The library itself is compiled for a
/// baseline x86-64 level (x86-64-v2 by default) so that it runs on any such CPU; the kernels that
/// gain from wider vectors exist per level (force field: generic, avx2, avx512; DCA, coupling_forces:
/// generic, avx2, used at avx512 too), and the level used is chosen here from the CPU at run time:
///   generic  any CPU (the library's baseline)
///   avx2     x86-64-v3: AVX2 + FMA (Intel Haswell, AMD Zen and later)
///   avx512   x86-64-v4: AVX-512 F/VL/DQ/BW/CD (Intel Skylake-SP and later servers, AMD Zen 4/5)
/// The environment variable HAPTREE_ISA (generic | avx2 | avx512 | auto) caps the level, e.g. to
/// compare kernels on one machine; a level the CPU lacks is never used.
#pragma once

#include <optional>
#include <string_view>

/// The instruction-set level of the vectorised kernels, chosen at run time.
namespace haptree::isa {

/// A kernel level: the library's baseline, x86-64-v3 or x86-64-v4.
enum class Level { generic = 0, avx2 = 1, avx512 = 2 };

/// "generic", "avx2" or "avx512".
const char* name(Level l);
std::optional<Level> parse(std::string_view s);   ///< "generic", "avx2", "avx512"; nothing otherwise
bool supported(Level l);   ///< the CPU and the OS support it and the kernels were built for it
Level best();              ///< the highest supported level
/// The level the kernels run at: best(), capped by HAPTREE_ISA when that is set (read once, at the
/// first call; an unknown value is reported on stderr and ignored), or as set_active left it.
Level active();
/// Kernels at l from now on (all threads). False, and nothing changed, when l is not supported.
bool set_active(Level l);

}  // namespace haptree::isa
