#!/usr/bin/env python3
"""Measured coupling-stiffness limit K_max against the passivity bound 2b/T, from passivity_sweep's CSV.

K_max of each (scene, sim step, hand damping b, haptic period T) is the largest K of its grid and
bisection runs that stayed stable. The solid line is K = 2b/T (Colgate); points on it match the bound.

    python3 tools/plot_passivity.py passivity.csv --out docs/img/passivity_sweep.png
"""
import argparse
import csv
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv", help="CSV written by passivity_sweep --csv")
    ap.add_argument("--out", default="docs/img/passivity_sweep.png", help="PNG path")
    a = ap.parse_args()
    kmax = defaultdict(float)
    with open(a.csv, newline="") as f:
        for r in csv.DictReader(f):
            if r["phase"] not in ("grid", "refine"):
                continue
            key = (r["scene"], float(r["dt_sim"]), float(r["b"]), float(r["T"]))
            kmax[key] = max(kmax[key], float(r["K"]) if r["stable"] == "1" else 0.0)
    fig, ax = plt.subplots(figsize=(7, 5.5))
    markers = {"wall": "s", "chain": "o", "protein_like": "^"}
    groups = defaultdict(list)
    for (scene, dt, b, T), k in kmax.items():
        if k > 0:
            groups[(scene, dt)].append((2 * b / T, k, b, T))
    lo, hi = float("inf"), 0.0
    for (scene, dt), pts in sorted(groups.items()):
        xs = [p[0] for p in pts]
        ys = [p[1] for p in pts]
        lo, hi = min(lo, *xs, *ys), max(hi, *xs, *ys)
        ax.scatter(xs, ys, marker=markers.get(scene, "x"), label=f"{scene}, sim step {dt:g} s", alpha=0.8)
    ax.plot([lo / 2, hi * 2], [lo / 2, hi * 2], "k-", linewidth=1, label="K = 2b/T (Colgate)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("passivity bound 2b/T (N/m)")
    ax.set_ylabel("measured K_max (N/m)")
    ax.set_title("Coupling stiffness limit, virtual hand (m = 0.2 kg) in closed loop", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)


if __name__ == "__main__":
    main()
