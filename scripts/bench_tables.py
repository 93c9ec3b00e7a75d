#!/usr/bin/env python3
"""Tables of docs/performance.md from the benchmark programs' CSV (used by scripts/bench_report.sh).

  bench_tables.py peers CSV          bench_peers --csv: one row per model, a cell per engine
  bench_tables.py adaptive CSV       adaptive_sweep --csv: step time per setting, then the errors
  bench_tables.py scaling CSV        scaling_bench --csv: the adaptive step against n
  bench_tables.py threads DIR        scaling_threads_T.csv of one machine: full pass against T
  bench_tables.py latency CSV        scripts/measure_latency.sh CSV: the latest run of each row
  bench_tables.py gbench CSV         a Google Benchmark CSV (dca_bench): mean, median, worst repetition
  bench_tables.py md2csv < TABLE     the first Markdown table on stdin, as CSV on stdout
  bench_tables.py splice PAGE ID F   replace what lies between <!-- bench:ID begin --> and
                                     <!-- bench:ID end --> in PAGE by the contents of F
Standard library only. Every table goes to stdout as Markdown.
"""
import csv
import glob
import os
import re
import sys


def num(s):
    try:
        return float(s)
    except (TypeError, ValueError):
        return None


def fmt(x, digits=3):
    """A time or ratio with `digits` significant figures, thousands as in the pages (1 046.0)."""
    if x is None:
        return "n/a"
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 1e6:
        return f"{x / 1e6:.3g} s" if digits else f"{x:.3g}"
    decimals = max(0, digits - 1 - int(f"{a:e}".split("e")[1]))
    s = f"{x:,.{decimals}f}".replace(",", " ")
    return s


def err(x):
    return "n/a" if x is None else f"{x:.1e}"


def table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def peers(path):
    rows = read_csv(path)
    engines, models = [], []
    cell = {}
    for r in rows:
        if r["engine"] not in engines:
            engines.append(r["engine"])
        key = (r["model"], int(r["nv"]))
        if key not in models:
            models.append(key)
        cell[(key, r["engine"])] = r
    order = ["haptree", "haptree_plain", "haptree_refine", "haptree_exact"]
    engines.sort(key=lambda e: (order.index(e) if e in order else
                                (len(order) if e.startswith("haptree_adaptive") else len(order) + 1), e))
    header = ["model", "DOF"] + [e.replace("_", " ") for e in engines]
    plain = "haptree_plain" if "haptree_plain" in engines else "haptree"
    if plain in engines and "bullet" in engines:
        header.append(f"{plain.replace('_', ' ')} / bullet")
    out = []
    for key in models:
        line = [key[0].replace("_", " "), key[1]]
        for e in engines:
            r = cell.get((key, e))
            if r is None:
                line.append("—")
                continue
            locked = e.startswith("haptree_adaptive")
            e_rel = num(r["rel_err_locked"] if locked else r["rel_err"])
            line.append(f"{fmt(num(r['us_median']), 4)} / {fmt(num(r.get('us_mean')), 4)} ({err(e_rel)})")
        a, b = cell.get((key, plain)), cell.get((key, "bullet"))
        if plain in engines and "bullet" in engines:
            line.append(f"{num(a['us_median']) / num(b['us_median']):.2f}×" if a and b else "—")
        out.append(line)
    print(table(header, out))
    print("\nCells: median / mean µs per forward-dynamics call (wall clock), in brackets the relative "
          "error of q̈ against the quad-precision-refined oracle; for the adaptive engines against the "
          "oracle with the inactive joints locked (the neglected part is the adaptive method's by design).")


def adaptive(path):
    rows = read_csv(path)
    scenes, settings = [], []
    cell = {}
    for r in rows:
        key = (r["scene"], r["dof"])
        if key not in scenes:
            scenes.append(key)
        if r["setting"] not in settings:
            settings.append(r["setting"])
        cell[(key, r["setting"])] = r
    header = ["scene", "full DCA µs (median / mean)"] + settings
    t_rows, e_rows = [], []
    for key in scenes:
        first = next(cell[(key, s)] for s in settings if (key, s) in cell)
        line = [f"{key[0]} {key[1]}", f"{fmt(num(first['full_cpu_us_median']), 4)} / "
                                      f"{fmt(num(first['full_cpu_us_mean']), 4)}"]
        eline = [f"{key[0]} {key[1]}"]
        for s in settings:
            r = cell.get((key, s))
            if r is None:
                line.append("—")
                eline.append("—")
                continue
            line.append(f"{fmt(num(r['cpu_us_median']))} / **{fmt(num(r['cpu_us_mean']))}** "
                        f"({fmt(num(r['speedup_mean']), 3)}×)")
            eline.append(f"{err(num(r['neglected_mean']))} / {err(num(r['rms_q_dev']))}")
        t_rows.append(line)
        e_rows.append(eline)
    print(table(header, t_rows))
    print("\nStep µs, thread CPU: median / **mean** (every selection included), in brackets the speed-up "
          "of the mean against full DCA's mean.\n")
    print(table(["scene"] + settings, e_rows))
    print("\nErrors: mean neglected metric at the selections / RMS joint deviation from full DCA at the "
          "end of the run (rad).")


def scaling(path):
    rows = read_csv(path)
    out = []
    for r in rows:
        out.append([r["shape"].replace("_", " "), r["n"], r["k"], r.get("threads", "1"),
                    fmt(num(r["median_us"])), fmt(num(r["mean_us"])), fmt(num(r["p99_us"])),
                    fmt(num(r["worst_us"])), f"{num(r['worst_over_median']):.1f}",
                    fmt(num(r["rss_total_mb"])), f"{num(r['kb_per_body_beyond_model']):.1f}",
                    fmt(num(r["full_pass_us"]) / 1e3), r.get("load1", "")])
    print(table(["shape", "n", "k", "threads", "median µs", "mean µs", "p99 µs", "worst µs",
                 "worst / median", "RSS MB", "KB / body beyond the model", "full pass ms",
                 "load average"], out))
    print("\nEvery step after the first (wall clock); the selection runs on its worker thread.")


def threads(folder):
    runs = {}
    for p in glob.glob(os.path.join(folder, "scaling_threads_*.csv")):
        for r in read_csv(p):
            # the first row of a shape and size (its smallest k) carries the pass timed for it
            runs.setdefault((r["shape"], int(r["n"])), {}).setdefault(int(r["threads"]), num(r["full_pass_us"]))
    if not runs:
        sys.exit(f"bench_tables: no scaling_threads_*.csv in {folder}")
    ts = sorted({t for v in runs.values() for t in v})
    out = []
    for (shape, n), by_t in sorted(runs.items()):
        base, top = by_t.get(ts[0]), by_t.get(ts[-1])
        line = [shape.replace("_", " "), f"{n:,}".replace(",", " ")]
        line += [fmt(by_t[t] / 1e3) if t in by_t else "—" for t in ts]
        if base and top:
            line += [f"{base / top:.1f}", f"{base / top / (ts[-1] / ts[0]):.2f}"]
        else:
            line += ["—", "—"]
        out.append(line)
    print(table(["shape", "n"] + [f"{t} thread{'s' if t > 1 else ''} ms" for t in ts] +
                [f"speed-up at {ts[-1]}", f"efficiency at {ts[-1]}"], out))
    print("\nFull DCA pass (one `forward_dynamics`, mean of the repetitions), wall clock.")


def latency(path):
    rows = read_csv(path)
    latest = {}
    order = []
    for r in rows:
        if r["link"] == "floor":
            continue
        key = (r["link"], r["load"], r["options"])
        if key not in order:
            order.append(key)
        latest[key] = r        # rows are appended run after run: the last one is the newest
    out = []
    for key in order:
        r = latest[key]
        out.append([r["link"], r["load"], r["options"], r["p50_us"], r["p99_us"], r["p999_us"],
                    r["samples"], r["coupler_rate_hz"], r["load1"], r["run"]])
    print(table(["link", "background load", "options", "p50 µs", "p99 µs", "p99.9 µs", "samples",
                 "coupler Hz", "load average", "run"], out))
    floor = [r for r in rows if r["link"] == "floor"]
    if floor:
        last = floor[-1]["run"]
        f = [r for r in floor if r["run"] == last]
        print("\nMachine floor (cyclictest, SCHED_FIFO 80 timer thread per CPU, 1 ms interval), µs: " +
              "; ".join(f"{r['load']} {r['options'].split('-')[-1]}: p50 {r['p50_us']}, p99 {r['p99_us']}, "
                        f"p99.9 {r['p999_us']}" for r in f) + ".")


def gbench(path):
    with open(path, newline="") as f:
        lines = f.read().splitlines()
    start = next((i for i, l in enumerate(lines) if l.startswith("name,")), None)
    if start is None:
        sys.exit(f"bench_tables: {path} holds no Google Benchmark CSV")
    runs, order = {}, []
    for r in csv.DictReader(lines[start:]):
        name = r["name"]
        if re.search(r"_(mean|median|stddev|cv)$", name):
            continue
        if name not in runs:
            runs[name] = []
            order.append(name)
        runs[name].append(r)
    out = []
    for name in order:
        rs = runs[name]
        real = sorted(num(r["real_time"]) for r in rs)
        cpu = sorted(num(r["cpu_time"]) for r in rs)
        med = lambda v: v[len(v) // 2] if len(v) % 2 else (v[len(v) // 2 - 1] + v[len(v) // 2]) / 2
        out.append([name, rs[0].get("bodies", ""), rs[0].get("threads", ""), len(rs),
                    fmt(sum(real) / len(real), 4), fmt(med(real), 4), fmt(real[-1], 4), fmt(med(cpu), 4)])
    print(table(["benchmark", "bodies", "threads", "repetitions", "wall µs mean", "median", "worst",
                 "CPU µs median (all threads)"], out))


def md2csv():
    lines = [l.strip() for l in sys.stdin if l.strip().startswith("|")]
    w = csv.writer(sys.stdout)
    for l in lines:
        cells = [c.strip() for c in l.strip("|").split("|")]
        if all(re.fullmatch(r":?-+:?", c) for c in cells):
            continue
        w.writerow(cells)
    if not lines:
        sys.exit("bench_tables: no Markdown table on stdin")


def splice(page, ident, path):
    text = open(page).read()
    begin, end = f"<!-- bench:{ident} begin -->", f"<!-- bench:{ident} end -->"
    i, j = text.find(begin), text.find(end)
    if i < 0 or j < i:
        sys.exit(f"bench_tables: {page} has no '{begin}' … '{end}' block")
    body = open(path).read().strip("\n")
    text = text[:i + len(begin)] + "\n" + body + "\n" + text[j:]
    tmp = page + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, page)


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print(__doc__)
        return 0 if len(argv) >= 2 else 2
    cmd, args = argv[1], argv[2:]
    fns = {"peers": peers, "adaptive": adaptive, "scaling": scaling, "threads": threads,
           "latency": latency, "gbench": gbench, "md2csv": md2csv, "splice": splice}
    if cmd not in fns:
        sys.exit(f"bench_tables: unknown command '{cmd}' (see --help)")
    fns[cmd](*args)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
