// kinfly-keygen: creates a vehicle's 32-byte signing key (mode 0600). The same file goes to the
// ground station and to the drone; both refuse to start if anyone but the owner can read it.
#include <CLI/CLI.hpp>

#include <cstdio>
#include <iostream>
#include <string>

#include "kinfly/link/signing.h"

int main(int argc, char** argv) {
  CLI::App app{
      "Create a per-vehicle signing key for kinfly's uplink (HMAC-SHA256, 32 random bytes).\n"
      "Copy it to the drone keeping its mode (scp -p), e.g. to /etc/kinfly/vehicle.key."};
  std::string out_path;
  bool force = false;
  app.add_option("--out", out_path, "key file to create (mode 0600)")->required();
  app.add_flag("--force", force, "replace an existing key file");
  app.set_version_flag("--version", "kinfly-keygen 0.1.0");
  CLI11_PARSE(app, argc, argv);

  const kinfly::StatusOr<kinfly::link::Key> key = kinfly::link::createKeyFile(out_path, force);
  if (!key.ok()) {
    std::cerr << "kinfly-keygen: error: " << key.status().message() << "\n";
    return 1;
  }
  std::printf("wrote %s (key id 0x%08x)\n", out_path.c_str(), key->id);
  return 0;
}
