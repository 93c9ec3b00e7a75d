#!/usr/bin/env python3
"""Default-built programs on an older CPU: under qemu-user as a Nehalem (x86-64-v2: SSE4.2, no AVX)
they run, the dispatcher picks the generic kernels, and the results equal this machine's run; as a
Haswell (x86-64-v3) the avx2 kernel is picked.

Usage: qemu_isa_test.py QEMU ISA_PROBE HAPTREE_FD

The DCA has a baseline and an x86-64-v3 copy chosen the same way (haptree/dca_detail.hpp).

Tolerances (derived, not tuned):
  force field (isa_probe): every kernel level is within 1e-9 of the energy scale (sum of |energy
    terms|) and of the largest wrench component of the all-pairs reference (summation order and a
    1/r within a few ulp; tests/molecule/isa_kernel_test.cpp), so two runs are within 2e-9.
  forward dynamics (haptree-fd, a chain of 8): the DCA is within 1e-10 (relative to max |qdd|) of the
    long-double oracle on every CPU (tests/core/dca_test.cpp), so two runs are within 2e-10. The
    DCA code is the same in both; libm's sin/cos may take another path on another CPU (glibc picks
    FMA variants at run time).
"""
import json
import os
import subprocess
import sys

qemu, probe, fd = sys.argv[1:4]
if not os.access(qemu, os.X_OK):
    sys.exit(f"FAIL: no qemu-x86_64 ({qemu}): install Debian's qemu-user (scripts/install_deps.sh)")
env = {k: v for k, v in os.environ.items() if k != "HAPTREE_ISA"}
failures = []


def run(cmd, extra_env=None):
    e = dict(env)
    e.update(extra_env or {})
    p = subprocess.run(cmd, capture_output=True, text=True, env=e, timeout=600)
    if p.returncode != 0:
        sys.exit(f"FAIL: {' '.join(cmd)} exited {p.returncode}: {p.stderr.strip()[-400:]}")
    return json.loads(p.stdout)


def check(ok, what):
    print(("ok   " if ok else "FAIL ") + what)
    if not ok:
        failures.append(what)


def compare_ff(a, b, label):
    for name in a["scenes"]:
        x, y = a["scenes"][name], b["scenes"][name]
        e_scale = sum(abs(t) for t in x["terms"])
        w_scale = max(abs(w) for w in x["wrench"])
        de = max([abs(x["E"] - y["E"])] + [abs(s - t) for s, t in zip(x["terms"], y["terms"])])
        dw = max(abs(s - t) for s, t in zip(x["wrench"], y["wrench"]))
        check(len(x["wrench"]) == len(y["wrench"]) and len(x["wrench"]) > 6, f"{label} {name}: same bodies")
        check(de <= 2e-9 * e_scale, f"{label} {name}: energy differs by {de:.3e} <= 2e-9 x {e_scale:.4e}")
        check(dw <= 2e-9 * w_scale, f"{label} {name}: wrenches differ by {dw:.3e} <= 2e-9 x {w_scale:.4e}")


host = run([probe])
check(host["isa"] == host["best"], f"host picks its best level ({host['best']})")
host_generic = run([probe], {"HAPTREE_ISA": "generic"})
check(host_generic["isa"] == "generic", "HAPTREE_ISA=generic selects the generic kernel on the host")

old = run([qemu, "-cpu", "Nehalem", probe])
check(old["best"] == "generic" and old["isa"] == "generic",
      f"qemu Nehalem: dispatcher picks generic (best {old['best']}, active {old['isa']})")
old_forced = run([qemu, "-cpu", "Nehalem", probe], {"HAPTREE_ISA": "avx512"})
check(old_forced["isa"] == "generic", "qemu Nehalem with HAPTREE_ISA=avx512: still generic (never a level the CPU lacks)")
compare_ff(host, old, f"host {host['isa']} vs qemu Nehalem generic")
# qemu's TCG runs AVX2 + FMA (x86-64-v3) but no AVX-512: as a Haswell the avx2 kernel is picked.
v3 = run([qemu, "-cpu", "Haswell", probe])
check(v3["best"] == "avx2" and v3["isa"] == "avx2", f"qemu Haswell: dispatcher picks avx2 (best {v3['best']}, active {v3['isa']})")
compare_ff(v3, old, "qemu Haswell avx2 vs qemu Nehalem generic")
compare_ff(host_generic, old, "host generic vs qemu Nehalem generic")

# The DCA: its x86-64-v3 copy wherever the kernels run at avx2 or above, the baseline copy otherwise;
# the protein-like tree's q̈ on every CPU within twice the oracle tolerance of tests/core/dca_test.cpp
# (each copy is within 1e-10 of the long-double oracle, relative to max |q̈|).
check(host["dca"] == ("avx2" if host["best"] in ("avx2", "avx512") else "generic"),
      f"host: the DCA runs at {host['dca']} (kernels {host['isa']})")
check(host_generic["dca"] == "generic", "HAPTREE_ISA=generic: the DCA's baseline copy on the host")
check(old["dca"] == "generic", f"qemu Nehalem: the DCA's baseline copy ({old['dca']})")
check(v3["dca"] == "avx2", f"qemu Haswell: the DCA's x86-64-v3 copy ({v3['dca']})")


def compare_dca(a, b, label):
    x, y = a["dca_qdd"], b["dca_qdd"]
    scale = max(abs(v) for v in x)
    d = max(abs(s - t) for s, t in zip(x, y))
    check(len(x) == len(y) and len(x) > 100 and scale > 0 and d <= 2e-10 * scale,
          f"{label}: protein-like q̈ differs by {d:.3e} <= 2e-10 x {scale:.4e}")


compare_dca(host, old, f"host DCA {host['dca']} vs qemu Nehalem generic")
compare_dca(v3, old, "qemu Haswell DCA avx2 vs qemu Nehalem generic")
compare_dca(host, host_generic, f"host DCA {host['dca']} vs host generic")

fd_cmd = [fd, "--scene", "chain", "--n", "8", "--indent", "-1"]
a = run(fd_cmd)["qdd"]
b = run([qemu, "-cpu", "Nehalem"] + fd_cmd)["qdd"]
check(sorted(a) == sorted(b) and len(a) == 8, "haptree-fd: same joints")
scale = max(abs(v) for v in a.values())
d = max(abs(a[k] - b[k]) for k in a)
check(scale > 0 and d <= 2e-10 * scale, f"haptree-fd chain 8: qdd differs by {d:.3e} <= 2e-10 x {scale:.4e}")

if failures:
    sys.exit(f"{len(failures)} check(s) failed")
print("all checks passed")
