"""Browser test of the viewer's pacing (CTest label `browser`): a tab that stops reading for a while
gets the newest state when it reads again, not a queue of old frames.

  viewer_slow_tab_test.py HAPTREE_RUN OUT_DIR

Runs `haptree_run --scene bacteriorhodopsin` (frames of tens of KB) with one page in Debian's chromium
headless, then blocks the page's main thread for BLOCK_S seconds (a busy loop in Runtime.evaluate: what
a slow machine or a long draw does to a tab). Each frame carries the time the viewer built it, so the
page knows how old the frame it reads is (dataset.frameAgeMs, same clock: one host). The page
acknowledges every frame and the viewer keeps at most 4 unacknowledged frames on a socket: after the
block the page reads those few, then frames as old as one of its own draws. FRESH_AFTER frames after
the block the newest must be less than BLOCK_S / 2 old. Without the pacing the socket's and the
browser's buffers hold every frame sent during the block (5–30 a second), read in order: that many
frames later the page still reads frames from the block, BLOCK_S minus a few seconds old (measured
11.4 s after an 8-s block). Also checks that the frames keep coming and are drawn afterwards.
Exit 0 on success."""
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cdp  # noqa: E402
from session import Checks, Launcher, ds, free_port, wait_for  # noqa: E402

BLOCK_S = 10.0
FRESH_AFTER = 12        # frames read after the block before the age is read

check = Checks()


def main():
    exe, out_dir = sys.argv[1], sys.argv[2]
    os.makedirs(out_dir, exist_ok=True)
    port = free_port()
    launcher = Launcher([exe, "--scene", "bacteriorhodopsin", "--users", "1", "--viewer-users", "1",
                         "--viewer-port", str(port), "--duration-s", "200"],
                        os.path.join(out_dir, "launcher_slow_tab.log"))
    browser = page = None
    try:
        if not launcher.url_seen.wait(120):
            raise AssertionError("no viewer URL:\n" + "".join(launcher.lines[-10:]))
        browser = cdp.Browser()
        page = browser.new_page(launcher.url)
        page.call("Page.bringToFront")
        wait_for("the page ready", lambda: ds(page, "ready") == "1" and int(ds(page, "frames") or 0) > 3, 120)
        wait_for("a frame read on time", lambda: 0 <= float(ds(page, "frameAgeMs") or -1) < 500 * BLOCK_S, 60)
        late0 = int(ds(page, "lateFrames") or 0)
        # Block the main thread; the value returned is the count of frames read when it ends.
        at_end = page.eval("(() => { const t = performance.now() + %d; while (performance.now() < t) {} "
                           "return Number(document.body.dataset.wsReceived); })()" % int(BLOCK_S * 1000))
        wait_for(f"{FRESH_AFTER} frames after the block",
                 lambda: int(ds(page, "wsReceived") or 0) >= at_end + FRESH_AFTER, 120)
        late = int(ds(page, "lateFrames") or 0) - late0
        age = float(ds(page, "frameAgeMs") or -1)
        print(f"after a {BLOCK_S:.0f}-s block: {late} frames read more than 2 s late; the newest is {age:.0f} ms old",
              flush=True)
        check(0 <= age < 500 * BLOCK_S,
              f"{FRESH_AFTER} frames after the block the page reads frames built less than {BLOCK_S / 2:.0f} s ago "
              f"({age:.0f} ms), not the queue of the block")
        f0 = int(ds(page, "frames") or 0)
        wait_for("a draw after the block", lambda: int(ds(page, "frames") or 0) > f0, 60)
        check(int(ds(page, "frames") or 0) > f0, "the page draws after the block")
        check(ds(page, "error") == "", f"no page error ({ds(page, 'error')!r})")
    except Exception as e:
        check.failures.append(str(e))
        print("FAIL", e, flush=True)
    finally:
        if browser:
            if page:
                browser.close_page(page)
            browser.quit()
        rc = launcher.stop()
    check(rc == 0, f"launcher exit status {rc}")
    if check.failures:
        print(f"{len(check.failures)} failure(s)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
