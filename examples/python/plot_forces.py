#!/usr/bin/python3
"""Plot the feedback force against time for each user (device) of a recorded haptree session.

    lcm-logger --lcm-url=URL session.lcmlog          # while a session runs (see docs/python.md)
    PYTHONPATH=build/python /usr/bin/python3 examples/python/plot_forces.py session.lcmlog --out forces.png

Reads the log with haptree.lcmlog (no LCM Python package needed): one panel per device with the
three force components and |f| (device units, N), the watchdog-ramp periods shaded.
"""
import argparse
import sys

import numpy as np

import haptree.lcmlog as lcmlog
from haptree.lcmtypes import lcmt_feedback


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("log", help="LCM log (lcm-logger or lcm::LogFile)")
    ap.add_argument("--out", default="forces.png", help="PNG to write")
    ap.add_argument("--start-s", type=float, default=None, help="from this time (s after the first event)")
    ap.add_argument("--end-s", type=float, default=None, help="up to this time (s after the first event)")
    a = ap.parse_args(argv)
    try:
        log = lcmlog.read(a.log, start_s=a.start_s, end_s=a.end_s, channels=r"HAPTREE_FEEDBACK_.*")
    except (OSError, lcmlog.LogFormatError) as e:
        print(f"plot_forces: {e}", file=sys.stderr)
        return 2
    fb = log.feedback()
    if len(fb) == 0:
        print(f"plot_forces: {a.log} holds no HAPTREE_FEEDBACK_* messages in the window", file=sys.stderr)
        return 1
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    devices = sorted(fb.device_id.unique())
    fig, axes = plt.subplots(len(devices), 1, figsize=(9, 2.6 * len(devices) + 0.6), sharex=True, squeeze=False)
    for ax, dev in zip(axes[:, 0], devices):
        f = fb[fb.device_id == dev]
        t = f.t_s.to_numpy()
        F = f[["force_n_0", "force_n_1", "force_n_2"]].to_numpy()
        for k, name in enumerate("xyz"):
            ax.plot(t, F[:, k], lw=0.8, label=f"f{name}")
        ax.plot(t, np.linalg.norm(F, axis=1), lw=1.2, color="k", label="|f|")
        ramp = (f["flags"].to_numpy() & lcmt_feedback.FLAG_WATCHDOG) != 0
        if ramp.any():
            ax.fill_between(t, 0, 1, where=ramp, transform=ax.get_xaxis_transform(), color="C3", alpha=0.12,
                            step="post", label="watchdog ramp")
        ax.set_ylabel(f"device {dev}\nforce (N)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, ncol=5)
        print(f"device {dev}: {len(f)} feedback messages over {t[-1] - t[0]:.2f} s, max |f| "
              f"{np.linalg.norm(F, axis=1).max():.3f} N, {ramp.sum()} in the watchdog ramp")
    axes[-1, 0].set_xlabel("time since the first logged event (s)")
    axes[0, 0].set_title(f"feedback forces: {a.log}")
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
