"""Browser test of the viewer (CTest label `browser`): a real launcher, Debian's chromium headless over CDP.

  viewer_browser_test.py HAPTREE_RUN OUT_DIR [--processes]

Starts `haptree_run --scene bacteriorhodopsin ... --users 1 --viewer-users 2` (user 0 scripted, user 1
browser only), opens two tabs (two users), and checks:
  * the page loads from the launcher, frames arrive and document.body.dataset.frames advances;
  * a drag sent with Input.dispatchMouseEvent on an atom in tab B (user 1, idle until then) grabs that
    atom's body and gives a nonzero feedback force within the clamp, in the session's own status lines
    (coupler counters) and in dataset.forceN; a screenshot is written while it pulls;
  * a drag in tab A takes user 0 over from its scripted device (another body is grabbed);
  * closing tab B while it pulls releases user 1: its force in the status lines goes back to exactly 0.
Exit 0 on success; prints what failed otherwise."""
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cdp  # noqa: E402
from session import Checks, Launcher, ca_atoms, drag, ds, free_port, wait_for  # noqa: E402

MAX_FORCE_N = 3.0


def screenshot_when_pulling(page, path, tries=20):
    """The session's watchdog may zero the force for a moment on a loaded machine: shoot when |f| > 0."""
    for _ in range(tries):
        if float(ds(page, "forceN") or 0) > 0:
            break
        time.sleep(0.5)
    page.screenshot(path)


def main():
    exe, out_dir = sys.argv[1], sys.argv[2]
    processes = "--processes" in sys.argv[3:]
    os.makedirs(out_dir, exist_ok=True)
    tag = "processes" if processes else "embedded"
    port = free_port()
    args = [exe, "--scene", "bacteriorhodopsin", "--users", "1", "--viewer-users", "2", "--viewer-port", str(port),
            "--duration-s", "300"] + (["--processes"] if processes else [])
    launcher = Launcher(args, os.path.join(out_dir, f"launcher_{tag}.log"))
    browser = a = b = None
    check = Checks()
    failures = check.failures

    try:
        if not launcher.url_seen.wait(120):
            raise AssertionError("the launcher printed no viewer URL:\n" + "".join(launcher.lines[-20:]))
        url = launcher.url
        check(url.startswith(f"http://127.0.0.1:{port}/?token="), f"the launcher prints the URL with its token ({url})")
        browser = cdp.Browser()
        a = browser.new_page(url)
        wait_for("tab A ready", lambda: ds(a, "ready") == "1", 120)
        b = browser.new_page(url)
        wait_for("tab B ready", lambda: ds(b, "ready") == "1", 120)
        check(ds(a, "user") == "0" and ds(b, "user") == "1", f"two tabs are two users (A {ds(a, 'user')}, B {ds(b, 'user')})")

        # frames arrive and the counter advances (rate in headless SwiftShader, for the log)
        f0, t0 = int(ds(b, "frames") or 0), time.time()
        time.sleep(5)
        f1, t1 = int(ds(b, "frames") or 0), time.time()
        check(f1 > f0, f"frames advance in tab B ({f0} -> {f1})")
        print(f"tab B rendered {(f1 - f0) / (t1 - t0):.1f} frames/s (headless chromium, SwiftShader)", flush=True)
        # every user's device cursor is drawn (user 0: the scripted device, grabbing; user 1: the idle
        # browser device), and the HUD says "no grab" for the idle one
        wait_for("the device cursors in tab B", lambda: int(ds(b, "cursors") or 0) >= 1, 30)
        check(int(ds(b, "cursors") or 0) >= 1, f"device cursors drawn in tab B: {ds(b, 'cursors')} (JS-side count)")
        hud = b.eval("document.getElementById('hudtab').innerText")
        check("no grab" in hud and "-1.0 ms" not in hud, f"the HUD says 'no grab' for the idle user ({hud[-120:]!r})")
        b.call("Page.bringToFront")
        shot = os.path.join(out_dir, f"viewer_cursor_{tag}.png")
        b.screenshot(shot)
        check(os.path.getsize(shot) > 10000, f"cursor screenshot {shot} ({os.path.getsize(shot)} bytes)")
        before = launcher.forces_since(1, 0)
        check(all(f == 0.0 for f in before), f"user 1 idle before the drag (|f| {before[-3:]})")

        # drag in tab B on a backbone atom (a hidden tab renders nothing: bring it to the front)
        b.call("Page.bringToFront")   # on a backbone atom in the middle of the chain
        ca = ca_atoms(url)
        mid = len(ca) // 2
        t_drag = time.time()
        check(drag(b, ca[mid:mid + 10], 150, -110) is not None, "tab B pressed on an atom")
        grabbed = wait_for("tab B's grab to show", lambda: ds(b, "grab") == "1", 60)
        check(bool(grabbed), "tab B's press grabbed an atom")
        body = int(ds(b, "grabBody") or 0)
        check(body >= 1, f"user 1 grabs body {body}")
        wait_for("user 1 force in the status lines", lambda: any(f > 0 for f in launcher.forces_since(1, t_drag)), 60)
        time.sleep(2.5)
        fs = launcher.forces_since(1, t_drag)
        check(any(f > 0 for f in fs), f"nonzero feedback force for user 1 in the session's status lines {fs}")
        check(all(f <= MAX_FORCE_N + 1e-9 for f in fs), f"clamped to {MAX_FORCE_N} N {fs}")
        # The page shows the newest |f| of its frames (≈ 8 frames/s here); the coupler's watchdog may zero
        # it for a moment on a loaded machine, so wait for a frame that carries the pull, then check it.
        wait_for("tab B to show a nonzero force", lambda: float(ds(b, "forceN") or 0) > 0, 20)
        fn = float(ds(b, "forceN") or 0)
        check(0 < fn <= MAX_FORCE_N + 1e-9, f"dataset.forceN {fn} in (0, {MAX_FORCE_N}]")
        shot = os.path.join(out_dir, f"viewer_pull_{tag}.png")
        screenshot_when_pulling(b, shot)
        check(os.path.getsize(shot) > 10000, f"screenshot {shot} written ({os.path.getsize(shot)} bytes)")

        # tab A takes user 0 over from its script
        a.call("Page.bringToFront")
        time.sleep(2)
        scripted_body = int(ds(a, "grabBody") or 0)
        q = len(ca) // 4
        check(drag(a, ca[q:q + 10], -70, 50) is not None, "tab A pressed on an atom")
        wait_for("tab A's grab", lambda: ds(a, "grabBody") not in ("", "0", str(scripted_body)), 60)
        check(ds(a, "grabBody") != str(scripted_body),
              f"a page grab takes user 0 over (script body {scripted_body} -> page body {ds(a, 'grabBody')})")
        a.mouse("mouseReleased", 0, 0, button="left")

        # a closed tab (dropped WebSocket) releases its user at once
        t_close = time.time()
        browser.close_page(b)
        wait_for("user 1 released", lambda: [f for f in launcher.forces_since(1, t_close + 1.5)][:1] == [0.0], 60)
        after = launcher.forces_since(1, t_close + 1.5)
        check(after and all(f == 0.0 for f in after), f"user 1's force is 0 after its tab closed {after}")
    except Exception as e:  # a failed wait or CDP call: report it with the launcher's tail and the pages' state
        failures.append(str(e))
        print("FAIL", e, flush=True)
        for name, page in (("A", a), ("B", b)):
            try:
                state = page.eval("JSON.stringify(document.body.dataset)") if page else None
            except Exception as e2:  # a closed or hung tab
                state = f"unreadable ({e2})"
            print(f"tab {name}: {state}", flush=True)
    finally:
        if browser:
            browser.quit()
        rc = launcher.stop()
    check(rc == 0, f"launcher exit status {rc} after SIGINT")
    if failures:
        print("launcher tail:\n" + "".join(launcher.lines[-15:]))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
