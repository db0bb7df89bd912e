# Toolchain file: aarch64 Linux with Debian's cross compiler (g++-aarch64-linux-gnu) against a
# Debian arm64 sysroot (scripts/aarch64-sysroot.sh makes one; `make firmware-aarch64` passes it).
#
#   cmake -S . -B build-aarch64/build -DCMAKE_TOOLCHAIN_FILE=cmake/aarch64-linux-gnu.cmake \
#         -DKINFLY_SYSROOT=/path/to/sysroot
#
# The sysroot comes in as KINFLY_SYSROOT (cache variable or environment), never as a path written
# here. Binaries the build runs (test discovery, ctest) go through qemu-aarch64 with that sysroot
# as its library prefix, so no binfmt_misc registration is needed.
set(CMAKE_SYSTEM_NAME Linux)
set(CMAKE_SYSTEM_PROCESSOR aarch64)

set(CMAKE_C_COMPILER aarch64-linux-gnu-gcc)
set(CMAKE_CXX_COMPILER aarch64-linux-gnu-g++)

if(NOT KINFLY_SYSROOT AND DEFINED ENV{KINFLY_SYSROOT})
  set(KINFLY_SYSROOT $ENV{KINFLY_SYSROOT})
endif()
if(NOT KINFLY_SYSROOT OR NOT EXISTS ${KINFLY_SYSROOT}/usr/include)
  message(FATAL_ERROR "aarch64 toolchain: set KINFLY_SYSROOT to a Debian arm64 sysroot "
                      "(scripts/aarch64-sysroot.sh DIR makes one), got '${KINFLY_SYSROOT}'")
endif()
set(KINFLY_SYSROOT ${KINFLY_SYSROOT} CACHE PATH "Debian arm64 sysroot")
# try_compile projects re-read this file without the cache; this hands the path on to them.
set(ENV{KINFLY_SYSROOT} ${KINFLY_SYSROOT})

set(CMAKE_SYSROOT ${KINFLY_SYSROOT})
set(CMAKE_LIBRARY_ARCHITECTURE aarch64-linux-gnu)
# Headers, libraries and CMake packages from the sysroot only; programs (lcm-gen, pkg-config)
# from the build host.
set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)

# The host's pkg-config reads only the sysroot's .pc files and prefixes what they say with it.
set(ENV{PKG_CONFIG_SYSROOT_DIR} ${KINFLY_SYSROOT})
set(ENV{PKG_CONFIG_LIBDIR}
    "${KINFLY_SYSROOT}/usr/lib/aarch64-linux-gnu/pkgconfig:${KINFLY_SYSROOT}/usr/share/pkgconfig")
set(ENV{PKG_CONFIG_PATH} "")

# The cross compiler links its own copies of libstdc++ and libgomp (same GCC 12 release as the
# sysroot's); at run time the loader under qemu finds the sysroot's, as it will on the board.
find_program(KINFLY_QEMU_AARCH64 qemu-aarch64 NO_CMAKE_FIND_ROOT_PATH)
if(KINFLY_QEMU_AARCH64)
  set(CMAKE_CROSSCOMPILING_EMULATOR ${KINFLY_QEMU_AARCH64} -L ${KINFLY_SYSROOT})
endif()
