# replay_coupling: reproduce logged feedback forces from logged snapshots + poses (docs/processes.md).
find_package(CLI11 REQUIRED)
find_package(spdlog REQUIRED)
add_executable(replay_coupling ${CMAKE_CURRENT_LIST_DIR}/replay_coupling.cpp)
target_link_libraries(replay_coupling PRIVATE haptree_coupler CLI11::CLI11 spdlog::spdlog)
