#include "haptree/device/inverse3.hpp"

#include "haptree/device/vendor_library.hpp"

#define ASIO_STANDALONE
#define _WEBSOCKETPP_CPP11_STL_
#include <nlohmann/json.hpp>
#include <websocketpp/client.hpp>
#include <websocketpp/config/asio_no_tls_client.hpp>

#include <cctype>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <mutex>
#include <sstream>
#include <stdexcept>

namespace haptree::device {

namespace {

using json = nlohmann::json;
using WsClient = websocketpp::client<websocketpp::config::asio_client>;
using Clock = std::chrono::steady_clock;

double mono_s() noexcept {
  return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
}

// link_ values: 0 connecting, 1 up, then the reason read()/write() report (static strings).
enum Link : int { kConnecting = 0, kUp = 1, kClosed, kNoReply, kRemoteClosed, kNoValidState, kSocketError, kStale };
const char* const kLinkReason[] = {
    "inverse3: not connected",
    "",
    "inverse3: closed",
    "inverse3: no reply from the Inverse Service within timeout_s (link lost, zero force sent)",
    "inverse3: the Inverse Service closed the connection (link lost)",
    "inverse3: no valid Inverse3 state within timeout_s (malformed replies, or the device left the service's list)",
    "inverse3: WebSocket error (link lost)",
    "inverse3: no state from the Inverse Service within timeout_s (no reply, malformed replies, or the device left "
    "the service's list)",
};

// A vec3 as the service writes it: {x,y,z}, or wrapped as {"vector":{x,y,z}} (current services) or
// {"values":{x,y,z}} (older ones). False if absent or not three finite numbers.
bool read_vec3(const json& j, Vec3& v) {
  if (!j.is_object()) return false;
  for (const char* wrap : {"vector", "values"}) {
    auto it = j.find(wrap);
    if (it != j.end()) return read_vec3(*it, v);
  }
  const auto x = j.find("x"), y = j.find("y"), z = j.find("z");
  if (x == j.end() || y == j.end() || z == j.end() || !x->is_number() || !y->is_number() || !z->is_number())
    return false;
  v = Vec3(x->get<double>(), y->get<double>(), z->get<double>());
  return v.allFinite();
}

bool read_quat(const json& j, Quat& q) {
  if (!j.is_object()) return false;
  const auto w = j.find("w"), x = j.find("x"), y = j.find("y"), z = j.find("z");
  for (auto it : {w, x, y, z})
    if (it == j.end() || !it->is_number()) return false;
  Quat r(w->get<double>(), x->get<double>(), y->get<double>(), z->get<double>());
  const double n = r.norm();
  if (!std::isfinite(n) || n < 0.5 || n > 2.0) return false;   // not a rotation
  q = r.normalized();
  return true;
}

// device_id may come as a string ("049D") or, for some grips, a number.
std::string id_of(const json& entry) {
  auto it = entry.find("device_id");
  if (it == entry.end()) return "";
  if (it->is_string()) return it->get<std::string>();
  if (it->is_number_integer()) return std::to_string(it->get<int64_t>());
  return "";
}

const json* find_device(const json& msg, const char* kind, const std::string& id) {
  auto arr = msg.find(kind);
  if (arr == msg.end() || !arr->is_array()) return nullptr;
  for (const auto& e : *arr)
    if (e.is_object() && id_of(e) == id) return &e;
  return nullptr;
}

}  // namespace

// The I/O side: everything here runs on the device's own thread (asio's), except open()'s wait.
struct Inverse3Device::Io {
  explicit Io(Inverse3Device& d) : dev(d) {}
  Inverse3Device& dev;
  WsClient client;
  websocketpp::connection_hdl hdl;
  std::unique_ptr<asio::steady_timer> timer;
  Clock::time_point next;
  // open() waits for the inventory (not the haptic loop: a mutex is fine here)
  std::mutex m;
  std::condition_variable cv;
  int phase = 0;                    // 0 waiting, 1 ready, 2 failed
  std::string error;
  bool finished = false;            // the I/O thread returned
  // I/O thread only
  bool have_inventory = false, awaiting = false, final_sent = false, socket_open = false;
  double sent_s = 0, last_good_s = 0;
  Inverse3Sample last;
  std::atomic<bool> closing{false};

  void fail_open(const std::string& why) {
    std::lock_guard<std::mutex> lock(m);
    if (phase == 0) {
      phase = 2;
      error = why;
    }
    cv.notify_all();
  }

  // Sends one set_cursor_force command (device axes, N). False on a socket error.
  bool send_json(const Vec3& f_device) {
    json cmd = {{"inverse3",
                 json::array({{{"device_id", dev.device_id_},
                               {"commands",
                                {{"set_cursor_force",
                                  {{dev.p_.force_key, {{"x", f_device.x()}, {"y", f_device.y()}, {"z", f_device.z()}}}}}}}}})}};
    websocketpp::lib::error_code ec;
    client.send(hdl, cmd.dump(), websocketpp::frame::opcode::text, ec);
    if (ec) return false;
    awaiting = true;
    sent_s = mono_s();
    return true;
  }
  void send_force(const Vec3& f_device) {
    if (!socket_open || final_sent) return;
    if (!send_json(f_device)) lose(kSocketError);
  }

  // Link lost: report it to the haptic loop, send a zero force as the last command, close.
  void lose(Link why) {
    int expected = kUp;
    dev.link_.compare_exchange_strong(expected, why, std::memory_order_acq_rel);
    finish();
  }
  void finish() {
    if (!final_sent && socket_open && have_inventory) {
      final_sent = true;
      send_json(Vec3::Zero());   // the last command, on every way out
    }
    final_sent = true;
    if (timer) timer->cancel();
    if (socket_open) {
      websocketpp::lib::error_code ec;
      client.close(hdl, websocketpp::close::status::normal, "haptree device closed", ec);
    }
  }

  // One state message: the chosen Inverse3 and grip, in view axes. False if it holds no valid state.
  bool parse_state(const json& msg, Inverse3Sample& s) {
    const json* inv = find_device(msg, "inverse3", dev.device_id_);
    if (!inv) return false;
    auto st = inv->find("state");
    if (st == inv->end() || !st->is_object()) return false;
    Vec3 x;
    auto pos = st->find("cursor_position");
    if (pos == st->end() || !read_vec3(*pos, x) || x.cwiseAbs().maxCoeff() > dev.p_.max_abs_m) return false;
    Vec3 v = Vec3::Zero();
    auto vel = st->find("cursor_velocity");
    if (vel != st->end() && !read_vec3(*vel, v)) v.setZero();
    s.position_m = dev.axes_ * (x - dev.p_.origin_m);
    s.velocity_mps = dev.axes_ * v;
    if (!dev.grip_id_.empty()) {
      const json* g = find_device(msg, "wireless_verse_grip", dev.grip_id_);
      const bool wireless = g != nullptr;
      if (!g) g = find_device(msg, "verse_grip", dev.grip_id_);
      auto gs = g ? g->find("state") : json::const_iterator();
      if (g && gs != g->end() && gs->is_object()) {
        Quat q;
        auto o = gs->find("orientation");
        if (o != gs->end() && read_quat(*o, q))
          s.orientation = Quat(dev.axes_ * q.toRotationMatrix() * dev.axes_.transpose()).normalized();
        int32_t b = 0;
        if (wireless) {
          auto bs = gs->find("buttons");
          if (bs != gs->end() && bs->is_object()) {
            const char* names[] = {"a", "b", "c"};
            for (int i = 0; i < 3; ++i) {
              auto it = bs->find(names[i]);
              if (it != bs->end() && it->is_boolean() && it->get<bool>()) b |= 1 << i;
            }
            s.buttons = b;
          }
        } else {
          auto it = gs->find("button");
          if (it != gs->end() && it->is_boolean()) s.buttons = it->get<bool>() ? kButtonGrab : 0;
        }
      }
    }
    return true;
  }

  void on_inventory(const json& msg) {
    auto arr = msg.find("inverse3");
    std::string ids;
    if (arr != msg.end() && arr->is_array())
      for (const auto& e : *arr) ids += (ids.empty() ? "" : ", ") + id_of(e);
    if (ids.empty()) {
      fail_open("inverse3: the Inverse Service at " + dev.p_.url +
                " reports no Inverse3 (is the device plugged in, powered and calibrated?)");
      return;
    }
    const json* inv = nullptr;
    if (dev.p_.device_id.empty()) {
      inv = &(*arr)[0];
      dev.device_id_ = id_of(*inv);
    } else {
      dev.device_id_ = dev.p_.device_id;
      inv = find_device(msg, "inverse3", dev.device_id_);
      if (!inv) {
        fail_open("inverse3: no Inverse3 with device_id=" + dev.p_.device_id + " at " + dev.p_.url +
                  "; the service reports: " + ids);
        return;
      }
    }
    // The grip: the one asked for, else the first wireless one, else the first wired one.
    dev.grip_id_ = dev.p_.grip_id;
    if (dev.grip_id_.empty()) {
      for (const char* kind : {"wireless_verse_grip", "verse_grip"}) {
        auto g = msg.find(kind);
        if (g != msg.end() && g->is_array() && !g->empty() && (*g)[0].is_object()) {
          dev.grip_id_ = id_of((*g)[0]);
          break;
        }
      }
    } else if (!find_device(msg, "wireless_verse_grip", dev.grip_id_) && !find_device(msg, "verse_grip", dev.grip_id_)) {
      fail_open("inverse3: no Verse Grip with grip_id=" + dev.grip_id_ + " at " + dev.p_.url);
      return;
    }
    // "Inverse3 049D (firmware 7.4, right-handed)" from the config, where given.
    // "Haply Inverse3 (version 7.4, right-handed)" from the config, where given.
    std::string type = "Inverse3", details;
    auto cfg = inv->find("config");
    if (cfg != inv->end() && cfg->is_object()) {
      auto t = cfg->find("type");
      if (t != cfg->end() && t->is_string() && !t->get<std::string>().empty()) {
        type = t->get<std::string>();
        type[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(type[0])));
      }
      auto info = cfg->find("device_info");
      if (info != cfg->end() && info->is_object()) {
        auto ma = info->find("major_version"), mi = info->find("minor_version");
        if (ma != info->end() && mi != info->end() && ma->is_number_integer() && mi->is_number_integer())
          details += "version " + std::to_string(ma->get<int64_t>()) + "." + std::to_string(mi->get<int64_t>());
      }
      auto h = cfg->find("handedness");
      if (h != cfg->end() && h->is_string()) details += (details.empty() ? "" : ", ") + h->get<std::string>() + "-handed";
    }
    dev.model_ = "Haply " + type + (details.empty() ? "" : " (" + details + ")");
    std::string d = dev.model_ + " " + dev.device_id_;
    if (!dev.grip_id_.empty()) {
      d += ", Verse Grip " + dev.grip_id_;
      dev.grip_buttons_ = find_device(msg, "wireless_verse_grip", dev.grip_id_) ? 3 : 1;
    }
    dev.description_ = d;
    if (!parse_state(msg, last)) {
      fail_open("inverse3: the Inverse Service's first message has no valid state for Inverse3 " + dev.device_id_);
      return;
    }
    last_good_s = last.received_s = mono_s();
    dev.state_box_.write(last);
    have_inventory = true;
    dev.link_.store(kUp, std::memory_order_release);
    send_force(Vec3::Zero());   // the first command: state flows from here on
    {
      std::lock_guard<std::mutex> lock(m);
      phase = 1;
    }
    cv.notify_all();
    next = Clock::now();
    arm();
  }

  void on_message(const std::string& payload) {
    awaiting = false;
    const json msg = json::parse(payload, nullptr, false);
    if (!have_inventory) {
      if (msg.is_discarded() || !msg.is_object()) {
        fail_open("inverse3: the service at " + dev.p_.url + " sent something that is not JSON: is it the Inverse Service?");
        finish();
        return;
      }
      on_inventory(msg);
      if (!have_inventory) finish();
      return;
    }
    if (!msg.is_discarded() && msg.is_object() && parse_state(msg, last)) {
      last_good_s = last.received_s = mono_s();
      dev.state_box_.write(last);
      dev.replies_.fetch_add(1, std::memory_order_relaxed);
    } else {
      dev.malformed_.fetch_add(1, std::memory_order_relaxed);
    }
  }

  void arm() {
    const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / dev.p_.rate_hz));
    next += period;
    const auto now = Clock::now();
    if (next < now) next = now + period;
    timer->expires_at(next);
    timer->async_wait([this](const asio::error_code& ec) {
      if (!ec) tick();
    });
  }

  // Each period: close if asked, check the link, send the newest force (one command in flight).
  void tick() {
    if (dev.link_.load(std::memory_order_acquire) != kUp) return;
    if (closing.load(std::memory_order_acquire)) {
      dev.link_.store(kClosed, std::memory_order_release);
      finish();
      return;
    }
    const double now = mono_s();
    if (awaiting && now - sent_s > dev.p_.timeout_s) return lose(kNoReply);
    if (now - last_good_s > dev.p_.timeout_s) return lose(kNoValidState);
    if (!awaiting) {
      dev.command_box_.update();
      Vec3 f = dev.force_on_.load(std::memory_order_acquire) ? dev.command_box_.front().force_n : Vec3::Zero();
      const double n = f.norm();
      if (n > dev.spec_.max_force_n) f *= dev.spec_.max_force_n / n;   // second guard after the bridge's clamp
      send_force(dev.axes_.transpose() * f);
    }
    arm();
  }
};

namespace {
Mat3 axes_option(const std::string& axes) {
  try {
    return AxisMap::parse(axes).matrix();
  } catch (const std::invalid_argument& e) {
    throw std::invalid_argument(std::string("device option ") + e.what());
  }
}
}  // namespace

Inverse3Device::Inverse3Device(const DeviceSpec& spec, const Inverse3Params& p)
    : spec_(spec), p_(p), axes_(axes_option(p.axes)) {
  if (p_.url.rfind("ws://", 0) != 0)
    throw std::invalid_argument("device option url='" + p_.url + "': expected ws://host:port (the Inverse Service)");
  if (!(p_.rate_hz > 0 && p_.rate_hz <= 10000)) throw std::invalid_argument("device 'inverse3': rate_hz must be in (0, 10000]");
  if (!(p_.timeout_s > 0 && p_.timeout_s <= 10)) throw std::invalid_argument("device 'inverse3': timeout_s must be in (0, 10]");
  if (!(p_.connect_timeout_s > 0 && p_.connect_timeout_s <= 60))
    throw std::invalid_argument("device 'inverse3': connect_timeout_s must be in (0, 60]");
  if (p_.force_key != "vector" && p_.force_key != "values")
    throw std::invalid_argument("device option force_key='" + p_.force_key + "': expected vector or values");
  if (!p_.origin_m.allFinite()) throw std::invalid_argument("device 'inverse3': origin_m must be finite");
}

Inverse3Device::~Inverse3Device() { close(); }

Status Inverse3Device::open() {
  if (io_) return Status::Error("inverse3: already open");
  io_ = std::make_unique<Io>(*this);
  Io& io = *io_;
  WsClient& c = io.client;
  c.clear_access_channels(websocketpp::log::alevel::all);
  c.clear_error_channels(websocketpp::log::elevel::all);
  c.init_asio();
  c.set_open_handshake_timeout(static_cast<long>(1000 * p_.connect_timeout_s));
  c.set_close_handshake_timeout(200);
  c.set_socket_init_handler([](websocketpp::connection_hdl, asio::ip::tcp::socket& s) {
    asio::error_code ec;
    s.set_option(asio::ip::tcp::no_delay(true), ec);   // one small message each way per tick
  });
  c.set_open_handler([&io](websocketpp::connection_hdl) { io.socket_open = true; });
  c.set_fail_handler([this, &io](websocketpp::connection_hdl h) {
    auto con = io.client.get_con_from_hdl(h);
    const auto tec = con->get_transport_ec();
    io.fail_open("inverse3: cannot connect to the Inverse Service at " + p_.url + " (" +
                 (tec ? tec.message() : con->get_ec().message()) +
                 "): is it installed and running? (Linux: systemctl status haply-inverse-service)");
  });
  c.set_close_handler([this, &io](websocketpp::connection_hdl) {
    io.socket_open = false;
    if (!io.have_inventory) io.fail_open("inverse3: the service at " + p_.url + " closed the connection before sending its device list");
    int expected = kUp;
    link_.compare_exchange_strong(expected, kRemoteClosed, std::memory_order_acq_rel);
    if (io.timer) io.timer->cancel();
  });
  c.set_message_handler([&io](websocketpp::connection_hdl, WsClient::message_ptr m) { io.on_message(m->get_payload()); });
  websocketpp::lib::error_code ec;
  WsClient::connection_ptr con = c.get_connection(p_.url, ec);
  if (ec) {
    open_error_ = "inverse3: url='" + p_.url + "': " + ec.message();
    io_.reset();
    return Status::Error(open_error_.c_str());
  }
  io.hdl = con->get_handle();
  io.timer = std::make_unique<asio::steady_timer>(c.get_io_service());
  c.connect(con);
  thread_ = std::thread([this] {
    try {
      io_->client.run();
    } catch (const std::exception&) {
      int expected = kUp;
      link_.compare_exchange_strong(expected, kSocketError);
    }
    std::lock_guard<std::mutex> lock(io_->m);
    io_->finished = true;
    if (io_->phase == 0) {
      io_->phase = 2;
      io_->error = "inverse3: the connection to " + p_.url + " ended before the device list arrived";
    }
    io_->cv.notify_all();
  });
  std::unique_lock<std::mutex> lock(io.m);
  const bool answered = io.cv.wait_for(lock, std::chrono::duration<double>(p_.connect_timeout_s), [&io] { return io.phase != 0; });
  if (answered && io.phase == 1) {
    // A crash of the bridge: force off (one atomic store) so a still-running I/O thread sends zero; when
    // the process is gone its socket closes and the service, getting no more commands, idles the device.
    register_emergency_stop(this, [](void* self) noexcept {
      static_cast<Inverse3Device*>(self)->force_on_.store(false, std::memory_order_release);
    });
    return Status::Ok();
  }
  open_error_ = answered ? io.error
                         : "inverse3: no device list from " + p_.url + " within " + std::to_string(p_.connect_timeout_s) +
                               " s: is it the Inverse Service?";
  lock.unlock();
  close();
  return Status::Error(open_error_.c_str());
}

DeviceDescription Inverse3Device::describe() const {
  DeviceDescription d;
  d.model = model_;
  d.serial = device_id_;
  d.max_torque_nm = 0;   // no actuated rotation; the service reports no other limit
  d.buttons = grip_buttons_;
  d.orientation = !grip_id_.empty();
  d.torque = false;
  d.axes = AxisMap::parse(p_.axes).str();
  return d;
}

Status Inverse3Device::enable_force(bool on) noexcept {
  force_on_.store(on, std::memory_order_release);
  const int link = link_.load(std::memory_order_acquire);
  return link == kUp || !on ? Status::Ok() : Status::Error(kLinkReason[link]);
}

Status Inverse3Device::read(double time_s, DeviceReading& out) noexcept {
  state_box_.update();
  const int link = link_.load(std::memory_order_acquire);
  if (link != kUp) return Status::Error(kLinkReason[link]);
  const Inverse3Sample& s = state_box_.front();
  if (state_box_.front_seq() == 0) return Status::Error(kLinkReason[kConnecting]);
  if (mono_s() - s.received_s > p_.timeout_s) return Status::Error(kLinkReason[kStale]);
  out.time_s = time_s;
  out.seq = ++seq_;
  out.position_m = s.position_m;
  out.linear_velocity_mps = s.velocity_mps;
  out.orientation = s.orientation;
  out.buttons = s.buttons;
  out.grab_body = 0;
  out.grab_seq = 0;
  return Status::Ok();
}

Status Inverse3Device::write(const Vec3& force_n, const Vec3& torque_nm) noexcept {
  if (!force_n.allFinite() || !torque_nm.allFinite()) return Status::Error("non-finite force");
  command_box_.back().force_n = force_n;   // the Inverse3 renders no torque; zero while force is off
  command_box_.publish();
  const int link = link_.load(std::memory_order_acquire);
  return link == kUp ? Status::Ok() : Status::Error(kLinkReason[link]);
}

void Inverse3Device::close() noexcept {
  if (closed_ || !io_) return;
  closed_ = true;
  unregister_emergency_stop(this);
  force_on_.store(false, std::memory_order_release);
  Io& io = *io_;
  io.closing.store(true, std::memory_order_release);
  if (link_.load(std::memory_order_acquire) != kConnecting) {
    // The I/O thread's next tick sends the zero force and closes; the close handshake is bounded.
    std::unique_lock<std::mutex> lock(io.m);
    io.cv.wait_for(lock, std::chrono::seconds(1), [&io] { return io.finished; });
  }
  io.client.stop();   // whatever is still pending (a link already lost, a service that never answers)
  if (thread_.joinable()) thread_.join();
  int up = kUp;
  link_.compare_exchange_strong(up, kClosed);
}

}  // namespace haptree::device
