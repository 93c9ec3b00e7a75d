#!/usr/bin/python3
"""Draw docs/img/concepts.png: an 8-body chain, its balanced assembly tree, and the regions the
adaptive dynamics and the force-feedback coupling work on (docs/concepts.md).

    /usr/bin/python3 docs/img/make_concepts_figure.py --out docs/img/concepts.png

The example: bodies B1..B8 joined by joints J2..J8 (Jk joins B(k-1) and Bk); the assembly tree
bisects the chain, so the root owns J5, its children J3 and J7, and so on. The user grabs B6. The
active region is {J5, J7, J6}; J2, J3, J4 and J8 are inactive, so {B1..B4} and {B7, B8} move as rigid
bodies.
"""
import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyBboxPatch, Circle, Rectangle  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

ACTIVE = "#f28e2b"     # active joint / node
RIGID = "#bab0ac"      # inactive (rigid) node / locked joint
LEAF = "#ffffff"
GRAB = "#e15759"
UPC = "#4e79a7"        # up-region outline
EXTC = "#59a14f"       # extended up-region outline

# Assembly tree: node -> (x, y, label, kind, children)
# kinds: 'active', 'rigid', 'leaf'
NODES = {
    "J5": (4.5, 4.0, "J5", "active", ["J3", "J7"]),
    "J3": (2.5, 3.0, "J3", "rigid", ["J2", "J4"]),
    "J7": (6.5, 3.0, "J7", "active", ["J6", "J8"]),
    "J2": (1.5, 2.0, "J2", "rigid", ["B1", "B2"]),
    "J4": (3.5, 2.0, "J4", "rigid", ["B3", "B4"]),
    "J6": (5.5, 2.0, "J6", "active", ["B5", "B6"]),
    "J8": (7.5, 2.0, "J8", "rigid", ["B7", "B8"]),
}
for k in range(1, 9):
    NODES[f"B{k}"] = (k, 1.0, f"B{k}", "leaf", [])

UP = {"B6", "J6", "J7", "J5"}            # the grabbed leaf and its ancestors
EXT = {"B5", "J8", "J3"}                 # siblings of the up-region's non-root nodes
HYBRID = {"J5", "J7"}                    # active nodes with a rigid (non-leaf) child


def draw_chain(ax):
    ax.set_title("kinematic chain: bodies and joints", fontsize=11)
    y = 0.0
    locked = {2, 3, 4, 8}
    for k in range(1, 9):
        colour = GRAB if k == 6 else ("#d4d4d4" if k <= 4 or k >= 7 else "#ffffff")
        ax.add_patch(FancyBboxPatch((k - 0.38, y - 0.22), 0.76, 0.44, boxstyle="round,pad=0.02",
                                    fc=colour, ec="black", lw=1.2))
        ax.text(k, y, f"B{k}", ha="center", va="center", fontsize=10,
                color="white" if k == 6 else "black")
    for k in range(2, 9):
        x = k - 0.5
        ax.add_patch(Circle((x, y), 0.09, fc=RIGID if k in locked else ACTIVE, ec="black", lw=1, zorder=3))
        ax.text(x, y - 0.42, f"J{k}", ha="center", va="center", fontsize=9)
    # rigid groups
    for lo, hi, name in ((1, 4, "rigid: J2–J4 inactive"), (7, 8, "rigid: J8 inactive")):
        ax.add_patch(Rectangle((lo - 0.45, y - 0.62), hi - lo + 0.9, 1.02, fill=False, ls="--",
                               ec="#7f7f7f", lw=1))
        ax.text((lo + hi) / 2, y + 0.55, name, ha="center", va="bottom", fontsize=8.5, color="#555555")
    # the user's pull on B6
    ax.annotate("", xy=(6, y + 0.25), xytext=(6.6, y + 1.15),
                arrowprops=dict(arrowstyle="<-", color=GRAB, lw=2))
    ax.text(6.65, y + 1.2, "user force f_u at the grab point\n(coupler: f_feed back to the device)",
            fontsize=8.5, color=GRAB, va="bottom")
    ax.set_xlim(0.3, 9.2)
    ax.set_ylim(-0.9, 2.0)
    ax.set_aspect("equal")
    ax.axis("off")


def draw_tree(ax):
    ax.set_title("assembly tree: regions of the adaptive step and of the coupling", fontsize=11)
    for name, (x, y, _, _, children) in NODES.items():
        for c in children:
            cx, cy = NODES[c][0], NODES[c][1]
            ax.plot([x, cx], [y, cy], color="black", lw=1, zorder=1)
    for name, (x, y, label, kind, _) in NODES.items():
        if kind == "leaf":
            fc = GRAB if name == "B6" else LEAF
            ax.add_patch(Rectangle((x - 0.28, y - 0.22), 0.56, 0.44, fc=fc, ec="black", lw=1.2, zorder=2))
            ax.text(x, y, label, ha="center", va="center", fontsize=9, zorder=3,
                    color="white" if name == "B6" else "black")
        else:
            fc = ACTIVE if kind == "active" else RIGID
            ax.add_patch(Circle((x, y), 0.3, fc=fc, ec="black", lw=1.2, zorder=2))
            ax.text(x, y, label, ha="center", va="center", fontsize=9, zorder=3)
        if name in UP:
            ax.add_patch(Circle((x, y), 0.44, fill=False, ec=UPC, lw=2.2, zorder=1.5))
        if name in EXT:
            ax.add_patch(Circle((x, y), 0.44, fill=False, ec=EXTC, lw=2.2, ls="--", zorder=1.5))
        if name in HYBRID:
            ax.text(x + 0.38, y + 0.3, "hybrid", fontsize=8, color="#8c510a", ha="left")
    # joint owners of B6's joints (J6, J7): both on B6's root path
    ax.text(5.5, 2.55, "owner of J6", fontsize=7.5, ha="center", color="#333333")
    ax.text(6.5, 3.55, "owner of J7", fontsize=7.5, ha="center", color="#333333")
    ax.text(0.45, 4.1, "active region: J5, J7, J6 (a rooted subtree)\n"
                       "rigid frontier: J3, J8 (composite inertias, cached)\n"
                       "neglected metric: Σ q̈ᵀq̈ over J2, J3, J4, J8",
            fontsize=8.5, va="top")
    handles = [
        Line2D([], [], marker="o", ls="", mfc=ACTIVE, mec="black", ms=11, label="active node (joint simulated)"),
        Line2D([], [], marker="o", ls="", mfc=RIGID, mec="black", ms=11, label="rigid node (joint locked)"),
        Line2D([], [], marker="s", ls="", mfc=LEAF, mec="black", ms=10, label="leaf = one body"),
        Line2D([], [], marker="o", ls="", mfc="none", mec=UPC, mew=2.2, ms=15,
               label="up-region U of the grabbed body B6"),
        Line2D([], [], marker="o", ls="", mfc="none", mec=EXTC, mew=2.2, ms=15,
               label="+ siblings: extended up-region E (the snapshot)"),
    ]
    ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=2, fontsize=8.5,
              frameon=False)
    ax.set_xlim(0.3, 9.2)
    ax.set_ylim(-0.4, 4.6)
    ax.set_aspect("equal")
    ax.axis("off")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/img/concepts.png", help="PNG to write")
    a = ap.parse_args()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 8.8), gridspec_kw={"height_ratios": [1, 1.9]})
    draw_chain(top)
    draw_tree(bottom)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
