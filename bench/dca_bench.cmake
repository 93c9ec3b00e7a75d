# dca_bench: µs per forward_dynamics call (Google Benchmark) on chains, binary trees and the
# 857-DOF protein-like tree. Results and the command: docs/performance.md.
if(benchmark_FOUND)
  add_executable(dca_bench ${CMAKE_CURRENT_LIST_DIR}/dca_bench.cpp)
  target_link_libraries(dca_bench PRIVATE haptree benchmark::benchmark)
else()
  message(STATUS "dca_bench: Google Benchmark not found, not built")
endif()
