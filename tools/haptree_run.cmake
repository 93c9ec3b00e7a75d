# haptree_run: the README's main command (embedded: the three process classes in threads over memq://;
# --processes: the three executables as child processes, shared memory + a 127.0.0.1 LCM tcpq hub).
find_package(CLI11 REQUIRED)
find_package(spdlog REQUIRED)
# Loopback-only hub for LCM's tcpq:// provider (also used by tests/integration).
add_library(haptree_tcpq_hub ${CMAKE_CURRENT_LIST_DIR}/tcpq_hub.cpp)
target_include_directories(haptree_tcpq_hub PUBLIC ${PROJECT_SOURCE_DIR})
target_link_libraries(haptree_tcpq_hub PUBLIC Threads::Threads)
add_executable(haptree_run ${CMAKE_CURRENT_LIST_DIR}/haptree_run.cpp ${CMAKE_CURRENT_LIST_DIR}/haptree_run_processes.cpp)
target_link_libraries(haptree_run PRIVATE haptree_sim_server haptree_coupler haptree_device_bridge haptree_tcpq_hub haptree_viewer haptree_imd_bridge
                      CLI11::CLI11 spdlog::spdlog)
# --processes finds the executables next to haptree_run in the build tree: build them with it.
add_dependencies(haptree_run sim_server coupler device_bridge viewer)
