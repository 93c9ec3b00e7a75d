"""What the browser tests share: a launcher whose stdout is parsed (the viewer's URL, each user's |f|
from the status lines), waiting for a page condition, reading the page's dataset, dragging on atoms,
and a list of checks."""
import re
import signal
import socket
import subprocess
import threading
import time
import urllib.request


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


class Launcher:
    """`haptree_run` (or any command that runs it, e.g. under `ip netns exec`): its output goes to
    log_path; `url` is the viewer's URL once printed (with its token), `force[user]` the (time, |f| N)
    of each status line (the coupler's counters)."""
    STATUS = re.compile(r"user (\d+): +([\d.]+) Hz, \|f\| ([\d.]+) N")

    def __init__(self, cmd, log_path):
        self.log = open(log_path, "w")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines, self.url, self.force = [], None, {}
        self.url_seen = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self.log.write(line)
            self.log.flush()
            self.lines.append(line)
            m = re.match(r"viewer: open (\S+)", line)
            if m:
                self.url = m.group(1)
                self.url_seen.set()
            if line.startswith("t "):
                for s in self.STATUS.finditer(line):
                    self.force.setdefault(int(s.group(1)), []).append((time.time(), float(s.group(3))))

    def forces_since(self, user, t0):
        return [f for (t, f) in self.force.get(user, []) if t >= t0]

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return -9


class Checks:
    def __init__(self):
        self.failures = []

    def __call__(self, cond, what):
        print(("ok   " if cond else "FAIL ") + what, flush=True)
        if not cond:
            self.failures.append(what)


def wait_for(what, fn, timeout):
    t_end = time.time() + timeout
    while time.time() < t_end:
        v = fn()
        if v:
            return v
        time.sleep(0.25)
    raise AssertionError(f"timed out ({timeout} s) waiting for {what}")


def ds(page, key):
    return page.eval(f"(document.body && document.body.dataset.{key}) || ''")


def ca_atoms(url):
    """Indices (file order = NGL's atom index) of the CA atoms in the viewer's /scene.pdb: always drawn."""
    base, query = url.split("?", 1)
    with urllib.request.urlopen(base + "scene.pdb?" + query, timeout=30) as r:
        lines = [l for l in r.read().decode().splitlines() if l.startswith(("ATOM", "HETATM"))]
    return [i for i, l in enumerate(lines) if l[12:16].strip() == "CA"]


def drag(page, atoms, dx, dy, steps=12):
    """Presses on the first of `atoms` (display points) the page picks as an atom, moves by (dx, dy)
    pixels and keeps the button down. Returns the atom pressed on, or None."""
    for atom in atoms:
        p = page.eval(f"haptreePointOnScreen({atom})")
        x, y = p["x"], p["y"]
        page.eval("document.body.dataset.pick = ''")
        page.mouse("mouseMoved", x, y)
        page.mouse("mousePressed", x, y, buttons=1, button="left")
        pick = ds(page, "pick")
        print(f"press on point {atom} at ({x:.0f}, {y:.0f}): page picked {pick!r}", flush=True)
        if not pick.startswith("atom"):
            page.mouse("mouseReleased", x, y, button="left")
            continue
        for k in range(1, steps + 1):
            page.mouse("mouseMoved", x + dx * k / steps, y + dy * k / steps, buttons=1, button="left")
            time.sleep(0.05)
        return atom
    return None
