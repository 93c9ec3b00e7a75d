"""The viewer across two hosts in a real browser (CTest labels `browser`, `netns`).

  viewer_two_hosts_test.py HAPTREE_RUN OUT_DIR

Two private network namespaces joined by a veth pair stand for a server (10.214.0.1) and a workstation
(10.214.0.2). The session runs on the server: `haptree_run --scene ala20 --users 1 --viewer-users 2
--viewer-bind 10.214.0.1`, so the viewer listens on the server's LAN address with its token. Debian's
chromium runs headless in the workstation's namespace (this script again, under `ip netns exec`), and:
  * the page loads from the server with the token, frames arrive and advance;
  * the same page without the token is refused (HTTP 403 from the workstation, and the page never
    starts);
  * a drag on an atom in the second tab (user 1, idle until then) grabs that atom's body; the force the
    session feeds back for user 1 is nonzero and within the clamp, in the page (dataset.forceN) and in
    the launcher's own status lines on the server.
Nothing leaves the machine: the namespaces and the veth pair exist only inside this test and are deleted
at the end, even on failure. Needs root (ip netns); without it the test fails with a clear message.
Exit 0 on success; prints what failed otherwise."""
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cdp  # noqa: E402
from session import Checks, Launcher, ca_atoms, drag, ds, wait_for  # noqa: E402

SERVER, WORKSTATION = "10.214.0.1", "10.214.0.2"
PORT = 8080
MAX_FORCE_N = 3.0


def sh(*cmd):
    return subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


class TwoHosts:
    """The server and workstation namespaces and their veth pair; removed by close()."""

    def __init__(self):
        pid = os.getpid()
        self.server, self.workstation = f"hvS{pid}", f"hvW{pid}"
        self.vs, self.vw = f"hvs{pid}", f"hvw{pid}"
        self.error = ""
        steps = [
            ("ip", "netns", "add", self.server),
            ("ip", "netns", "add", self.workstation),
            ("ip", "link", "add", self.vs, "type", "veth", "peer", "name", self.vw),
            ("ip", "link", "set", self.vs, "netns", self.server),
            ("ip", "link", "set", self.vw, "netns", self.workstation),
            ("ip", "netns", "exec", self.server, "ip", "addr", "add", SERVER + "/24", "dev", self.vs),
            ("ip", "netns", "exec", self.workstation, "ip", "addr", "add", WORKSTATION + "/24", "dev", self.vw),
            ("ip", "netns", "exec", self.server, "ip", "link", "set", "lo", "up"),
            ("ip", "netns", "exec", self.workstation, "ip", "link", "set", "lo", "up"),
            ("ip", "netns", "exec", self.server, "ip", "link", "set", self.vs, "up"),
            ("ip", "netns", "exec", self.workstation, "ip", "link", "set", self.vw, "up"),
        ]
        if os.geteuid() != 0:
            self.error = ("not root: this test creates two network namespaces and a veth pair (ip netns add) and "
                          "needs root (CI runs it as root); exclude it with `ctest -LE netns`")
            return
        for step in steps:
            r = sh(*step)
            if r.returncode != 0:
                self.error = f"network namespace set-up failed at `{' '.join(step)}`: {r.stderr.strip()}"
                return

    def close(self):
        sh("ip", "netns", "delete", self.server)   # takes its end of the veth pair, and so the pair
        sh("ip", "netns", "delete", self.workstation)
        sh("ip", "link", "delete", self.vs)


def http_status(url):
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code
    except Exception as e:  # connection refused, timeout: no status
        return f"no answer ({e})"


def workstation(url, out_dir):
    """The browser side, run inside the workstation's namespace; prints its checks, exits 0 if all pass."""
    check = Checks()
    base = url.split("?", 1)[0]
    browser = None
    try:
        check(http_status(url) == 200, f"the page with the token answers 200 from the workstation ({base})")
        check(http_status(base) == 403, f"the page without the token answers 403 ({http_status(base)})")
        browser = cdp.Browser()
        stranger = browser.new_page(base)
        a = browser.new_page(url)
        wait_for("tab A ready", lambda: ds(a, "ready") == "1", 120)
        b = browser.new_page(url)
        wait_for("tab B ready", lambda: ds(b, "ready") == "1", 120)
        check(ds(a, "user") == "0" and ds(b, "user") == "1", f"two tabs are two users (A {ds(a, 'user')}, B {ds(b, 'user')})")
        b.call("Page.bringToFront")
        f0 = int(ds(b, "frames") or 0)
        time.sleep(4)
        f1 = int(ds(b, "frames") or 0)
        check(f1 > f0, f"frames from the server advance in tab B ({f0} -> {f1})")
        check(ds(stranger, "ready") != "1" and int(ds(stranger, "frames") or 0) == 0,
              "the tab opened without the token never starts (no frames)")
        ca = ca_atoms(url)
        t_drag = time.time()
        print(f"DRAG {t_drag:.3f}", flush=True)
        check(drag(b, ca[len(ca) // 2:] + ca[:len(ca) // 2], 120, -90) is not None, "tab B pressed on an atom")
        wait_for("tab B's grab", lambda: ds(b, "grab") == "1", 60)
        body = int(ds(b, "grabBody") or 0)
        check(body >= 1, f"user 1 grabs body {body}")
        wait_for("a nonzero force in tab B", lambda: float(ds(b, "forceN") or 0) > 0, 30)
        fn = float(ds(b, "forceN") or 0)
        check(0 < fn <= MAX_FORCE_N + 1e-9, f"the page shows the fed-back force {fn} N in (0, {MAX_FORCE_N}]")
        b.screenshot(os.path.join(out_dir, "viewer_two_hosts_pull.png"))
        time.sleep(2.5)   # the launcher's status lines (1 per second) see the pull
        b.mouse("mouseReleased", 0, 0, button="left")
        print(f"RELEASE {time.time():.3f}", flush=True)
    except Exception as e:  # a failed wait or CDP call
        check(False, str(e))
    finally:
        if browser:
            browser.quit()
    return 1 if check.failures else 0


def main():
    if sys.argv[1] == "--workstation":
        return workstation(sys.argv[2], sys.argv[3])
    exe, out_dir = sys.argv[1], sys.argv[2]
    os.makedirs(out_dir, exist_ok=True)
    hosts = TwoHosts()
    check = Checks()
    launcher = None
    try:
        if hosts.error:
            check(False, hosts.error)
            return 1
        launcher = Launcher(["ip", "netns", "exec", hosts.server, exe, "--scene", "ala20", "--users", "1",
                             "--viewer-users", "2", "--viewer-bind", SERVER, "--viewer-port", str(PORT),
                             "--duration-s", "300"], os.path.join(out_dir, "launcher_two_hosts.log"))
        if not launcher.url_seen.wait(120):
            check(False, "the launcher printed no viewer URL:\n" + "".join(launcher.lines[-20:]))
            return 1
        url = launcher.url
        check(url.startswith(f"http://{SERVER}:{PORT}/?token="), f"the viewer's URL is the server's address ({url})")
        ws = subprocess.run(["ip", "netns", "exec", hosts.workstation, sys.executable, os.path.abspath(__file__),
                             "--workstation", url, out_dir], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, timeout=400)
        print(ws.stdout, end="", flush=True)
        check(ws.returncode == 0, f"the workstation's browser checks (exit {ws.returncode})")
        marks = dict(line.split()[:2] for line in ws.stdout.splitlines() if line.startswith(("DRAG ", "RELEASE ")))
        if "DRAG" in marks and "RELEASE" in marks:
            t0, t1 = float(marks["DRAG"]), float(marks["RELEASE"])
            fs = [f for (t, f) in launcher.force.get(1, []) if t0 <= t <= t1 + 1.0]
            check(any(f > 0 for f in fs), f"the server's status lines show user 1's pull {fs}")
            check(all(f <= MAX_FORCE_N + 1e-9 for f in fs), f"clamped to {MAX_FORCE_N} N {fs}")
    finally:
        rc = launcher.stop() if launcher else 0
        hosts.close()
    check(rc == 0, f"launcher exit status {rc} after SIGINT")
    if check.failures:
        if launcher:
            print("launcher tail:\n" + "".join(launcher.lines[-15:]))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
