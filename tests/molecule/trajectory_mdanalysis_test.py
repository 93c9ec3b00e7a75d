"""A DCD and a multi-model PDB from `sim_server --trajectory`, read by MDAnalysis (Debian's
python3-mdanalysis), an outside reader of the CHARMM/NAMD format: same atoms, frames, time step, and
the same coordinates in both files (the PDB's 3 decimals)."""
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

warnings.simplefilter("ignore")
import MDAnalysis as mda  # noqa: E402
from MDAnalysis.lib.formats.libdcd import DCDFile  # noqa: E402
import numpy as np  # noqa: E402

sim_server = sys.argv[1]
with tempfile.TemporaryDirectory() as d:
    files = {}
    for ext in ("dcd", "pdb"):
        files[ext] = str(Path(d) / f"ala20.{ext}")
        subprocess.run([sim_server, "--lcm-url", "memq://", "--scene", "ala20", "--dt", "0.0005", "--steps", "300",
                        "--trajectory", files[ext], "--trajectory-every-steps", "100"], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with DCDFile(files["dcd"]) as f:
        assert f.header["natoms"] == 212, f.header
        assert f.n_frames == 3, f.n_frames
        assert f.header["nsavc"] == 100, f.header
        dcd = f.readframes().xyz
    pdb = mda.Universe(files["pdb"])
    assert len(pdb.trajectory) == 3, len(pdb.trajectory)
    u = mda.Universe(files["pdb"], files["dcd"])
    assert abs(u.trajectory.dt - 0.05) < 1e-6, u.trajectory.dt   # ps: 100 steps of 0.5 fs
    worst = 0.0
    for i, ts in enumerate(pdb.trajectory):
        worst = max(worst, float(np.abs(ts.positions - dcd[i]).max()))
    # %8.3f in the PDB: half a unit of the last decimal (plus float32 of the DCD, 1e-5 Å).
    assert worst <= 5e-4 + 1e-5, worst
    print(f"MDAnalysis {mda.__version__}: 3 frames of 212 atoms, dt {u.trajectory.dt:.3f} ps, "
          f"DCD vs PDB max |dx| {worst:.2e} A")
