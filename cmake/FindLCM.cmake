# Finds the LCM C library and the lcm-gen code generator (Debian: liblcm-dev, liblcm-bin).
# Debian's lcm.pc requires glib's development files only to describe LCM's private dependencies,
# so the library is found directly instead of through pkg-config.
#
# Defines LCM::lcm (imported library) and LCM_GEN_EXECUTABLE (a program of the build host, also
# when cross-compiling).
find_path(LCM_INCLUDE_DIR lcm/lcm-cpp.hpp)
find_library(LCM_LIBRARY lcm)
find_program(LCM_GEN_EXECUTABLE lcm-gen NO_CMAKE_FIND_ROOT_PATH)

include(FindPackageHandleStandardArgs)
find_package_handle_standard_args(LCM REQUIRED_VARS LCM_LIBRARY LCM_INCLUDE_DIR LCM_GEN_EXECUTABLE)

if(LCM_FOUND AND NOT TARGET LCM::lcm)
  add_library(LCM::lcm UNKNOWN IMPORTED)
  set_target_properties(LCM::lcm PROPERTIES
    IMPORTED_LOCATION ${LCM_LIBRARY}
    INTERFACE_INCLUDE_DIRECTORIES ${LCM_INCLUDE_DIR})
endif()
mark_as_advanced(LCM_INCLUDE_DIR LCM_LIBRARY LCM_GEN_EXECUTABLE)
