# placedb_discover_tests(<target> LABELS <label> [FIXTURES <fixture>...]
#                        [WORKING_DIRECTORY <dir>])
#
# gtest_discover_tests() with a label and any number of required fixtures. Its PROPERTIES
# argument flattens list values (FIXTURES_REQUIRED "a;b" would become extra property names and
# silently lose the fixtures and the label), so the fixtures are set on the discovered tests by an
# include file that ctest reads after the discovery's own.
include(GoogleTest)

function(placedb_discover_tests target)
  cmake_parse_arguments(ARG "" "LABELS;WORKING_DIRECTORY" "FIXTURES" ${ARGN})
  if(NOT ARG_WORKING_DIRECTORY)
    set(ARG_WORKING_DIRECTORY ${CMAKE_CURRENT_BINARY_DIR})
  endif()
  gtest_discover_tests(${target} PROPERTIES LABELS ${ARG_LABELS} DISCOVERY_TIMEOUT 60
    WORKING_DIRECTORY ${ARG_WORKING_DIRECTORY})
  if(ARG_FIXTURES)
    set(include_file ${CMAKE_CURRENT_BINARY_DIR}/${target}_fixtures.cmake)
    file(WRITE ${include_file}
      "if(${target}_TESTS)\n"
      "  set_tests_properties(\${${target}_TESTS} PROPERTIES FIXTURES_REQUIRED \"${ARG_FIXTURES}\")\n"
      "endif()\n")
    set_property(DIRECTORY APPEND PROPERTY TEST_INCLUDE_FILES ${include_file})
  endif()
endfunction()

# placedb_add_test(<name> LABEL <label> [CONCURRENCY] LIBS <target>... [SOURCES <file>...]
#                  [FIXTURES <fixture>...] [DEFINITIONS <definition>...] [DIRECTORY <dir>])
#
# The one way a test is registered (tests/CMakeLists.txt holds every call): a GoogleTest binary
# from SOURCES (default <name>.cc), linked to LIBS, discovered with LABEL and FIXTURES. DIRECTORY
# (relative to the current binary directory) is where the binary is built and run, for tests
# whose paths are documented there (tests/cluster: build/tests/cluster/<name>). Unit tests
# join the target `placedb_unit_tests` (built by the ASan+UBSan stage of tools/test.sh);
# CONCURRENCY marks binaries with concurrency cases (test names containing "Concurren"), which
# join `placedb_concurrency_tests` (built and run by the ThreadSanitizer stage).
function(placedb_add_test name)
  cmake_parse_arguments(ARG "CONCURRENCY" "LABEL;DIRECTORY" "SOURCES;LIBS;FIXTURES;DEFINITIONS"
    ${ARGN})
  if(NOT ARG_SOURCES)
    set(ARG_SOURCES ${name}.cc)
  endif()
  add_executable(${name} ${ARG_SOURCES})
  target_link_libraries(${name} PRIVATE ${ARG_LIBS} GTest::gtest_main)
  if(ARG_DEFINITIONS)
    target_compile_definitions(${name} PRIVATE ${ARG_DEFINITIONS})
  endif()
  set(directory ${CMAKE_CURRENT_BINARY_DIR})
  if(ARG_DIRECTORY)
    set(directory ${CMAKE_CURRENT_BINARY_DIR}/${ARG_DIRECTORY})
    set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${directory})
  endif()
  placedb_discover_tests(${name} LABELS ${ARG_LABEL} FIXTURES ${ARG_FIXTURES}
    WORKING_DIRECTORY ${directory})
  if(ARG_LABEL STREQUAL "unit")
    add_dependencies(placedb_unit_tests ${name})
  endif()
  if(ARG_CONCURRENCY)
    add_dependencies(placedb_concurrency_tests ${name})
  endif()
endfunction()
