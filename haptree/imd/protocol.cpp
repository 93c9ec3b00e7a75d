#include "haptree/imd/protocol.hpp"

#include <cmath>
#include <cstring>

namespace haptree::imd {

int32_t read_be32(const uint8_t* p) noexcept {
  return static_cast<int32_t>((uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) |
                              uint32_t(p[3]));
}
void write_be32(uint8_t* p, int32_t v) noexcept {
  const auto u = static_cast<uint32_t>(v);
  p[0] = uint8_t(u >> 24);
  p[1] = uint8_t(u >> 16);
  p[2] = uint8_t(u >> 8);
  p[3] = uint8_t(u);
}

const char* type_name(int32_t t) noexcept {
  static const char* names[] = {"DISCONNECT", "ENERGIES", "FCOORDS", "GO",   "HANDSHAKE",  "KILL",
                                "MDCOMM",     "PAUSE",    "TRATE",   "IOERROR", "SESSIONINFO", "RESUME",
                                "TIME",       "BOX",      "VELOCITIES", "FORCES", "WAIT"};
  return t >= 0 && t <= 16 ? names[t] : "UNKNOWN";
}

namespace {
template <class T>
void append_native(std::vector<uint8_t>& out, const T* v, size_t n) {
  const size_t at = out.size();
  out.resize(at + n * sizeof(T));
  if (n) std::memcpy(out.data() + at, v, n * sizeof(T));
}
}  // namespace

void append_header(std::vector<uint8_t>& out, Type type, int32_t length) {
  uint8_t h[kHeaderBytes];
  write_be32(h, static_cast<int32_t>(type));
  write_be32(h + 4, length);
  out.insert(out.end(), h, h + kHeaderBytes);
}

void append_handshake(std::vector<uint8_t>& out, int32_t version) {
  uint8_t h[kHeaderBytes];
  write_be32(h, static_cast<int32_t>(Type::kHandshake));
  std::memcpy(h + 4, &version, 4);   // unswapped: the receiver infers our byte order from it
  out.insert(out.end(), h, h + kHeaderBytes);
}

void append_session_info(std::vector<uint8_t>& out, const SessionInfo& s) {
  append_header(out, Type::kSessionInfo, 7);
  const uint8_t flags[7] = {s.time, s.energies, s.box, s.coordinates, s.wrapped, s.velocities, s.forces};
  out.insert(out.end(), flags, flags + 7);
}

void append_vectors(std::vector<uint8_t>& out, Type type, const float* xyz, int32_t n) {
  append_header(out, type, n);
  append_native(out, xyz, 3 * static_cast<size_t>(n));
}

void append_time(std::vector<uint8_t>& out, double dt, double time, int64_t step) {
  append_header(out, Type::kTime, 1);
  append_native(out, &dt, 1);
  append_native(out, &time, 1);
  append_native(out, &step, 1);
}

void append_mdcomm(std::vector<uint8_t>& out, const int32_t* indices, const float* forces, int32_t n) {
  append_header(out, Type::kMdcomm, n);
  append_native(out, indices, static_cast<size_t>(n));
  append_native(out, forces, 3 * static_cast<size_t>(n));
}

size_t max_client_message_bytes(int32_t max_atoms) noexcept {
  return kHeaderBytes + 16 * static_cast<size_t>(max_atoms > 0 ? max_atoms : 0);
}

ParseResult parse_client_message(const uint8_t* data, size_t size, int32_t max_atoms, ClientMessage& out) {
  ParseResult r;
  if (data == nullptr || size < kHeaderBytes) return r;   // kNeedMore
  const int32_t type = read_be32(data);
  const int32_t length = read_be32(data + 4);
  auto error = [&r, type](std::string what) {
    r.status = ParseStatus::kError;
    r.error = std::string(type_name(type)) + " (type " + std::to_string(type) + "): " + what;
    return r;
  };
  switch (static_cast<Type>(type)) {
    case Type::kDisconnect: case Type::kGo: case Type::kKill: case Type::kPause: case Type::kTrate:
    case Type::kIoerror: case Type::kResume: case Type::kWait:
      out.type = static_cast<Type>(type);
      out.value = length;
      out.indices.clear();
      out.forces.clear();
      r.status = ParseStatus::kMessage;
      r.consumed = kHeaderBytes;
      return r;
    case Type::kMdcomm: {
      if (length < 0) return error("negative atom count " + std::to_string(length));
      if (length > max_atoms)
        return error(std::to_string(length) + " atoms, more than the " + std::to_string(max_atoms) + " served");
      const size_t n = static_cast<size_t>(length);
      const size_t need = kHeaderBytes + 16 * n;
      if (size < need) return r;   // kNeedMore: at most max_client_message_bytes() to wait for
      out.type = Type::kMdcomm;
      out.value = length;
      out.indices.resize(n);
      out.forces.resize(3 * n);
      if (n) {
        std::memcpy(out.indices.data(), data + kHeaderBytes, 4 * n);
        std::memcpy(out.forces.data(), data + kHeaderBytes + 4 * n, 12 * n);
      }
      for (size_t i = 0; i < n; ++i)
        if (out.indices[i] < 0 || out.indices[i] >= max_atoms)
          return error("atom index " + std::to_string(out.indices[i]) + " outside [0, " +
                       std::to_string(max_atoms) + ")");
      // A repeated index would apply one atom's pull twice, past the per-atom clamp (found by fuzz/imd_client).
      out.seen.assign(static_cast<size_t>(max_atoms), 0);
      for (size_t i = 0; i < n; ++i) {
        uint8_t& s = out.seen[static_cast<size_t>(out.indices[i])];
        if (s) return error("atom index " + std::to_string(out.indices[i]) + " given twice");
        s = 1;
      }
      for (float f : out.forces)
        if (!std::isfinite(f)) return error("non-finite force component");
      r.status = ParseStatus::kMessage;
      r.consumed = need;
      return r;
    }
    default:
      if (type >= 0 && type <= 16) return error("not a packet a receiver sends to an engine");
      return error("unknown packet type");
  }
}

}  // namespace haptree::imd
