# placedb_module_closure(<property prefix> <what> <name> <out var> <dependency>...)
# A module's transitive dependencies (itself included) into <out var>, recorded under
# <prefix>_<name> for the modules declared after it; a dependency not declared yet is an error
# naming <what>.
function(placedb_module_closure prefix what name out)
  set(closure ${name})
  foreach(dep IN LISTS ARGN)
    get_property(declared GLOBAL PROPERTY ${prefix}_${dep} SET)
    if(NOT declared)
      message(FATAL_ERROR "${what}: depends on '${dep}', which is not declared before it")
    endif()
    get_property(dep_closure GLOBAL PROPERTY ${prefix}_${dep})
    list(APPEND closure ${dep_closure})
  endforeach()
  list(REMOVE_DUPLICATES closure)
  set_property(GLOBAL PROPERTY ${prefix}_${name} ${closure})
  set(${out} ${closure} PARENT_SCOPE)
endfunction()

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

  placedb_module_closure(PLACEDB_MODULE_CLOSURE "core/${name}" ${name} closure ${ARG_DEPENDS})
  foreach(dep IN LISTS ARG_DEPENDS)
    target_link_libraries(placedb_${name} PUBLIC placedb_${dep})
  endforeach()
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

# placedb_server_module(<name> [DIR <folder of server/>] [FILES <file>...] SOURCES <file>...
#                       [DEPENDS <module>...] [PUBLIC_LIBS <target>...] [PRIVATE_LIBS <target>...])
#
# The same for server/: the library placedb_<name> (a folder of server/ named by DIR, or the
# files of server/ itself named by FILES), linked to the server modules it DEPENDS on. At configure
# time every `#include "server/<folder>/..."` and `#include "server/<file>.h"` of its files is
# checked against its dependencies (transitively): the handlers never reach into cluster/, the
# backend never into the handlers. A top-level header belongs to the module that lists it in
# FILES. A folder that declares several libraries itself (server/cluster/) is checked as one with
# placedb_server_folder_check.
function(placedb_server_module name)
  cmake_parse_arguments(ARG "" "DIR" "FILES;SOURCES;DEPENDS;PUBLIC_LIBS;PRIVATE_LIBS" ${ARGN})
  add_library(placedb_${name} ${ARG_SOURCES})
  target_include_directories(placedb_${name} PUBLIC ${PROJECT_SOURCE_DIR})
  foreach(dep IN LISTS ARG_DEPENDS)
    target_link_libraries(placedb_${name} PUBLIC placedb_${dep})
  endforeach()
  target_link_libraries(placedb_${name} PUBLIC ${ARG_PUBLIC_LIBS} PRIVATE ${ARG_PRIVATE_LIBS})
  placedb_server_folder_check(${name} DIR "${ARG_DIR}" FILES ${ARG_FILES} DEPENDS ${ARG_DEPENDS})
endfunction()

# placedb_server_folder_check(<name> [DIR <folder of server/>] [FILES <file>...]
#                             [DEPENDS <module>...])
# The include check alone, for a module whose libraries are declared by hand.
function(placedb_server_folder_check name)
  cmake_parse_arguments(ARG "" "DIR" "FILES;DEPENDS" ${ARGN})
  placedb_module_closure(PLACEDB_SERVER_MODULE_CLOSURE "server module ${name}" ${name} closure
                         ${ARG_DEPENDS})

  set(server_dir ${PROJECT_SOURCE_DIR}/server)
  if(ARG_DIR)
    set_property(GLOBAL PROPERTY PLACEDB_SERVER_FOLDER_${ARG_DIR} ${name})
    file(GLOB files CONFIGURE_DEPENDS ${server_dir}/${ARG_DIR}/*.h ${server_dir}/${ARG_DIR}/*.cc)
  else()
    set(files)
    foreach(file IN LISTS ARG_FILES)
      list(APPEND files ${server_dir}/${file})
      get_filename_component(stem ${file} NAME_WE)
      set_property(GLOBAL PROPERTY PLACEDB_SERVER_TOP_${stem} ${name})
    endforeach()
  endif()
  foreach(file IN LISTS files)
    file(STRINGS ${file} includes REGEX "^#include \"server/")
    foreach(line IN LISTS includes)
      if(line MATCHES "^#include \"server/([a-z_]+)/")
        get_property(owner GLOBAL PROPERTY PLACEDB_SERVER_FOLDER_${CMAKE_MATCH_1})
        set(what "server/${CMAKE_MATCH_1}/")
      elseif(line MATCHES "^#include \"server/([a-z_]+)\\.h\"")
        get_property(owner GLOBAL PROPERTY PLACEDB_SERVER_TOP_${CMAKE_MATCH_1})
        set(what "server/${CMAKE_MATCH_1}.h")
      else()
        continue()
      endif()
      if(NOT owner OR NOT owner IN_LIST closure)
        file(RELATIVE_PATH rel ${PROJECT_SOURCE_DIR} ${file})
        message(FATAL_ERROR "${rel} includes ${what}, which server module ${name} does not depend "
                            "on (it depends on: ${closure}); see docs/architecture.md")
      endif()
    endforeach()
  endforeach()
endfunction()
