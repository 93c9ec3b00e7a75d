# Ideal ACE-(ALA)n-NME helix builder (PDB out).
if(TARGET haptree_molecule)
  find_package(CLI11 REQUIRED)
  add_executable(molecule_helix ${CMAKE_CURRENT_LIST_DIR}/molecule_helix.cpp)
  target_link_libraries(molecule_helix PRIVATE haptree_molecule CLI11::CLI11)
endif()
