#!/usr/bin/env python3
"""How many Debian packages scripts/install_deps.sh installs on a fresh Debian 12 machine, without
installing anything: apt-get --simulate against a dpkg status that holds only the "required" and
"important" packages of this machine plus what they depend on (a minimal Debian 12 system), with the
apt lists of this machine. Prints the count for `install_deps.sh` (main) and `install_deps.sh --tests`."""
import re
import subprocess

status = [e for e in open("/var/lib/dpkg/status").read().split("\n\n") if "Status: install ok installed" in e]
by_name = {re.search(r"^Package: (\S+)", e, re.M).group(1): e for e in status}
provides = {}
for n, e in by_name.items():
    m = re.search(r"^Provides: (.*)$", e, re.M)
    for p in (m.group(1).split(",") if m else []):
        provides.setdefault(re.sub(r"[ (].*", "", p.strip()), []).append(n)
base = {n for n, e in by_name.items() if re.search(r"^Priority: (required|important)$", e, re.M)}
todo = list(base)
while todo:
    e = by_name[todo.pop()]
    for field in ("Depends", "Pre-Depends"):
        m = re.search(r"^" + field + r": (.*)$", e, re.M)
        for alt in (m.group(1).split(",") if m else []):
            cands = [re.sub(r"[ (:].*", "", a.strip()) for a in alt.split("|")]
            hit = [c for c in cands if c in by_name] or [x for c in cands for x in provides.get(c, [])]
            if hit and hit[0] not in base:
                base.add(hit[0])
                todo.append(hit[0])
with open("/tmp/haptree_base_status", "w") as f:
    f.write("\n\n".join(by_name[n] for n in sorted(base)) + "\n\n")

src = open(__file__.replace("count_deps.py", "install_deps.sh")).read()
def names(array):
    body = re.search(array + r"=\((.*?)\n\)", src, re.S).group(1)
    return [w for line in body.splitlines() for w in line.split("#")[0].split()]
build_run, tests = names("BUILD_RUN"), names("TESTS")
print(f"base system: {len(base)} packages (required + important + their dependencies)")
for label, pkgs in (("install_deps.sh (main.sh)", build_run), ("install_deps.sh --tests (test.sh)", build_run + tests)):
    out = subprocess.run(["apt-get", "-s", "-o", "Dir::State::status=/tmp/haptree_base_status", "install",
                          "--no-install-recommends"] + pkgs, capture_output=True, text=True, check=True).stdout
    n = sum(1 for line in out.splitlines() if line.startswith("Inst "))
    print(f"{label}: {len(pkgs)} named, {n} installed")
