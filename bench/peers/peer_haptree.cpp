#include "bench/peers/peer_engine.hpp"

#include "haptree/dca.hpp"

namespace haptree::peers {

namespace {

class HaptreeEngine final : public PeerEngine {
 public:
  // threads: set_dca_threads (1 = serial; 0 = automatic, "haptree_auto").
  // refine: Data::refine: "haptree" is the library's default (kDouble, one refinement
  // step with the residual in double), "haptree_plain" the single pass (kOff), "haptree_exact" the
  // residual in long double from q (kExtended).
  HaptreeEngine(const Model& m, int threads, Refinement refine = Refinement::kDouble)
      : model_(m), data_(m), threads_(threads) {
    set_dca_threads(m, data_, threads);
    set_refinement(m, data_, refine);
  }
  std::string name() const override {
    if (data_.refine == Refinement::kOff) return "haptree_plain";
    if (data_.refine == Refinement::kExtended) return "haptree_exact";
    return threads_ == 1 ? "haptree" : "haptree_auto";
  }
  std::string timed_call() const override {
    return "haptree::forward_dynamics (kinematics + DCA bottom-up + top-down)";
  }
  void compute(const State& st) override { forward_dynamics(model_, data_, st); }
  const Eigen::VectorXd& qdd() const override { return data_.qdd; }

 private:
  const Model& model_;
  Data data_;
  int threads_;
};

}  // namespace

std::unique_ptr<PeerEngine> make_haptree_engine(const Model& model) {
  return std::make_unique<HaptreeEngine>(model, 1);
}
std::unique_ptr<PeerEngine> make_haptree_auto_engine(const Model& model) {
  return std::make_unique<HaptreeEngine>(model, 0);
}
std::unique_ptr<PeerEngine> make_haptree_plain_engine(const Model& model) {
  return std::make_unique<HaptreeEngine>(model, 1, Refinement::kOff);
}
std::unique_ptr<PeerEngine> make_haptree_exact_engine(const Model& model) {
  return std::make_unique<HaptreeEngine>(model, 1, Refinement::kExtended);
}

std::vector<std::string> compiled_peers() {
  std::vector<std::string> out;
#ifdef HAPTREE_PEER_MUJOCO
  out.push_back("mujoco");
#endif
#ifdef HAPTREE_PEER_SIMBODY
  out.push_back("simbody");
#endif
#ifdef HAPTREE_PEER_BULLET
  out.push_back("bullet");
#endif
  return out;
}

Mat3 frame_with_z(const Vec3& a) {
  const Vec3 z = a.normalized();
  const Vec3 helper = std::abs(z.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  const Vec3 x = (helper - helper.dot(z) * z).normalized();
  const Vec3 y = z.cross(x);
  Mat3 R;
  R.col(0) = x;
  R.col(1) = y;
  R.col(2) = z;
  return R;
}

}  // namespace haptree::peers
