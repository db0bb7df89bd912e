# MAVLink's C headers (the common dialect, MAVLink 2, with signing), generated at build time by
# mavgen from the XML that pymavlink ships, never vendored. The build's Python is .venv-build
# (requirements-build.txt, made by scripts/install-deps.sh for every group that compiles);
# KINFLY_MAVGEN_PYTHON points elsewhere. Gives the interface target kinfly::mavlink.
set(KINFLY_MAVGEN_PYTHON "${PROJECT_SOURCE_DIR}/.venv-build/bin/python" CACHE FILEPATH
    "Python with pymavlink, whose mavgen generates the MAVLink C headers")
execute_process(
  COMMAND "${KINFLY_MAVGEN_PYTHON}" -c
          "import os, pymavlink; print(os.path.join(os.path.dirname(pymavlink.__file__), 'dialects', 'v20'), end='')"
  OUTPUT_VARIABLE KINFLY_MAVLINK_XML_DIR
  RESULT_VARIABLE mavgen_found
  ERROR_QUIET)
if(NOT mavgen_found EQUAL 0)
  message(FATAL_ERROR "the firmware's MAVLink headers need pymavlink's mavgen: "
                      "${KINFLY_MAVGEN_PYTHON} cannot import pymavlink. Run "
                      "`scripts/install-deps.sh unit` (it makes .venv-build), or set "
                      "-DKINFLY_MAVGEN_PYTHON to a Python that has it")
endif()

set(mavlink_dir "${CMAKE_BINARY_DIR}/generated/mavlink")
set(mavlink_xml "${KINFLY_MAVLINK_XML_DIR}/common.xml")
add_custom_command(
  OUTPUT "${mavlink_dir}/mavlink/common/mavlink.h"
  COMMAND "${KINFLY_MAVGEN_PYTHON}" -m pymavlink.tools.mavgen --lang=C --wire-protocol=2.0
          --no-validate "--output=${mavlink_dir}/mavlink" "${mavlink_xml}"
  DEPENDS "${mavlink_xml}" "${KINFLY_MAVLINK_XML_DIR}/standard.xml"
          "${KINFLY_MAVLINK_XML_DIR}/minimal.xml"
  COMMENT "mavgen: MAVLink 2 C headers from pymavlink's common.xml"
  VERBATIM)
add_custom_target(kinfly_mavlink_headers DEPENDS "${mavlink_dir}/mavlink/common/mavlink.h")
add_library(kinfly_mavlink INTERFACE)
add_library(kinfly::mavlink ALIAS kinfly_mavlink)
# SYSTEM: the generated C is not held to kinfly's warnings.
target_include_directories(kinfly_mavlink SYSTEM INTERFACE "${mavlink_dir}")
add_dependencies(kinfly_mavlink kinfly_mavlink_headers)
