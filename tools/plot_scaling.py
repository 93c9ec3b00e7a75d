#!/usr/bin/env python3
"""Plot of scaling_bench's CSV: worst and mean adaptive step (wall and thread CPU) against n.

    python3 tools/plot_scaling.py docs/data/scaling.csv docs/data/scaling.png
"""
import csv
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    if len(sys.argv) != 3:
        sys.exit("usage: plot_scaling.py SCALING.csv OUT.png")
    rows = list(csv.DictReader(open(sys.argv[1])))
    series = {}
    for r in rows:
        key = (r["shape"], int(r["k"]), int(r["threads"]), int(r["background"]))
        series.setdefault(key, []).append(r)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True)
    for (shape, k, threads, bg), rs in sorted(series.items()):
        rs.sort(key=lambda r: int(r["n"]))
        n = [int(r["n"]) for r in rs]
        label = f"{shape} k={k}" + ("" if bg else " synchronous") + (f" {threads} thr" if threads > 1 else "")
        axes[0].plot(n, [float(r["worst_us"]) for r in rs], "o-", label=label + " worst")
        axes[0].plot(n, [float(r["mean_us"]) for r in rs], "s--", label=label + " mean")
        if "cpu_worst_us" in rs[0]:
            axes[1].plot(n, [float(r["cpu_worst_us"]) for r in rs], "o-", label=label + " worst")
            axes[1].plot(n, [float(r["cpu_median_us"]) for r in rs], "s--", label=label + " median")
    axes[0].set_title("adaptive step, wall time (every step after the first)")
    axes[1].set_title("adaptive step, thread CPU time")
    for ax in axes:
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("bodies n")
        ax.axhline(3000, color="gray", lw=0.8, ls=":")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    axes[0].set_ylabel("µs")
    fig.tight_layout()
    fig.savefig(sys.argv[2], dpi=110)


if __name__ == "__main__":
    main()
