# What shared/ and its tools need, found once for every build that adds shared/ (the main build
# and the ground package's).
find_package(Eigen3 3.3 REQUIRED NO_MODULE)
find_package(OpenMP REQUIRED COMPONENTS CXX)
find_package(PkgConfig REQUIRED)
find_package(CLI11 REQUIRED)
