# fault_relay: fault-injecting UDP multicast relay for the network-fault sessions (docs/network_faults.md).
find_package(CLI11 REQUIRED)
add_executable(fault_relay ${CMAKE_CURRENT_LIST_DIR}/fault_relay.cpp)
target_compile_definitions(fault_relay PRIVATE _GNU_SOURCE)
target_link_libraries(fault_relay PRIVATE CLI11::CLI11)
# fault_metrics: the per-fault table (clamp, rate limit, ramp, recovery, rates) from an LCM log.
add_executable(fault_metrics ${CMAKE_CURRENT_LIST_DIR}/fault_metrics.cpp)
target_include_directories(fault_metrics PRIVATE ${PROJECT_SOURCE_DIR})
target_link_libraries(fault_metrics PRIVATE haptree_bus CLI11::CLI11)
