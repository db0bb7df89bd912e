# What the kinfly-fw Debian package holds, and how CPack builds it (`cpack -G DEB` in a build
# tree; `make package-aarch64` for the drone). Install rules for the package's files live here,
# in one place, rather than beside each target.
#
#   /usr/bin/kinfly-fw, /usr/bin/kinfly-keygen
#   /etc/kinfly/kinfly-fw.toml                      conffile (a drone's edits survive upgrades)
#   /lib/systemd/system/kinfly-fw.service           enabled by the postinst
#   /usr/lib/sysusers.d/kinfly-fw.conf              the service user `kinfly`
#   /usr/share/doc/kinfly-fw/                       README.md, aarch64.md
include(GNUInstallDirs)

install(TARGETS kinfly-fw kinfly-keygen RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR})
install(FILES ${PROJECT_SOURCE_DIR}/firmware/config/kinfly-fw.toml DESTINATION /etc/kinfly)
# Debian 12 packages ship units under /lib, not /usr/lib (dpkg does not know the two are one).
install(FILES ${PROJECT_SOURCE_DIR}/firmware/systemd/kinfly-fw.service
        DESTINATION /lib/systemd/system)
install(FILES ${PROJECT_SOURCE_DIR}/firmware/systemd/kinfly-fw.sysusers
        DESTINATION lib/sysusers.d RENAME kinfly-fw.conf)
install(FILES ${PROJECT_SOURCE_DIR}/README.md ${PROJECT_SOURCE_DIR}/docs/aarch64.md
        DESTINATION ${CMAKE_INSTALL_DATAROOTDIR}/doc/kinfly-fw)

set(CPACK_GENERATOR DEB)
set(CPACK_PACKAGE_NAME kinfly-fw)
set(CPACK_PACKAGE_VERSION ${PROJECT_VERSION})
set(CPACK_PACKAGE_CONTACT "kinfly developers <kinfly@localhost>")
set(CPACK_PACKAGE_DESCRIPTION_SUMMARY
    "kinfly drone firmware: onboard KinectFusion odometry, keyframe link, signed corrections")
set(CPACK_PACKAGING_INSTALL_PREFIX /usr)
set(CPACK_DEBIAN_FILE_NAME DEB-DEFAULT)
set(CPACK_DEBIAN_PACKAGE_SECTION misc)
set(CPACK_DEBIAN_PACKAGE_CONTROL_STRICT_PERMISSION TRUE)
set(CPACK_DEBIAN_PACKAGE_CONTROL_EXTRA
    ${PROJECT_SOURCE_DIR}/firmware/debian/conffiles
    ${PROJECT_SOURCE_DIR}/firmware/debian/postinst
    ${PROJECT_SOURCE_DIR}/firmware/debian/prerm
    ${PROJECT_SOURCE_DIR}/firmware/debian/postrm)
# The postinst uses these; both are in every Debian 12 system with systemd.
set(CPACK_DEBIAN_PACKAGE_RECOMMENDS "iproute2, systemd")

if(CMAKE_SYSTEM_PROCESSOR MATCHES "^(aarch64|arm64)$")
  set(CPACK_DEBIAN_PACKAGE_ARCHITECTURE arm64)
endif()

# Depends: dpkg-shlibdeps needs the target's dpkg database, which an extracted sysroot does not
# have, so the cross build maps each binary's DT_NEEDED through the shlibs files that
# scripts/aarch64-sysroot.sh saved (cmake/KinflyDebDepends.cmake, run by cpack). Natively,
# dpkg-shlibdeps does the same from the host's database.
if(CMAKE_CROSSCOMPILING AND KINFLY_SYSROOT)
  set(CPACK_KINFLY_SHLIBS ${KINFLY_SYSROOT}/.kinfly-shlibs)
  set(CPACK_KINFLY_READELF ${CMAKE_READELF})
  set(CPACK_KINFLY_BINARIES
      ${CMAKE_RUNTIME_OUTPUT_DIRECTORY}/kinfly-fw ${CMAKE_RUNTIME_OUTPUT_DIRECTORY}/kinfly-keygen)
  set(CPACK_PROJECT_CONFIG_FILE ${CMAKE_CURRENT_LIST_DIR}/KinflyDebDepends.cmake)
else()
  set(CPACK_DEBIAN_PACKAGE_SHLIBDEPS ON)
endif()

include(CPack)
