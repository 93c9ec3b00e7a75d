#include "haptree/io/state_json.hpp"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>

namespace haptree::io {

namespace {

[[noreturn]] void fail(const std::string& src, const std::string& where, const std::string& what) {
  throw StateJsonError(src + ": " + where + ": " + what);
}

// Reads `n` numbers from a number or a list.
Eigen::VectorXd numbers(const nlohmann::json& v, int n, const std::string& src,
                        const std::string& where) {
  Eigen::VectorXd out(n);
  if (v.is_number()) {
    if (n != 1) fail(src, where, "expected a list of " + std::to_string(n) + " numbers");
    out(0) = v.get<double>();
  } else if (v.is_array()) {
    if (static_cast<int>(v.size()) != n)
      fail(src, where, "expected " + std::to_string(n) + " numbers, got " +
                           std::to_string(v.size()));
    for (int i = 0; i < n; ++i) {
      if (!v[i].is_number()) fail(src, where, "element " + std::to_string(i) + " is not a number");
      out(i) = v[i].get<double>();
    }
  } else {
    fail(src, where, "expected a number or a list of numbers");
  }
  if (!out.allFinite()) fail(src, where, "non-finite value");
  return out;
}

void normalise_quat(Eigen::Ref<Eigen::VectorXd> q4, const std::string& src,
                    const std::string& where) {
  // stableNorm: norm() squares first, so finite entries above ~1e154 gave n = inf and a zero
  // quaternion (found with fuzz/state_json's oracle).
  const double n = q4.stableNorm();
  if (!(n > 1e-12)) fail(src, where, "quaternion is zero");
  q4 /= n;
}

}  // namespace

State state_from_json(const Model& m, const nlohmann::json& doc, const std::string& src) {
  State st(m);
  st.q = neutral_configuration(m);
  if (!doc.is_object()) fail(src, "document", "expected a JSON object");
  for (auto it = doc.begin(); it != doc.end(); ++it) {
    const std::string sec = it.key();
    if (sec != "q" && sec != "qd" && sec != "tau" && sec != "f_ext")
      fail(src, sec, "unknown section (expected q, qd, tau, f_ext)");
    if (!it.value().is_object()) fail(src, sec, "expected an object keyed by name");
    for (auto e = it.value().begin(); e != it.value().end(); ++e) {
      const std::string where = sec + "." + e.key();
      if (sec == "f_ext") {
        const int b = m.body_index(e.key());
        if (b <= 0) fail(src, where, "unknown body");
        st.f_ext[b] = numbers(e.value(), 6, src, where);
        continue;
      }
      const int k = m.joint_index(e.key());
      if (k <= 0) fail(src, where, "unknown joint");
      const JointType t = m.joint_type[k];
      if (t == JointType::kFixed) fail(src, where, "fixed joint has no coordinates");
      if (sec == "q") {
        const int nq = joint_nq(t);
        st.q.segment(m.q_adr[k], nq) = numbers(e.value(), nq, src, where);
        if (t == JointType::kSpherical) normalise_quat(st.q.segment(m.q_adr[k], 4), src, where);
        if (t == JointType::kFree) normalise_quat(st.q.segment(m.q_adr[k] + 3, 4), src, where);
      } else {
        const int nv = joint_dofs(t);
        Eigen::VectorXd& dst = sec == "qd" ? st.qd : st.tau;
        dst.segment(m.v_adr[k], nv) = numbers(e.value(), nv, src, where);
      }
    }
  }
  return st;
}

State load_state_json(const Model& m, const std::string& path) {
  std::ifstream in(path);
  if (!in) throw StateJsonError(path + ": cannot open state file");
  nlohmann::json doc;
  try {
    doc = nlohmann::json::parse(in);
  } catch (const nlohmann::json::parse_error& e) {
    std::string w = e.what();
    throw StateJsonError(path + ": JSON parse error: " + w);
  }
  return state_from_json(m, doc, path);
}

nlohmann::ordered_json qdd_to_json(const Model& m, const Eigen::VectorXd& qdd) {
  nlohmann::ordered_json out = nlohmann::ordered_json::object();
  nlohmann::ordered_json body = nlohmann::ordered_json::object();
  for (int k = 1; k < m.nbodies; ++k) {
    const int n = m.v_num[k];
    if (n == 0) continue;
    if (n == 1) {
      body[m.joint_name[k]] = qdd(m.v_adr[k]);
    } else {
      nlohmann::ordered_json list = nlohmann::ordered_json::array();
      for (int i = 0; i < n; ++i) list.push_back(qdd(m.v_adr[k] + i));
      body[m.joint_name[k]] = list;
    }
  }
  out["qdd"] = body;
  return out;
}

namespace {

void dump(const nlohmann::ordered_json& j, int indent, int level, std::string& s) {
  const bool pretty = indent >= 0;
  auto nl = [&](int lvl) {
    if (pretty) {
      s += '\n';
      s.append(static_cast<size_t>(indent * lvl), ' ');
    }
  };
  if (j.is_number_float()) {
    const double x = j.get<double>();
    if (!std::isfinite(x)) {
      s += "null";
      return;
    }
    char buf[40];
    std::snprintf(buf, sizeof buf, "%.17g", x);
    s += buf;
  } else if (j.is_object()) {
    if (j.empty()) { s += "{}"; return; }
    s += '{';
    bool first = true;
    for (auto it = j.begin(); it != j.end(); ++it) {
      if (!first) s += ',';
      first = false;
      nl(level + 1);
      s += nlohmann::json(it.key()).dump();
      s += pretty ? ": " : ":";
      dump(it.value(), indent, level + 1, s);
    }
    nl(level);
    s += '}';
  } else if (j.is_array()) {
    s += '[';
    for (size_t i = 0; i < j.size(); ++i) {
      if (i) s += pretty ? ", " : ",";
      dump(j[i], indent, level + 1, s);
    }
    s += ']';
  } else {
    s += j.dump();
  }
}

}  // namespace

std::string dump_json_exact(const nlohmann::ordered_json& j, int indent) {
  std::string s;
  dump(j, indent, 0, s);
  return s;
}

}  // namespace haptree::io
