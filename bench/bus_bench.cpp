// bus_bench: round-trip latency (median, p99) and rate of a device-state -> feedback ping-pong, the
// device_bridge <-> coupler link, over each transport:
//   shm-thread   shared-memory channels, two threads of one process (busy polling)
//   shm-process  shared-memory channels, two processes (fork; busy polling)
//   memq         one memq:// Bus; the echo runs in the bus's HandlerThread
//   udpm         udpm://, two processes inside a private network namespace (needs root)
// The "device" side publishes lcmt_device_state seq k and waits for lcmt_feedback echo_device_seq k.
// Encoding/decoding is included (the real messages are sent). Figures in docs/performance.md.
#include <sys/wait.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "haptree/bus/bus.hpp"
#include "haptree/bus/shm_channel.hpp"
#include "netns.hpp"

using namespace haptree;
using namespace haptree::bus;
using Clock = std::chrono::steady_clock;

namespace {

struct Result {
  std::string transport;
  int n = 0;
  double median_us = 0, p99_us = 0, max_us = 0, rate_hz = 0;
};

Result summarize(const std::string& name, std::vector<double> rtt_us, double elapsed_s) {
  Result r;
  r.transport = name;
  r.n = static_cast<int>(rtt_us.size());
  if (rtt_us.empty()) return r;
  std::sort(rtt_us.begin(), rtt_us.end());
  r.median_us = rtt_us[rtt_us.size() / 2];
  r.p99_us = rtt_us[std::min(rtt_us.size() - 1, static_cast<size_t>(0.99 * rtt_us.size()))];
  r.max_us = rtt_us.back();
  r.rate_hz = rtt_us.size() / elapsed_s;
  return r;
}

void print(const Result& r) {
  std::printf("| %-12s | %7d | %9.2f | %9.2f | %9.1f | %10.0f |\n", r.transport.c_str(), r.n, r.median_us,
              r.p99_us, r.max_us, r.rate_hz);
  std::fflush(stdout);
}

lcmt_device_state make_state(int64_t k) {
  lcmt_device_state m{};
  stamp(m, 7);
  m.seq = k;
  m.position_m[0] = 1e-3 * static_cast<double>(k % 100);
  m.orientation[0] = 1;
  return m;
}

// Device side over shm: publish state k, spin until feedback echoes k.
std::vector<double> shm_device_side(const std::string& state_ch, const std::string& fb_ch, int warmup, int n,
                                    double* elapsed_s) {
  ShmWriter out(state_ch);
  ShmReader in(fb_ch);
  lcmt_feedback fb{};
  std::vector<double> rtt;
  rtt.reserve(static_cast<size_t>(n));
  Clock::time_point t_start;
  for (int k = 1; k <= warmup + n; ++k) {
    if (k == warmup + 1) t_start = Clock::now();
    const auto t0 = Clock::now();
    out.write_msg(make_state(k));
    const auto give_up = t0 + std::chrono::seconds(5);
    auto resend = t0 + std::chrono::milliseconds(10);
    while (true) {
      if (in.read_msg(fb) == ShmRead::kNew && fb.echo_device_seq == k) break;
      // A reader drops what was written before it opened: until the echo side is up (a forked
      // process starts later than this loop), the first state is published again.
      if (Clock::now() > resend) {
        out.write_msg(make_state(k));
        resend = Clock::now() + std::chrono::milliseconds(10);
      }
      if (Clock::now() > give_up) {
        std::fprintf(stderr, "shm: no echo for seq %d within 5 s\n", k);
        *elapsed_s = std::chrono::duration<double>(Clock::now() - t_start).count();
        return rtt;
      }
    }
    if (k > warmup) rtt.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
  }
  *elapsed_s = std::chrono::duration<double>(Clock::now() - t_start).count();
  return rtt;
}

// Coupler side over shm: echo every new state as feedback until seq `last`.
void shm_echo_side(const std::string& state_ch, const std::string& fb_ch, int64_t last) {
  ShmReader in(state_ch);
  ShmWriter out(fb_ch);
  lcmt_device_state st{};
  lcmt_feedback fb{};
  const auto give_up = Clock::now() + std::chrono::seconds(120);
  while (Clock::now() < give_up) {
    if (in.read_msg(st) != ShmRead::kNew) continue;
    stamp(fb, 7);
    fb.seq = st.seq;
    fb.echo_device_seq = st.seq;
    fb.force_n[0] = -st.position_m[0];
    out.write_msg(fb);
    if (st.seq >= last) return;
  }
}

Result bench_shm(bool processes, int warmup, int n) {
  const std::string tag = std::to_string(::getpid());
  const std::string state_ch = "HAPTREE_BENCH_STATE_" + tag, fb_ch = "HAPTREE_BENCH_FB_" + tag;
  ShmChannel::remove(state_ch);
  ShmChannel::remove(fb_ch);
  { ShmWriter a(state_ch), b(fb_ch); }  // create both segments before either side starts
  double elapsed = 0;
  std::vector<double> rtt;
  if (processes) {
    const pid_t pid = ::fork();
    if (pid == 0) {
      shm_echo_side(state_ch, fb_ch, warmup + n);
      ::_exit(0);
    }
    rtt = shm_device_side(state_ch, fb_ch, warmup, n, &elapsed);
    ::waitpid(pid, nullptr, 0);
  } else {
    std::thread echo([&] { shm_echo_side(state_ch, fb_ch, warmup + n); });
    rtt = shm_device_side(state_ch, fb_ch, warmup, n, &elapsed);
    echo.join();
  }
  ShmChannel::remove(state_ch);
  ShmChannel::remove(fb_ch);
  return summarize(processes ? "shm-process" : "shm-thread", rtt, elapsed);
}

// LCM device side: publish, then handle until the echo arrives (handler writes into a mailbox).
std::vector<double> lcm_device_side(Bus& bus, bool handle_here, int warmup, int n, double* elapsed_s) {
  LatestValue<lcmt_feedback> box;
  bus.subscribe_latest<lcmt_feedback>("HAPTREE_FEEDBACK_0", box);
  std::vector<double> rtt;
  rtt.reserve(static_cast<size_t>(n));
  lcmt_feedback fb{};
  Clock::time_point t_start;
  for (int k = 1; k <= warmup + n; ++k) {
    if (k == warmup + 1) t_start = Clock::now();
    const auto t0 = Clock::now();
    bus.publish("HAPTREE_DEVICE_STATE_0", make_state(k));
    const auto give_up = t0 + std::chrono::seconds(2);
    bool got = false;
    while (!got && Clock::now() < give_up) {
      if (handle_here) bus.handle_timeout(100);
      if (box.update() && box.front().echo_device_seq == k) got = true;
    }
    if (!got) {  // a lost datagram: counted by its absence (n below the requested count)
      std::fprintf(stderr, "lcm: no echo for seq %d\n", k);
      continue;
    }
    if (k > warmup) rtt.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
  }
  *elapsed_s = std::chrono::duration<double>(Clock::now() - t_start).count();
  (void)fb;
  return rtt;
}

struct Echo {
  Bus* bus;
  lcmt_feedback fb{};
  void on_state(const lcmt_device_state& st) {
    stamp(fb, 7);
    fb.seq = st.seq;
    fb.echo_device_seq = st.seq;
    fb.force_n[0] = -st.position_m[0];
    bus->publish("HAPTREE_FEEDBACK_0", fb);
  }
};

Result bench_memq(int warmup, int n) {
  Bus bus("memq://");
  Echo echo{&bus};
  bus.subscribe<lcmt_device_state>("HAPTREE_DEVICE_STATE_0",
                                   [&](const lcmt_device_state& st, const std::string&) { echo.on_state(st); });
  HandlerThread thread(bus, 50);
  double elapsed = 0;
  auto rtt = lcm_device_side(bus, false, warmup, n, &elapsed);
  thread.stop();
  return summarize("memq", rtt, elapsed);
}

// Inside a private network namespace: fork an echo process, run the device side here; the result goes
// back to the parent through the pipe as one line.
Result bench_udpm(int warmup, int n) {
  const std::string url = "udpm://239.255.76.67:7671?ttl=0";
  auto res = haptree::testing::run_in_private_netns(haptree::testing::kNetnsMulticastSetup, [&](int fd) {
    const pid_t pid = ::fork();
    if (pid == 0) {
      try {
        Bus bus(url);
        Echo echo{&bus};
        int64_t last = 0;
        bus.subscribe<lcmt_device_state>("HAPTREE_DEVICE_STATE_0",
                                         [&](const lcmt_device_state& st, const std::string&) {
                                           echo.on_state(st);
                                           last = st.seq;
                                         });
        const auto give_up = Clock::now() + std::chrono::seconds(120);
        while (last < warmup + n && Clock::now() < give_up) bus.handle_timeout(100);
      } catch (const std::exception& e) {
        std::fprintf(stderr, "udpm echo: %s\n", e.what());
      }
      ::_exit(0);
    }
    try {
      Bus bus(url);
      std::this_thread::sleep_for(std::chrono::milliseconds(200));  // let the echo subscribe
      double elapsed = 0;
      auto rtt = lcm_device_side(bus, true, warmup, n, &elapsed);
      ::kill(pid, SIGTERM);
      ::waitpid(pid, nullptr, 0);
      const Result r = summarize("udpm", rtt, elapsed);
      dprintf(fd, "%d %.6f %.6f %.6f %.6f", r.n, r.median_us, r.p99_us, r.max_us, r.rate_hz);
      return 0;
    } catch (const std::exception& e) {
      dprintf(fd, "error %s", e.what());
      ::kill(pid, SIGTERM);
      ::waitpid(pid, nullptr, 0);
      return 1;
    }
  });
  Result r;
  r.transport = "udpm";
  if (res.exit_code != 0 ||
      std::sscanf(res.output.c_str(), "%d %lf %lf %lf %lf", &r.n, &r.median_us, &r.p99_us, &r.max_us, &r.rate_hz) != 5)
    std::fprintf(stderr, "udpm benchmark failed: %s\n", res.output.c_str());
  return r;
}

// Cost of authentication per message (auth.hpp): seal on the sender + open on the receiver, thread
// CPU time, for messages of `bytes` bytes. Prints median and mean over `reps` batches of 1000.
void bench_auth(int reps) {
  const auto key = session_key_from_bytes("bus_bench session key, thirty-two bytes or more");
  Authenticator tx(key), rx(key);
  const std::string ch = "HAPTREE_FEEDBACK_0";
  std::printf("\n| authentication (seal + open, HMAC-SHA512-256) | bytes | median µs/msg | mean µs/msg |\n|---|---:|---:|---:|\n");
  for (size_t bytes : {size_t(93), size_t(109), size_t(1517), size_t(3236)}) {
    std::vector<uint8_t> msg(bytes + kAuthTrailerBytes, 0x5a);
    std::vector<double> per_msg;
    for (int r = 0; r < reps; ++r) {
      timespec a{}, b{};
      clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
      for (int i = 0; i < 1000; ++i) {
        const size_t n = tx.seal(ch, msg.data(), bytes);
        size_t payload = 0;
        if (rx.open(ch, msg.data(), n, &payload) != AuthVerdict::kOk) std::abort();
      }
      clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
      per_msg.push_back(((b.tv_sec - a.tv_sec) * 1e9 + (b.tv_nsec - a.tv_nsec)) / 1000.0 / 1000.0);
    }
    std::sort(per_msg.begin(), per_msg.end());
    double mean = 0;
    for (double v : per_msg) mean += v / per_msg.size();
    std::printf("| %s | %zu | %.2f | %.2f |\n", bytes < 200 ? "feedback / device state" : "coupling snapshot",
                bytes, per_msg[per_msg.size() / 2], mean);
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"bus_bench: device-state -> feedback round-trip latency over shm, memq and udpm (netns)"};
  std::vector<std::string> transports = {"shm-thread", "shm-process", "memq", "udpm"};
  int round_trips = 20000, warmup = 1000;
  app.add_option("--transport", transports, "transports to measure")
      ->check(CLI::IsMember({"shm-thread", "shm-process", "memq", "udpm", "auth"}))
      ->capture_default_str();
  app.add_option("--round-trips", round_trips, "measured round trips per transport")
      ->check(CLI::Range(10, 10000000))
      ->capture_default_str();
  app.add_option("--warmup", warmup, "round trips before measuring")->check(CLI::Range(0, 1000000))->capture_default_str();
  std::string key_file;
  app.add_option("--session-key-file", key_file,
                 "measure keyed sessions (every message sealed and verified); transport `auth`: the cost per message alone")
      ->envname("HAPTREE_SESSION_KEY_FILE");
  CLI11_PARSE(app, argc, argv);
  if (!key_file.empty()) {
    set_process_session_key_file(key_file);
    std::printf("keyed session: key %s\n", process_session_key()->fingerprint.c_str());
  }

  std::printf("| transport    | round trips | median µs | p99 µs | max µs | round trips/s |\n");
  std::printf("|---|---:|---:|---:|---:|---:|\n");
  for (const auto& t : transports) {
    try {
      if (t == "shm-thread") print(bench_shm(false, warmup, round_trips));
      else if (t == "shm-process") print(bench_shm(true, warmup, round_trips));
      else if (t == "memq") print(bench_memq(warmup, round_trips));
      else if (t == "udpm") print(bench_udpm(warmup, round_trips));
      else if (t == "auth") bench_auth(std::max(5, round_trips / 1000));
    } catch (const std::exception& e) {
      std::fprintf(stderr, "%s: %s\n", t.c_str(), e.what());
      return 1;
    }
  }
  return 0;
}
