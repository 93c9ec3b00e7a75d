# bus_bench: device-state -> feedback ping-pong over the shared-memory channel, memq:// and udpm:// (netns).
if(TARGET haptree_bus)
  find_package(CLI11 REQUIRED)
  add_executable(bus_bench ${CMAKE_CURRENT_LIST_DIR}/bus_bench.cpp)
  target_link_libraries(bus_bench PRIVATE haptree_bus haptree_device CLI11::CLI11)
  target_include_directories(bus_bench PRIVATE ${PROJECT_SOURCE_DIR}/tests/bus)  # netns.hpp
endif()
