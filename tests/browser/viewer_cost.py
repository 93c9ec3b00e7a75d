"""Cost of the viewer to the sim and the coupler, and the viewer's frame rate in headless chromium.

  /usr/bin/python3 tests/browser/viewer_cost.py build/launcher/haptree_run [SECONDS] [--only tab]

Runs the bacteriorhodopsin session (README: --dt 0.0005 --position-scale 1 --stiffness 200) three times
for SECONDS (default 20) each: no viewer; viewer with no tab; viewer with one headless chromium tab
(SwiftShader). Prints a markdown table from the launcher's own summary lines (sim steps, mean sampled
step, coupler iterations, device pose-to-force latency p50/p99) and the tab's frames/s (dataset.frames),
then the page's own JavaScript time per frame (dataset.msFrame/msPos/msOverlay: running means) and, where
the page has the hook, SwiftShader's time per draw with and without each representation
(haptreeRasterMs). `--only tab` runs the tab configuration alone (the frame-rate figures).
HAPTREE_VIEWER_WEB_DIR=DIR serves another copy of the page (e.g. an older one, to compare).

  /usr/bin/python3 tests/browser/viewer_cost.py build/launcher/haptree_run --frames [SECONDS]

The cost per frame of the page in headless chromium (SwiftShader, no GPU) for ala20, bacteriorhodopsin
and the sample robots (data/robots: arm, cable, snake): per scene one session and one tab for SECONDS
(default 10) of steady state; prints a markdown table: frames drawn per second, the page's JavaScript
time per frame (mean and median of the last 64), SwiftShader's time per draw (a draw plus a 1-pixel read,
mean of 8), and the WebSocket bytes per frame received (binary frames, positions only when the scene
moved)."""
import json
import os
import re
import signal
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cdp  # noqa: E402
from session import free_port  # noqa: E402

ARGS = ["--scene", "bacteriorhodopsin", "--dt", "0.0005", "--position-scale", "1", "--stiffness", "200",
        "--viewer-users", "1"]   # one user (scripted) in every run: the same couplers with and without viewer


def run(exe, seconds, mode):
    port = free_port() if mode != "off" else 0
    p = subprocess.Popen([exe, *ARGS, "--duration-s", str(seconds), "--viewer-port", str(port)],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    fps = None
    if mode == "tab":
        out = []
        url = None
        for line in p.stdout:   # wait for the URL (with its token)
            out.append(line)
            if line.startswith("viewer: open"):
                url = line.split()[2]
                break
        b = cdp.Browser()
        try:
            page = b.new_page(url)
            page.call("Page.bringToFront")   # a background tab gets no animation frames
            t_end = time.time() + 120
            while time.time() < t_end and page.eval("(document.body && document.body.dataset.ready) || ''") != "1":
                time.sleep(0.5)
            time.sleep(2)
            f0, t0 = int(page.eval("document.body.dataset.frames")), time.time()
            time.sleep(min(10, seconds / 2))
            f1, t1 = int(page.eval("document.body.dataset.frames")), time.time()
            fps = (f1 - f0) / (t1 - t0)
            page_ms = {k: page.eval(f"document.body.dataset.{k} || ''") for k in
                       ("msFrame", "msPos", "msPosMedian", "msOverlay", "msCartoon", "cartoonUpdates", "direct", "directWhy", "error")}
            page_ms["fps"] = f"{fps:.1f}"
            page_ms["raster"] = page.eval("window.haptreeRasterMs ? JSON.stringify(haptreeRasterMs(4)) : ''")
            print("page:", page_ms, flush=True)
            rest = p.communicate()[0]
        finally:
            b.quit()
        text = "".join(out) + rest
    else:
        text = p.communicate()[0]
    m = re.search(r"summary: (\d+) sim steps .*mean sampled step ([\d.]+) ms", text)
    u = re.search(r"user 0: body \d+, (\d+) coupler iterations.*latency p50 ([\d.]+) us p99 ([\d.]+) us", text)
    return {"mode": mode, "steps": int(m.group(1)), "step_ms": float(m.group(2)), "iters": int(u.group(1)),
            "p50": float(u.group(2)), "p99": float(u.group(3)), "fps": fps}


ROBOTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "data", "robots")
FRAME_SCENES = [
    ("ala20", ["--scene", "ala20", "--dt", "0.0005", "--position-scale", "1", "--stiffness", "200"]),
    ("bacteriorhodopsin", ARGS[:-2]),
    ("arm (meshes)", ["--urdf", os.path.join(ROBOTS, "arm.urdf")]),
    ("cable (24 cylinders)", ["--urdf", os.path.join(ROBOTS, "cable.urdf")]),
    ("snake (boxes, spheres)", ["--urdf", os.path.join(ROBOTS, "snake.urdf")]),
]


def frame_cost(exe, name, args, seconds):
    port = free_port()
    p = subprocess.Popen([exe, *args, "--users", "1", "--viewer-users", "1", "--viewer-port", str(port),
                          "--duration-s", str(seconds + 60)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    url = None
    for line in p.stdout:
        if line.startswith("viewer: open"):
            url = line.split()[2]
            break
    b = cdp.Browser()
    try:
        page = b.new_page(url)
        page.call("Page.bringToFront")
        ds = lambda k: page.eval(f"(document.body && document.body.dataset.{k}) || ''")  # noqa: E731
        t_end = time.time() + 120
        while time.time() < t_end and not (ds("ready") == "1" and int(ds("frames") or 0) > 5):
            time.sleep(0.5)
        time.sleep(2)
        f0, b0, m0, t0 = int(ds("frames")), int(ds("wsBytes")), int(ds("wsFrames")), time.time()
        ms0 = float(ds("msFrame") or 0)
        time.sleep(seconds)
        f1, b1, m1, t1 = int(ds("frames")), int(ds("wsBytes")), int(ds("wsFrames")), time.time()
        ms1 = float(ds("msFrame") or 0)
        # msFrame is a running mean since the start: the mean over the window from the two readings
        js = (ms1 * f1 - ms0 * f0) / max(1, f1 - f0)
        raster = json.loads(page.eval("JSON.stringify(haptreeRasterMs(8))"))
        row = {"scene": name, "fps": (f1 - f0) / (t1 - t0), "msgs": (m1 - m0) / (t1 - t0), "js": js,
               "js_median": float(ds("msPosMedian") or 0), "draw": raster["all"],
               "bytes": (b1 - b0) / max(1, m1 - m0), "error": ds("error")}
    finally:
        b.quit()
        p.send_signal(signal.SIGINT)
        try:
            p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
    return row


def frames_table(exe, seconds):
    print(f"| scene | frames drawn/s | frames received/s | page JS ms/frame (mean) | positions ms (median) | "
          "draw ms (SwiftShader) | WebSocket bytes/frame |")
    print("|---|---|---|---|---|---|---|", flush=True)
    for name, args in FRAME_SCENES:   # a row as each scene is measured
        r = frame_cost(exe, name, args, seconds)
        print(f"| {r['scene']} | {r['fps']:.1f} | {r['msgs']:.1f} | {r['js']:.2f} | {r['js_median']:.2f} | "
              f"{r['draw']:.1f} | {r['bytes']:.0f} |" + (f" page error: {r['error']}" if r["error"] else ""), flush=True)


def main():
    exe = sys.argv[1]
    if "--frames" in sys.argv:
        rest = [a for a in sys.argv[2:] if not a.startswith("-")]
        frames_table(exe, float(rest[0]) if rest else 10)
        return
    seconds = float(sys.argv[2]) if len(sys.argv) > 2 and not sys.argv[2].startswith("-") else 20
    modes = ("tab",) if "--only" in sys.argv else ("off", "no_tab", "tab")
    rows = [run(exe, seconds, m) for m in modes]
    print(f"| viewer | sim steps in {seconds:.0f} s | mean sampled step ms | coupler iterations (user 0) | "
          "pose-to-force p50 us | p99 us | tab frames/s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        fps = f"{r['fps']:.1f}" if r["fps"] is not None else "—"
        print(f"| {r['mode']} | {r['steps']} | {r['step_ms']:.2f} | {r['iters']} | {r['p50']:.1f} | {r['p99']:.1f} | {fps} |")


if __name__ == "__main__":
    main()
