"""The bindings against the C++ results on the same inputs.

The C++ side is reached through its own front ends (the haptree-fd CLI, the OpenMM reference numbers
the molecule tests use) or through identities the C++ tests establish, so a binding that passes
arrays in the wrong layout, the wrong order or a copy instead of the buffer fails here.
"""
import gc
import json
import subprocess

import numpy as np
import pytest

import haptree
from conftest import SOURCE_DIR, tool

RNG = np.random.default_rng(7)


def random_state(model, state):
    """Random q (unit quaternions for spherical/free joints), qd, tau, written through the views."""
    q, qd, tau = state.q, state.qd, state.tau
    q[:] = RNG.uniform(-1, 1, model.nq)
    qd[:] = RNG.uniform(-1, 1, model.nv)
    tau[:] = RNG.uniform(-1, 1, model.nv)
    for k in range(1, model.nbodies):
        t, a = model.joint_type[k], model.q_adr[k]
        if t == haptree.JointType.spherical:
            q[a:a + 4] /= np.linalg.norm(q[a:a + 4])
        elif t == haptree.JointType.free:
            q[a + 3:a + 7] /= np.linalg.norm(q[a + 3:a + 7])


def state_json(model, state):
    """The haptree-fd state document (io/state_json.hpp) of a State, keyed by joint name."""
    doc = {"q": {}, "qd": {}, "tau": {}}
    for k in range(1, model.nbodies):
        t = model.joint_type[k]
        if t == haptree.JointType.fixed:
            continue
        name, nq = model.joint_name[k], {"revolute": 1, "prismatic": 1, "spherical": 4, "free": 7}[t.name]
        a, v, nv = model.q_adr[k], model.v_adr[k], model.v_num[k]
        doc["q"][name] = state.q[a:a + nq].tolist()
        doc["qd"][name] = state.qd[v:v + nv].tolist()
        doc["tau"][name] = state.tau[v:v + nv].tolist()
    return doc


def fd_cli(args, state_doc, tmp_path):
    path = tmp_path / "state.json"
    path.write_text(json.dumps(state_doc))   # json writes doubles with repr: exact round trip
    out = subprocess.run([tool("tools/haptree-fd"), *args, "--state", str(path), "--indent", "-1"],
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out)["qdd"]


@pytest.mark.parametrize("scene,n,seed,mixed", [("random_tree", 24, 3, True), ("chain", 12, 0, False),
                                                ("protein_like", 16, 0, False)])
def test_forward_dynamics_matches_haptree_fd(scene, n, seed, mixed, tmp_path):
    model = haptree.make_scene(scene, n=n, seed=seed, mixed_joints=mixed)
    state, data = haptree.State(model), haptree.Data(model)
    random_state(model, state)
    qdd = haptree.forward_dynamics(model, data, state)
    args = ["--scene", scene, "--n", str(n), "--seed", str(seed)] + (["--mixed-joints"] if mixed else [])
    ref = fd_cli(args, state_json(model, state), tmp_path)
    got = []
    want = []
    for k in range(1, model.nbodies):
        if model.v_num[k] == 0:
            continue
        v, nv = model.v_adr[k], model.v_num[k]
        got += list(qdd[v:v + nv])
        r = ref[model.joint_name[k]]
        want += r if isinstance(r, list) else [r]
    # The CLI runs the same C++ function on the same doubles (JSON round-trips them exactly), compiled
    # separately (position-dependent vs PIC): only instruction-level rounding may differ, a few ulps
    # amplified by the conditioning of the articulated system; 1e-9 relative to the largest |q̈|
    # leaves 4 orders of margin on these sizes and still catches any layout or ordering error (O(1)).
    got, want = np.array(got), np.array(want)
    assert got.shape == (model.nv,)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize("urdf,floating", [("arm.urdf", False), ("floating.urdf", False), ("arm.urdf", True)])
def test_urdf_forward_dynamics_matches_haptree_fd(urdf, floating, tmp_path):
    path = str(SOURCE_DIR / "tests/data/urdf" / urdf)
    model = haptree.load_urdf(path, floating_base=floating)
    state, data = haptree.State(model), haptree.Data(model)
    random_state(model, state)
    qdd = haptree.forward_dynamics(model, data, state)
    ref = fd_cli(["--urdf", path] + (["--floating-base"] if floating else []), state_json(model, state), tmp_path)
    want = []
    for k in range(1, model.nbodies):
        if model.v_num[k]:
            r = ref[model.joint_name[k]]
            want += r if isinstance(r, list) else [r]
    # Same argument as for the generated scenes above.
    np.testing.assert_allclose(qdd, want, rtol=0, atol=1e-9 * max(1.0, np.abs(want).max()))
    for bad, what in (("bad_massless.urdf", "massless"), ("bad_planar.urdf", "planar")):
        with pytest.raises(haptree.UrdfError, match=bad) as e:
            haptree.load_urdf(str(SOURCE_DIR / "tests/data/urdf" / bad))
        assert what in str(e.value).lower(), str(e.value)


def test_state_arrays_are_views_on_the_cpp_buffers():
    model = haptree.make_scene("chain", n=6)
    state, data = haptree.State(model), haptree.Data(model)
    q = state.q
    assert q.base is not None and not q.flags.owndata      # a view, not a copy
    assert state.q.ctypes.data == q.ctypes.data              # every access sees the same buffer
    assert state.f_ext.shape == (model.nbodies, 6)
    # Writing through numpy changes the C++ state: the C++ kinematics sees the new angle.
    haptree.forward_kinematics(model, data, state)
    r_before = data.r.copy()
    q[0] = 0.5
    haptree.forward_kinematics(model, data, state)
    assert not np.allclose(data.r[2:], r_before[2:])
    assert state.copy().q[0] == 0.5                          # C++ copy of the State holds the write
    # Assignment copies into the same buffer: older views stay valid and see it.
    state.q = np.full(model.nq, 0.25)
    assert q.ctypes.data == state.q.ctypes.data and np.all(q == 0.25)
    # The f_ext view feeds the C++ dynamics: a force on the last body changes q̈ exactly as a
    # separately built State with the same force does.
    qdd_view = haptree.forward_dynamics(model, data, state)
    assert isinstance(qdd_view.base, haptree.Data) and qdd_view.ctypes.data == data.qdd.ctypes.data   # no copy
    qdd0 = qdd_view.copy()
    state.f_ext[model.nbodies - 1] = [0, 0, 0, 0, 3.0, 0]
    qdd1 = haptree.forward_dynamics(model, data, state).copy()
    other = haptree.State(model)
    other.q = state.q
    other.f_ext = state.f_ext
    qdd2 = haptree.forward_dynamics(model, haptree.Data(model), other)
    assert not np.allclose(qdd0, qdd1)
    np.testing.assert_array_equal(qdd1, qdd2)
    # A view keeps its owner alive (numpy base = the State), and a State its Model.
    view = haptree.State(model).qd
    gc.collect()
    assert isinstance(view.base, haptree.State)
    view[:] = 1.0
    assert view.sum() == model.nv
    orphan = haptree.State(haptree.make_scene("chain", n=3))
    gc.collect()
    assert orphan.model.nv == 3 and orphan.q.shape == (3,)
    haptree.forward_dynamics(orphan.model, haptree.Data(orphan.model), orphan)
    # Data arrays are read-only views (the algorithms own them).
    with pytest.raises(ValueError):
        data.qdd[0] = 1.0


def test_errors_carry_the_cpp_message(tmp_path):
    with pytest.raises(haptree.ModelError) as e:
        haptree.load_urdf(str(tmp_path / "missing.urdf"))
    assert isinstance(e.value, ValueError) and isinstance(e.value, haptree.UrdfError)
    assert str(e.value) == f"{tmp_path / 'missing.urdf'}: cannot open URDF file"
    bad = tmp_path / "massless.urdf"
    bad.write_text('<robot name="r"><link name="a"><inertial><mass value="1"/>'
                   '<inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link>'
                   '<link name="b"/><joint name="j" type="revolute"><parent link="a"/><child link="b"/>'
                   '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>')
    with pytest.raises(haptree.UrdfError, match=r"massless.urdf: .*'b'"):
        haptree.load_urdf(str(bad))
    with pytest.raises(ValueError, match="unknown scene 'nope'"):
        haptree.make_scene("nope")
    with pytest.raises(RuntimeError, match="none.pdb': not a scene name"):
        haptree.load_molecular_scene(str(tmp_path / "none.pdb"))
    empty = tmp_path / "empty.pdb"
    empty.write_text("REMARK nothing here\nEND\n")
    with pytest.raises(haptree.StructureError, match="empty.pdb"):
        haptree.load_molecular_scene(str(empty))
    m1, m2 = haptree.make_scene("chain", n=4), haptree.make_scene("chain", n=5)
    with pytest.raises(haptree.ModelError, match="State was made for another Model"):
        haptree.forward_dynamics(m1, haptree.Data(m1), haptree.State(m2))
    with pytest.raises(ValueError, match=r"State.q: expected shape \(4,\), got \(3,\)"):
        haptree.State(m1).q = np.zeros(3)
    model = haptree.make_scene("chain", n=4)
    with pytest.raises(ValueError, match="make_coupling_snapshot"):
        haptree.make_coupling_snapshot(model, haptree.Data(model), [haptree.Grab(9, np.zeros(3))])


def test_adaptive_step_report_and_full_equivalence():
    model = haptree.make_scene("protein_like")
    opts = haptree.AdaptiveOptions(mode=haptree.AdaptiveMode.budget, budget=model.nv, reselect_every=1)
    state, data, ad = haptree.State(model), haptree.Data(model), haptree.AdaptiveData(model)
    random_state(model, state)
    full = haptree.State(model)
    full.q, full.qd, full.tau = state.q, state.qd, state.tau
    # With every DOF active the hybrid pass is the full DCA (docs/algorithms.md §6): same q̈ as forward_dynamics.
    haptree.select_active_region(model, data, state, ad, opts)
    qdd_h = haptree.adaptive_forward_dynamics(model, data, state, ad).copy()
    qdd_f = haptree.forward_dynamics(model, haptree.Data(model), full)
    np.testing.assert_allclose(qdd_h, qdd_f, rtol=0, atol=1e-9 * max(1.0, np.abs(qdd_f).max()))
    # Budget mode: the report counts the budget, the neglected metric is a part of the total, and
    # the inactive joints neither accelerate nor move.
    budget = haptree.AdaptiveOptions(budget=48, reselect_every=5)
    budget.background_selection = False   # selections inside the due step: a fixed schedule
    s2, d2, ad2 = haptree.State(model), haptree.Data(model), haptree.AdaptiveData(model)
    s2.q, s2.tau = state.q, state.tau
    reports = [haptree.adaptive_step(model, d2, s2, ad2, budget, 1e-3) for _ in range(12)]
    assert [r.reselected for r in reports] == [True, False, False, False, False] * 2 + [True, False]
    assert reports[-1].selections == 3
    for r in reports:
        assert 0 < r.active_dofs <= 48
        assert 0 <= r.neglected_metric <= r.total_metric
        assert r.nodes_top_down >= r.active_nodes
    active = ad2.active_joints
    assert len(active) == reports[-1].active_dofs          # revolute joints: one DOF each
    inactive = np.setdiff1d(np.arange(1, model.nbodies), active)
    v_inactive = np.array(model.v_adr)[inactive]
    assert np.all(d2.qdd[v_inactive] == 0) and np.all(s2.qd[v_inactive] == 0)
    assert ad2.report.selections == reports[-1].selections


def test_coupling_forces_identities():
    """Coupling from the snapshot alone (coupling.hpp): a welded body feeds back −f_u, a free body its
    own external load, f_feed is affine in f_u, and β_ext recovery makes the snapshot independent of
    the user force the pass applied (the C++ coupling tests prove each against a full DCA pass)."""
    # Welded: protein_like's first body is welded to the ground.
    model = haptree.make_scene("protein_like")
    assert model.joint_type[1] == haptree.JointType.fixed
    state, data = haptree.State(model), haptree.Data(model)
    random_state(model, state)
    haptree.forward_dynamics(model, data, state)
    grabs = [haptree.make_grab(data, 1, [0.01, 0.0, 0.0]), haptree.make_grab(data, model.nbodies - 1, [0, 0, 0.02])]
    snap = haptree.make_coupling_snapshot(model, data, grabs, version=7, sim_time=0.5)
    assert snap.version == 7 and snap.model_fingerprint == model.fingerprint and len(snap.grabs) == 2
    ws = haptree.CouplingWorkspace(snap)
    f_u = np.array([[0, 0, 0, 1.0, -2.0, 0.5], [0.1, 0, 0, 0, 0, -1.0]])
    st, f_feed = haptree.coupling_forces(snap, f_u, ws)
    assert st == haptree.CouplingStatus.ok and f_feed.shape == (2, 6)
    np.testing.assert_allclose(f_feed[0], -f_u[0], atol=1e-9)
    # Affine in f_u (zero and a sum of two loads), through the out= path (no allocation).
    out = np.empty((2, 6))
    f0 = haptree.coupling_forces(snap, np.zeros((2, 6)), ws, out)[1].copy()
    f2 = haptree.coupling_forces(snap, 2 * f_u, ws, out)[1].copy()
    assert haptree.coupling_forces(snap, f_u, ws, out)[1] is out
    scale = np.abs(f2).max()
    np.testing.assert_allclose(f2 - f0, 2 * (f_feed - f0), atol=1e-9 * scale)
    # Same snapshot when built from a pass that applied f_u (β_ext recovery).
    applied = state.copy()
    for g, gr in enumerate(grabs):
        applied.f_ext[gr.body] += haptree.grab_force_at_body_origin(snap, g, f_u[g])
    d_applied = haptree.Data(model)
    haptree.forward_dynamics(model, d_applied, applied)
    snap2 = haptree.make_coupling_snapshot(model, d_applied, grabs, f_u_applied=f_u, version=8)
    st2, f_feed2 = haptree.coupling_forces(snap2, f_u, haptree.CouplingWorkspace(snap2))
    np.testing.assert_allclose(f_feed2, f_feed, atol=1e-9 * scale)
    # Free body alone: f_feed = its gravity load, at the grab point (force part m·g).
    free = haptree.make_scene("chain", n=1, free_root=True)
    fs, fd_ = haptree.State(free), haptree.Data(free)
    haptree.forward_dynamics(free, fd_, fs)
    gs = haptree.make_coupling_snapshot(free, fd_, [haptree.make_grab(fd_, 1, [0, 0, 0])])
    stf, ff = haptree.coupling_forces(gs, np.array([[0, 0, 0, 5.0, 0, 0]]), haptree.CouplingWorkspace(gs))
    np.testing.assert_allclose(ff[0, 3:], free.mass[1] * free.gravity, atol=1e-12 * free.mass[1] * 9.81)
    assert ws.nodes_read > 0


def test_molecular_force_field_matches_openmm_reference():
    """ala20: energy terms and per-atom forces against the OpenMM numbers in data/molecules/oracle
    (the same file and tolerances as tests/molecule/molecule_test.cpp)."""
    sc = haptree.load_molecular_scene("ala20")
    ref_dir = SOURCE_DIR / "data/molecules/oracle/ala20_helix_h"
    B = json.loads((ref_dir / "energies.json").read_text())["B"]
    x = sc.file_positions()
    E, F, terms = sc.evaluate_all_pairs(x)
    rel = lambda a, b: abs(a - b) / max(1.0, abs(b))  # noqa: E731
    assert rel(terms.coulomb, B["coulomb_ddd4r_switched"]) < 1e-8
    assert rel(terms.lj, B["lj_switched"]) < 1e-8
    assert rel(terms.torsion, B["torsion_proper"]) < 1e-8
    assert rel(E, B["total"]) < 1e-8
    fr = np.loadtxt(ref_dir / "forces_B.csv", delimiter=",", skiprows=1, usecols=(1, 2, 3))
    assert fr.shape == F.shape
    # Oracle prints 6 decimals: 2e-6 absolute + 1e-9 relative (docs/molecules.md).
    assert np.max(np.abs(F - fr) - 1e-9 * np.abs(fr).max(axis=1, keepdims=True)) < 2e-6
    # Scene path (rigid terms folded into a constant, forces gathered per body): same energy.
    state, data = haptree.State(sc.model), haptree.Data(sc.model)
    haptree.forward_kinematics(sc.model, data, state)
    Es = sc.compute(data, state)
    assert rel(Es, B["total"]) < 1e-8 and rel(sc.energy_terms.total, Es) < 1e-15
    np.testing.assert_allclose(sc.atom_positions(data), x, atol=1e-12)
    # state.f_ext now holds the body wrenches: the sum of forces over bodies is the sum over atoms
    # of the forces the scene evaluator computed (internal pairs of a rigid body cancel).
    assert np.abs(state.f_ext[:, 3:].sum(axis=0) - sc.atom_forces.sum(axis=0)).max() < 1e-8
    # A pull on one atom adds exactly [x_a × F; F] about the body origin.
    before = state.f_ext.copy()
    sc.add_atom_force(data, 5, [0, 0, 10.0], state)
    b = sc.atom_body[5]
    assert np.allclose(state.f_ext[b, 3:] - before[b, 3:], [0, 0, 10.0])
    with pytest.raises(IndexError, match="atom 9999 out of range"):
        sc.atom_position(data, 9999)
