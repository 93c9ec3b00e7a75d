#!/usr/bin/env python3
"""Writes the sample robots of data/robots (the files are committed; re-run to regenerate them):

  arm.urdf    a 4-joint arm whose links are mesh files in meshes/arm/: the base a Collada DAE, the two
              links binary STL, the wrist ASCII STL, the gripper OBJ (simple solids made here)
  cable.urdf  a 24-segment cable of cylinders, joints alternating about y and z
  snake.urdf  a 10-segment snake robot of boxes and spheres, yaw and pitch joints alternating

  python3 data/robots/make_robots.py
"""
import math
import os
import struct

HERE = os.path.dirname(os.path.abspath(__file__))


# ---- solids as triangle lists ------------------------------------------------------------------
def box(sx, sy, sz, cx=0.0, cy=0.0, cz=0.0):
    h = (sx / 2, sy / 2, sz / 2)
    v = [(cx + (h[0] if i & 1 else -h[0]), cy + (h[1] if i & 2 else -h[1]), cz + (h[2] if i & 4 else -h[2]))
         for i in range(8)]
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return [(v[a], v[b], v[c]) for q in quads for (a, b, c) in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]


def cylinder_x(r, x0, x1, seg=20):
    """A cylinder along x from x0 to x1 (closed)."""
    tris = []
    for i in range(seg):
        a, b = 2 * math.pi * i / seg, 2 * math.pi * (i + 1) / seg
        pa = (r * math.cos(a), r * math.sin(a))
        pb = (r * math.cos(b), r * math.sin(b))
        A0, B0, A1, B1 = (x0, *pa), (x0, *pb), (x1, *pa), (x1, *pb)
        tris += [(A0, B1, B0), (A0, A1, B1), ((x0, 0, 0), B0, A0), ((x1, 0, 0), A1, B1)]
    return tris


def cylinder_z(r, z0, z1, seg=24):
    return [tuple((p[1], p[2], p[0]) for p in t) for t in cylinder_x(r, z0, z1, seg)]


def normal(t):
    a, b, c = t
    u = [b[i] - a[i] for i in range(3)]
    w = [c[i] - a[i] for i in range(3)]
    n = (u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0])
    l = math.sqrt(sum(x * x for x in n)) or 1.0
    return tuple(x / l for x in n)


# ---- writers -----------------------------------------------------------------------------------
def write_stl_binary(path, tris):
    with open(path, "wb") as f:
        f.write(b"haptree sample mesh".ljust(80, b" "))
        f.write(struct.pack("<I", len(tris)))
        for t in tris:
            f.write(struct.pack("<3f", *normal(t)))
            for p in t:
                f.write(struct.pack("<3f", *p))
            f.write(b"\0\0")


def write_stl_ascii(path, tris):
    with open(path, "w") as f:
        f.write("solid haptree\n")
        for t in tris:
            f.write("  facet normal %g %g %g\n    outer loop\n" % normal(t))
            for p in t:
                f.write("      vertex %.6g %.6g %.6g\n" % p)
            f.write("    endloop\n  endfacet\n")
        f.write("endsolid haptree\n")


def indexed(tris):
    verts, index, faces = [], {}, []
    for t in tris:
        face = []
        for p in t:
            key = tuple(round(x, 9) for x in p)
            if key not in index:
                index[key] = len(verts)
                verts.append(p)
            face.append(index[key])
        faces.append(face)
    return verts, faces


def write_obj(path, tris):
    verts, faces = indexed(tris)
    with open(path, "w") as f:
        f.write("# haptree sample mesh\n")
        for v in verts:
            f.write("v %.6g %.6g %.6g\n" % v)
        for fc in faces:
            f.write("f %d %d %d\n" % tuple(i + 1 for i in fc))


def write_dae(path, tris, unit_m=0.001):
    """Collada in millimetres (unit meter=0.001) under a node with a translate: both must be applied."""
    verts, faces = indexed(tris)
    mm = [x / unit_m for v in verts for x in v]
    p = " ".join(str(i) for fc in faces for i in fc)
    with open(path, "w") as f:
        f.write(f"""<?xml version="1.0" encoding="utf-8"?>
<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">
  <asset><unit name="millimeter" meter="{unit_m}"/><up_axis>Z_UP</up_axis></asset>
  <library_geometries>
    <geometry id="base-mesh" name="base">
      <mesh>
        <source id="base-positions">
          <float_array id="base-positions-array" count="{len(mm)}">{" ".join("%.6g" % x for x in mm)}</float_array>
          <technique_common><accessor source="#base-positions-array" count="{len(verts)}" stride="3">
            <param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>
          </accessor></technique_common>
        </source>
        <vertices id="base-vertices"><input semantic="POSITION" source="#base-positions"/></vertices>
        <triangles count="{len(faces)}"><input semantic="VERTEX" source="#base-vertices" offset="0"/><p>{p}</p></triangles>
      </mesh>
    </geometry>
  </library_geometries>
  <library_visual_scenes>
    <visual_scene id="scene">
      <node id="base" name="base"><translate>0 0 10</translate><instance_geometry url="#base-mesh"/></node>
    </visual_scene>
  </library_visual_scenes>
  <scene><instance_visual_scene url="#scene"/></scene>
</COLLADA>
""")


# ---- URDF helpers ------------------------------------------------------------------------------
def inertial(m, sx, sy, sz, com=(0, 0, 0)):
    ixx, iyy, izz = m * (sy * sy + sz * sz) / 12, m * (sx * sx + sz * sz) / 12, m * (sx * sx + sy * sy) / 12
    return (f'    <inertial><origin xyz="{com[0]:g} {com[1]:g} {com[2]:g}"/><mass value="{m:g}"/>'
            f'<inertia ixx="{ixx:.6g}" ixy="0" ixz="0" iyy="{iyy:.6g}" iyz="0" izz="{izz:.6g}"/></inertial>\n')


def joint(name, parent, child, xyz, axis, kind="revolute"):
    lim = '<limit lower="-2.5" upper="2.5" effort="50" velocity="5"/>' if kind == "revolute" else ""
    return (f'  <joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz[0]:g} {xyz[1]:g} {xyz[2]:g}"/><axis xyz="{axis[0]} {axis[1]} {axis[2]}"/>{lim}</joint>\n')


def arm():
    d = os.path.join(HERE, "meshes", "arm")
    os.makedirs(d, exist_ok=True)
    # base: a puck (DAE, millimetres, shifted 10 mm down inside the file by its node)
    write_dae(os.path.join(d, "base.dae"), [tuple((p[0], p[1], p[2] - 0.01) for p in t) for t in cylinder_z(0.08, 0.0, 0.05)])
    write_stl_binary(os.path.join(d, "upper.stl"), cylinder_z(0.03, 0.0, 0.3) + box(0.07, 0.07, 0.06, cz=0.0))
    write_stl_binary(os.path.join(d, "fore.stl"), cylinder_x(0.025, 0.0, 0.25) + box(0.06, 0.06, 0.06))
    write_stl_ascii(os.path.join(d, "wrist.stl"), box(0.06, 0.05, 0.05, cx=0.03))
    write_obj(os.path.join(d, "gripper.obj"), box(0.02, 0.08, 0.02, cx=0.01) + box(0.05, 0.012, 0.02, cx=0.045, cy=0.034) +
              box(0.05, 0.012, 0.02, cx=0.045, cy=-0.034))
    mesh = lambda f, rgba, scale="1 1 1": (  # noqa: E731
        f'    <visual><geometry><mesh filename="{f}" scale="{scale}"/></geometry>'
        f'<material name="m_{os.path.basename(f).split(".")[0]}"><color rgba="{rgba}"/></material></visual>\n')
    x = ['<?xml version="1.0"?>\n<!-- haptree sample: an arm drawn with mesh files (data/robots/make_robots.py) -->\n'
         '<robot name="mesh_arm">\n  <link name="world"/>\n',
         joint("base_fix", "world", "base", (0, 0, 0), (0, 0, 1), "fixed"),
         '  <link name="base">\n', inertial(4.0, 0.16, 0.16, 0.05, (0, 0, 0.025)),
         mesh("package://haptree_robots/meshes/arm/base.dae", "0.25 0.27 0.3 1"), "  </link>\n",
         joint("shoulder_yaw", "base", "upper", (0, 0, 0.05), (0, 0, 1)),
         '  <link name="upper">\n', inertial(1.5, 0.06, 0.06, 0.3, (0, 0, 0.15)),
         mesh("package://haptree_robots/meshes/arm/upper.stl", "0.95 0.55 0.1 1"), "  </link>\n",
         joint("elbow", "upper", "fore", (0, 0, 0.3), (0, 1, 0)),
         '  <link name="fore">\n', inertial(0.8, 0.25, 0.05, 0.05, (0.125, 0, 0)),
         mesh("meshes/arm/fore.stl", "0.2 0.5 0.85 1"), "  </link>\n",
         joint("wrist", "fore", "wrist", (0.25, 0, 0), (1, 0, 0)),
         '  <link name="wrist">\n', inertial(0.2, 0.06, 0.05, 0.05, (0.03, 0, 0)),
         mesh("meshes/arm/wrist.stl", "0.3 0.3 0.32 1"), "  </link>\n",
         joint("gripper_mount", "wrist", "gripper", (0.06, 0, 0), (0, 0, 1), "fixed"),
         '  <link name="gripper">\n', inertial(0.1, 0.07, 0.08, 0.02, (0.03, 0, 0)),
         mesh("meshes/arm/gripper.obj", "0.85 0.85 0.2 1"), "  </link>\n",
         "</robot>\n"]
    with open(os.path.join(HERE, "arm.urdf"), "w") as f:
        f.write("".join(x))


def cable(n=24, seg=0.05, r=0.012):
    x = ['<?xml version="1.0"?>\n<!-- haptree sample: a cable of cylinders (data/robots/make_robots.py) -->\n'
         '<robot name="cable">\n  <material name="sheath"><color rgba="0.15 0.45 0.25 1"/></material>\n'
         '  <material name="tip"><color rgba="0.85 0.2 0.15 1"/></material>\n  <link name="world"/>\n']
    parent = "world"
    for i in range(n):
        name = f"seg{i:02d}"
        axis = (0, 1, 0) if i % 2 == 0 else (0, 0, 1)
        x.append(joint(f"j{i:02d}", parent, name, (seg if i else 0, 0, 0.4 if i == 0 else 0), axis))
        mat = "tip" if i == n - 1 else "sheath"
        x.append(f'  <link name="{name}">\n' + inertial(0.02, seg, 2 * r, 2 * r, (seg / 2, 0, 0)) +
                 f'    <visual><origin xyz="{seg / 2:g} 0 0" rpy="0 1.5707963267948966 0"/><geometry>'
                 f'<cylinder radius="{r:g}" length="{seg:g}"/></geometry><material name="{mat}"/></visual>\n  </link>\n')
        parent = name
    x.append("</robot>\n")
    with open(os.path.join(HERE, "cable.urdf"), "w") as f:
        f.write("".join(x))


def snake(n=10, seg=0.12):
    x = ['<?xml version="1.0"?>\n<!-- haptree sample: a snake robot of boxes and spheres (data/robots/make_robots.py) -->\n'
         '<robot name="snake">\n  <link name="world"/>\n']
    parent = "world"
    for i in range(n):
        name = f"module{i}"
        axis = (0, 0, 1) if i % 2 == 0 else (0, 1, 0)
        x.append(joint(f"joint{i}", parent, name, (seg if i else 0, 0, 0.1 if i == 0 else 0), axis))
        rgba = "0.9 0.75 0.1 1" if i % 2 == 0 else "0.12 0.12 0.14 1"
        head = i == n - 1
        x.append(f'  <link name="{name}">\n' + inertial(0.3, seg, 0.06, 0.06, (seg / 2, 0, 0)) +
                 f'    <visual><origin xyz="{seg / 2:g} 0 0"/><geometry><box size="{seg * 0.8:g} 0.06 0.06"/></geometry>'
                 f'<material name="m{i}"><color rgba="{rgba}"/></material></visual>\n'
                 '    <visual><geometry><sphere radius="0.034"/></geometry><material name="joint"><color rgba="0.55 0.55 0.6 1"/></material></visual>\n' +
                 ('    <visual><origin xyz="0.14 0 0"/><geometry><sphere radius="0.045"/></geometry>'
                  '<material name="head"><color rgba="0.8 0.15 0.1 1"/></material></visual>\n' if head else "") +
                 "  </link>\n")
        parent = name
    x.append("</robot>\n")
    with open(os.path.join(HERE, "snake.urdf"), "w") as f:
        f.write("".join(x))


if __name__ == "__main__":
    arm()
    cable()
    snake()
