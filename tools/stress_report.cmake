# stress_report: long numerical-stability report (energy drift, far origin, mass ratios, coaxial
# axes, long chains); links the long-double oracle from tests/support.
find_package(CLI11 QUIET)
find_package(spdlog QUIET)
if(CLI11_FOUND AND spdlog_FOUND)
  add_executable(stress_report ${CMAKE_CURRENT_LIST_DIR}/stress_report.cpp
                 ${PROJECT_SOURCE_DIR}/tests/support/oracle.cpp)
  target_link_libraries(stress_report PRIVATE haptree CLI11::CLI11 spdlog::spdlog)
  target_include_directories(stress_report PRIVATE ${PROJECT_SOURCE_DIR})
else()
  message(STATUS "stress_report: CLI11 or spdlog not found, not built")
endif()
