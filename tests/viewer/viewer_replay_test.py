"""The viewer on a replay: a session recorded by lcm-logger, played back by lcm-logplayer into a
stand-alone viewer, checked on the viewer's own WebSocket frames (what the page draws).

  viewer_replay_test.py HAPTREE_RUN VIEWER LCMTYPES_DIR OUT_DIR

Everything runs inside a private network namespace (`unshare -n`, udpm on its loopback only, as
python/tests/test_lcmlog.py), so no datagram leaves the machine; needs root (CI runs as root): without it
the test fails with that reason. Checks, against the log itself (decoded with the lcm-gen -p types):
  * the frames' versions are logged scene-state versions, in order, and many of them: the page follows the
    replay;
  * every body of every frame sits where that logged scene state puts it (display = (r - c) x scale, c
    and scale from the ground body and the hello message), to float32 rounding: nothing is made up;
  * the bodies move (the recorded pull): the first and the last frame differ by more than 0.05 display
    units (Å-like) somewhere;
  * each frame's force and its flags (clamped, watchdog, stale) are those of ONE logged FEEDBACK message
    (the HUD never mixes fields of different messages), and no frame or logged message shows the watchdog
    with |f| at the clamp (the watchdog gain scales the clamped force).
Exit 0 on success."""
import glob
import importlib.util
import json
import os
import re
import struct
import subprocess
import sys
import time

URL = "udpm://239.255.76.67:7667?ttl=0"
SCENE = ["--scene", "chain", "--n", "24"]          # small and fast to load; the scripted user pulls it
MAX_FORCE_N = 3.0                                   # haptree_run's default clamp
F32 = 2.0 ** -24                                    # float32 unit roundoff
SHOWN_AS_CLAMP = MAX_FORCE_N - 5e-4                 # what the HUD prints as "3.000" N (toFixed(3))


def norm(v):
    return sum(x * x for x in v) ** 0.5


def load_types(lcm_dir, out_dir):
    """lcm-gen -p of the two types this test reads (pure Python, no LCM Python package needed)."""
    gen = os.path.join(out_dir, "lcmgen")
    os.makedirs(gen, exist_ok=True)
    files = [os.path.join(lcm_dir, f"{n}.lcm") for n in ("lcmt_scene_state", "lcmt_feedback")]
    subprocess.run(["lcm-gen", "-p", "--ppath", gen, *files], check=True)
    mods = {}
    for name in ("lcmt_scene_state", "lcmt_feedback"):
        spec = importlib.util.spec_from_file_location(name, os.path.join(gen, "haptree", f"{name}.py"))
        m = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(m)
        mods[name] = getattr(m, name)
    return mods


def read_log(path):
    """(channel, data) of every event of an LCM log (the documented 28-byte big-endian event header)."""
    out = []
    with open(path, "rb") as f:
        raw = f.read()
    o = 0
    while o + 28 <= len(raw):
        sync, _, _, cl, dl = struct.unpack_from(">IqqII", raw, o)
        assert sync == 0xEDA1DA01, f"bad sync word at byte {o}"
        ch = raw[o + 28:o + 28 + cl].decode()
        out.append((ch, raw[o + 28 + cl:o + 28 + cl + dl]))
        o += 28 + cl + dl
    return out


def record(run, log):
    script = f"""set -e
lcm-logger --lcm-url='{URL}' -f -q '{log}' & L=$!
sleep 0.3
'{run}' --viewer-port 0 --lcm-url '{URL}' --duration-s 2 --users 1 {' '.join(SCENE)}
sleep 0.2
kill -INT $L; wait $L
"""
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"recording failed (rc {r.returncode}):\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"


def watch_replay(viewer, log, out_dir):
    """Starts the viewer, connects as a page would, plays the log; returns (hello, [(frame json, floats)])."""
    import websocket  # python3-websocket
    vlog = open(os.path.join(out_dir, "viewer_replay.log"), "w")
    v = subprocess.Popen([viewer, "--lcm-url", URL, *SCENE, "--viewer-port", "0", "--viewer-users", "1"],
                         stdout=subprocess.PIPE, stderr=vlog, text=True)
    player = None
    try:
        m, seen = None, []
        for line in v.stdout:   # its log lines come first (spdlog on stdout)
            seen.append(line)
            m = re.match(r"viewer: open http://127\.0\.0\.1:(\d+)/\?token=(\S+)", line)
            if m:
                break
        assert m, f"the viewer printed no URL: {seen[-5:]}"
        ws = websocket.create_connection(f"ws://127.0.0.1:{m.group(1)}/ws?token={m.group(2)}", timeout=10)
        hello = json.loads(ws.recv())
        assert hello["t"] == "hello" and hello["user"] == 0, hello
        player = subprocess.Popen(["lcm-logplayer", f"--lcm-url={URL}", log],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        frames, meta, t_over = [], None, None
        t_end = time.time() + 30
        while time.time() < t_end and (t_over is None or time.time() - t_over < 0.5):
            try:
                op, data = ws.recv_data()
            except websocket.WebSocketTimeoutException:
                break
            if op == websocket.ABNF.OPCODE_BINARY:   # "HTF1", uint32 JSON length, JSON, float32 positions
                assert data[:4] == b"HTF1", data[:8]
                n = struct.unpack("<I", data[4:8])[0]
                meta = json.loads(data[8:8 + n])
                pos = data[8 + n:]
                frames.append((meta, struct.unpack(f"<{len(pos) // 4}f", pos) if pos else None))
            if t_over is None and player.poll() is not None:
                t_over = time.time()           # the replay is over: 0.5 s of frames more
        ws.close()
        return hello, frames
    finally:
        if player and player.poll() is None:
            player.kill()
        v.terminate()
        v.wait(timeout=10)
        vlog.close()


def main():
    run, viewer, lcm_dir, out_dir = sys.argv[1:5]
    if os.geteuid() != 0:
        print("FAIL: the replay test records a udpm session in a private network namespace (unshare -n): run as root")
        return 1
    if os.environ.get("HAPTREE_IN_NETNS") != "1":   # re-run inside a fresh namespace with multicast on lo
        setup = ("ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && "
                 f"HAPTREE_IN_NETNS=1 exec '{sys.executable}' \"$@\"")
        return subprocess.run(["unshare", "-n", "bash", "-c", setup, "bash", *sys.argv]).returncode
    os.makedirs(out_dir, exist_ok=True)
    types = load_types(lcm_dir, out_dir)
    log = os.path.join(out_dir, "replay_session.lcmlog")
    if os.path.exists(log):
        os.remove(log)
    record(run, log)
    states, feedback = {}, []
    for ch, data in read_log(log):
        if ch == "HAPTREE_SCENE_STATE":
            s = types["lcmt_scene_state"].decode(data)
            states[s.version] = s
        elif ch == "HAPTREE_FEEDBACK_0":
            feedback.append(types["lcmt_feedback"].decode(data))
    F = types["lcmt_feedback"]
    by_force = {}
    for fb in feedback:
        by_force.setdefault(tuple(fb.force_n), set()).add(fb.flags)
    print(f"log: {len(states)} scene states, {len(feedback)} FEEDBACK_0 messages", flush=True)
    failures = []

    def check(cond, what):
        print(("ok   " if cond else "FAIL ") + what, flush=True)
        if not cond:
            failures.append(what)

    check(len(states) >= 20 and len(feedback) >= 1000, "the session was recorded")
    # The watchdog gain scales the clamped force: a message flagged WATCHDOG shows "3.000" N (>= 2.9995)
    # only at the last step of a ramp-in (gain 1 minus rounding), at most once per completed ramp-in.
    wd_at_clamp = sum(1 for fb in feedback if (fb.flags & F.FLAG_WATCHDOG) and norm(fb.force_n) >= SHOWN_AS_CLAMP)
    ramp_ins = sum(1 for a, b in zip(feedback, feedback[1:])
                   if (a.flags & F.FLAG_WATCHDOG) and not (b.flags & F.FLAG_WATCHDOG))
    check(wd_at_clamp <= ramp_ins,
          f"logged FEEDBACK flagged WATCHDOG at the clamp: {wd_at_clamp}, at most one per ramp-in ({ramp_ins})")

    hello, frames = watch_replay(viewer, log, out_dir)
    versions = [f["version"] for f, _ in frames]
    played = [v for v in versions if v in states]
    print(f"replay: {len(frames)} frames, {len(set(played))} distinct logged versions", flush=True)
    check(len(set(played)) >= len(states) // 3, f"the frames follow the replay ({len(set(played))} of {len(states)} versions)")
    check(played == sorted(played), "frame versions never go back")

    # positions travel only with a new scene state: a frame without them repeats its predecessor's version
    bare = [(a[0]["version"], b[0]["version"]) for a, b in zip(frames, frames[1:]) if b[1] is None]
    check(all(x == y for x, y in bare) and sum(1 for _, fl in frames if fl is not None) >= len(set(played)),
          f"positions sent only when the scene changed ({len(bare)} frames without, all at an unchanged version)")
    nb = hello["bodies"] + 1
    s_disp = hello["disp_per_scene_unit"]
    worst, moved, first = 0.0, 0.0, None
    for meta, fl in frames:
        s = states.get(meta["version"])
        if s is None or fl is None:   # a frame without positions: the scene did not move since the last
            continue
        pts = fl
        assert len(pts) == 3 * nb
        c = [s.body_position[0][a] - pts[a] / s_disp for a in range(3)]   # the ground body fixes the centre
        mag = max(abs(x) for x in pts)
        tol = 8 * F32 * mag   # two float32 roundings (this point and the ground's) of coordinates <= mag
        for k in range(nb):
            for a in range(3):
                worst = max(worst, abs(pts[3 * k + a] - (s.body_position[k][a] - c[a]) * s_disp) - tol)
        if first is None:
            first = pts
        moved = max(moved, max(abs(x - y) for x, y in zip(pts, first)))
    check(worst <= 0, f"every body of every frame at its logged pose (worst excess over float32 tolerance {worst:.3g})")
    check(moved > 0.05, f"the bodies move in the replay (largest displacement {moved:.3f} display units)")

    mixed, shown, wd_clamp = 0, 0, 0
    for meta, _ in frames:
        u = meta["users"][0]
        flags = {fl for fl in by_force.get(tuple(u["f"]), set())}
        if not flags:
            mixed += 1          # a force no logged message carried
            continue
        want = (F.FLAG_CLAMPED if u["clamped"] else 0) | (F.FLAG_WATCHDOG if u["watchdog"] else 0) | \
               (F.FLAG_STALE if u["stale"] else 0)
        if not any((fl & (F.FLAG_CLAMPED | F.FLAG_WATCHDOG | F.FLAG_STALE)) == want for fl in flags):
            mixed += 1          # the force of one message with the flags of another
        shown += u["fn"] > 0
        wd_clamp += bool(u["watchdog"] and u["fn"] >= SHOWN_AS_CLAMP)
    check(mixed == 0, f"each frame's |f| and flags come from one logged FEEDBACK ({mixed} of {len(frames)} not)")
    check(shown > 0, f"the recorded pull shows ({shown} frames with |f| > 0)")
    check(wd_clamp <= ramp_ins, f"frames showing the watchdog at the clamp: {wd_clamp} (<= {ramp_ins})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
