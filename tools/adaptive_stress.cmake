# adaptive_stress: long adaptive runs switching eps / budget k every step, checked every step, oracle
# every M steps (tests/stress/adaptive_switching.hpp). Results: docs/accuracy_and_stability.md.
find_package(CLI11 QUIET)
find_package(spdlog QUIET)
if(CLI11_FOUND AND spdlog_FOUND)
  add_executable(adaptive_stress ${CMAKE_CURRENT_LIST_DIR}/adaptive_stress.cpp
                 ${PROJECT_SOURCE_DIR}/tests/support/oracle.cpp)
  target_link_libraries(adaptive_stress PRIVATE haptree CLI11::CLI11 spdlog::spdlog)
  target_include_directories(adaptive_stress PRIVATE ${PROJECT_SOURCE_DIR})
else()
  message(STATUS "adaptive_stress: CLI11 or spdlog not found, not built")
endif()
