"""Browser test of robots drawn with their visuals (CTest label `browser`): the sample robots of
data/robots in a real launcher, Debian's chromium headless over CDP.

  viewer_robots_test.py HAPTREE_RUN ROBOTS_DIR OUT_DIR [--docs DOCS_IMG_DIR]

For each of arm.urdf (STL binary and ASCII, DAE, OBJ meshes), cable.urdf (cylinders) and snake.urdf
(boxes, spheres): `haptree_run --urdf ... --users 1 --viewer-users 1` (user 0: the scripted device,
which a page grab takes over) and checks
  * the launcher's viewer reads every visual, none missing (its log line), and the page builds one mesh
    per body with visuals (dataset.meshBodies) and draws frames;
  * the scripted device's cursor is drawn (dataset.cursors >= 1) before any page grab;
  * the meshes follow the live poses: a mesh's centre on screen moves while the session runs (the
    bodies hang under gravity and the script pulls);
  * a press on a body's mesh picks that mesh (dataset.pick "mesh body K") and grabs body K (the grab
    shows in the frames: dataset.grabBody);
  * a screenshot (OUT_DIR/viewer_robot_NAME.png; with --docs also into the docs' image folder).
Then a URDF whose mesh file is missing: the viewer warns once and draws it as a sphere (meshes still
built). Exit 0 on success."""
import os
import re
import shutil
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cdp  # noqa: E402
from session import Checks, Launcher, ds, free_port, wait_for  # noqa: E402

check = Checks()
failures = check.failures


def robot(exe, browser, urdf, out_dir, docs, name, watch_body, expect_missing=0, pull_body=None, extra=()):
    port = free_port()
    launcher = Launcher([exe, "--urdf", urdf, "--users", "1", "--viewer-users", "1", "--viewer-port", str(port),
                              "--duration-s", "120", "--pull-distance-m", "0.02", *extra],
                        os.path.join(out_dir, f"launcher_{name}.log"))
    page = None
    try:
        if not launcher.url_seen.wait(60):
            raise AssertionError("no viewer URL:\n" + "".join(launcher.lines[-10:]))
        text = "".join(launcher.lines)
        m = re.search(r"viewer: (\d+) visuals drawn on (\d+) bodies \((\d+) meshes, (\d+) shapes, (\d+) missing", text)
        check(m is not None, f"{name}: the viewer read the visuals ({m.group(0) if m else 'no log line'})")
        if m:
            check(int(m.group(5)) == expect_missing, f"{name}: {m.group(5)} missing meshes (expected {expect_missing})")
        warns = [l for l in launcher.lines if "drawn as a sphere" in l]
        check(len(warns) == expect_missing, f"{name}: {len(warns)} missing-mesh warnings (expected {expect_missing})")
        page = browser.new_page(launcher.url)
        page.call("Page.bringToFront")
        wait_for(f"{name} ready", lambda: ds(page, "ready") == "1" and int(ds(page, "frames") or 0) > 3, 90)
        nb = int(ds(page, "meshBodies") or 0)
        check(m is not None and nb == int(m.group(2)), f"{name}: the page built {nb} body meshes")
        check(ds(page, "error") == "", f"{name}: no page error ({ds(page, 'error')!r})")
        wait_for(f"{name}: the device cursor", lambda: int(ds(page, "cursors") or 0) >= 1, 30)
        check(int(ds(page, "cursors") or 0) >= 1, f"{name}: the scripted device's cursor is drawn ({ds(page, 'cursors')})")
        first = page.eval("JSON.stringify(document.body.dataset.meshBodies && window.haptreeMeshOnScreen ? "
                          "window.haptreeMeshOnScreen(%d) : null)" % watch_body)
        time.sleep(2.0)
        later = page.eval("JSON.stringify(window.haptreeMeshOnScreen(%d))" % watch_body)
        check(first != later, f"{name}: body {watch_body}'s mesh moves with the live pose ({first} -> {later})")
        shot = os.path.join(out_dir, f"viewer_robot_{name}.png")
        page.screenshot(shot)
        if pull_body is not None:
            # the centre of the mesh, else the centres of its triangles, until a press picks a mesh. The
            # body moves (it hangs and swings), so each press goes where the mesh is drawn just before it,
            # and the presses go on for a while: on a loaded machine a frame can take long enough for a
            # thin body to leave the point between the query and the press.
            pick, attempt, deadline = "", 0, time.time() + 30
            while time.time() < deadline:
                pts = [page.eval(f"haptreeMeshOnScreen({pull_body})")] + \
                    page.eval(f"haptreeMeshTrianglesOnScreen({pull_body}, 24)")
                p = pts[attempt % len(pts)]
                attempt += 1
                page.mouse("mouseMoved", p["x"], p["y"])
                page.mouse("mousePressed", p["x"], p["y"], buttons=1, button="left")
                pick = ds(page, "pick")
                if pick.startswith("mesh body"):
                    break
                page.mouse("mouseReleased", p["x"], p["y"], button="left")
            check(pick.startswith("mesh body"), f"{name}: a press on body {pull_body}'s mesh picks a mesh ({pick!r}, press {attempt})")
            picked = int(pick.split()[-1]) if pick.startswith("mesh body") else -1
            for k in range(1, 9):
                page.mouse("mouseMoved", p["x"] + 6 * k, p["y"] - 8 * k, buttons=1, button="left")
                time.sleep(0.05)
            wait_for(f"{name}: the grab of body {picked}", lambda: ds(page, "grabBody") == str(picked), 30)
            check(ds(page, "grabBody") == str(picked), f"{name}: the press grabs the picked body {picked}")
            time.sleep(1.0)
            page.screenshot(shot)
            page.mouse("mouseReleased", p["x"] + 48, p["y"] - 64, button="left")
        else:
            page.screenshot(shot)
        check(os.path.getsize(shot) > 5000, f"{name}: screenshot {shot} ({os.path.getsize(shot)} bytes)")
        if docs:
            shutil.copy(shot, os.path.join(docs, os.path.basename(shot)))
    except Exception as e:
        failures.append(f"{name}: {e}")
        print("FAIL", name, e, flush=True)
    finally:
        if page:
            browser.close_page(page)
        rc = launcher.stop()
    check(rc == 0, f"{name}: launcher exit status {rc}")


def main():
    exe, robots, out_dir = sys.argv[1:4]
    docs = sys.argv[sys.argv.index("--docs") + 1] if "--docs" in sys.argv else None
    os.makedirs(out_dir, exist_ok=True)
    # a copy of the arm elsewhere, its meshes found through --mesh-path, one of them not there
    missing = os.path.join(out_dir, "arm_missing_mesh.urdf")
    with open(os.path.join(robots, "arm.urdf")) as f:
        text = f.read().replace("meshes/arm/wrist.stl", "meshes/arm/no_such_wrist.stl")
    with open(missing, "w") as f:
        f.write(text)
    browser = cdp.Browser()
    try:
        robot(exe, browser, os.path.join(robots, "arm.urdf"), out_dir, docs, "arm", 3, pull_body=3)
        robot(exe, browser, os.path.join(robots, "cable.urdf"), out_dir, docs, "cable", 24)
        robot(exe, browser, os.path.join(robots, "snake.urdf"), out_dir, docs, "snake", 6, pull_body=6)
        robot(exe, browser, missing, out_dir, None, "arm_missing_mesh", 3, expect_missing=1,
              extra=("--mesh-path", os.path.abspath(robots)))
    finally:
        browser.quit()
    if failures:
        print(f"{len(failures)} failure(s)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
