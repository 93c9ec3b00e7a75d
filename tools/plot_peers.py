#!/usr/bin/env python3
"""Plot bench_peers CSV: time per forward-dynamics call vs n per engine, and error vs the oracle.

usage: tools/plot_peers.py bench_peers.csv -o docs/benchmarks_peers.png [--table]
--table also prints the CSV as a markdown table (µs median, relative errors) on stdout.
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
    ap.add_argument("-o", "--out", default="benchmarks_peers.png")
    ap.add_argument("--table", action="store_true", help="print a markdown table on stdout")
    a = ap.parse_args()
    rows = list(csv.DictReader(open(a.csv)))
    if a.table:
        print("| model | DOF | engine | µs / call (median) | reps | rel. error vs oracle | "
              "rel. error vs oracle, inactive DOFs locked |")
        print("|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['model']} | {r['nv']} | {r['engine']} | {float(r['us_median']):.4g} | "
                  f"{r['reps']} | {float(r['rel_err']):.2e} | {float(r['rel_err_locked']):.2e} |")
    models = sorted({r["model"] for r in rows if r["model"] != "protein_like"})
    engines = sorted({r["engine"] for r in rows})
    fig, axes = plt.subplots(2, len(models) + 1, figsize=(5 * (len(models) + 1), 8))
    markers = "osD^v<>px*"
    for col, model in enumerate(models):
        for i, eng in enumerate(engines):
            pts = sorted((int(r["nv"]), float(r["us_median"]), float(r["rel_err"]))
                         for r in rows if r["model"] == model and r["engine"] == eng)
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
        axes[0][col].set_ylabel("µs (median)")
        axes[1][col].set_title(f"{model}: relative q̈ error vs long-double oracle")
        axes[1][col].set_xlabel("DOF n")
        axes[1][col].set_ylabel("‖q̈ − q̈_oracle‖ / ‖q̈_oracle‖")
        for ax in (axes[0][col], axes[1][col]):
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
    # Protein-like tree: bars.
    prot = [r for r in rows if r["model"] == "protein_like"]
    names = [r["engine"] for r in prot]
    axes[0][-1].bar(names, [float(r["us_median"]) for r in prot])
    axes[0][-1].set_yscale("log")
    axes[0][-1].set_title("protein-like (857 DOF): µs per call")
    full = [r for r in prot if not r["engine"].startswith("haptree_adaptive")]
    axes[1][-1].bar([r["engine"] for r in full], [max(float(r["rel_err"]), 1e-17) for r in full])
    axes[1][-1].set_yscale("log")
    axes[1][-1].set_title("protein-like: relative q̈ error vs oracle")
    for ax in (axes[0][-1], axes[1][-1]):
        ax.tick_params(axis="x", rotation=45, labelsize=8)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    if not a.table:
        print("wrote", a.out)


if __name__ == "__main__":
    main()
