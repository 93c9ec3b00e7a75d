// scaling_bench: adaptive step cost against the number of bodies, from the public API.
//
// For each shape (chain, balanced binary tree) and size n, and each DOF budget k: builds the model
// (timed), Data and AdaptiveData (timed), then runs a pulled, gravity-free session of adaptive_step
// calls (a constant pull on the last body, the library's default options) and reports the step's
// median, mean, p99 and worst wall time (every step after the first), the selections, the resident
// memory, and one full forward_dynamics pass. One CSV row per (shape, n, k).
//
//   scaling_bench --sizes 1024,4096,16384,65536,262144 --k 48,256 --steps 2000 --csv scaling.csv
//   OMP_NUM_THREADS=4 scaling_bench --threads 4 ...   (full pass and selection worker on 4 threads)
//   scaling_bench --sizes 65536 --k 48 --memory        (bytes per body of every workspace container)
#include <algorithm>
#include <chrono>
#include <ctime>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <numeric>
#include <sstream>
#include <string>
#include <vector>

#include "haptree/adaptive.hpp"
#include "haptree/dca.hpp"
#include "haptree/scenes.hpp"

namespace {

using Clock = std::chrono::steady_clock;

double rss_mb() {
  std::ifstream f("/proc/self/status");
  std::string line;
  while (std::getline(f, line))
    if (line.rfind("VmRSS:", 0) == 0) return std::atof(line.c_str() + 6) / 1024.0;
  return -1;
}

std::vector<std::string> split(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string x;
  while (std::getline(ss, x, ','))
    if (!x.empty()) out.push_back(x);
  return out;
}

// CPU time of the calling thread (µs): a step's own work, without the time the OS gave other
// processes (on a loaded machine the wall time's worst case is a preemption, not the step).
double thread_cpu_us() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return 1e6 * static_cast<double>(ts.tv_sec) + 1e-3 * static_cast<double>(ts.tv_nsec);
}

double ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

// Bytes per body of every workspace container above 1 % of the total (the rest summed), largest
// first, against the resident memory the run added beyond the model.
std::string memory_table(const std::string& shape, const haptree::Model& model, int k, double rss_mb_beyond,
                         const haptree::State& st, const haptree::Data& d, const haptree::AdaptiveData& ad) {
  std::vector<haptree::MemoryItem> items = haptree::memory_usage(st);
  for (auto&& part : {haptree::memory_usage(d), haptree::memory_usage(ad)})
    items.insert(items.end(), part.begin(), part.end());
  const double total = static_cast<double>(haptree::total_bytes(items));
  std::sort(items.begin(), items.end(), [](const auto& a, const auto& b) { return a.bytes > b.bytes; });
  const double nb = model.nbodies;
  char line[256];
  std::snprintf(line, sizeof line,
                "\nMemory of the workspaces, %s n = %d, k = %d (bytes per body, capacity after the run; %d assembly "
                "nodes):\n\n| container | bytes / body | share |\n|---|---|---|\n",
                shape.c_str(), model.nbodies - 1, k, model.tree.nnodes());
  std::string s = line;
  double rest = 0;
  for (const auto& i : items) {
    if (i.bytes < 0.01 * total) {
      rest += static_cast<double>(i.bytes);
      continue;
    }
    std::snprintf(line, sizeof line, "| %s | %.0f | %.1f %% |\n", i.name.c_str(), i.bytes / nb, 100.0 * i.bytes / total);
    s += line;
  }
  std::snprintf(line, sizeof line, "| others (each < 1 %%) | %.0f | %.1f %% |\n| **total** | **%.0f** | 100 %% |\n"
                "\nResident memory beyond the model: %.0f bytes per body.\n",
                rest / nb, 100.0 * rest / total, total / nb, rss_mb_beyond * 1024.0 * 1024.0 / nb);
  s += line;
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  std::string sizes = "1024,4096,16384,65536", ks = "48,256", shapes = "chain,binary_tree", csv;
  int steps = 2000, threads = 1, full_reps = 3;
  bool background = true, memory = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "scaling_bench: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--sizes") sizes = next();
    else if (a == "--k") ks = next();
    else if (a == "--shapes") shapes = next();
    else if (a == "--steps") steps = std::stoi(next());
    else if (a == "--threads") threads = std::stoi(next());
    else if (a == "--full-reps") full_reps = std::stoi(next());
    else if (a == "--csv") csv = next();
    else if (a == "--synchronous") background = false;
    else if (a == "--memory") memory = true;
    else if (a == "--help" || a == "-h") {
      std::printf(
          "scaling_bench [--sizes 1024,4096,...] [--k 48,256] [--shapes chain,binary_tree] [--steps N]\n"
          "              [--threads T] [--full-reps R] [--synchronous] [--memory] [--csv FILE]\n"
          "  sizes: bodies per model (a binary tree gets n-1, a complete tree); k: active DOF budgets;\n"
          "  steps: adaptive steps per run (dt 1 ms, gravity off, 2 N pull on the last body);\n"
          "  threads: set_dca_threads for the full pass (1 = serial); --synchronous: selections inside\n"
          "  the step (background_selection = false); --memory: after the table, the bytes per body of\n"
          "  every container of State, Data, AdaptiveData and the selection worker's copies (capacity),\n"
          "  after the run. Times in microseconds, memory in MB.\n");
      return 0;
    } else {
      std::fprintf(stderr, "scaling_bench: unknown option %s (see --help)\n", a.c_str());
      return 2;
    }
  }
  std::FILE* out = csv.empty() ? nullptr : std::fopen(csv.c_str(), "w");
  if (!csv.empty() && !out) {
    std::fprintf(stderr, "scaling_bench: cannot write %s\n", csv.c_str());
    return 1;
  }
  const char* header =
      "shape,n,k,threads,background,steps,median_us,mean_us,p99_us,worst_us,worst_over_median,first_us,"
      "selections,mean_active_dofs,model_ms,data_ms,rss_model_mb,rss_total_mb,kb_per_body_beyond_model,full_pass_us,"
      "cpu_median_us,cpu_p99_us,cpu_worst_us,worst_step_work,load1\n";
  if (out) std::fputs(header, out);
  std::printf("| shape | n | k | median µs | mean µs | p99 µs | worst µs | worst/median | CPU median/p99/worst µs | "
              "worst step work | selections | model ms | Data ms | RSS MB | KB/body beyond model | full pass µs | load |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::string memory_tables;
  for (const auto& shape : split(shapes))
    for (const auto& ns : split(sizes)) {
      const int n_req = std::stoi(ns);
      haptree::SceneOptions so;
      so.n = shape == "binary_tree" ? n_req - 1 : n_req;
      so.gravity = haptree::Vec3::Zero();
      for (const auto& kstr : split(ks)) {
        const int k = std::stoi(kstr);
        const double rss0 = rss_mb();
        auto t0 = Clock::now();
        auto model = haptree::make_scene(shape, so);
        const double model_ms = ms(Clock::now() - t0);
        const double rss_model = rss_mb();
        t0 = Clock::now();
        double full_us = -1;
        {
          haptree::State st(*model);
          haptree::Data d(*model);
          haptree::AdaptiveData ad(*model);
          const double data_ms = ms(Clock::now() - t0);
          if (threads > 1) haptree::set_dca_threads(*model, d, threads);
          haptree::AdaptiveOptions opt;
          opt.budget = k;
          opt.background_selection = background;
          const int tip = model->nbodies - 1;
          std::vector<double> us, cpu;
          us.reserve(steps);
          cpu.reserve(steps);
          std::int64_t worst_work = 0;
          double first = 0, dofs = 0;
          for (int s = 0; s < steps; ++s) {
            st.f_ext[tip] = haptree::Vec6::Zero();
            st.f_ext[tip](4) = 2.0;
            const double c0 = thread_cpu_us();
            const auto a = Clock::now();
            const auto& rep = haptree::adaptive_step(*model, d, st, ad, opt, 1e-3);
            const double t = 1e3 * ms(Clock::now() - a);
            const double c = thread_cpu_us() - c0;
            if (s == 0) {
              first = t;
            } else {
              us.push_back(t);
              cpu.push_back(c);
              worst_work = std::max(worst_work, ad.step_work);
            }
            dofs += rep.active_dofs;
          }
          const std::int64_t selections = ad.report.selections;
          const double rss_total = rss_mb();
          if (memory) memory_tables += memory_table(shape, *model, k, rss_total - rss_model, st, d, ad);
          // One full pass (the selection's and every start-up's cost), best of full_reps.
          for (int r = 0; r < full_reps; ++r) {
            const auto a = Clock::now();
            haptree::forward_dynamics(*model, d, st);
            const double t = 1e3 * ms(Clock::now() - a);
            full_us = full_us < 0 ? t : std::min(full_us, t);
          }
          std::vector<double> sorted = us;
          std::sort(sorted.begin(), sorted.end());
          const double med = sorted[sorted.size() / 2];
          const double mean = std::accumulate(us.begin(), us.end(), 0.0) / us.size();
          const double p99 = sorted[std::min(sorted.size() - 1, sorted.size() * 99 / 100)];
          const double worst = sorted.back();
          std::sort(cpu.begin(), cpu.end());
          const double cmed = cpu[cpu.size() / 2], cworst = cpu.back();
          const double cp99 = cpu[std::min(cpu.size() - 1, cpu.size() * 99 / 100)];
          const double kb_body = 1024.0 * (rss_total - rss_model) / model->nbodies;
          double load1 = -1;
          if (std::FILE* la = std::fopen("/proc/loadavg", "r")) {
            if (std::fscanf(la, "%lf", &load1) != 1) load1 = -1;
            std::fclose(la);
          }
          std::printf("| %s | %d | %d | %.1f | %.1f | %.1f | %.1f | %.1f | %.0f / %.0f / %.0f | %lld | %lld | %.0f | %.0f | "
                      "%.0f | %.2f | %.0f | %.1f |\n",
                      shape.c_str(), model->nbodies - 1, k, med, mean, p99, worst, worst / med, cmed, cp99, cworst,
                      static_cast<long long>(worst_work), static_cast<long long>(selections), model_ms, data_ms,
                      rss_total, kb_body, full_us, load1);
          std::fflush(stdout);
          if (out) {
            std::fprintf(out, "%s,%d,%d,%d,%d,%d,%.2f,%.2f,%.2f,%.2f,%.2f,%.1f,%lld,%.1f,%.1f,%.1f,%.1f,%.1f,%.3f,%.1f,"
                         "%.2f,%.2f,%.2f,%lld,%.2f\n",
                         shape.c_str(), model->nbodies - 1, k, threads, background ? 1 : 0, steps, med, mean, p99,
                         worst, worst / med, first, static_cast<long long>(selections), dofs / steps, model_ms,
                         data_ms, rss_model - rss0, rss_total, kb_body, full_us, cmed, cp99, cworst,
                         static_cast<long long>(worst_work), load1);
            std::fflush(out);
          }
        }
      }
    }
  std::fputs(memory_tables.c_str(), stdout);
  if (out) std::fclose(out);
  return 0;
}
