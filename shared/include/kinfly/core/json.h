// Text for a JSON string literal, for the programs' hand-written summaries.
#pragma once

#include <cstdio>
#include <string>

namespace kinfly {

// s with JSON's escapes: quote, backslash and the control characters (a path or a name from a
// file may hold any of them).
inline std::string jsonEscape(const std::string& s) {
  std::string out;
  out.reserve(s.size());
  for (const char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char code[8];
      std::snprintf(code, sizeof(code), "\\u%04x", static_cast<unsigned>(static_cast<unsigned char>(c)));
      out += code;
    } else {
      out += c;
    }
  }
  return out;
}

}  // namespace kinfly
