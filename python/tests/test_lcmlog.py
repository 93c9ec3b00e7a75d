"""The Python log reader on a real recorded session, against the C++ decoding of the same log.

The session is `haptree_run` (sim_server, two couplers, two scripted devices in one process) over LCM
udpm, recorded by Debian's `lcm-logger`, both inside a private network namespace (`unshare -n`, as the
netns C++ tests do) so no datagram leaves the machine. Needs root (CI runs as root); without it the
test fails with that reason, it is not skipped.
"""
import json
import os
import re
import shutil
import sys
import subprocess

import numpy as np
import pytest

import haptree
import haptree.lcmlog as lcmlog
from conftest import SOURCE_DIR, tool

URL = "udpm://239.255.76.67:7667?ttl=0"
SESSION = dict(stiffness=20.0, damping=0.0, position_scale=10.0, force_scale=0.5, max_force_n=3.0)
USERS = 2


@pytest.fixture(scope="module")
def session_log(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.fail("recording a udpm session needs a private network namespace (unshare -n): run as root")
    if shutil.which("lcm-logger") is None:
        pytest.fail("lcm-logger is missing (Debian package liblcm-bin)")
    log = tmp_path_factory.mktemp("lcm") / "session.lcmlog"
    run = tool("launcher/haptree_run")
    opts = (f"--stiffness {SESSION['stiffness']} --damping {SESSION['damping']} "
            f"--position-scale {SESSION['position_scale']} --force-scale {SESSION['force_scale']} "
            f"--max-force-n {SESSION['max_force_n']}")
    script = f"""set -e
ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo
lcm-logger --lcm-url='{URL}' -f -q '{log}' & L=$!
sleep 0.3
'{run}' --viewer-port 0 --lcm-url '{URL}' --duration-s 1.5 --users {USERS} {opts}
sleep 0.2
kill -INT $L; wait $L
"""
    r = subprocess.run(["unshare", "-n", "bash", "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"session failed (rc {r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    assert log.stat().st_size > 0
    return str(log)


def cpp_dump(log, *window):
    out = subprocess.run([tool("python/haptree_log_dump"), log, *window], check=True, capture_output=True,
                         text=True).stdout
    return json.loads(out)


def seq_sum(values):
    s = 0.0
    for v in values:   # file order, one addition at a time: the same rounding as the C++ loop
        s += float(v)
    return s


def check_against_cpp(log, ref):
    assert log.events == ref["events"] and ref["undecodable"] == 0
    counts = log.channels()
    for ch, n in ref["channels"].items():
        assert counts.get(ch, 0) + log.undecoded.get(ch, 0) == n, ch
    fb = log.feedback()
    for ch, r in ref["feedback"].items():
        f = fb[fb.channel == ch]
        assert len(f) == r["n"] and int(f.snapshot_version.sum()) == r["isum"]
        assert [seq_sum(f[f"force_n_{k}"]) for k in range(3)] == r["sum"], ch
    ds = log.device_states()
    for ch, r in ref["device_state"].items():
        d = ds[ds.channel == ch]
        assert len(d) == r["n"] and int(d.seq.sum()) == r["isum"]
        assert [seq_sum(d[f"position_m_{k}"]) for k in range(3)] == r["sum"], ch
    sn = log.snapshots()
    for ch, r in ref["snapshots"].items():
        s = sn[sn.channel == ch]
        assert len(s) == r["n"] and int(s.version.sum()) == r["isum"] and seq_sum(s.sim_time) == r["sum"][0]
    uf = log.user_forces()
    for ch, r in ref["user_force"].items():
        u = uf[uf.channel == ch]
        assert len(u) == r["n"] and [seq_sum(u[f"force_{k}"]) for k in range(6)] == r["sum"], ch
    st = log.stats()
    for ch, r in ref["stats"].items():
        s = st[st.channel == ch]
        assert len(s) == r["n"] and int(s.messages_out.sum()) == r["isum"]
    sc = log.scene_states()
    for ch, r in ref["scene_state"].items():
        s = sc[sc.channel == ch]
        assert len(s) == r["n"] and int(s.active_dofs.sum()) == r["isum"]


def test_reader_matches_cpp_decoding(session_log):
    log = lcmlog.read(session_log)
    ref = cpp_dump(session_log)
    # A real session: both users' feedback, poses, snapshots, user forces and stats are there.
    for u in range(USERS):
        for ch in (f"HAPTREE_FEEDBACK_{u}", f"HAPTREE_DEVICE_STATE_{u}", f"HAPTREE_COEFFS_{u}", f"HAPTREE_USER_FORCE_{u}"):
            assert ref["channels"].get(ch, 0) > 10, (ch, ref["channels"])
    assert any(c.startswith("HAPTREE_STATS_") for c in ref["channels"])
    check_against_cpp(log, ref)
    fb = log.feedback()
    # Forces are clamped to the session's limit; snapshot versions never go back for a device.
    norms = np.linalg.norm(fb[["force_n_0", "force_n_1", "force_n_2"]].to_numpy(), axis=1)
    assert norms.max() <= SESSION["max_force_n"] * (1 + 1e-12) and norms.max() > 0
    for _, f in fb.groupby("device_id"):
        v = f.snapshot_version.to_numpy()
        assert np.all(np.diff(v) >= 0)
    for _, s in log.snapshots().groupby("channel"):
        assert np.all(np.diff(s.version.to_numpy()) > 0)     # "strictly increasing" (lcmt_coupling_snapshot)


def test_window_matches_cpp_window(session_log):
    log = lcmlog.read(session_log, start_s=0.4, end_s=1.1)
    ref = cpp_dump(session_log, "--start-s", "0.4", "--end-s", "1.1")
    check_against_cpp(log, ref)
    assert 0 < log.events < lcmlog.read(session_log).events
    assert log.messages[0][0] >= 0.4 and log.messages[-1][0] < 1.1


def replay(log, user, window=()):
    """replay_coupling for one user, with the coupler options of the recorded session. The device
    offset is what haptree_run sets (grab waypoint 1 cm above the device origin onto the grabbed
    body's origin at q = 0), computed here through the bindings from the logged grab body."""
    snaps = lcmlog.read(log, channels=f"HAPTREE_COEFFS_{user}").snapshots()
    body = int(snaps.grab_body.iloc[0][0])
    model = haptree.make_scene("protein_like", gravity=[0, 0, 0])   # haptree_run's default: no gravity
    assert np.int64(np.uint64(model.fingerprint)) == snaps.model_fingerprint.iloc[0]
    data = haptree.Data(model)
    haptree.forward_kinematics(model, data, haptree.State(model))
    offset = data.r[body] - SESSION["position_scale"] * np.array([0, 0, 0.01])
    cmd = [tool("tools/replay_coupling"), log, "--user", str(user), "--device", str(user),
           "--stiffness", repr(SESSION["stiffness"]), "--damping", repr(SESSION["damping"]),
           "--position-scale", repr(SESSION["position_scale"]), "--force-scale", repr(SESSION["force_scale"]),
           "--max-force-n", repr(SESSION["max_force_n"]), "--offset", *map(repr, offset), *window]
    return subprocess.run(cmd, capture_output=True, text=True)


def test_replay_coupling_seek(session_log):
    full = lcmlog.read(session_log).feedback()
    for user in range(USERS):
        r = replay(session_log, user)
        assert r.returncode == 0, r.stdout + r.stderr     # every force reproduced to 1e-12 N
        n = int(re.search(r"(\d+) feedback messages, (\d+) compared", r.stdout).group(1))
        assert n == (full.channel == f"HAPTREE_FEEDBACK_{user}").sum()
    # Seek: a window around one reproducible feedback message (its snapshot and device pose inside the
    # window; chosen from the data because how many forces a loaded machine renders in the watchdog ramp
    # varies), replayed to 1e-12 N, and the window's feedback count is the Python reader's.
    log = lcmlog.read(session_log)
    fb = log.feedback()
    F = haptree.lcmtypes.lcmt_feedback
    ok = fb[(fb.channel == "HAPTREE_FEEDBACK_0") & (fb.snapshot_version >= 0)
            & ((fb["flags"] & (F.FLAG_WATCHDOG | F.FLAG_NONFINITE)) == 0)]
    sn = log.snapshots()
    ds = log.device_states()
    # udpm under load can drop a datagram before lcm-logger reads it (the CI run lost one): pick a
    # feedback whose snapshot and device pose both made it into the log.
    t_snap = sn[sn.channel == "HAPTREE_COEFFS_0"].groupby("version").t_s.min()
    t_dev = ds[ds.channel == "HAPTREE_DEVICE_STATE_0"].groupby("seq").t_s.min()
    ok = ok[ok.snapshot_version.isin(t_snap.index) & ok.echo_device_seq.isin(t_dev.index)]
    assert len(ok) > 0
    pick = ok.iloc[len(ok) // 2]
    t_snap = t_snap[pick.snapshot_version]
    t_dev = t_dev[pick.echo_device_seq]
    start = float(np.floor(min(t_snap, t_dev) * 1e3) / 1e3)
    end = float(np.ceil(pick.t_s * 1e3) / 1e3 + 0.2)
    assert start > 0.0
    w = lcmlog.read(session_log, start_s=start, end_s=end, channels="HAPTREE_FEEDBACK_0").feedback()
    r = replay(session_log, 0, ("--start-s", repr(start), "--end-s", repr(end)))
    assert r.returncode == 0, r.stdout + r.stderr
    m = re.search(r"(\d+) feedback messages, (\d+) compared", r.stdout)
    assert int(m.group(1)) == len(w) > 0 and int(m.group(2)) > 0
    assert f"window [{start:g}, {end:g}) s" in r.stdout
    bad = replay(session_log, 0, ("--start-s", "1.0", "--end-s", "0.5"))
    assert bad.returncode == 2 and "--end-s 0.5 must be greater than --start-s 1" in bad.stderr


def test_reader_rejects_non_logs_and_resyncs(tmp_path, session_log):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a log at all" * 10)
    with pytest.raises(lcmlog.LogFormatError, match="not an LCM log"):
        lcmlog.read(junk)
    # Garbage spliced between two events is skipped by resynchronising on the sync word.
    raw = open(session_log, "rb").read()
    first = next(lcmlog.iter_events(session_log))
    cut = 28 + len(first[3]) + len(first[4])
    spliced = tmp_path / "spliced.lcmlog"
    spliced.write_bytes(raw[:cut] + b"\x00garbage\xff" * 7 + raw[cut:])
    assert lcmlog.read(spliced).events == lcmlog.read(session_log).events


def test_plot_forces_example(session_log, tmp_path):
    out = tmp_path / "forces.png"
    r = subprocess.run([sys.executable, str(SOURCE_DIR / "examples/python/plot_forces.py"), session_log,
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fb = lcmlog.read(session_log).feedback()
    for dev in range(USERS):
        assert f"device {dev}: {(fb.device_id == dev).sum()} feedback messages" in r.stdout
