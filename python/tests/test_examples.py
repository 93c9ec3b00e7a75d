"""The example scripts run and write their plots (short runs; the committed figures are full runs)."""
import subprocess
import sys

from conftest import SOURCE_DIR


def test_pull_bacteriorhodopsin_example(tmp_path):
    out = tmp_path / "pull.png"
    r = subprocess.run([sys.executable, str(SOURCE_DIR / "examples/python/pull_bacteriorhodopsin.py"),
                        "--steps", "40", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "step    40" in r.stdout and "dof=786" in r.stdout
    bad = subprocess.run([sys.executable, str(SOURCE_DIR / "examples/python/pull_bacteriorhodopsin.py"),
                          "--atom", "999999", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "--atom 999999 out of range [0, 3577)" in bad.stderr


def test_bench_bindings_example():
    r = subprocess.run([sys.executable, str(SOURCE_DIR / "examples/python/bench_bindings.py")],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 3, r.stdout
    for line, name in zip(lines, ("forward_dynamics", "State.q", "coupling_forces")):
        assert line.startswith(name), line
        median, mean = (float(x) for x in line.split(":")[-1].split("/"))
        assert median > 0 and mean > 0, line
