# What `cmake --install build --prefix P` puts under P, the CMake package find_package(haptree) reads,
# haptree.pc, and the Debian packages (cpack -G DEB). Included last by the top-level CMakeLists.txt,
# when every target exists. Components: runtime (libraries, programs, data, web page, systemd units,
# man pages), dev (headers, static libraries, CMake package, pkg-config), python (the haptree module).
include(CMakePackageConfigHelpers)
set(HAPTREE_CMAKE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/haptree)
set(HAPTREE_DATA_ROOT ${CMAKE_INSTALL_DATADIR}/haptree)   # the programs look for <bin>/../share/haptree

# Programs: the three processes, the launcher, the viewer and IMD bridge, and the tools a user runs on
# a session's files. Next to each other in bin/, as haptree_run --processes expects them.
set(haptree_programs sim_server coupler device_bridge viewer imd_bridge haptree_run haptree_fd
    replay_coupling trajectory_from_log molecule_helix haptree_demo fault_relay fault_metrics)
set(installed_programs)
foreach(p ${haptree_programs})
  if(TARGET ${p})
    list(APPEND installed_programs ${p})
  endif()
endforeach()
install(TARGETS ${installed_programs} RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR} COMPONENT runtime)

# Public headers keep their include path: <prefix>/include/haptree/xxx.hpp is #include "haptree/xxx.hpp".
# dca_detail.hpp is the DCA sources' own (internal) header, not part of the API.
install(DIRECTORY ${PROJECT_SOURCE_DIR}/haptree/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/haptree
        COMPONENT dev FILES_MATCHING PATTERN "*.hpp" PATTERN "dca_detail.hpp" EXCLUDE)

# Data: molecules and force-field tables (found by haptree::molecule::data_dir()), sample URDF models,
# the viewer's page (NGL vendored), the LCM schemas (lcmtypes/CMakeLists.txt), lcm-spy's jar if built.
install(DIRECTORY ${PROJECT_SOURCE_DIR}/data/ DESTINATION ${HAPTREE_DATA_ROOT}/data COMPONENT runtime
        PATTERN oracle EXCLUDE PATTERN tools EXCLUDE)   # OpenMM reference numbers and the scripts that made them
install(FILES ${PROJECT_SOURCE_DIR}/tests/data/urdf/arm.urdf ${PROJECT_SOURCE_DIR}/tests/data/urdf/floating.urdf
        DESTINATION ${HAPTREE_DATA_ROOT}/models COMPONENT runtime)
install(DIRECTORY ${PROJECT_SOURCE_DIR}/viewer/web/ DESTINATION ${HAPTREE_DATA_ROOT}/viewer/web
        COMPONENT runtime)
if(TARGET haptree_lcmtypes_jar)
  install(FILES ${PROJECT_BINARY_DIR}/java/haptree_lcmtypes.jar DESTINATION ${HAPTREE_DATA_ROOT}/java
          COMPONENT runtime)
endif()
install(FILES ${PROJECT_SOURCE_DIR}/LICENSE ${PROJECT_SOURCE_DIR}/THIRD_PARTY.md
        DESTINATION ${CMAKE_INSTALL_DOCDIR} COMPONENT runtime)

# The Python module (pure-Python part, generated LCM types, the extension) as one package directory.
set(HAPTREE_PYTHON_INSTALL_DIR lib/python3/dist-packages CACHE STRING
    "Where the haptree Python package goes, relative to the prefix (Debian's layout by default)")
if(TARGET haptree_py)
  install(DIRECTORY ${PROJECT_BINARY_DIR}/python/haptree DESTINATION ${HAPTREE_PYTHON_INSTALL_DIR}
          COMPONENT python PATTERN "__pycache__" EXCLUDE)
endif()

# Eigen's ABI follows the compiler's target flags: the alignment of fixed-size members (16 bytes for
# SSE, 32 with AVX, 64 with AVX-512), the alignment assumed for dynamic arrays, and whether its
# aligned_malloc is plain malloc (only when that alignment is 16) or its own allocator (an offset stored
# before the block). A program built without the library's -march would disagree with it on struct
# layouts and free its blocks with the wrong function ("double free or corruption"). So the values the
# libraries were compiled with are read here, by preprocessing Eigen with the libraries' own flags,
# and carried to every user of the installed package (exported targets, haptree.pc): with them, any
# -march (or none) on the user's side gives the library's layout and allocator.
string(TOUPPER "${CMAKE_BUILD_TYPE}" build_type)
separate_arguments(probe_flags UNIX_COMMAND "${CMAKE_CXX_FLAGS} ${CMAKE_CXX_FLAGS_${build_type}}")
get_target_property(probe_opts haptree COMPILE_OPTIONS)
get_target_property(probe_defs haptree COMPILE_DEFINITIONS)
get_target_property(probe_eigen Eigen3::Eigen INTERFACE_INCLUDE_DIRECTORIES)
foreach(v probe_opts probe_defs)
  if(NOT ${v})
    set(${v} "")
  endif()
  list(FILTER ${v} EXCLUDE REGEX "\\$<")   # generator expressions: not abi-relevant here
endforeach()
list(TRANSFORM probe_defs PREPEND "-D")
list(TRANSFORM probe_eigen PREPEND "-I")
file(WRITE ${PROJECT_BINARY_DIR}/eigen_abi_probe.cpp
     "#include <Eigen/Core>\nhaptree_eigen_abi EIGEN_MAX_STATIC_ALIGN_BYTES EIGEN_MAX_ALIGN_BYTES EIGEN_MALLOC_ALREADY_ALIGNED\n")
execute_process(COMMAND ${CMAKE_CXX_COMPILER} ${probe_flags} ${probe_opts} ${probe_defs} ${probe_eigen} -std=c++17
                        -E ${PROJECT_BINARY_DIR}/eigen_abi_probe.cpp
                OUTPUT_VARIABLE probe_out ERROR_VARIABLE probe_err RESULT_VARIABLE probe_rc)
if(NOT probe_rc EQUAL 0 OR NOT probe_out MATCHES "haptree_eigen_abi ([0-9]+) ([0-9]+) ([0-9]+)")
  message(FATAL_ERROR "Eigen ABI probe failed (${probe_rc}): ${probe_err}")
endif()
set(HAPTREE_EIGEN_ABI_DEFINITIONS EIGEN_MAX_STATIC_ALIGN_BYTES=${CMAKE_MATCH_1}
    EIGEN_MAX_ALIGN_BYTES=${CMAKE_MATCH_2} EIGEN_MALLOC_ALREADY_ALIGNED=${CMAKE_MATCH_3})
message(STATUS "haptree: Eigen ABI of the libraries, carried to their users: ${HAPTREE_EIGEN_ABI_DEFINITIONS}")
get_property(exported GLOBAL PROPERTY HAPTREE_EXPORTED_LIBS)
foreach(lib ${exported})
  set(twins ${lib})
  if(TARGET ${lib}_shared)
    list(APPEND twins ${lib}_shared)
  endif()
  foreach(t ${twins})
    foreach(d ${HAPTREE_EIGEN_ABI_DEFINITIONS})
      # Installed users only: the tree's own targets are compiled with the very flags probed.
      set_property(TARGET ${t} APPEND PROPERTY INTERFACE_COMPILE_DEFINITIONS "$<INSTALL_INTERFACE:${d}>")
    endforeach()
  endforeach()
endforeach()

# CMake package: haptree::core, ::io, ::molecule, ::bus, ::device, ::imd (shared), the same with
# _static, and ::lcmtypes (generated message headers).
install(EXPORT haptreeTargets NAMESPACE haptree:: DESTINATION ${HAPTREE_CMAKE_DIR} COMPONENT dev)
if(TARGET OpenMP::OpenMP_CXX)
  set(HAPTREE_WITH_OPENMP 1)
else()
  set(HAPTREE_WITH_OPENMP 0)
endif()
configure_package_config_file(${PROJECT_SOURCE_DIR}/cmake/haptreeConfig.cmake.in
  ${PROJECT_BINARY_DIR}/haptreeConfig.cmake INSTALL_DESTINATION ${HAPTREE_CMAKE_DIR}
  PATH_VARS CMAKE_INSTALL_INCLUDEDIR HAPTREE_DATA_ROOT)
write_basic_package_version_file(${PROJECT_BINARY_DIR}/haptreeConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/haptreeConfig.cmake ${PROJECT_BINARY_DIR}/haptreeConfigVersion.cmake
        DESTINATION ${HAPTREE_CMAKE_DIR} COMPONENT dev)

# pkg-config: one haptree.pc for all the libraries (shared by default; --static adds what the static
# archives need). The Eigen ABI definitions travel in Cflags like in the CMake targets.
list(TRANSFORM HAPTREE_EIGEN_ABI_DEFINITIONS PREPEND "-D" OUTPUT_VARIABLE pc_defs)
string(JOIN " " HAPTREE_PC_DEFINITIONS ${pc_defs})
# Relocatable: the prefix is found from the .pc file's own place (cmake --install --prefix may differ
# from CMAKE_INSTALL_PREFIX).
file(RELATIVE_PATH HAPTREE_PC_UP /p/${CMAKE_INSTALL_LIBDIR}/pkgconfig /p)
configure_file(${PROJECT_SOURCE_DIR}/cmake/haptree.pc.in ${PROJECT_BINARY_DIR}/haptree.pc @ONLY)
install(FILES ${PROJECT_BINARY_DIR}/haptree.pc DESTINATION ${CMAKE_INSTALL_LIBDIR}/pkgconfig COMPONENT dev)

# systemd: sim_server@, coupler@, device_bridge@ (instance NAME: the session file /etc/haptree/NAME.toml,
# optional settings in /etc/haptree/<program>-NAME.conf), the haptree user (sysusers.d), an example
# settings file and an example session. Written at install time so that ExecStart names the prefix
# actually installed into (cmake --install --prefix, or /usr in the .deb).
set(HAPTREE_SYSCONF_DIR /etc/haptree CACHE STRING "Where the services read their session and settings files")
foreach(unit sim_server coupler device_bridge)
  install(CODE "
    set(PROGRAM ${unit})
    set(SYSCONF ${HAPTREE_SYSCONF_DIR})
    set(BINDIR \"\${CMAKE_INSTALL_PREFIX}/${CMAKE_INSTALL_BINDIR}\")
    set(DATADIR \"\${CMAKE_INSTALL_PREFIX}/${HAPTREE_DATA_ROOT}\")
    configure_file(\"${PROJECT_SOURCE_DIR}/packaging/systemd/haptree-process@.service.in\"
                   \"\$ENV{DESTDIR}\${CMAKE_INSTALL_PREFIX}/lib/systemd/system/${unit}@.service\" @ONLY)
    message(STATUS \"Installing: \$ENV{DESTDIR}\${CMAKE_INSTALL_PREFIX}/lib/systemd/system/${unit}@.service\")"
    COMPONENT runtime)
endforeach()
install(FILES ${PROJECT_SOURCE_DIR}/packaging/systemd/haptree.sysusers DESTINATION lib/sysusers.d
        RENAME haptree.conf COMPONENT runtime)
set(SYSCONF ${HAPTREE_SYSCONF_DIR})
configure_file(${PROJECT_SOURCE_DIR}/packaging/systemd/example.conf ${PROJECT_BINARY_DIR}/systemd/example.conf @ONLY)
install(FILES ${PROJECT_BINARY_DIR}/systemd/example.conf DESTINATION ${HAPTREE_DATA_ROOT}/systemd
        COMPONENT runtime)
install(FILES ${PROJECT_SOURCE_DIR}/examples/sessions/two_hosts.toml DESTINATION ${HAPTREE_DATA_ROOT}/examples/sessions
        COMPONENT runtime)

# Man pages from each program's --help (Debian's help2man), gzipped as Debian installs them.
find_program(HAPTREE_HELP2MAN help2man)
if(HAPTREE_PACKAGE AND HAPTREE_HELP2MAN)
  set(man_pages)
  foreach(p ${installed_programs})
    get_target_property(out ${p} OUTPUT_NAME)
    if(NOT out)
      set(out ${p})
    endif()
    set(man ${PROJECT_BINARY_DIR}/man/${out}.1)
    add_custom_command(OUTPUT ${man}.gz
      COMMAND ${CMAKE_COMMAND} -E make_directory ${PROJECT_BINARY_DIR}/man
      COMMAND ${HAPTREE_HELP2MAN} --no-info --no-discard-stderr --version-string=${PROJECT_VERSION}
              --name=${out} --output=${man} $<TARGET_FILE:${p}>
      COMMAND gzip -9nf ${man}
      DEPENDS ${p} VERBATIM COMMENT "help2man: ${out}.1")
    list(APPEND man_pages ${man}.gz)
  endforeach()
  add_custom_target(haptree_man ALL DEPENDS ${man_pages})
  install(FILES ${man_pages} DESTINATION ${CMAKE_INSTALL_MANDIR}/man1 COMPONENT runtime)
else()
  message(STATUS "man pages: not generated (needs -DHAPTREE_PACKAGE=ON and help2man)")
endif()

# Debian packages: `cpack -G DEB` in the build directory (run after the build) writes
# haptree_<v>_<arch>.deb (runtime), haptree-dev_... (headers, static libs, CMake package, haptree.pc)
# and python3-haptree_... (the module). Depends: dpkg-shlibdeps for what the binaries link, plus the
# ones it cannot see. Java (lcm-spy) is only suggested.
set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME haptree)
set(CPACK_PACKAGE_VENDOR haptree)
set(CPACK_PACKAGE_CONTACT "haptree maintainers <haptree@localhost>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY "haptic interaction with adaptive articulated-body simulation")
set(CPACK_PACKAGE_VERSION ${PROJECT_VERSION})
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_RESOURCE_FILE_LICENSE ${PROJECT_SOURCE_DIR}/LICENSE)
set(CPACK_DEB_COMPONENT_INSTALL ON)
set(CPACK_COMPONENTS_ALL runtime dev python)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_SECTION science)
set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
set(CPACK_DEBIAN_RUNTIME_PACKAGE_NAME haptree)
set(CPACK_DEBIAN_RUNTIME_DESCRIPTION "haptic interaction with adaptive articulated-body simulation
 sim_server, coupler and device_bridge (with systemd unit templates), the haptree_run launcher, the web
 viewer, the IMD bridge and the session tools; shared libraries, molecules and force-field tables.")
set(CPACK_DEBIAN_RUNTIME_PACKAGE_DEPENDS "adduser")
set(CPACK_DEBIAN_RUNTIME_PACKAGE_RECOMMENDS "liblcm-bin")
set(CPACK_DEBIAN_RUNTIME_PACKAGE_SUGGESTS "liblcm-java, default-jre-headless")
set(CPACK_DEBIAN_RUNTIME_PACKAGE_CONTROL_EXTRA ${PROJECT_SOURCE_DIR}/packaging/postinst)
set(CPACK_DEBIAN_DEV_PACKAGE_NAME haptree-dev)
set(CPACK_DEBIAN_DEV_PACKAGE_SECTION libdevel)
set(CPACK_DEBIAN_DEV_DESCRIPTION "haptree development files
 Headers, static libraries, the CMake package (find_package(haptree)) and haptree.pc.")
set(CPACK_DEBIAN_DEV_PACKAGE_DEPENDS
    "haptree (= ${PROJECT_VERSION}), libeigen3-dev, liblcm-dev, libglib2.0-dev, nlohmann-json3-dev, liburdfdom-dev, libsodium-dev, libspdlog-dev, libcli11-dev, pkg-config")
set(CPACK_DEBIAN_PYTHON_PACKAGE_NAME python3-haptree)
set(PYTHON_PACKAGE_DIR ${CPACK_PACKAGING_INSTALL_PREFIX}/${HAPTREE_PYTHON_INSTALL_DIR}/haptree)
configure_file(${PROJECT_SOURCE_DIR}/packaging/python-prerm ${PROJECT_BINARY_DIR}/packaging/python/prerm @ONLY)
set(CPACK_DEBIAN_PYTHON_PACKAGE_CONTROL_EXTRA ${PROJECT_BINARY_DIR}/packaging/python/prerm)
set(CPACK_DEBIAN_PYTHON_PACKAGE_SECTION python)
set(CPACK_DEBIAN_PYTHON_DESCRIPTION "haptree Python module
 Models, dynamics, molecules and the LCM log reader from Python (import haptree).")
# The extension is built for one Python minor version (its ABI tag): the package says which.
if(Python3_EXECUTABLE)
  execute_process(COMMAND ${Python3_EXECUTABLE} -c "import sys; print('%d.%d %d.%d' % (sys.version_info[0], sys.version_info[1], sys.version_info[0], sys.version_info[1] + 1))"
                  OUTPUT_VARIABLE py_versions OUTPUT_STRIP_TRAILING_WHITESPACE)
endif()
if(py_versions MATCHES "^([0-9.]+) ([0-9.]+)$")
  set(CPACK_DEBIAN_PYTHON_PACKAGE_DEPENDS
      "python3 (>= ${CMAKE_MATCH_1}), python3 (<< ${CMAKE_MATCH_2}), python3-numpy, haptree (= ${PROJECT_VERSION})")
else()
  set(CPACK_DEBIAN_PYTHON_PACKAGE_DEPENDS "python3, python3-numpy, haptree (= ${PROJECT_VERSION})")
endif()
include(CPack)

if(HAPTREE_BUILD_TESTS AND HAPTREE_PACKAGE)
  # Install into a temporary prefix, build examples/consumer against it (-O2, no -march), run the
  # installed launcher with the source tree hidden, build and check the .debs (scripts/test_install.sh).
  add_test(NAME install_package COMMAND bash ${PROJECT_SOURCE_DIR}/scripts/test_install.sh ${PROJECT_BINARY_DIR})
  set_tests_properties(install_package PROPERTIES LABELS install TIMEOUT 900)
endif()
