#include "haptree/device/axes.hpp"

#include <stdexcept>

#include "haptree/device/registry.hpp"

namespace haptree::device {

AxisMap AxisMap::parse(const std::string& spec) {
  auto bad = [&](const std::string& why) {
    return std::invalid_argument("axes '" + spec + "': " + why +
                                 " (expected three of x,y,z,-x,-y,-z, e.g. 'y,z,x': the vendor axis that becomes "
                                 "haptree's x (right), y (up), z (towards the user))");
  };
  AxisMap m;
  m.R_.setZero();
  std::string text;
  size_t pos = 0;
  bool used[3] = {false, false, false};
  for (int row = 0; row < 3; ++row) {
    const size_t comma = spec.find(',', pos);
    if ((row < 2) != (comma != std::string::npos)) throw bad("not three comma-separated axes");
    std::string tok = spec.substr(pos, row < 2 ? comma - pos : std::string::npos);
    pos = comma + 1;
    double sign = 1;
    if (!tok.empty() && (tok[0] == '-' || tok[0] == '+')) {
      sign = tok[0] == '-' ? -1 : 1;
      tok.erase(0, 1);
    }
    if (tok.size() != 1 || tok[0] < 'x' || tok[0] > 'z') throw bad("'" + tok + "' is not an axis");
    const int col = tok[0] - 'x';
    if (used[col]) throw bad("axis " + tok + " used twice");
    used[col] = true;
    m.R_(row, col) = sign;
    text += std::string(row ? "," : "") + (sign < 0 ? "-" : "") + tok;
  }
  if (m.R_.determinant() < 0) throw bad("a mirror (determinant -1); flip the sign of one axis");
  m.text_ = text;
  return m;
}

AxisMap axis_map_option(const DeviceConfig& c, const std::string& family_default) {
  const std::string s = option_string(c, "axes", family_default);
  try {
    return AxisMap::parse(s);
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("device option ") + e.what());
  }
}

}  // namespace haptree::device
