# chaos_soak: a three-process session under SIGKILLs and garbage/stale/replayed messages; counts that must
# be zero (docs/chaos.md). A 25 s run is in CTest (labels integration, chaos).
find_package(CLI11 REQUIRED)
add_executable(chaos_soak ${CMAKE_CURRENT_LIST_DIR}/chaos_soak.cpp)
target_link_libraries(chaos_soak PRIVATE haptree_sim_server haptree_device_bridge haptree_bus haptree_tcpq_hub CLI11::CLI11)
target_include_directories(chaos_soak PRIVATE ${PROJECT_SOURCE_DIR})
add_dependencies(chaos_soak sim_server coupler device_bridge replay_coupling)
if(HAPTREE_BUILD_TESTS)
  enable_testing()   # tools/ is added before the top-level enable_testing()
  add_test(NAME chaos_soak_short
           COMMAND chaos_soak --duration-s 25 --kill-min-s 1 --kill-max-s 2.5 --seed 15
                   --log-dir ${CMAKE_CURRENT_BINARY_DIR}/chaos_soak_short)
  set_tests_properties(chaos_soak_short PROPERTIES LABELS "integration;chaos" TIMEOUT 180)
endif()
