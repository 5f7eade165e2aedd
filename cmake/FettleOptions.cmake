# Compile options shared by every Fettle target, as interface targets: no global flags.

# fettle::options - language level, warnings and sanitizers.
add_library(fettle_options INTERFACE)
add_library(fettle::options ALIAS fettle_options)
target_compile_features(fettle_options INTERFACE cxx_std_20)

target_compile_options(fettle_options INTERFACE
  $<$<COMPILE_LANGUAGE:CXX>:-Wall -Wextra -Wpedantic -Wshadow -Wnon-virtual-dtor -Wold-style-cast
                             -Wcast-align -Woverloaded-virtual -Wformat=2>)
if(FETTLE_WERROR)
  target_compile_options(fettle_options INTERFACE $<$<COMPILE_LANGUAGE:CXX>:-Werror>)
endif()
# Boost 1.74's Asio enables co_await under clang only with libc++'s <experimental/coroutine>;
# Debian's clang uses libstdc++ 12, whose <coroutine> works with it (the sanitizer and fuzz builds).
if(CMAKE_CXX_COMPILER_ID STREQUAL "Clang")
  target_compile_definitions(fettle_options INTERFACE BOOST_ASIO_HAS_CO_AWAIT=1)
endif()

# FETTLE_FUZZ: every Fettle target gets libFuzzer's coverage instrumentation (clang only) and,
# unless FETTLE_SANITIZE says otherwise, ASan + UBSan; the fuzzers in tests/fuzz link -fsanitize=fuzzer.
if(FETTLE_FUZZ)
  if(NOT CMAKE_CXX_COMPILER_ID STREQUAL "Clang")
    message(FATAL_ERROR "FETTLE_FUZZ=ON needs clang (libFuzzer): configure a separate build dir with "
                        "-DCMAKE_C_COMPILER=clang -DCMAKE_CXX_COMPILER=clang++ (see docs/development.md)")
  endif()
  if(NOT FETTLE_SANITIZE)
    set(FETTLE_SANITIZE address,undefined)
  endif()
  target_compile_options(fettle_options INTERFACE -fsanitize=fuzzer-no-link)
endif()

if(FETTLE_SANITIZE)
  if(NOT FETTLE_SANITIZE MATCHES "^(address|undefined|address,undefined|undefined,address|thread)$")
    message(FATAL_ERROR "FETTLE_SANITIZE='${FETTLE_SANITIZE}': use address,undefined or thread")
  endif()
  target_compile_options(fettle_options INTERFACE -fsanitize=${FETTLE_SANITIZE} -fno-omit-frame-pointer -fno-sanitize-recover=all)
  target_link_options(fettle_options INTERFACE -fsanitize=${FETTLE_SANITIZE})
  # GCC 12 with -fsanitize=address reports Boost.Asio's coroutine frames (awaitable_frame_base's
  # operator new / sized operator delete) as -Wmismatched-new-delete: a known false positive
  # (gcc PR middle-end/109224), so that one warning is off in sanitizer builds only.
  if(CMAKE_CXX_COMPILER_ID STREQUAL "GNU")
    target_compile_options(fettle_options INTERFACE $<$<COMPILE_LANGUAGE:CXX>:-Wno-mismatched-new-delete>)
  endif()
  # clang 14's UBSan check of indirect call types (-fsanitize=function) cannot compile C++20
  # coroutines ("Cannot represent a difference across sections"): that one check is off.
  if(CMAKE_CXX_COMPILER_ID STREQUAL "Clang" AND FETTLE_SANITIZE MATCHES "undefined")
    target_compile_options(fettle_options INTERFACE -fno-sanitize=function)
    # UBSan's checks are left out of Eigen's, PCL's and FLANN's headers (third-party code, as
    # their compiled libraries are): in Eigen they stop inlining and made tests 100x slower.
    # ASan still instruments that code. The list and the measurements: tests/sanitizers/ubsan-ignore.txt
    # Spelled -fsanitize-blacklist (clang 14's alias of -fsanitize-ignorelist): ccache 4.7 hashes
    # the list's contents only under that name, so an edited list would otherwise reuse old objects.
    target_compile_options(fettle_options INTERFACE
                           -fsanitize-blacklist=${PROJECT_SOURCE_DIR}/tests/sanitizers/ubsan-ignore.txt)
  endif()
  # Code that must know it runs under ThreadSanitizer (vision/src/registration.cpp: PCL's
  # OpenMP estimators on one thread) tests FETTLE_TSAN.
  if(FETTLE_SANITIZE STREQUAL "thread")
    target_compile_definitions(fettle_options INTERFACE FETTLE_TSAN=1)
  endif()
endif()

# Third-party headers are included as SYSTEM so their warnings do not drown ours.
# (Never -march=native: Debian's PCL is built without it and misaligned Eigen types crash.)

# fettle_library(NAME name SOURCES ... PUBLIC_LIBS ... PRIVATE_LIBS ...)
# One library per top-level folder, with the alias fettle::<name> and include/ as its public headers.
function(fettle_library)
  cmake_parse_arguments(ARG "" "NAME" "SOURCES;PUBLIC_LIBS;PRIVATE_LIBS" ${ARGN})
  if(ARG_SOURCES)
    add_library(fettle_${ARG_NAME} STATIC ${ARG_SOURCES})
    target_include_directories(fettle_${ARG_NAME} PUBLIC $<BUILD_INTERFACE:${CMAKE_CURRENT_SOURCE_DIR}/include>)
    target_link_libraries(fettle_${ARG_NAME} PUBLIC fettle::options ${ARG_PUBLIC_LIBS} PRIVATE ${ARG_PRIVATE_LIBS})
    set_target_properties(fettle_${ARG_NAME} PROPERTIES POSITION_INDEPENDENT_CODE ON)
  else()
    add_library(fettle_${ARG_NAME} INTERFACE)
    target_include_directories(fettle_${ARG_NAME} INTERFACE $<BUILD_INTERFACE:${CMAKE_CURRENT_SOURCE_DIR}/include>)
    target_link_libraries(fettle_${ARG_NAME} INTERFACE fettle::options ${ARG_PUBLIC_LIBS})
  endif()
  add_library(fettle::${ARG_NAME} ALIAS fettle_${ARG_NAME})
endfunction()
