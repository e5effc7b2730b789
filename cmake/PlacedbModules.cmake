# placedb_core_module(<name> SOURCES <file>... [DEPENDS <module>...] [LIBS <target>...])
#
# Declares core/<name>/ as the library placedb_<name>, linked to the modules it DEPENDS on and
# to LIBS (third-party targets, PRIVATE when listed after the PRIVATE keyword). Modules are
# declared bottom-up, so a module can only depend on the ones declared before it; at configure
# time every `#include "core/<module>/..."` in the folder is checked against its dependencies
# (transitively), so a header that reaches into a layer above fails the build, not a review.
function(placedb_core_module name)
  cmake_parse_arguments(ARG "" "" "SOURCES;DEPENDS;LIBS" ${ARGN})
  add_library(placedb_${name} ${ARG_SOURCES})
  target_include_directories(placedb_${name} PUBLIC ${PROJECT_SOURCE_DIR})

  set(closure ${name})
  foreach(dep IN LISTS ARG_DEPENDS)
    get_property(dep_closure GLOBAL PROPERTY PLACEDB_MODULE_CLOSURE_${dep} SET)
    if(NOT dep_closure)
      message(FATAL_ERROR "core/${name}: depends on '${dep}', which is not declared below it")
    endif()
    get_property(dep_closure GLOBAL PROPERTY PLACEDB_MODULE_CLOSURE_${dep})
    list(APPEND closure ${dep_closure})
    target_link_libraries(placedb_${name} PUBLIC placedb_${dep})
  endforeach()
  list(REMOVE_DUPLICATES closure)
  set_property(GLOBAL PROPERTY PLACEDB_MODULE_CLOSURE_${name} ${closure})
  if(ARG_LIBS)
    target_link_libraries(placedb_${name} PUBLIC ${ARG_LIBS})
  endif()

  file(GLOB files CONFIGURE_DEPENDS ${CMAKE_CURRENT_SOURCE_DIR}/*.h ${CMAKE_CURRENT_SOURCE_DIR}/*.cc)
  foreach(file IN LISTS files)
    file(STRINGS ${file} includes REGEX "^#include \"core/[a-z_]+/")
    foreach(line IN LISTS includes)
      string(REGEX REPLACE "^#include \"core/([a-z_]+)/.*" "\\1" used "${line}")
      if(NOT used IN_LIST closure)
        file(RELATIVE_PATH rel ${PROJECT_SOURCE_DIR} ${file})
        message(FATAL_ERROR "${rel} includes core/${used}/, which core/${name} does not depend on "
                            "(it depends on: ${closure}); see docs/architecture.md")
      endif()
    endforeach()
  endforeach()
endfunction()
