// Authenticated sessions (docs/sessions.md): with a session key, every message on the bus carries a trailer
//   [magic "HTA1" 4][key id 4][sender id 4][seq 8][MAC 32]           (52 bytes, integers big-endian)
// appended after its LCM bytes. MAC = HMAC-SHA512-256 (libsodium crypto_auth) under the session key
// over (channel, NUL, message bytes, the first 20 trailer bytes): a message moved to another channel,
// altered in any byte, or signed with another key does not verify. A receiver drops and counts messages
// without a trailer, with another key id, with a wrong MAC, and replays: per (sender id, channel) the
// sequence number must increase (the first message of a sender is trusted, so a recorded log replays
// into a fresh session that has the key). A sender id is random per Bus / shm writer.
//
// The key file: 32 bytes or more of anything (e.g. `head -c 32 /dev/urandom > s.key; chmod 600 s.key`);
// trailing whitespace is ignored; the key is BLAKE2b-256 of the rest. Logs name the key by its
// fingerprint (first 8 bytes of a BLAKE2b hash, hex), never by its bytes.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <unordered_map>

namespace haptree::bus {

constexpr size_t kAuthTrailerBytes = 52;
constexpr uint32_t kAuthMagic = 0x48544131;   // "HTA1"

struct SessionKey {
  std::array<uint8_t, 32> key{};
  uint32_t key_id = 0;          // first 4 bytes of the fingerprint hash: which key signed a message
  std::string fingerprint;      // 16 hex digits
  // libsodium's HMAC state right after init with the key (opaque here): copied per message, which
  // saves the two SHA-512 blocks of key padding that an init costs.
  std::shared_ptr<const void> mac_init;
};

// Reads a key file; throws std::runtime_error naming the file and the problem (missing, < 32 bytes).
// Warns on stderr if the file is readable by group or others.
std::shared_ptr<const SessionKey> load_session_key(const std::string& path);
// A key from raw bytes (tests, tools). Throws if fewer than 32 bytes.
std::shared_ptr<const SessionKey> session_key_from_bytes(const std::string& bytes);

// The process's session key file: set by --session-key-file (add_bus_options), otherwise the
// environment variable HAPTREE_SESSION_KEY_FILE; "" = no key. Every Bus and shm channel created
// afterwards without an explicit key uses it.
void set_process_session_key_file(const std::string& path);
std::string process_session_key_file();
// The loaded process key (cached per path), or nullptr when there is none. Throws like load_session_key.
std::shared_ptr<const SessionKey> process_session_key();

enum class AuthVerdict { kOk, kNoTrailer, kWrongKey, kBadMac, kReplay };
const char* to_string(AuthVerdict v) noexcept;

struct AuthStats {
  std::atomic<int64_t> sealed{0}, accepted{0}, no_trailer{0}, wrong_key{0}, bad_mac{0}, replayed{0};
  int64_t rejected() const noexcept {
    return no_trailer.load() + wrong_key.load() + bad_mac.load() + replayed.load();
  }
};

// Seals outgoing and opens incoming messages under one key. seal() is thread-safe and lock-free;
// open() takes a mutex around the replay table (receiving threads only, never the haptic loop's).
class Authenticator {
 public:
  explicit Authenticator(std::shared_ptr<const SessionKey> key);
  const SessionKey& key() const noexcept { return *key_; }
  uint32_t sender_id() const noexcept { return sender_id_; }

  // Writes the trailer for msg[0, size) on `channel` into msg[size, size + kAuthTrailerBytes).
  // The caller provides the room. Returns size + kAuthTrailerBytes.
  size_t seal(const std::string& channel, uint8_t* msg, size_t size) noexcept;
  // Verifies data[0, size) on `channel`; on kOk sets *payload_size (size − trailer). Counts the verdict.
  AuthVerdict open(const std::string& channel, const void* data, size_t size, size_t* payload_size) noexcept;
  // The same checks without the replay table (reading a log file whose order is known).
  AuthVerdict verify(const std::string& channel, const void* data, size_t size, size_t* payload_size,
                     uint32_t* sender = nullptr, uint64_t* seq = nullptr) const noexcept;

  const AuthStats& stats() const noexcept { return stats_; }

 private:
  std::shared_ptr<const SessionKey> key_;
  uint32_t sender_id_;
  std::atomic<uint64_t> seq_;
  std::mutex replay_mutex_;
  // sender id -> channel -> newest seq seen (lookups by const std::string&: no allocation once seen)
  std::unordered_map<uint32_t, std::unordered_map<std::string, uint64_t>> last_seq_;
  AuthStats stats_;
};

}  // namespace haptree::bus
