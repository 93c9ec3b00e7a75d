#!/usr/bin/env python3
"""Log-log plots of step time against error from adaptive_sweep's CSV (one PNG per scene).

Each PNG has two panels: MEAN step time (thread CPU, µs, every selection included — what a user
pays on average) against (left) the mean neglected acceleration metric (the error
estimate) and (right) the RMS joint deviation from the full-DCA run after the fixed simulated time. Budget settings are circles labelled with k, threshold settings are
triangles labelled with eps; the dashed line is full DCA.

    python3 tools/plot_adaptive.py adaptive_sweep.csv --out-dir docs/img
"""
import argparse
import csv
import os
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

FLOOR = 1e-18  # errors of exactly 0 (every DOF active) are drawn at this floor


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("csv", help="CSV written by adaptive_sweep --csv")
    ap.add_argument("--out-dir", default="docs/img", help="folder for the PNGs (default: docs/img)")
    ap.add_argument("--prefix", default="adaptive_", help="PNG name prefix (default: adaptive_)")
    a = ap.parse_args()
    rows = defaultdict(list)
    with open(a.csv, newline="") as f:
        for r in csv.DictReader(f):
            rows[r["scene"]].append(r)
    os.makedirs(a.out_dir, exist_ok=True)
    for scene, rs in rows.items():
        fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
        full = float(rs[0]["full_cpu_us_mean"])
        for ax, key, xlabel in (
            (axes[0], "neglected_mean", "mean neglected metric Σ q̈ᵀq̈ over inactive joints (error estimate)"),
            (axes[1], "rms_q_dev", "RMS joint deviation from full DCA at t_end (rad)"),
        ):
            for mode, marker, color in (("budget", "o", "tab:blue"), ("threshold", "^", "tab:red")):
                pts = [r for r in rs if r["mode"] == mode]
                if not pts:
                    continue
                xs = [max(float(r[key]), FLOOR) for r in pts]
                ys = [float(r["cpu_us_mean"]) for r in pts]
                ax.plot(xs, ys, marker=marker, linestyle="-" if mode == "budget" else ":", color=color,
                        label="budget k" if mode == "budget" else "threshold ε (rel.)")
                for r, x, y in zip(pts, xs, ys):
                    lab = r["setting"].split("=")[1]
                    if mode == "budget":
                        lab = f"k={lab} ({float(r['speedup_mean']):.1f}×)"
                    ax.annotate(lab, (x, y), textcoords="offset points", xytext=(4, 4 if mode == "budget" else -11),
                                fontsize=7, color=color)
            ax.axhline(full, color="k", linestyle="--", linewidth=1, label=f"full DCA, mean ({full:.0f} µs)")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel(xlabel, fontsize=8)
            ax.set_ylabel("step time, mean thread CPU incl. selections (µs)")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7, loc="lower left")
        r0 = rs[0]
        sel = r0.get("selections", "?")
        fig.suptitle(f"{scene}: {r0['dof']} DOF, {r0['steps']} steps of {r0['dt']} "
                     f"({'ps' if r0['length_unit'] == 'nm' else 's'}), error-controlled reselection "
                     f"({sel} selections at {r0['setting']})", fontsize=10)
        fig.tight_layout()
        out = os.path.join(a.out_dir, f"{a.prefix}{scene}.png")
        fig.savefig(out, dpi=110)
        plt.close(fig)
        print(out)


if __name__ == "__main__":
    main()
