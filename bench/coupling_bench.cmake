# O(log n) coupling benchmark (plain runner, Markdown table on stdout): docs/performance.md.
find_package(CLI11 REQUIRED)
add_executable(coupling_bench ${CMAKE_CURRENT_LIST_DIR}/coupling_bench.cpp)
target_link_libraries(coupling_bench PRIVATE haptree CLI11::CLI11)
