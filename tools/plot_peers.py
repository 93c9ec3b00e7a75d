#!/usr/bin/env python3
"""Plot bench_peers CSV: time per forward-dynamics call vs n per engine, and error vs the oracle.

usage: tools/plot_peers.py bench_peers.csv -o peers.png [--table]
--table also prints the CSV as a markdown table (µs median, relative errors) on stdout.
Times: the thread-CPU median per call (column cpu_us_median) when the CSV has it, else the wall-clock
median (us_median); the table shows both.
"""
import argparse
import csv
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("csv")
    ap.add_argument("-o", "--out", default="peers.png")
    ap.add_argument("--table", action="store_true", help="print a markdown table on stdout")
    a = ap.parse_args()
    rows = list(csv.DictReader(open(a.csv)))
    has_cpu = bool(rows) and "cpu_us_median" in rows[0]
    tkey = "cpu_us_median" if has_cpu else "us_median"
    if a.table:
        cpu_h = "µs / call, thread CPU (median) | " if has_cpu else ""
        print(f"| model | DOF | engine | {cpu_h}µs / call, wall (median) | reps | "
              "rel. error vs oracle | rel. error vs oracle, inactive DOFs locked |")
        print("|---|---|---|" + ("---|" if has_cpu else "") + "---|---|---|---|")
        for r in rows:
            if math.isnan(float(r["us_median"])):   # engine could not take the model
                print(f"| {r['model']} | {r['nv']} | {r['engine']} | " + ("n/a | " if has_cpu else "")
                      + f"n/a | – | {r['timed_call']} | n/a |")
                continue
            cpu = f"{float(r['cpu_us_median']):.4g} | " if has_cpu else ""
            print(f"| {r['model']} | {r['nv']} | {r['engine']} | {cpu}{float(r['us_median']):.4g} | "
                  f"{r['reps']} | {float(r['rel_err']):.2e} | {float(r['rel_err_locked']):.2e} |")
    # Single-size models (protein-like tree, bacteriorhodopsin) get bar charts, the size sweeps lines.
    tlabel = "µs, thread CPU (median)" if has_cpu else "µs, wall (median)"
    single = [m for m in ("protein_like", "bacteriorhodopsin") if any(r["model"] == m for r in rows)]
    models = sorted({r["model"] for r in rows if r["model"] not in single})
    engines = sorted({r["engine"] for r in rows})
    ncol = max(len(models) + len(single), 1)
    fig, axes = plt.subplots(2, ncol, figsize=(5 * ncol, 8), squeeze=False)
    markers = "osD^v<>px*"
    for col, model in enumerate(models):
        for i, eng in enumerate(engines):
            pts = sorted((int(r["nv"]), float(r[tkey]), float(r["rel_err"]))
                         for r in rows if r["model"] == model and r["engine"] == eng
                         and not math.isnan(float(r["us_median"])))
            if not pts:
                continue
            n = [p[0] for p in pts]
            axes[0][col].loglog(n, [p[1] for p in pts], marker=markers[i % len(markers)], label=eng)
            errs = [(p[0], max(p[2], 1e-17)) for p in pts if not math.isnan(p[2])]
            if errs and not eng.startswith("haptree_adaptive"):
                axes[1][col].loglog([e[0] for e in errs], [e[1] for e in errs],
                                    marker=markers[i % len(markers)], label=eng)
        axes[0][col].set_title(f"{model}: time per forward-dynamics call")
        axes[0][col].set_xlabel("DOF n")
        axes[0][col].set_ylabel(tlabel)
        axes[1][col].set_title(f"{model}: relative q̈ error vs reference")
        axes[1][col].set_xlabel("DOF n")
        axes[1][col].set_ylabel("‖q̈ − q̈_ref‖ / ‖q̈_ref‖ (oracle; quad-refined)")
        for ax in (axes[0][col], axes[1][col]):
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
    titles = {"protein_like": "protein-like", "bacteriorhodopsin": "bacteriorhodopsin"}
    for j, model in enumerate(single):
        col = len(models) + j
        sel = [r for r in rows if r["model"] == model and not math.isnan(float(r["us_median"]))]
        if not sel:
            continue
        nv = sel[0]["nv"]
        axes[0][col].bar([r["engine"] for r in sel], [float(r[tkey]) for r in sel])
        axes[0][col].set_yscale("log")
        axes[0][col].set_ylabel(tlabel)
        axes[0][col].set_title(f"{titles[model]} ({nv} DOF): µs per call")
        full = [r for r in sel if not r["engine"].startswith("haptree_adaptive")
                and not math.isnan(float(r["rel_err"]))]
        axes[1][col].bar([r["engine"] for r in full],
                         [max(float(r["rel_err"]), 1e-17) for r in full])
        axes[1][col].set_yscale("log")
        axes[1][col].set_title(f"{titles[model]}: relative q̈ error vs reference")
        for ax in (axes[0][col], axes[1][col]):
            ax.tick_params(axis="x", rotation=45, labelsize=8)
            ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    if not a.table:
        print("wrote", a.out)


if __name__ == "__main__":
    main()
