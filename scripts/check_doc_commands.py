#!/usr/bin/python3
"""Every shell command of README.md and docs/*.md either runs, or says on the page why it does not.

    /usr/bin/python3 scripts/check_doc_commands.py BUILD_DIR [--source DIR] [--only PAGE] [--list]

What counts as a command: each line of a fenced block whose info string is sh, bash or console,
except blank lines and lines that are only a comment; a console block's "$ " prompt is dropped. A line
ending in a backslash, or one that leaves a quote open, continues on the next line.

The rule, for each command (its trailing comment is the text after the first unquoted " #"):

  1. The comment starts with a marker (the word, then ":", ";" or the end of the comment), and the
     command is not run:
       # needs: WHAT       something CI does not have: a haptic device, a second host, root on the
                           host (real-time scheduling, /etc), a display, VMD, a recorded log, ...
       # long: TIME, ctest -R NAME | ctest -L LABEL
                           runs for minutes; the named tests (which must exist in BUILD_DIR) run it
                           or the same code as a smoke
       # installs          installs packages or files (apt-get, the setup scripts, cmake --install,
                           systemd units) or is the whole test suite
       # builds            configures or compiles (cmake, cpack, a second build tree): CI's own build
       # ci                runs CTest tests, which CI runs directly
  2. Otherwise it is run, and must exit 0 (or N where the comment starts with "exits N") within
     --timeout seconds. It runs with bash in a scratch folder where every top-level entry of the
     source tree is a link (docs/img is a fresh folder, so a page's figure is never overwritten)
     and build/ is BUILD_DIR; BUILD_DIR's program folders are first on PATH (a bare sim_server,
     coupler, haptree_run ... is the build's). The commands of one page run in page order in one
     folder (a key or a log made by one line is there for the next). A command is changed only by
     appending or replacing options, so that it ends within seconds:
       - `bash scripts/main.sh ARGS` runs as `build/launcher/haptree_run ARGS`: main.sh is
         install_deps.sh + build.sh + exec haptree_run, and CI has installed and built already;
       - haptree_run: --duration-s at most 1 (added when missing), --viewer-port 0 when not given;
       - the programs in SHORTEN get their size or step option replaced by a small value.

  3. Every command, run or marked, names only options its program has: for each program of
     BUILD_DIR (build/launcher/haptree_run, or a bare sim_server, coupler, ...), every --option of the
     command must appear in that program's --help.

Prints a table (page, line, command, run/marker, result, seconds). Exits 1 if a command has neither a
marker nor a passing run, names an option its program does not have, or has a `long:` marker that
names no existing test.
"""
import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

# program (basename) -> {option: value}; the option is replaced when present and, for the entries
# marked with "+", added when missing.
SHORTEN = {
    "haptree_run": {"--duration-s": "1", "+--duration-s": "1", "+--viewer-port": "0"},
    "molecule_bench": {"--steps": "10"},
    "bus_bench": {"--round-trips": "100"},
    "adaptive_stress": {"--steps": "40", "--oracle-every": "20"},
    "passivity_sweep": {"+--per-decade": "1", "+--refine": "1", "+--hold-s": "0.1"},
    "chaos_soak": {"--duration-s": "3"},
    "sim_server": {"--steps": "200"},
    "pull_bacteriorhodopsin.py": {"+--steps": "20"},
}
# haptree_run's --duration-s is capped, not raised: a shorter one stays.
CAP = {("haptree_run", "--duration-s"), ("chaos_soak", "--duration-s")}


def extract(path):
    """Yields (line number, command text, trailing comment) for each command of a page."""
    lines = open(path, encoding="utf-8").read().split("\n")
    in_block = False
    pending, start = "", 0
    for i, raw in enumerate(lines, 1):
        s = raw.strip()
        if s.startswith("```"):
            if in_block:
                in_block = False
                if pending:
                    yield start, *split_comment(pending)
                    pending = ""
            else:
                info = s[3:].strip().split()
                in_block = bool(info) and info[0] in ("sh", "bash", "console")
            continue
        if not in_block:
            continue
        if not pending:
            if not s or s.startswith("#"):
                continue
            if s.startswith("$ "):
                s = s[2:]
            start, pending = i, s
        else:
            pending += "\n" + raw
        body = pending.rstrip()
        if body.endswith("\\"):
            continue
        if not balanced(body):
            continue
        yield start, *split_comment(pending)
        pending = ""
    if pending:
        yield start, *split_comment(pending)


def balanced(text):
    try:
        shlex.split(text, comments=True)
        return True
    except ValueError:
        return False


def split_comment(text):
    """(command, comment of its last line) -- '#' outside quotes, at a word start."""
    cmd_lines, comment = [], ""
    q = None
    for line in text.split("\n"):
        out, j = [], 0
        cut = None
        while j < len(line):
            c = line[j]
            if q:
                if c == q:
                    q = None
                elif c == "\\" and q == '"':
                    out.append(c)
                    j += 1
                    c = line[j] if j < len(line) else ""
            elif c in "'\"":
                q = c
            elif c == "\\":
                out.append(c)
                j += 1
                c = line[j] if j < len(line) else ""
            elif c == "#" and (j == 0 or line[j - 1] in " \t"):
                cut = j
                break
            out.append(c)
            j += 1
        if cut is not None:
            comment = line[cut + 1:].strip()
            line = line[:cut]
        cmd_lines.append(line.rstrip())
    cmd = "\n".join(cmd_lines).strip()
    return cmd, comment


def marker_of(comment):
    c = comment.strip()
    m = re.match(r"(needs|long|installs|builds|ci)(:|;|$)", c)
    if not m or (m.group(1) in ("needs", "long") and m.group(2) != ":"):
        return None
    return m.group(1)


def shorten(cmd):
    """Appends/replaces options of known programs in each simple command of cmd."""
    # main.sh = install_deps.sh + build.sh + exec build/launcher/haptree_run "$@"
    cmd = re.sub(r"(^|[;&|(]\s*)(bash\s+)?(\./)?scripts/main\.sh\b", r"\1build/launcher/haptree_run", cmd)
    parts = re.split(r"(\s*(?:&&|\|\||;|\|)\s*|\n)", cmd)
    out = []
    for p in parts:
        out.append(shorten_simple(p) if p and not re.fullmatch(r"\s*(?:&&|\|\||;|\||\n)\s*", p) else p)
    return "".join(out)


def shorten_simple(p):
    try:
        words = shlex.split(p)
    except ValueError:
        return p
    prog = None
    for w in words:
        b = os.path.basename(w)
        if b in SHORTEN:
            prog = b
            break
    if prog is None:
        return p
    rules = SHORTEN[prog]
    for opt, val in rules.items():
        if opt.startswith("+"):
            continue
        m = re.search(r"(%s)(=|\s+)(\S+)" % re.escape(opt), p)
        if m:
            v = val
            if (prog, opt) in CAP:
                try:
                    v = str(min(float(m.group(3)), float(val))).rstrip("0").rstrip(".")
                except ValueError:
                    pass
            p = p[:m.start(3)] + v + p[m.end(3):]
    for opt, val in rules.items():
        if opt.startswith("+") and not re.search(r"(^|\s)%s(=|\s|$)" % re.escape(opt[1:]), p):
            tail = re.search(r"\s*(>|2>|&>|\|)", p)
            ins = " %s %s" % (opt[1:], val)
            p = p[:tail.start()] + ins + p[tail.start():] if tail else p.rstrip() + ins
    return p


def make_farm(source, build):
    d = tempfile.mkdtemp(prefix="haptree_doc_cmds.")
    for e in os.listdir(source):
        if e in ("build", ".git"):
            continue
        if e == "docs":
            os.mkdir(os.path.join(d, "docs"))
            for f in os.listdir(os.path.join(source, "docs")):
                if f != "img":
                    os.symlink(os.path.join(source, "docs", f), os.path.join(d, "docs", f))
            os.mkdir(os.path.join(d, "docs", "img"))
            continue
        os.symlink(os.path.join(source, e), os.path.join(d, e))
    os.symlink(build, os.path.join(d, "build"))
    return d


HELP = {}


def unknown_options(cmd, build, dirs):
    """--options of BUILD_DIR's programs in cmd that the program's --help does not name."""
    bad = []
    for part in re.split(r"&&|\|\||;|\||\n", cmd):
        try:
            words = shlex.split(part)
        except ValueError:
            continue
        while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):
            words = words[1:]
        if not words:
            continue
        prog = words[0]
        if prog.startswith("build/"):
            exe = os.path.join(build, prog[len("build/"):])
        elif "/" not in prog:
            exe = next((os.path.join(d, prog) for d in dirs if os.path.isfile(os.path.join(d, prog))), None)
        else:
            exe = None
        if not exe or not os.access(exe, os.X_OK):
            continue
        if exe not in HELP:
            try:
                r = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=20)
                HELP[exe] = r.stdout + r.stderr
            except (OSError, subprocess.TimeoutExpired):
                HELP[exe] = None
        text = HELP[exe]
        if text is None:
            continue
        for w in words[1:]:
            if w.startswith("--") and len(w) > 2:
                opt = w.split("=", 1)[0]
                if not re.search(re.escape(opt) + r"(?![A-Za-z0-9_-])", text):
                    bad.append("%s %s" % (os.path.basename(exe), opt))
    return bad


def ctest_exists(build, comment):
    m = re.search(r"ctest\s+(-R|-L)\s+([^\s;,]+)", comment)
    if not m:
        return False, "a long: marker must name its test: ctest -R NAME or ctest -L LABEL"
    r = subprocess.run(["ctest", "-N", m.group(1), m.group(2)], cwd=build, capture_output=True, text=True)
    n = re.search(r"Total Tests:\s*(\d+)", r.stdout)
    if not n or int(n.group(1)) == 0:
        return False, "no test matches ctest %s %s" % (m.group(1), m.group(2))
    return True, "%s tests" % n.group(1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("build", help="build directory (built, with its tests)")
    ap.add_argument("--source", default=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                    help="source tree (default: this script's)")
    ap.add_argument("--only", action="append", default=[], help="only this page (repeatable), e.g. docs/imd.md")
    ap.add_argument("--list", action="store_true", help="print the decisions and the rewritten commands; run nothing")
    ap.add_argument("--timeout", type=float, default=30, help="per command, s")
    a = ap.parse_args()
    src, build = os.path.abspath(a.source), os.path.abspath(a.build)
    pages = ["README.md"] + sorted("docs/" + f for f in os.listdir(os.path.join(src, "docs")) if f.endswith(".md"))
    if a.only:
        pages = [p for p in pages if p in a.only]
    dirs = [os.path.join(build, d) for d in
            ("launcher", "tools", "tools/faults", "sim_server", "coupler", "device_bridge", "viewer", "imd_bridge", "bench")]
    path = os.pathsep.join(dirs)
    env = dict(os.environ, PATH=path + os.pathsep + os.environ.get("PATH", ""),
               PYTHONDONTWRITEBYTECODE="1", MPLBACKEND="Agg")
    rows, failures = [], 0
    counts = {}
    t_all = time.monotonic()
    for page in pages:
        farm = None
        try:
            for line, cmd, comment in extract(os.path.join(src, page)):
                mk = marker_of(comment)
                bad = unknown_options(cmd, build, dirs)
                if bad:
                    failures += 1
                    counts["unknown option"] = counts.get("unknown option", 0) + 1
                    rows.append((page, line, cmd, "# " + comment if mk else "run",
                                 "FAIL: unknown option " + ", ".join(bad), ""))
                    continue
                if mk:
                    result, secs = "not run", ""
                    if mk == "long":
                        ok, why = ctest_exists(build, comment)
                        result = "covered: " + why if ok else "FAIL: " + why
                        failures += not ok
                    counts[mk] = counts.get(mk, 0) + 1
                    rows.append((page, line, cmd, "# " + comment, result, secs))
                    continue
                run = shorten(cmd)
                counts["run"] = counts.get("run", 0) + 1
                if a.list:
                    rows.append((page, line, cmd, "run: " + run if run != cmd else "run", "", ""))
                    continue
                if farm is None:
                    farm = make_farm(src, build)
                m = re.match(r"exits (\d+)", comment)
                want = int(m.group(1)) if m else 0
                t0 = time.monotonic()
                try:
                    r = subprocess.run(["bash", "-c", run], cwd=farm, env=env, stdin=subprocess.DEVNULL,
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=a.timeout,
                                       start_new_session=True)
                    rc, out = r.returncode, r.stdout
                except subprocess.TimeoutExpired as e:
                    rc, out = "timeout", e.stdout or b""
                dt = time.monotonic() - t0
                ok = rc == want
                failures += not ok
                result = "ok" if ok else "FAIL: exit %s (want %d)" % (rc, want)
                rows.append((page, line, cmd, "run" if run == cmd else "run: " + run, result, "%.1f" % dt))
                if not ok:
                    text = out.decode("utf-8", "replace") if isinstance(out, bytes) else out
                    print("---- %s:%d: %s\n%s\n----" % (page, line, run, "\n".join(text.splitlines()[-15:])),
                          file=sys.stderr)
        finally:
            if farm:
                shutil.rmtree(farm, ignore_errors=True)
    for page, line, cmd, how, result, secs in rows:
        one = " ".join(cmd.split())
        print("%-34s %4d  %-70s | %s | %s | %s" % (page, line, one[:70], " ".join(how.split())[:90], result, secs))
    unmarked = [r for r in rows if r[4].startswith("FAIL")]
    print("\n%d commands: %s; %d failed; %.0f s" % (
        len(rows), ", ".join("%s %d" % kv for kv in sorted(counts.items())), len(unmarked),
        time.monotonic() - t_all))
    for page, line, cmd, how, result, _ in unmarked:
        print("%s:%d: %s -- %s (run it in CI, or mark it: # needs: / # long: / # installs / # builds / # ci)"
              % (page, line, " ".join(cmd.split())[:80], result))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
