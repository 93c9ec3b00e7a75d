# haptree-fd: forward dynamics of a URDF or a generated scene, printed as JSON (for cross-checks).
if(TARGET haptree_io)
  find_package(CLI11 REQUIRED)
  add_executable(haptree_fd ${CMAKE_CURRENT_LIST_DIR}/haptree_fd.cpp)
  set_target_properties(haptree_fd PROPERTIES OUTPUT_NAME haptree-fd)
  target_link_libraries(haptree_fd PRIVATE haptree haptree_io CLI11::CLI11)
endif()
