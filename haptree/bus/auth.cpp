#include "haptree/bus/auth.hpp"

#include <sodium.h>
#include <sys/stat.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iterator>
#include <map>
#include <stdexcept>

namespace haptree::bus {

namespace {

void init_sodium() {
  static const bool ok = sodium_init() >= 0;
  if (!ok) throw std::runtime_error("libsodium could not be initialised");
}

void put32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<uint8_t>(v >> (24 - 8 * i));
}
void put64(uint8_t* p, uint64_t v) {
  for (int i = 0; i < 8; ++i) p[i] = static_cast<uint8_t>(v >> (56 - 8 * i));
}
uint32_t get32(const uint8_t* p) {
  return (uint32_t(p[0]) << 24) | (uint32_t(p[1]) << 16) | (uint32_t(p[2]) << 8) | uint32_t(p[3]);
}
uint64_t get64(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = (v << 8) | p[i];
  return v;
}

// HMAC-SHA512-256 (= crypto_auth) over channel, NUL, bytes: multi-part so nothing is copied.
void mac(const SessionKey& k, const std::string& channel, const uint8_t* data, size_t n, uint8_t* out) {
  crypto_auth_hmacsha512256_state st = *static_cast<const crypto_auth_hmacsha512256_state*>(k.mac_init.get());
  crypto_auth_hmacsha512256_update(&st, reinterpret_cast<const unsigned char*>(channel.c_str()),
                                   channel.size() + 1);
  crypto_auth_hmacsha512256_update(&st, data, n);
  crypto_auth_hmacsha512256_final(&st, out);
}

std::mutex g_process_mutex;
std::string g_process_file;
bool g_process_file_set = false;

}  // namespace

std::shared_ptr<const SessionKey> session_key_from_bytes(const std::string& bytes_in) {
  init_sodium();
  std::string bytes = bytes_in;
  while (!bytes.empty() && (bytes.back() == '\n' || bytes.back() == '\r' || bytes.back() == ' ' ||
                            bytes.back() == '\t'))
    bytes.pop_back();
  if (bytes.size() < 32)
    throw std::runtime_error("session key has " + std::to_string(bytes.size()) +
                             " bytes; it needs at least 32 (e.g. head -c 32 /dev/urandom > session.key)");
  auto k = std::make_shared<SessionKey>();
  static const char kKeyCtx[] = "haptree session key v1";
  crypto_generichash(k->key.data(), k->key.size(), reinterpret_cast<const unsigned char*>(bytes.data()),
                     bytes.size(), reinterpret_cast<const unsigned char*>(kKeyCtx), sizeof kKeyCtx - 1);
  // Fingerprint: a hash of the derived key under another context, so it reveals nothing of the key.
  uint8_t fp[16];
  static const char kFpCtx[] = "haptree key fingerprint v1";
  crypto_generichash(fp, sizeof fp, k->key.data(), k->key.size(),
                     reinterpret_cast<const unsigned char*>(kFpCtx), sizeof kFpCtx - 1);
  char hex[17];
  sodium_bin2hex(hex, sizeof hex, fp, 8);
  k->fingerprint = hex;
  k->key_id = get32(fp);
  auto init = std::make_shared<crypto_auth_hmacsha512256_state>();
  crypto_auth_hmacsha512256_init(init.get(), k->key.data(), k->key.size());
  k->mac_init = init;
  return k;
}

std::shared_ptr<const SessionKey> load_session_key(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error("session key file '" + path + "': cannot open (" + std::strerror(errno) + ")");
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && (st.st_mode & (S_IRGRP | S_IROTH)))
    std::fprintf(stderr, "warning: session key file '%s' is readable by other users (chmod 600 it)\n",
                 path.c_str());
  try {
    return session_key_from_bytes(bytes);
  } catch (const std::exception& e) {
    throw std::runtime_error("session key file '" + path + "': " + e.what());
  }
}

void set_process_session_key_file(const std::string& path) {
  std::lock_guard<std::mutex> lock(g_process_mutex);
  g_process_file = path;
  g_process_file_set = true;
}

std::string process_session_key_file() {
  std::lock_guard<std::mutex> lock(g_process_mutex);
  if (g_process_file_set) return g_process_file;
  const char* env = std::getenv("HAPTREE_SESSION_KEY_FILE");
  return env ? env : "";
}

std::shared_ptr<const SessionKey> process_session_key() {
  const std::string path = process_session_key_file();
  if (path.empty()) return nullptr;
  static std::mutex m;
  static std::map<std::string, std::shared_ptr<const SessionKey>> cache;
  std::lock_guard<std::mutex> lock(m);
  auto& k = cache[path];
  if (!k) k = load_session_key(path);
  return k;
}

const char* to_string(AuthVerdict v) noexcept {
  switch (v) {
    case AuthVerdict::kOk: return "ok";
    case AuthVerdict::kNoTrailer: return "no authentication trailer (unkeyed sender)";
    case AuthVerdict::kWrongKey: return "signed with another session key";
    case AuthVerdict::kBadMac: return "MAC does not verify (tampered bytes or forged trailer)";
    case AuthVerdict::kReplay: return "replay (sequence number not newer than the last from that sender)";
  }
  return "?";
}

Authenticator::Authenticator(std::shared_ptr<const SessionKey> key) : key_(std::move(key)) {
  if (!key_) throw std::invalid_argument("Authenticator needs a key");
  init_sodium();
  sender_id_ = randombytes_random();
  seq_.store(1);
}

size_t Authenticator::seal(const std::string& channel, uint8_t* msg, size_t size) noexcept {
  uint8_t* t = msg + size;
  put32(t, kAuthMagic);
  put32(t + 4, key_->key_id);
  put32(t + 8, sender_id_);
  put64(t + 12, seq_.fetch_add(1, std::memory_order_relaxed));
  mac(*key_, channel, msg, size + 20, t + 20);
  stats_.sealed.fetch_add(1, std::memory_order_relaxed);
  return size + kAuthTrailerBytes;
}

AuthVerdict Authenticator::verify(const std::string& channel, const void* data, size_t size,
                                  size_t* payload_size, uint32_t* sender, uint64_t* seq) const noexcept {
  const auto* d = static_cast<const uint8_t*>(data);
  if (d == nullptr || size < kAuthTrailerBytes) return AuthVerdict::kNoTrailer;
  const uint8_t* t = d + size - kAuthTrailerBytes;
  if (get32(t) != kAuthMagic) return AuthVerdict::kNoTrailer;
  if (get32(t + 4) != key_->key_id) return AuthVerdict::kWrongKey;
  uint8_t expect[32];
  mac(*key_, channel, d, size - kAuthTrailerBytes + 20, expect);
  if (sodium_memcmp(expect, t + 20, 32) != 0) return AuthVerdict::kBadMac;
  if (sender) *sender = get32(t + 8);
  if (seq) *seq = get64(t + 12);
  *payload_size = size - kAuthTrailerBytes;
  return AuthVerdict::kOk;
}

AuthVerdict Authenticator::open(const std::string& channel, const void* data, size_t size,
                                size_t* payload_size) noexcept {
  uint32_t sender = 0;
  uint64_t seq = 0;
  size_t n = 0;
  AuthVerdict v = verify(channel, data, size, &n, &sender, &seq);
  if (v == AuthVerdict::kOk) {
    std::lock_guard<std::mutex> lock(replay_mutex_);
    try {
      auto& per_channel = last_seq_[sender];
      auto it = per_channel.find(channel);
      if (it == per_channel.end()) per_channel.emplace(channel, seq);
      else if (seq <= it->second) v = AuthVerdict::kReplay;
      else it->second = seq;
    } catch (...) {   // out of memory growing the table: refuse rather than accept unchecked
      v = AuthVerdict::kReplay;
    }
  }
  switch (v) {
    case AuthVerdict::kOk: stats_.accepted.fetch_add(1, std::memory_order_relaxed); *payload_size = n; break;
    case AuthVerdict::kNoTrailer: stats_.no_trailer.fetch_add(1, std::memory_order_relaxed); break;
    case AuthVerdict::kWrongKey: stats_.wrong_key.fetch_add(1, std::memory_order_relaxed); break;
    case AuthVerdict::kBadMac: stats_.bad_mac.fetch_add(1, std::memory_order_relaxed); break;
    case AuthVerdict::kReplay: stats_.replayed.fetch_add(1, std::memory_order_relaxed); break;
  }
  return v;
}

}  // namespace haptree::bus
