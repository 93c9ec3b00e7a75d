// Shared by every fuzz target: the libFuzzer entry point, a scratch file for readers that take a path,
// and FUZZ_CHECK (an oracle failure aborts, so libFuzzer keeps the input and the replay test fails).
// Each target is one .cpp with LLVMFuzzerTestOneInput; the same source is linked into libFuzzer under
// clang (scripts/fuzz.sh) and into a plain replay program under gcc (fuzz/replay_main.cpp, CTest).
#pragma once

#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "%s:%d: FUZZ_CHECK failed: %s\n", __FILE__, __LINE__, #cond);  \
      std::abort();                                                                       \
    }                                                                                     \
  } while (0)

namespace haptree::fuzz {

// One file per process (libFuzzer runs inputs one after another in a process), rewritten per input:
// for readers whose only entry point is a path (read_structure picks the format from the suffix).
class ScratchFile {
 public:
  explicit ScratchFile(const char* suffix) {
    const char* dir = std::getenv("TMPDIR");
    std::string tmpl = std::string(dir && *dir ? dir : "/tmp") + "/haptree-fuzz-XXXXXX" + suffix;
    const int fd = ::mkstemps(tmpl.data(), static_cast<int>(std::char_traits<char>::length(suffix)));
    if (fd < 0) {
      std::perror("mkstemps");
      std::abort();
    }
    ::close(fd);
    path_ = tmpl;
  }
  ~ScratchFile() { ::unlink(path_.c_str()); }
  const std::string& write(const uint8_t* data, size_t size) {
    std::FILE* f = std::fopen(path_.c_str(), "wb");
    FUZZ_CHECK(f != nullptr);
    FUZZ_CHECK(size == 0 || std::fwrite(data, 1, size, f) == size);
    std::fclose(f);
    return path_;
  }

 private:
  std::string path_;
};

}  // namespace haptree::fuzz
