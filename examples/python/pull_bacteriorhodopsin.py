#!/usr/bin/python3
"""Pull one atom of bacteriorhodopsin (1C3W, 786 torsion DOF) for 1000 adaptive steps and plot the
force-field energy and the active DOF.

The loop is sim_server's molecular step (docs/processes.md), written with the Python bindings:
every --reselect-every steps the active region is selected; every step the body poses are updated,
the force field overwrites state.f_ext (it finds by itself which bodies moved together since the last
step and evaluates only the pairs between them), the pull (a spring from the atom to a target
--pull-nm away, radially outwards) is added on the atom, and one adaptive step runs.

    PYTHONPATH=build/python /usr/bin/python3 examples/python/pull_bacteriorhodopsin.py --out pull.png
"""
import argparse
import sys
import time

import numpy as np

import haptree


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bacteriorhodopsin", help="molecular scene name or PDB path")
    ap.add_argument("--steps", type=int, default=1000, help="adaptive steps")
    ap.add_argument("--dt", type=float, default=0.0005, help="time step, ps")
    ap.add_argument("--mode", choices=("threshold", "budget"), default="threshold",
                    help="adaptive selection: error threshold (active DOF vary) or a fixed DOF budget")
    ap.add_argument("--eps-rel", type=float, default=0.05,
                    help="threshold mode: ε = this × the total acceleration metric at the first selection")
    ap.add_argument("--budget", type=int, default=48, help="budget mode: active DOF budget")
    ap.add_argument("--reselect-every", type=int, default=10, help="steps between active-region selections")
    ap.add_argument("--atom", type=int, default=-1,
                    help="atom to pull (0-based, PDB order); default: the CA farthest from the centre")
    ap.add_argument("--pull-nm", type=float, default=1.0, help="target distance of the pull spring, nm")
    ap.add_argument("--stiffness", type=float, default=200.0, help="pull spring, kJ/mol/nm^2")
    ap.add_argument("--out", default="pull_bacteriorhodopsin.png", help="PNG to write")
    a = ap.parse_args(argv)
    for name, v, lo in (("--steps", a.steps, 1), ("--budget", a.budget, 1), ("--reselect-every", a.reselect_every, 1)):
        if v < lo:
            ap.error(f"{name} must be >= {lo}, got {v}")
    if not (a.dt > 0 and a.stiffness >= 0 and 0 < a.eps_rel < 1):
        ap.error("--dt must be > 0, --stiffness >= 0 and --eps-rel in (0, 1)")

    t0 = time.perf_counter()
    sc = haptree.load_molecular_scene(a.scene)
    m = sc.model
    x0 = sc.file_positions()
    labels = sc.atom_labels
    atom = a.atom
    if atom < 0:
        centre = x0.mean(axis=0)
        ca = [i for i, s in enumerate(labels) if s.startswith("CA ")]
        atom = max(ca, key=lambda i: np.linalg.norm(x0[i] - centre))
    if not 0 <= atom < sc.natoms:
        ap.error(f"--atom {atom} out of range [0, {sc.natoms})")
    direction = x0[atom] - x0.mean(axis=0)
    target = x0[atom] + a.pull_nm * direction / np.linalg.norm(direction)
    print(f"{sc!r}: pulling atom {atom} ({labels[atom]}) towards {np.round(target, 3)} nm, "
          f"k = {a.stiffness} kJ/mol/nm², {a.steps} steps of {a.dt} ps "
          f"(loaded in {time.perf_counter() - t0:.1f} s)", flush=True)

    state, data, ad = haptree.State(m), haptree.Data(m), haptree.AdaptiveData(m)
    select = haptree.AdaptiveOptions(budget=a.budget, reselect_every=a.reselect_every)
    step = haptree.AdaptiveOptions(budget=a.budget, reselect_every=2**31 - 1)   # we select ourselves
    haptree.forward_kinematics(m, data, state)
    sc.compute(data, state)                      # f_ext for the first selection
    if a.mode == "threshold":
        haptree.select_active_region(m, data, state, ad, select)   # budget selection: the total metric
        total = ad.report.total_metric
        eps = a.eps_rel * total
        select = haptree.AdaptiveOptions(mode=haptree.AdaptiveMode.threshold, epsilon=eps,
                                         reselect_every=a.reselect_every)
        step = haptree.AdaptiveOptions(mode=haptree.AdaptiveMode.threshold, epsilon=eps, reselect_every=2**31 - 1)
        setting = f"ε = {a.eps_rel:g} × total metric"
        print(f"threshold mode: ε = {eps:.4g} ({a.eps_rel:g} × total metric {total:.4g})")
    else:
        setting = f"budget {a.budget} DOF"

    energy, active, dist, t_ps = [], [], [], []
    t1 = time.process_time()
    for i in range(a.steps):
        if i % a.reselect_every == 0:
            haptree.select_active_region(m, data, state, ad, select)
        haptree.update_all_body_poses(m, data, ad)
        E = sc.compute(data, state)              # overwrites state.f_ext with the force field
        x = sc.atom_position(data, atom)
        sc.add_atom_force(data, atom, a.stiffness * (target - x), state)
        rep = haptree.adaptive_step(m, data, state, ad, step, a.dt)
        energy.append(E)
        active.append(rep.active_dofs)
        dist.append(np.linalg.norm(x - x0[atom]))
        t_ps.append((i + 1) * a.dt)
        if (i + 1) % 200 == 0 or i + 1 == a.steps:
            print(f"step {i + 1:5d}  t {t_ps[-1]:.3f} ps  E {E:12.3f} kJ/mol  active {rep.active_dofs:3d} DOF  "
                  f"neglected {rep.neglected_metric:.3g}  atom moved {dist[-1]:.4f} nm", flush=True)
        if not np.isfinite(E):
            print(f"step {i + 1}: non-finite energy, stopping", file=sys.stderr)
            return 1
    cpu = time.process_time() - t1
    print(f"{a.steps} steps in {cpu:.2f} s CPU ({1e3 * cpu / a.steps:.2f} ms per step incl. force field "
          "and Python)")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    ax[0].plot(t_ps, energy, lw=1)
    ax[0].set_ylabel("potential energy\n(kJ/mol)")
    ax[0].set_title(f"{sc.name}: {m.nv} DOF, pull on atom {atom} ({labels[atom].split(' (')[0]}),\n" + setting)
    ax[1].step(t_ps, active, where="post", lw=1, color="C1")
    ax[1].set_ylabel("active DOF")
    ax[1].set_ylim(0, max(active) * 1.15)
    ax[2].plot(t_ps, dist, lw=1, color="C2")
    ax[2].set_ylabel("atom displacement\n(nm)")
    ax[2].set_xlabel("simulated time (ps)")
    for x in ax:
        x.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
