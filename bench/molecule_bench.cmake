# Molecular scenes: force-field and whole-step ms (plain runner, Markdown table): docs/molecules.md.
if(TARGET haptree_molecule)
  find_package(CLI11 REQUIRED)
  add_executable(molecule_bench ${CMAKE_CURRENT_LIST_DIR}/molecule_bench.cpp)
  target_link_libraries(molecule_bench PRIVATE haptree_molecule CLI11::CLI11)
endif()
