# trajectory_from_log: an LCM log's scene states -> DCD or multi-model PDB.
find_package(CLI11 REQUIRED)
find_package(spdlog REQUIRED)
add_executable(trajectory_from_log ${CMAKE_CURRENT_LIST_DIR}/trajectory_from_log.cpp)
target_link_libraries(trajectory_from_log PRIVATE haptree_molecule haptree_bus CLI11::CLI11 spdlog::spdlog)
