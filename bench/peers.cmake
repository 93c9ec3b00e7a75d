# bench_peers: haptree vs MuJoCo / Simbody / Bullet btMultiBody (each peer optional).
find_package(CLI11 QUIET)
if(NOT CLI11_FOUND)
  message(STATUS "bench_peers: CLI11 not found, not built")
  return()
endif()
set(_peers_dir ${CMAKE_CURRENT_LIST_DIR}/peers)
add_executable(bench_peers ${_peers_dir}/bench_peers.cpp ${_peers_dir}/peer_haptree.cpp
               ${PROJECT_SOURCE_DIR}/tests/support/oracle.cpp
               ${PROJECT_SOURCE_DIR}/tests/support/quad_reference.cpp)
target_link_libraries(bench_peers PRIVATE haptree CLI11::CLI11 quadmath)
target_include_directories(bench_peers PRIVATE ${PROJECT_SOURCE_DIR})

# Debian's mujoco::mujoco target lists a non-existent include dir (libqhull_r), which is a hard CMake
# error at generate time, so link the library file and header dir directly.
find_package(mujoco QUIET)
find_path(HAPTREE_MUJOCO_INCLUDE mujoco/mujoco.h)
find_library(HAPTREE_MUJOCO_LIB mujoco)
if(mujoco_FOUND AND HAPTREE_MUJOCO_INCLUDE AND HAPTREE_MUJOCO_LIB)
  target_sources(bench_peers PRIVATE ${_peers_dir}/peer_mujoco.cpp)
  target_include_directories(bench_peers SYSTEM PRIVATE ${HAPTREE_MUJOCO_INCLUDE})
  target_link_libraries(bench_peers PRIVATE ${HAPTREE_MUJOCO_LIB})
  target_compile_definitions(bench_peers PRIVATE HAPTREE_PEER_MUJOCO)
  message(STATUS "bench_peers: MuJoCo ${mujoco_VERSION} found")
else()
  message(STATUS "bench_peers: MuJoCo not found, peer skipped")
endif()

find_package(Simbody QUIET)
if(Simbody_FOUND)
  target_sources(bench_peers PRIVATE ${_peers_dir}/peer_simbody.cpp)
  # Debian's Simbody is built without NDEBUG and its inline State internals change layout with it:
  # compiling this file with -DNDEBUG crashes inside realizeTopology(). Undefine it here only.
  set_source_files_properties(${_peers_dir}/peer_simbody.cpp PROPERTIES COMPILE_OPTIONS "-UNDEBUG")
  target_include_directories(bench_peers SYSTEM PRIVATE ${Simbody_INCLUDE_DIR})
  target_link_libraries(bench_peers PRIVATE ${Simbody_LIBRARIES})
  target_compile_definitions(bench_peers PRIVATE HAPTREE_PEER_SIMBODY)
  message(STATUS "bench_peers: Simbody ${Simbody_VERSION} found")
else()
  message(STATUS "bench_peers: Simbody not found, peer skipped")
endif()

# Bullet: prefer the double-precision libraries (Debian ships *-float64 next to the float ones).
find_path(HAPTREE_BULLET_INCLUDE BulletDynamics/Featherstone/btMultiBody.h PATH_SUFFIXES bullet)
find_library(HAPTREE_BULLET_DYN64 BulletDynamics-float64)
find_library(HAPTREE_BULLET_COL64 BulletCollision-float64)
find_library(HAPTREE_BULLET_LM64 LinearMath-float64)
if(HAPTREE_BULLET_INCLUDE AND HAPTREE_BULLET_DYN64 AND HAPTREE_BULLET_COL64 AND HAPTREE_BULLET_LM64)
  target_sources(bench_peers PRIVATE ${_peers_dir}/peer_bullet.cpp)
  target_include_directories(bench_peers SYSTEM PRIVATE ${HAPTREE_BULLET_INCLUDE})
  target_link_libraries(bench_peers PRIVATE ${HAPTREE_BULLET_DYN64} ${HAPTREE_BULLET_COL64}
                        ${HAPTREE_BULLET_LM64})
  target_compile_definitions(bench_peers PRIVATE HAPTREE_PEER_BULLET BT_USE_DOUBLE_PRECISION)
  message(STATUS "bench_peers: Bullet (double precision) found")
else()
  find_package(Bullet QUIET)
  if(BULLET_FOUND)
    message(STATUS "bench_peers: only single-precision Bullet found; the peer needs the "
                   "double-precision (*-float64) libraries, skipped")
  else()
    message(STATUS "bench_peers: Bullet not found, peer skipped")
  endif()
endif()

# Adaptive column only when the adaptive layer is part of the library.
if(EXISTS ${PROJECT_SOURCE_DIR}/haptree/adaptive.cpp AND EXISTS ${PROJECT_SOURCE_DIR}/haptree/adaptive.hpp)
  target_compile_definitions(bench_peers PRIVATE HAPTREE_PEERS_ADAPTIVE)
endif()

# Bacteriorhodopsin (1c3w_protein_h torsion model) only when the molecule library is built.
if(TARGET haptree_molecule)
  target_link_libraries(bench_peers PRIVATE haptree_molecule)
  target_compile_definitions(bench_peers PRIVATE HAPTREE_PEERS_MOLECULE)
else()
  message(STATUS "bench_peers: haptree_molecule not built, bacteriorhodopsin model skipped")
endif()
