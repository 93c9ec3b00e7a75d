# scaling_bench: adaptive step (median/mean/p99/worst), selections, memory and construction time
# against n (chains and binary trees, 1 024 … 262 144 bodies). Results: docs/performance.md.
add_executable(scaling_bench ${CMAKE_CURRENT_LIST_DIR}/scaling_bench.cpp)
target_link_libraries(scaling_bench PRIVATE haptree)
