# The helper that turns a library of this tree into an installable one (static + shared, exported as
# haptree::<name>); cmake/HaptreePackage.cmake installs the rest.
include(GNUInstallDirs)

# SONAME: the ABI is not stable within 0.x, so the minor version is part of it (libhaptree.so.0.1).
if(PROJECT_VERSION_MAJOR EQUAL 0)
  set(HAPTREE_SOVERSION ${PROJECT_VERSION_MAJOR}.${PROJECT_VERSION_MINOR})
else()
  set(HAPTREE_SOVERSION ${PROJECT_VERSION_MAJOR})
endif()

# Shared libraries and man pages for the installed package and the .debs (scripts/test.sh turns it on:
# CI installs and packages). Off by default: the programs then link position-dependent libraries.
# With it, each library is compiled once, position-independent, and serves the programs, the static
# archive, the shared library and the Python module alike (docs/install.md: what it costs).
option(HAPTREE_PACKAGE "Build what the installed package adds: shared libraries (PIC) and man pages" OFF)

# haptree_export_library(<target> <name>): <target> (a static library) is installed and exported as
# haptree::<name>_static; with HAPTREE_PACKAGE it is compiled position-independent and gets a shared
# twin <target>_shared built from the same object files (no second compilation), haptree::<name>. Call it at the end of
# the directory that defines <target>, after its target_link_libraries. Its include directories must be
# given as $<BUILD_INTERFACE:...> (the installed ones are <prefix>/include).
function(haptree_export_library target name)
  if(HAPTREE_FUZZ)
    return()   # the sanitizer tree builds fuzz targets only
  endif()
  set_target_properties(${target} PROPERTIES EXPORT_NAME ${name}_static)
  target_compile_features(${target} PUBLIC cxx_std_17)
  target_include_directories(${target} INTERFACE $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>)
  set_property(GLOBAL APPEND PROPERTY HAPTREE_EXPORTED_LIBS ${target})
  install(TARGETS ${target} EXPORT haptreeTargets
          ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR} COMPONENT dev)
  if(NOT HAPTREE_PACKAGE)
    return()
  endif()
  set_target_properties(${target} PROPERTIES POSITION_INDEPENDENT_CODE ON)
  # PIC, but calls inside the library are bound to it (as in the executables' PIE code): same speed.
  target_compile_options(${target} PRIVATE $<$<CXX_COMPILER_ID:GNU,Clang>:-fno-semantic-interposition>)

  # Object files the static library takes from elsewhere (an object library's $<TARGET_OBJECTS:...>)
  # are part of the shared one too.
  get_target_property(srcs ${target} SOURCES)
  set(foreign_objects ${srcs})
  list(FILTER foreign_objects INCLUDE REGEX "^\\$<TARGET_OBJECTS:|\\.o$")   # and prebuilt objects
  add_library(${target}_shared SHARED $<TARGET_OBJECTS:${target}> ${foreign_objects})
  set_target_properties(${target}_shared PROPERTIES OUTPUT_NAME ${target} EXPORT_NAME ${name}
                        VERSION ${PROJECT_VERSION} SOVERSION ${HAPTREE_SOVERSION}
                        INSTALL_RPATH "$ORIGIN")   # its siblings, wherever the prefix is
  foreach(prop INTERFACE_INCLUDE_DIRECTORIES INTERFACE_SYSTEM_INCLUDE_DIRECTORIES
               INTERFACE_COMPILE_DEFINITIONS INTERFACE_COMPILE_FEATURES INTERFACE_COMPILE_OPTIONS)
    get_target_property(v ${target} ${prop})
    if(v)
      set_property(TARGET ${target}_shared PROPERTY ${prop} "${v}")
    endif()
  endforeach()
  # Links: the static library's public ones stay public, its link-only ones become private; a sibling
  # library of this tree is replaced by its shared twin.
  get_target_property(all ${target} LINK_LIBRARIES)
  get_target_property(pub ${target} INTERFACE_LINK_LIBRARIES)
  if(NOT all)
    set(all "")
  endif()
  if(NOT pub)
    set(pub "")
  endif()
  list(FILTER pub EXCLUDE REGEX "^\\$<LINK_ONLY:")
  set(priv ${all})
  if(pub)
    list(REMOVE_ITEM priv ${pub})
  endif()
  get_property(exported GLOBAL PROPERTY HAPTREE_EXPORTED_LIBS)
  foreach(kind pub priv)
    set(mapped "")
    foreach(l ${${kind}})
      if(l IN_LIST exported)
        list(APPEND mapped ${l}_shared)
      else()
        list(APPEND mapped ${l})
      endif()
    endforeach()
    set(${kind} ${mapped})
  endforeach()
  target_link_libraries(${target}_shared PUBLIC ${pub} PRIVATE ${priv})
  install(TARGETS ${target}_shared EXPORT haptreeTargets
          LIBRARY DESTINATION ${CMAKE_INSTALL_LIBDIR} COMPONENT runtime NAMELINK_COMPONENT dev)
endfunction()
