# passivity_sweep: stiff virtual coupling (k_s sweep) against the passivity bound b > K·T/2 on the
# virtual hand, closed in-process (tests/stress/coupling_loop.hpp); --bs-threshold: coupling damping
# on the simulated side. Results: docs/accuracy_and_stability.md.
find_package(CLI11 QUIET)
find_package(spdlog QUIET)
if(CLI11_FOUND AND spdlog_FOUND AND TARGET haptree_coupler AND TARGET haptree_device)
  add_executable(passivity_sweep ${CMAKE_CURRENT_LIST_DIR}/passivity_sweep.cpp)
  target_link_libraries(passivity_sweep PRIVATE haptree haptree_coupler haptree_device CLI11::CLI11 spdlog::spdlog)
  target_include_directories(passivity_sweep PRIVATE ${PROJECT_SOURCE_DIR})
  target_compile_definitions(passivity_sweep PRIVATE HAPTREE_TOOLS_DIR="${CMAKE_CURRENT_LIST_DIR}")
else()
  message(STATUS "passivity_sweep: CLI11, spdlog or haptree_coupler not available, not built")
endif()
