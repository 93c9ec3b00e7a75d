#include "tests/device/inverse3/fake_inverse_service.hpp"

#define ASIO_STANDALONE
#define _WEBSOCKETPP_CPP11_STL_
#include <nlohmann/json.hpp>
#include <websocketpp/config/asio_no_tls.hpp>
#include <websocketpp/server.hpp>

#include <algorithm>
#include <chrono>
#include <map>
#include <stdexcept>
#include <thread>

namespace haptree::testing {

namespace {
using json = nlohmann::json;
using WsServer = websocketpp::server<websocketpp::config::asio>;
using Clock = std::chrono::steady_clock;

json vec3(const Vec3& v) { return {{"x", v.x()}, {"y", v.y()}, {"z", v.z()}}; }
}  // namespace

struct FakeInverseService::Impl {
  FakeInverseService& self;
  FakeInverseOptions o;
  WsServer srv;
  std::thread thread;
  mutable std::mutex m;            // guards everything below (test thread vs server thread)
  std::vector<ForceRecord> log;
  Vec3 x, v, f = Vec3::Zero();
  struct Conn {
    int number = 0;
    Clock::time_point t0, last;
    bool faulted = false;
  };
  std::map<websocketpp::connection_hdl, Conn, std::owner_less<websocketpp::connection_hdl>> conns;
  bool stopped = false;

  Impl(FakeInverseService& s, const FakeInverseOptions& opt) : self(s), o(opt), x(opt.rest_m), v(Vec3::Zero()) {}

  int buttons_at(double t) const {
    int b = 0;
    for (const auto& e : o.buttons)
      if (t >= e.from_s && t < e.to_s) b |= e.mask;
    return b;
  }

  // The whole message: every device's state (and, for the inventory, config and status).
  json message(double t, bool inventory) const {
    json inv = {{"device_id", o.device_id},
                {"state",
                 {{"cursor_position", vec3(x)}, {"cursor_velocity", vec3(v)}, {"current_cursor_force", vec3(f)},
                  {"body_orientation", {{"w", 1.0}, {"x", 0.0}, {"y", 0.0}, {"z", 0.0}}}}},
                {"status", {{"calibrated", true}, {"in_use", true}, {"power_supply", true}, {"ready", true}, {"started", true}}}};
    if (inventory)
      inv["config"] = {{"type", "inverse3"},
                       {"device_info", {{"major_version", 7}, {"minor_version", 4}, {"id", o.device_id}, {"device_type", 4}}},
                       {"handedness", "right"},
                       {"basis", {{"permutation", "XYZ"}}}};
    json msg = json::object();
    if (inventory) msg["session_id"] = 1;
    msg["inverse3"] = o.no_inverse3 ? json::array() : json::array({inv});
    if (!o.grip_id.empty()) {
      const int b = buttons_at(t);
      const Quat& q = o.grip_orientation;
      json st = {{"orientation", {{"w", q.w()}, {"x", q.x()}, {"y", q.y()}, {"z", q.z()}}}, {"hall", 0}};
      if (o.wireless_grip) {
        st["buttons"] = {{"a", (b & 1) != 0}, {"b", (b & 2) != 0}, {"c", (b & 4) != 0}};
        st["battery_level"] = 0.9;
      } else {
        st["button"] = (b & 1) != 0;
      }
      json g = {{"device_id", o.grip_id}, {"state", st}};
      if (inventory) g["config"] = {{"type", o.wireless_grip ? "wireless_verse_grip" : "verse_grip"}};
      msg[o.wireless_grip ? "wireless_verse_grip" : "verse_grip"] = json::array({g});
    }
    return msg;
  }

  // Point mass on a damped spring to rest_m, under the last commanded force, over dt (1 ms substeps).
  void step(double dt) {
    dt = std::min(dt, 0.05);
    const int n = std::max(1, static_cast<int>(std::ceil(dt / 1e-3)));
    const double h = dt / n;
    for (int i = 0; i < n; ++i) {
      const Vec3 a = (f - o.stiffness_n_per_m * (x - o.rest_m) - o.damping_n_s_per_m * v) / o.mass_kg;
      v += h * a;
      x += h * v;
    }
  }

  void send(websocketpp::connection_hdl h, const std::string& s) {
    websocketpp::lib::error_code ec;
    srv.send(h, s, websocketpp::frame::opcode::text, ec);
  }

  void on_open(websocketpp::connection_hdl h) {
    std::string text;
    {
      std::lock_guard<std::mutex> lock(m);
      Conn c;
      c.number = static_cast<int>(self.connections_.fetch_add(1) + 1);
      c.t0 = c.last = Clock::now();
      conns[h] = c;
      self.open_.fetch_add(1);
      text = message(0, true).dump();
    }
    send(h, text);
  }

  void on_close(websocketpp::connection_hdl h) {
    std::lock_guard<std::mutex> lock(m);
    if (conns.erase(h)) self.open_.fetch_sub(1);
  }

  void on_message(websocketpp::connection_hdl h, WsServer::message_ptr msg) {
    std::string reply;
    FakeFault fault = FakeFault::kNone;
    {
      std::lock_guard<std::mutex> lock(m);
      auto it = conns.find(h);
      if (it == conns.end()) return;
      Conn& c = it->second;
      const auto now = Clock::now();
      const double t = std::chrono::duration<double>(now - c.t0).count();
      self.messages_.fetch_add(1);
      // The force this command sets, if it names our device with a field this service reads.
      const json j = json::parse(msg->get_payload(), nullptr, false);
      ForceRecord r;
      r.t_s = t;
      r.connection = c.number;
      bool is_force = false;
      if (j.is_object() && j.contains("inverse3") && j["inverse3"].is_array()) {
        for (const auto& d : j["inverse3"]) {
          if (!d.is_object() || d.value("device_id", std::string()) != o.device_id) continue;
          if (!d.contains("commands") || !d["commands"].is_object() || !d["commands"].contains("set_cursor_force")) continue;
          const json& sf = d["commands"]["set_cursor_force"];
          is_force = true;
          const char* key = sf.contains("values") ? "values" : sf.contains("vector") && !o.old_dialect ? "vector" : nullptr;
          if (key && sf[key].is_object()) {
            const json& fv = sf[key];
            r.force_n = Vec3(fv.value("x", 0.0), fv.value("y", 0.0), fv.value("z", 0.0));
            r.applied = r.force_n.allFinite();
          }
        }
      }
      step(std::chrono::duration<double>(now - c.last).count());
      c.last = now;
      if (is_force) {
        log.push_back(r);
        f = r.applied ? r.force_n : Vec3::Zero();   // a command is valid for one tick
      } else {
        f = Vec3::Zero();
      }
      if (o.fault != FakeFault::kNone && t >= o.fault_after_s) {
        fault = o.fault;
        c.faulted = true;
      }
      if (fault == FakeFault::kNone) reply = message(t, false).dump();
    }
    switch (fault) {
      case FakeFault::kNone: send(h, reply); break;
      case FakeFault::kStopReplying: break;
      case FakeFault::kMalformed: send(h, "{\"inverse3\": [ this is not json"); break;
      case FakeFault::kClose: {
        websocketpp::lib::error_code ec;
        srv.close(h, websocketpp::close::status::going_away, "fake service: injected close", ec);
        break;
      }
    }
  }
};

FakeInverseService::FakeInverseService(const FakeInverseOptions& o) : impl_(std::make_unique<Impl>(*this, o)) {
  Impl& im = *impl_;
  im.srv.clear_access_channels(websocketpp::log::alevel::all);
  im.srv.clear_error_channels(websocketpp::log::elevel::all);
  im.srv.init_asio();
  im.srv.set_reuse_addr(true);
  im.srv.set_socket_init_handler([](websocketpp::connection_hdl, asio::ip::tcp::socket& s) {
    asio::error_code ec;
    s.set_option(asio::ip::tcp::no_delay(true), ec);
  });
  im.srv.set_open_handler([&im](websocketpp::connection_hdl h) { im.on_open(h); });
  im.srv.set_close_handler([&im](websocketpp::connection_hdl h) { im.on_close(h); });
  im.srv.set_fail_handler([&im](websocketpp::connection_hdl h) { im.on_close(h); });
  im.srv.set_message_handler([&im](websocketpp::connection_hdl h, WsServer::message_ptr m) { im.on_message(h, m); });
  websocketpp::lib::error_code ec;
  im.srv.listen(asio::ip::tcp::endpoint(asio::ip::make_address("127.0.0.1"), 0), ec);
  if (ec) throw std::runtime_error("fake Inverse Service: cannot listen on 127.0.0.1: " + ec.message());
  asio::error_code aec;
  port_ = im.srv.get_local_endpoint(aec).port();
  if (aec) throw std::runtime_error("fake Inverse Service: no local port: " + aec.message());
  im.srv.start_accept(ec);
  if (ec) throw std::runtime_error("fake Inverse Service: accept: " + ec.message());
  im.thread = std::thread([&im] { im.srv.run(); });
}

FakeInverseService::~FakeInverseService() { stop(); }

void FakeInverseService::stop() {
  if (!impl_ || impl_->stopped) return;
  impl_->stopped = true;
  impl_->srv.stop();
  if (impl_->thread.joinable()) impl_->thread.join();
}

std::vector<ForceRecord> FakeInverseService::forces() const {
  std::lock_guard<std::mutex> lock(impl_->m);
  return impl_->log;
}

Vec3 FakeInverseService::position() const {
  std::lock_guard<std::mutex> lock(impl_->m);
  return impl_->x;
}

}  // namespace haptree::testing
