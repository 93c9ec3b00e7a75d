// IMD (Interactive Molecular Dynamics) wire protocol, v2 (VMD, NAMD, GROMACS) and v3 (IMDv3
// specification, Becksteinlab/imdclient docs/source/protocol_v3.rst). Bytes only: no sockets, no
// allocation beyond the caller's vectors, no exceptions. The parser is a pure function on a byte
// range, so it can be fuzzed and unit-tested without a network.
//
// Every packet starts with an 8-byte header: int32 type, int32 length, both big-endian, except the
// handshake's length (the IMD version), which is in the sender's native order so the receiver learns
// the sender's endianness. Bodies are in the *simulation engine's* native order, in both directions.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace haptree::imd {

enum class Type : int32_t {
  kDisconnect = 0,
  kEnergies = 1,
  kFcoords = 2,      // coordinates, float32 Å
  kGo = 3,
  kHandshake = 4,
  kKill = 5,
  kMdcomm = 6,       // receiver -> engine: atom indices + forces
  kPause = 7,
  kTrate = 8,        // transmission rate: steps between frames
  kIoerror = 9,
  kSessionInfo = 10, // v3
  kResume = 11,      // v3
  kTime = 12,        // v3: dt, time (float64), step (int64)
  kBox = 13,         // v3
  kVelocities = 14,  // v3: float32 Å/ps
  kForces = 15,      // v3: float32 kJ/(mol Å)
  kWait = 16,        // v3
};
const char* type_name(int32_t type) noexcept;

constexpr size_t kHeaderBytes = 8;

// v3 session info body: 7 one-byte flags, in this order.
struct SessionInfo {
  bool time = true, energies = false, box = false, coordinates = true, wrapped = false,
       velocities = false, forces = false;
};

// ---- encoding (engine side, and the receiver's packets for clients and tests) ----
// All append to `out`. Body arrays are written in this machine's native order.
void append_header(std::vector<uint8_t>& out, Type type, int32_t length);
void append_handshake(std::vector<uint8_t>& out, int32_t version);   // length field native order
void append_session_info(std::vector<uint8_t>& out, const SessionInfo& info);
// n atoms, xyz[3n] (kFcoords, kVelocities or kForces).
void append_vectors(std::vector<uint8_t>& out, Type type, const float* xyz, int32_t n);
void append_time(std::vector<uint8_t>& out, double dt, double time, int64_t step);
// Receiver -> engine MD communication: n indices, forces[3n]; native order of the engine (the caller
// is a client on this machine, or a test).
void append_mdcomm(std::vector<uint8_t>& out, const int32_t* indices, const float* forces, int32_t n);

// ---- decoding: what an engine accepts from a receiver ----
struct ClientMessage {
  Type type = Type::kIoerror;
  int32_t value = 0;               // header length field (e.g. the new rate of kTrate)
  std::vector<int32_t> indices;    // kMdcomm only
  std::vector<float> forces;       // kMdcomm only, 3 per index
  std::vector<uint8_t> seen;       // scratch of the repeated-index check (max_atoms flags, reused)
};

enum class ParseStatus { kNeedMore, kMessage, kError };
struct ParseResult {
  ParseStatus status = ParseStatus::kNeedMore;
  size_t consumed = 0;             // bytes of a complete message (kMessage), else 0
  std::string error;               // kError: what was wrong, in words (for the log line)
};

// Parses the first receiver->engine packet in data[0, size). kNeedMore: the bytes are a valid
// prefix, wait for more. kError: the stream cannot be a valid IMD stream (unknown or engine-only
// type, negative count, more than `max_atoms` MD-communication atoms, an index outside
// [0, max_atoms), a repeated index, a non-finite force); the caller drops the client. Reuses
// out.indices/out.forces/out.seen (no allocation once they reached max_atoms). Never reads past size.
ParseResult parse_client_message(const uint8_t* data, size_t size, int32_t max_atoms, ClientMessage& out);

// Largest packet parse_client_message can ask to buffer for max_atoms atoms (header + MDCOMM body).
size_t max_client_message_bytes(int32_t max_atoms) noexcept;

// Big-endian helpers (also used by tests and clients).
int32_t read_be32(const uint8_t* p) noexcept;
void write_be32(uint8_t* p, int32_t v) noexcept;

// Force units: VMD (IMDv2) sends kcal/(mol Å); IMDv3 fixes kJ/(mol Å). Scene units are kJ/(mol nm).
constexpr double kKcalPerMolAngstromToKjPerMolNm = 4.184 * 10.0;   // 1 kcal = 4.184 kJ, 1 nm = 10 Å
constexpr double kKjPerMolAngstromToKjPerMolNm = 10.0;
constexpr double kNmToAngstrom = 10.0;

}  // namespace haptree::imd
