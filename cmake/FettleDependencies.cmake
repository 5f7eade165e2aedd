# Every third-party dependency, found in one place. All of them are Debian 12
# packages installed by scripts/install-deps.
find_package(PkgConfig REQUIRED)
find_package(Threads REQUIRED)

find_package(Eigen3 3.4 REQUIRED NO_MODULE)
find_package(spdlog REQUIRED)
find_package(tomlplusplus REQUIRED)
find_package(nlohmann_json 3.10 REQUIRED)
find_package(CLI11 REQUIRED)
find_package(Boost 1.74 REQUIRED)

pkg_check_modules(libmodbus REQUIRED IMPORTED_TARGET libmodbus)
pkg_check_modules(aravis REQUIRED IMPORTED_TARGET aravis-0.8)
pkg_check_modules(libsystemd REQUIRED IMPORTED_TARGET libsystemd)

# Debian's PCL config pulls VTK, which needs the MPI::MPI_C target.
find_package(MPI REQUIRED COMPONENTS C)
find_package(PCL 1.13 REQUIRED COMPONENTS common io kdtree search filters features registration sample_consensus segmentation)
# PCL exports plain variables; wrap them in one target so nothing edits global flags.
add_library(fettle_pcl INTERFACE)
target_include_directories(fettle_pcl SYSTEM INTERFACE ${PCL_INCLUDE_DIRS})
target_link_libraries(fettle_pcl INTERFACE ${PCL_LIBRARIES})
target_compile_definitions(fettle_pcl INTERFACE ${PCL_DEFINITIONS})
add_library(fettle::pcl ALIAS fettle_pcl)

find_package(OpenCV 4.6 REQUIRED COMPONENTS core imgproc imgcodecs calib3d aruco)

if(FETTLE_BUILD_TESTS)
  find_package(GTest REQUIRED)
  include(GoogleTest)
endif()
if(FETTLE_BUILD_BENCH)
  find_package(benchmark REQUIRED)
endif()
