# fettle_add_test(NAME name SOURCES ... LIBS ... [LABELS unit|integration|slow|concurrency ...]
#                 [NETNS] [RESOURCE_LOCK lock] [TIMEOUT seconds] [ENVIRONMENT ...])
# One GoogleTest executable, its tests discovered into CTest with labels.
# Tests find their data through FETTLE_TEST_DATA_DIR and built programs through
# FETTLE_BIN_DIR; they never read ../shared.
#
# NETNS: the test starts a simulated GigE Vision camera, whose control port is fixed (UDP 3956 on
# 127.0.0.1). Each such test runs in a network namespace of its own (tests/support/netns-run), so
# ctest runs them side by side. Where the kernel allows no user namespaces they share the host's
# loopback and run one at a time instead (RESOURCE_LOCK gige); cmake says which when it configures.
set(FETTLE_NETNS_RUN "${CMAKE_CURRENT_LIST_DIR}/../tests/support/netns-run")
cmake_path(NORMAL_PATH FETTLE_NETNS_RUN)
if(NOT DEFINED FETTLE_TEST_NETNS)
  execute_process(COMMAND "${FETTLE_NETNS_RUN}" true RESULT_VARIABLE netns_rc OUTPUT_QUIET ERROR_VARIABLE netns_err)
  if(netns_rc EQUAL 0)
    set(netns_default ON)
  else()
    set(netns_default OFF)
    string(STRIP "${netns_err}" netns_err)
    message(STATUS "GigE Vision tests run one at a time: no network namespace for them (${netns_err})")
  endif()
  set(FETTLE_TEST_NETNS ${netns_default} CACHE BOOL
      "run each test that starts a GigE Vision camera in its own network namespace (tests/support/netns-run)")
endif()
function(fettle_add_test)
  cmake_parse_arguments(ARG "NETNS" "NAME;TIMEOUT;RESOURCE_LOCK" "SOURCES;LIBS;LABELS;ENVIRONMENT;DEPENDS" ${ARGN})
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
  if(ARG_NETNS AND FETTLE_TEST_NETNS)
    # gtest_discover_tests runs the listing and every test through the target's emulator.
    set_property(TARGET ${ARG_NAME} PROPERTY CROSSCOMPILING_EMULATOR "${FETTLE_NETNS_RUN}")
  elseif(ARG_NETNS)
    list(APPEND props RESOURCE_LOCK gige)
  endif()
  if(ARG_RESOURCE_LOCK)
    list(APPEND props RESOURCE_LOCK ${ARG_RESOURCE_LOCK})
  endif()
  if(ARG_ENVIRONMENT)
    list(APPEND props ENVIRONMENT "${ARG_ENVIRONMENT}")
  endif()
  gtest_discover_tests(${ARG_NAME} DISCOVERY_TIMEOUT 60 PROPERTIES ${props})
  # The labels are set after discovery, from the list of discovered tests: passed through
  # PROPERTIES, two labels ("integration;slow") are flattened into the property list and pair
  # up wrongly, and TIMEOUT and RESOURCE_LOCK get lost (CMake 3.25's GoogleTestAddTests).
  set(labels_file "${CMAKE_CURRENT_BINARY_DIR}/${ARG_NAME}_labels.cmake")
  file(WRITE "${labels_file}"
       "if(${ARG_NAME}_TESTS)\n  set_tests_properties(\${${ARG_NAME}_TESTS} PROPERTIES LABELS \"${ARG_LABELS}\")\nendif()\n")
  set_property(DIRECTORY APPEND PROPERTY TEST_INCLUDE_FILES "${labels_file}")
endfunction()
