# stress_report: long numerical-stability report (ISA level, energy drift, far origin, welds, light
# bodies, mass ratios, coaxial axes, long chains); links the long-double oracle from tests/support.
find_package(CLI11 QUIET)
find_package(spdlog QUIET)
if(CLI11_FOUND AND spdlog_FOUND)
  add_executable(stress_report ${CMAKE_CURRENT_LIST_DIR}/stress_report.cpp
                 ${PROJECT_SOURCE_DIR}/tests/support/oracle.cpp)
  target_link_libraries(stress_report PRIVATE haptree CLI11::CLI11 spdlog::spdlog)
  target_include_directories(stress_report PRIVATE ${PROJECT_SOURCE_DIR})
  # The report names the ISA level its numbers come from (section isa).
  if(HAPTREE_MARCH)
    set(stress_isa "-march=${HAPTREE_MARCH}")
  elseif(HAPTREE_NATIVE)
    set(stress_isa "-march=native")
  else()
    set(stress_isa "-march=x86-64-v2 (default), force field, DCA and coupler kernels chosen at run time")
  endif()
  target_compile_definitions(stress_report PRIVATE HAPTREE_BUILD_ISA="${stress_isa}"
    HAPTREE_BUILD_FLAGS="${CMAKE_CXX_FLAGS} ${CMAKE_CXX_FLAGS_RELEASE}")
else()
  message(STATUS "stress_report: CLI11 or spdlog not found, not built")
endif()
