# adaptive_sweep: run time against error of the adaptive dynamics (budget k / threshold eps sweep vs
# full DCA), CSV + Markdown table. Results, plots and the command: docs/performance.md.
find_package(CLI11 QUIET)
if(CLI11_FOUND)
  add_executable(adaptive_sweep ${CMAKE_CURRENT_LIST_DIR}/adaptive_sweep.cpp)
  target_link_libraries(adaptive_sweep PRIVATE haptree CLI11::CLI11)
  if(TARGET haptree_molecule)
    target_link_libraries(adaptive_sweep PRIVATE haptree_molecule)
    target_compile_definitions(adaptive_sweep PRIVATE HAPTREE_SWEEP_MOLECULES=1)
  endif()
  if(HAPTREE_BUILD_TESTS)
    # tools/ is added before the top-level enable_testing(): enable it here so the test registers.
    enable_testing()
    # Smoke run (< 20 s): small scenes, fails on non-finite states or a budget overrun.
    add_test(NAME adaptive_sweep_smoke
             COMMAND adaptive_sweep --smoke --csv ${CMAKE_CURRENT_BINARY_DIR}/adaptive_sweep_smoke.csv)
    set_tests_properties(adaptive_sweep_smoke PROPERTIES LABELS bench_smoke TIMEOUT 60)
  endif()
else()
  message(STATUS "adaptive_sweep: CLI11 not found, not built")
endif()
