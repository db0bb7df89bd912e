# Project-wide compile settings and the one helper per target pattern.

# Warnings and optimisation applied to every kinfly target (never globally, so that
# third-party code pulled in by find_package keeps its own flags).
function(kinfly_target_defaults target)
  target_compile_options(${target} PRIVATE -Wall -Wextra -Wpedantic -Wshadow -Wconversion
                                           -Wno-sign-conversion)
  # Release keeps IEEE semantics (the pipeline relies on isfinite checks), but drops errno
  # bookkeeping from sqrt and lets the vectoriser reassociate nothing it should not.
  target_compile_options(${target} PRIVATE $<$<CONFIG:Release>:-O3 -fno-math-errno>)
  # GCC fuses a*b+c into one FMA wherever the target has it (always on aarch64, never on baseline
  # x86-64), and where it fuses depends on the shape of the loop: the four-lane kernels would
  # then differ from their per-pixel definitions, and the drone's trajectory from the laptop's.
  target_compile_options(${target} PRIVATE -ffp-contract=off)
  if(KINFLY_SANITIZE)
    # -g1 (line tables) after the build type's -g: the sanitizers' reports keep their files and
    # lines, and full debug information of Eigen's unrolled fixed-size code under ASan and UBSan
    # had made this build 15 of a CI run's 64 minutes (riccati.cpp alone: 86 s, 59 s with -g1).
    target_compile_options(${target} PRIVATE -fsanitize=address,undefined -fno-omit-frame-pointer
                                             -fno-sanitize-recover=undefined -g1)
    target_link_options(${target} PRIVATE -fsanitize=address,undefined)
  endif()
  # Coverage feedback for libFuzzer in every library a fuzz target links; the target itself adds
  # -fsanitize=fuzzer, which brings libFuzzer's main.
  if(KINFLY_FUZZ)
    target_compile_options(${target} PRIVATE -fsanitize=fuzzer-no-link)
  endif()
endfunction()

# kinfly_add_test(NAME name SOURCES a.cpp ... [LIBS lib ...])
# One GoogleTest executable, registered test-by-test with CTest.
function(kinfly_add_test)
  cmake_parse_arguments(ARG "" "NAME" "SOURCES;LIBS" ${ARGN})
  add_executable(${ARG_NAME} ${ARG_SOURCES})
  kinfly_target_defaults(${ARG_NAME})
  target_link_libraries(${ARG_NAME} PRIVATE ${ARG_LIBS} GTest::gtest GTest::gtest_main)
  set_target_properties(${ARG_NAME} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR}/tests)
  add_dependencies(kinfly-unit-tests ${ARG_NAME})
  gtest_discover_tests(${ARG_NAME} DISCOVERY_TIMEOUT 60
                       PROPERTIES ENVIRONMENT "OMP_NUM_THREADS=2")
endfunction()

# kinfly_add_library(NAME name SOURCES a.cpp ... [PUBLIC dep ...] [PRIVATE dep ...])
# A kinfly library (shared/'s, the link): static kinfly_<name>, used as kinfly::<name>, headers
# in the calling folder's include/. Position-independent, because shared objects link them too
# (the ground package's Python module, the OpenNI2 test driver). -fno-semantic-interposition: nothing ever
# interposes these functions, and without it -fPIC would stop GCC inlining a library's own
# functions into its loops.
function(kinfly_add_library)
  cmake_parse_arguments(ARG "" "NAME" "SOURCES;PUBLIC;PRIVATE" ${ARGN})
  set(target kinfly_${ARG_NAME})
  add_library(${target} STATIC ${ARG_SOURCES})
  add_library(kinfly::${ARG_NAME} ALIAS ${target})
  set_target_properties(${target} PROPERTIES POSITION_INDEPENDENT_CODE ON)
  target_compile_options(${target} PRIVATE -fno-semantic-interposition)
  target_include_directories(${target} PUBLIC ${CMAKE_CURRENT_SOURCE_DIR}/include)
  target_link_libraries(${target} PUBLIC ${ARG_PUBLIC} PRIVATE ${ARG_PRIVATE})
  kinfly_target_defaults(${target})
endfunction()
