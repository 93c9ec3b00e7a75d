# haptree_run: the README's main command (embedded: the three process classes in threads over memq://).
find_package(CLI11 REQUIRED)
find_package(spdlog REQUIRED)
add_executable(haptree_run ${CMAKE_CURRENT_LIST_DIR}/haptree_run.cpp)
target_link_libraries(haptree_run PRIVATE haptree_sim_server haptree_coupler haptree_device_bridge CLI11::CLI11 spdlog::spdlog)
