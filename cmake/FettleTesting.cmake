# fettle_add_test(NAME name SOURCES ... LIBS ... [LABELS unit|integration|slow|concurrency ...]
#                 [RESOURCE_LOCK lock] [TIMEOUT seconds] [ENVIRONMENT ...])
# One GoogleTest executable, its tests discovered into CTest with labels.
# Tests find their data through FETTLE_TEST_DATA_DIR and built programs through
# FETTLE_BIN_DIR; they never read ../shared.
function(fettle_add_test)
  cmake_parse_arguments(ARG "" "NAME;TIMEOUT;RESOURCE_LOCK" "SOURCES;LIBS;LABELS;ENVIRONMENT;DEPENDS" ${ARGN})
  if(NOT ARG_LABELS)
    set(ARG_LABELS unit)
  endif()
  if(NOT ARG_TIMEOUT)
    set(ARG_TIMEOUT 120)
  endif()
  add_executable(${ARG_NAME} ${ARG_SOURCES})
  target_link_libraries(${ARG_NAME} PRIVATE fettle::options GTest::gtest GTest::gmock GTest::gtest_main ${ARG_LIBS})
  target_compile_definitions(${ARG_NAME} PRIVATE
    FETTLE_TEST_DATA_DIR="${PROJECT_SOURCE_DIR}/tests/data"
    FETTLE_SOURCE_DIR="${PROJECT_SOURCE_DIR}"
    FETTLE_BIN_DIR="${PROJECT_BINARY_DIR}/bin")
  if(ARG_DEPENDS)
    add_dependencies(${ARG_NAME} ${ARG_DEPENDS})
  endif()
  # Under the sanitizers (build-asan, build-tsan) programs run 3-15 times slower.
  if(FETTLE_SANITIZE)
    math(EXPR ARG_TIMEOUT "${ARG_TIMEOUT} * 4")
  endif()
  set(props TIMEOUT ${ARG_TIMEOUT})
  if(ARG_RESOURCE_LOCK)
    list(APPEND props RESOURCE_LOCK ${ARG_RESOURCE_LOCK})
  endif()
  if(ARG_ENVIRONMENT)
    list(APPEND props ENVIRONMENT "${ARG_ENVIRONMENT}")
  endif()
  gtest_discover_tests(${ARG_NAME} DISCOVERY_TIMEOUT 60 PROPERTIES ${props})
  # The labels are set after discovery, from the list of discovered tests: passed through
  # PROPERTIES, two labels ("integration;slow") are flattened into the property list and pair
  # up wrongly, so TIMEOUT and RESOURCE_LOCK were lost (CMake 3.25's GoogleTestAddTests).
  set(labels_file "${CMAKE_CURRENT_BINARY_DIR}/${ARG_NAME}_labels.cmake")
  file(WRITE "${labels_file}"
       "if(${ARG_NAME}_TESTS)\n  set_tests_properties(\${${ARG_NAME}_TESTS} PROPERTIES LABELS \"${ARG_LABELS}\")\nendif()\n")
  set_property(DIRECTORY APPEND PROPERTY TEST_INCLUDE_FILES "${labels_file}")
endfunction()
