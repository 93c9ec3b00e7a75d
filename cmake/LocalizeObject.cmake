# cmake -DOBJ=in.o -DOUT=out.o -DSUFFIX=.haptree_avx2 -DKEEP=regex -DNM=nm -DOBJCOPY=objcopy -P LocalizeObject.cmake
#
# Copies an object file compiled for a wider instruction set than the rest of the library, renaming
# every global symbol it defines (name → name${SUFFIX}) except those matching KEEP (its entry
# points). The inline functions of Eigen and of the standard library that it instantiates are weak
# symbols (COMDAT groups, keyed by the same names): without the renaming the linker would keep one
# copy of each for the whole program, possibly this one, and code that runs on any CPU would call
# AVX2 instructions. Renamed, they are this object's own; its calls to functions defined elsewhere
# (undefined here) are left alone.
foreach(v OBJ OUT SUFFIX KEEP NM OBJCOPY)
  if(NOT DEFINED ${v} OR "${${v}}" STREQUAL "")
    message(FATAL_ERROR "LocalizeObject.cmake: -D${v}=... missing")
  endif()
endforeach()
execute_process(COMMAND ${NM} --defined-only -g --format=posix ${OBJ}
                OUTPUT_VARIABLE syms ERROR_VARIABLE err RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "LocalizeObject.cmake: ${NM} ${OBJ} failed (${rc}): ${err}")
endif()
string(REPLACE "\n" ";" lines "${syms}")
set(map "")
set(kept 0)
set(renamed 0)
foreach(line ${lines})
  if(line MATCHES "^([^ ]+) ")
    set(name ${CMAKE_MATCH_1})
    if(name MATCHES "${KEEP}")
      math(EXPR kept "${kept} + 1")
    else()
      string(APPEND map "${name} ${name}${SUFFIX}\n")
      math(EXPR renamed "${renamed} + 1")
    endif()
  endif()
endforeach()
if(kept EQUAL 0)
  message(FATAL_ERROR "LocalizeObject.cmake: no symbol of ${OBJ} matches '${KEEP}' (its entry points)")
endif()
file(WRITE ${OUT}.map "${map}")
execute_process(COMMAND ${OBJCOPY} --redefine-syms=${OUT}.map ${OBJ} ${OUT}
                ERROR_VARIABLE err RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "LocalizeObject.cmake: ${OBJCOPY} failed (${rc}): ${err}")
endif()
