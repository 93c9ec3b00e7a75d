add_executable(haptree_demo ${CMAKE_CURRENT_LIST_DIR}/haptree_demo.cpp)
find_package(CLI11 REQUIRED)
target_link_libraries(haptree_demo PRIVATE haptree CLI11::CLI11)
