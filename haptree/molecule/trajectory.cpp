#include "haptree/molecule/trajectory.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace haptree::mol {

namespace {
void put_i32(std::vector<uint8_t>& b, int32_t v) {
  const auto* p = reinterpret_cast<const uint8_t*>(&v);
  b.insert(b.end(), p, p + 4);
}
void put_f32(std::vector<uint8_t>& b, float v) {
  const auto* p = reinterpret_cast<const uint8_t*>(&v);
  b.insert(b.end(), p, p + 4);
}
}  // namespace

DcdWriter::DcdWriter(const std::string& path, int natoms, double dt_ps, int step_interval, int first_step,
                     const std::string& title)
    : path_(path), natoms_(natoms), step_interval_(step_interval), first_step_(first_step) {
  if (natoms <= 0) throw std::invalid_argument(path + ": a DCD needs at least one atom");
  if (step_interval < 1) throw std::invalid_argument(path + ": DCD frame interval must be >= 1 step");
  if (!(dt_ps > 0) || !std::isfinite(dt_ps)) throw std::invalid_argument(path + ": DCD time step must be > 0");
  f_ = std::fopen(path.c_str(), "wb");
  if (!f_) throw std::runtime_error(path + ": cannot open for writing: " + std::strerror(errno));
  std::vector<uint8_t> h;
  put_i32(h, 84);
  h.insert(h.end(), {'C', 'O', 'R', 'D'});
  int32_t icntrl[20] = {};
  icntrl[1] = first_step;
  icntrl[2] = step_interval;
  icntrl[19] = 24;   // CHARMM version: readers then take DELTA as float32 and look for the cell flag
  for (int i = 0; i < 20; ++i) {
    if (i == 9) put_f32(h, static_cast<float>(dt_ps / kAkmaTimePs));
    else put_i32(h, icntrl[i]);
  }
  put_i32(h, 84);
  char t[2][80];
  std::memset(t, ' ', sizeof t);
  std::memcpy(t[0], title.data(), std::min<size_t>(80, title.size()));
  const std::string t2 = "REMARKS written by haptree (positions in angstrom)";
  std::memcpy(t[1], t2.data(), std::min<size_t>(80, t2.size()));
  put_i32(h, 4 + 160);
  put_i32(h, 2);
  h.insert(h.end(), &t[0][0], &t[0][0] + 160);
  put_i32(h, 4 + 160);
  put_i32(h, 4);
  put_i32(h, natoms);
  put_i32(h, 4);
  buf_.resize(static_cast<size_t>(natoms) + 2);
  if (std::fwrite(h.data(), 1, h.size(), f_) != h.size() || std::fflush(f_) != 0 || std::ferror(f_)) {
    const std::string why = std::strerror(errno);
    std::fclose(f_);
    f_ = nullptr;
    throw std::runtime_error(path + ": write failed: " + why);
  }
}

DcdWriter::~DcdWriter() {
  try { close(); } catch (...) {}
}

void DcdWriter::write_frame(const std::vector<Vec3>& x) {
  if (!f_) throw std::runtime_error(path_ + ": writer closed");
  if (static_cast<int>(x.size()) != natoms_)
    throw std::invalid_argument(path_ + ": frame has " + std::to_string(x.size()) + " atoms, the file " +
                                std::to_string(natoms_));
  const int32_t bytes = 4 * natoms_;
  for (int c = 0; c < 3; ++c) {
    std::memcpy(&buf_[0], &bytes, 4);
    for (int a = 0; a < natoms_; ++a) buf_[1 + a] = static_cast<float>(10.0 * x[a][c]);
    std::memcpy(&buf_[1 + natoms_], &bytes, 4);
    if (std::fwrite(buf_.data(), 4, buf_.size(), f_) != buf_.size())
      throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
  }
  ++frames_;
  patch_counts();
}

void DcdWriter::patch_counts() {
  const long end = std::ftell(f_);
  const int32_t nset = frames_, nstep = frames_ * step_interval_;
  std::fseek(f_, 8, SEEK_SET);     // after the 84 marker and "CORD"
  std::fwrite(&nset, 4, 1, f_);
  std::fseek(f_, 20, SEEK_SET);    // ICNTRL[3]
  std::fwrite(&nstep, 4, 1, f_);
  std::fseek(f_, end, SEEK_SET);
  // fseek flushes too and may swallow the error it met: check the stream's error flag as well.
  if (std::fflush(f_) != 0 || std::ferror(f_)) throw std::runtime_error(path_ + ": write failed: " + std::strerror(errno));
}

void DcdWriter::close() {
  if (!f_) return;
  std::FILE* f = f_;
  f_ = nullptr;
  if (std::fclose(f) != 0) throw std::runtime_error(path_ + ": close failed");
}

// ---------------------------------------------------------------- reader

namespace {
struct Bytes {
  std::string path;
  std::vector<uint8_t> d;
  size_t at = 0;
  bool swap = false;
  [[noreturn]] void fail(const std::string& what) const {
    throw std::runtime_error(path + ": not a readable DCD: " + what + " (at byte " + std::to_string(at) + ")");
  }
  uint32_t raw32() {
    if (at + 4 > d.size()) fail("file ends early");
    uint32_t v;
    std::memcpy(&v, d.data() + at, 4);
    at += 4;
    return swap ? __builtin_bswap32(v) : v;
  }
  int32_t i32() { return static_cast<int32_t>(raw32()); }
  float f32() {
    const uint32_t u = raw32();
    float f;
    std::memcpy(&f, &u, 4);
    return f;
  }
  void marker(int32_t want, const char* record) {
    const int32_t m = i32();
    if (m != want) fail(std::string(record) + " record marker " + std::to_string(m) + ", expected " + std::to_string(want));
  }
};
}  // namespace

DcdTrajectory read_dcd(const std::string& path) {
  Bytes b;
  b.path = path;
  {
    std::FILE* f = std::fopen(path.c_str(), "rb");
    if (!f) throw std::runtime_error(path + ": cannot open: " + std::strerror(errno));
    std::fseek(f, 0, SEEK_END);
    const long n = std::ftell(f);
    std::fseek(f, 0, SEEK_SET);
    b.d.resize(n > 0 ? static_cast<size_t>(n) : 0);
    const size_t got = b.d.empty() ? 0 : std::fread(b.d.data(), 1, b.d.size(), f);
    std::fclose(f);
    if (got != b.d.size()) throw std::runtime_error(path + ": read failed");
  }
  if (b.d.size() < 4) b.fail("file too short");
  uint32_t first;
  std::memcpy(&first, b.d.data(), 4);
  if (first != 84) {
    if (__builtin_bswap32(first) != 84) b.fail("first record is not the 84-byte header");
    b.swap = true;
  }
  DcdTrajectory t;
  DcdHeader& h = t.header;
  b.marker(84, "header");
  if (b.at + 4 > b.d.size() || std::memcmp(b.d.data() + b.at, "CORD", 4) != 0) b.fail("no 'CORD'");
  b.at += 4;
  int32_t icntrl[20];
  float delta = 0;
  for (int i = 0; i < 20; ++i) {
    if (i == 9) delta = b.f32(), icntrl[i] = 0;
    else icntrl[i] = b.i32();
  }
  b.marker(84, "header end");
  h.nframes = icntrl[0];
  h.first_step = icntrl[1];
  h.step_interval = icntrl[2];
  h.delta_akma = delta;
  h.unit_cell = icntrl[19] != 0 && icntrl[10] != 0;
  if (icntrl[8] != 0) b.fail("fixed atoms (NAMNF " + std::to_string(icntrl[8]) + ") are not supported");
  const int32_t tlen = b.i32();
  if (tlen < 4 || (tlen - 4) % 80 != 0 || static_cast<size_t>(tlen) > b.d.size() - b.at) b.fail("title record length");
  const int32_t ntitle = b.i32();
  if (ntitle * 80 + 4 != tlen) b.fail("title count " + std::to_string(ntitle));
  for (int i = 0; i < ntitle; ++i) {
    std::string s(reinterpret_cast<const char*>(b.d.data() + b.at), 80);
    s.erase(s.find_last_not_of(' ') + 1);
    h.titles.push_back(s);
    b.at += 80;
  }
  b.marker(tlen, "title end");
  b.marker(4, "atom count");
  h.natoms = b.i32();
  b.marker(4, "atom count end");
  if (h.natoms <= 0) b.fail("atom count " + std::to_string(h.natoms));
  const size_t n = static_cast<size_t>(h.natoms);
  const size_t frame_bytes = (h.unit_cell ? 56 : 0) + 3 * (8 + 4 * n);
  const size_t left = b.d.size() - b.at;
  // NSET may be 0 or stale in files cut short; the frames present are what counts.
  const size_t frames = left / frame_bytes;
  if (left % frame_bytes != 0) b.fail("trailing " + std::to_string(left % frame_bytes) + " bytes (a partial frame)");
  if (h.nframes != 0 && static_cast<size_t>(h.nframes) != frames)
    b.fail("header says " + std::to_string(h.nframes) + " frames, the file holds " + std::to_string(frames));
  h.nframes = static_cast<int32_t>(frames);
  t.xyz.resize(frames);
  const int32_t bytes = static_cast<int32_t>(4 * n);
  for (size_t fr = 0; fr < frames; ++fr) {
    if (h.unit_cell) {
      b.marker(48, "unit cell");
      b.at += 48;
      b.marker(48, "unit cell end");
    }
    auto& xyz = t.xyz[fr];
    xyz.resize(3 * n);
    for (int c = 0; c < 3; ++c) {
      b.marker(bytes, "coordinates");
      for (size_t a = 0; a < n; ++a) xyz[3 * a + c] = b.f32();
      b.marker(bytes, "coordinates end");
    }
  }
  return t;
}

// ---------------------------------------------------------------- recorder

std::string trajectory_format(const std::string& path) {
  const auto dot = path.find_last_of('.');
  std::string ext = dot == std::string::npos ? "" : path.substr(dot + 1);
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext == "dcd" || ext == "pdb") return ext;
  throw std::invalid_argument(path + ": trajectory format from the extension: .dcd or .pdb");
}

TrajectoryRecorder::TrajectoryRecorder(const TrajectoryOptions& o, const Structure* s, int natoms) : opt_(o) {
  const std::string fmt = trajectory_format(o.path);
  if (o.every_steps < 1 && !(o.every_time > 0))
    throw std::invalid_argument(o.path + ": trajectory interval must be >= 1 step or a time > 0");
  if (!(o.dt > 0)) throw std::invalid_argument(o.path + ": trajectory needs the time step (> 0)");
  if (s && static_cast<int>(s->atoms.size()) != natoms)
    throw std::invalid_argument(o.path + ": structure and atom count differ");
  scale_bodies_ = s == nullptr;
  if (!s) {
    bodies_.path = "bodies";
    bodies_.atoms.resize(static_cast<size_t>(natoms));
    for (int k = 0; k < natoms; ++k) {
      AtomRecord& a = bodies_.atoms[k];
      a.name = "CA";
      a.element = "C";
      a.resname = "BOD";
      a.chain = "A";
      a.resid = k + 1;
    }
    s = &bodies_;
  }
  const int interval = o.every_time > 0 ? std::max(1, static_cast<int>(std::lround(o.every_time / o.dt))) : o.every_steps;
  if (fmt == "dcd") dcd_ = std::make_unique<DcdWriter>(o.path, natoms, o.dt, interval);
  else pdb_ = std::make_unique<PdbTrajectoryWriter>(o.path, *s);
}

TrajectoryRecorder::~TrajectoryRecorder() = default;

bool TrajectoryRecorder::due(int64_t step, double time) const {
  if (!any_) return true;
  if (opt_.every_time > 0) return time >= last_time_ + opt_.every_time * (1 - 1e-9);
  return step - last_step_ >= opt_.every_steps || step < last_step_;   // step < last: a restarted server
}

void TrajectoryRecorder::write(const std::vector<Vec3>& x, int64_t step, double time) {
  const std::vector<Vec3>* p = &x;
  if (scale_bodies_) {   // 1 scene metre -> 1 Å: the writers take nm
    tmp_.resize(x.size());
    for (size_t i = 0; i < x.size(); ++i) tmp_[i] = 0.1 * x[i];
    p = &tmp_;
  }
  if (dcd_) dcd_->write_frame(*p);
  else pdb_->write_frame(*p);
  any_ = true;
  last_step_ = step;
  last_time_ = time;
}

int TrajectoryRecorder::frames() const { return dcd_ ? dcd_->frames() : pdb_->frames(); }

void TrajectoryRecorder::close() {
  if (dcd_) dcd_->close();
  if (pdb_) pdb_->close();
}

}  // namespace haptree::mol
