#!/usr/bin/env python3
"""Writes room.gltf (and room_glossy.gltf, the same room with a polished floor and a gold
cube): a Cornell-like room lit by an emissive ceiling panel, with a static
tall block, a dynamic cube that slides and spins across the floor, and a camera that dollies
in. Standard library only; run it to regenerate the committed file.

Tags are node extras {"motion": "static" | "dynamic"}, as Blender writes a custom property
"motion" and usd2gltf writes a USD attribute "gltf:motion".
"""
import base64, json, math, struct, os

buf = bytearray()
views, accessors, meshes, materials = [], [], [], []


def add_view(data: bytes, target=None):
    while len(buf) % 4:
        buf.append(0)
    off = len(buf)
    buf.extend(data)
    v = {"buffer": 0, "byteOffset": off, "byteLength": len(data)}
    if target:
        v["target"] = target
    views.append(v)
    return len(views) - 1


def add_accessor(values, kind, comp=5126, target=None, minmax=False):
    n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[kind]
    fmt = {5126: "f", 5125: "I"}[comp]
    flat = [x for v in values for x in (v if n > 1 else [v])]
    view = add_view(struct.pack("<%d%s" % (len(flat), fmt), *flat), target)
    a = {"bufferView": view, "componentType": comp, "count": len(values), "type": kind}
    if minmax:
        a["min"] = [min(v[i] for v in values) for i in range(n)]
        a["max"] = [max(v[i] for v in values) for i in range(n)]
    accessors.append(a)
    return len(accessors) - 1


def sub(a, b): return [a[i] - b[i] for i in range(3)]
def cross(a, b): return [a[1]*b[2]-a[2]*b[1], a[2]*b[0]-a[0]*b[2], a[0]*b[1]-a[1]*b[0]]
def dot(a, b): return sum(a[i]*b[i] for i in range(3))


def quads_mesh(name, quads, material):
    """quads: list of (4 corners, outward normal). Winding made counter-clockwise about it."""
    pos, nrm, uv, idx = [], [], [], []
    for corners, n in quads:
        base = len(pos)
        c = corners
        if dot(cross(sub(c[1], c[0]), sub(c[2], c[0])), n) < 0:
            c = [c[0], c[3], c[2], c[1]]
        pos += c
        nrm += [n] * 4
        uv += [[0, 0], [1, 0], [1, 1], [0, 1]]
        idx += [base, base + 1, base + 2, base, base + 2, base + 3]
    prim = {
        "attributes": {
            "POSITION": add_accessor(pos, "VEC3", target=34962, minmax=True),
            "NORMAL": add_accessor(nrm, "VEC3", target=34962),
            "TEXCOORD_0": add_accessor(uv, "VEC2", target=34962),
        },
        "indices": add_accessor(idx, "SCALAR", comp=5125, target=34963),
        "material": material,
    }
    meshes.append({"name": name, "primitives": [prim]})
    return len(meshes) - 1


def box(cx, cz, sx, sy, sz, y0=0.0):
    x0, x1, z0, z1, y1 = cx - sx / 2, cx + sx / 2, cz - sz / 2, cz + sz / 2, y0 + sy
    return [
        ([[x0, y1, z0], [x1, y1, z0], [x1, y1, z1], [x0, y1, z1]], [0, 1, 0]),
        ([[x0, y0, z0], [x1, y0, z0], [x1, y0, z1], [x0, y0, z1]], [0, -1, 0]),
        ([[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], [0, 0, 1]),
        ([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0]], [0, 0, -1]),
        ([[x1, y0, z0], [x1, y0, z1], [x1, y1, z1], [x1, y1, z0]], [1, 0, 0]),
        ([[x0, y0, z0], [x0, y0, z1], [x0, y1, z1], [x0, y1, z0]], [-1, 0, 0]),
    ]


def material(name, rgb, emission=None, metallic=0.0, roughness=1.0):
    m = {"name": name, "pbrMetallicRoughness": {"baseColorFactor": rgb + [1.0], "metallicFactor": metallic, "roughnessFactor": roughness}}
    if emission:
        m["emissiveFactor"] = [1.0, 1.0, 1.0]
        m["extensions"] = {"KHR_materials_emissive_strength": {"emissiveStrength": emission}}
    materials.append(m)
    return len(materials) - 1


def scene(glossy):
    """The room's glTF; `glossy`: with a polished floor and a gold cube (room_glossy.gltf)."""
    global buf, views, accessors, meshes, materials
    buf = bytearray()
    views, accessors, meshes, materials = [], [], [], []
    white = material("white", [0.73, 0.73, 0.73])
    red = material("red", [0.65, 0.05, 0.05])
    green = material("green", [0.12, 0.45, 0.15])
    blue = material("blue", [0.2, 0.3, 0.75])
    lamp = material("lamp", [0.78, 0.78, 0.78], emission=[17.0, 12.0, 4.0][0])
    if glossy:
        # A polished floor (a dielectric of roughness 0.45) and a gold cube (roughness 0.4).
        polished = material("polished floor", [0.6, 0.6, 0.6], roughness=0.45)
        gold = material("gold", [1.0, 0.78, 0.34], metallic=1.0, roughness=0.4)

    W, H, D = 2.0, 3.0, 2.0  # half width, height, half depth
    floor_quad = ([[-W, 0, -D], [W, 0, -D], [W, 0, D], [-W, 0, D]], [0, 1, 0])
    walls = quads_mesh("walls", ([] if glossy else [floor_quad]) + [
        ([[-W, H, -D], [W, H, -D], [W, H, D], [-W, H, D]], [0, -1, 0]),      # ceiling
        ([[-W, 0, -D], [W, 0, -D], [W, H, -D], [-W, H, -D]], [0, 0, 1]),     # back
    ], white)
    left = quads_mesh("left_wall", [([[-W, 0, -D], [-W, 0, D], [-W, H, D], [-W, H, -D]], [1, 0, 0])], red)
    right = quads_mesh("right_wall", [([[W, 0, -D], [W, 0, D], [W, H, D], [W, H, -D]], [-1, 0, 0])], green)
    panel = quads_mesh("lamp", [([[-0.6, H - 0.01, -0.6], [0.6, H - 0.01, -0.6], [0.6, H - 0.01, 0.6], [-0.6, H - 0.01, 0.6]], [0, -1, 0])], lamp)
    block = quads_mesh("block", box(-0.8, -0.7, 0.9, 1.8, 0.9), white)
    cube = quads_mesh("cube", box(0.0, 0.0, 0.7, 0.7, 0.7, -0.35), gold if glossy else blue)

    # Animation: 2 s at 24 fps. The cube slides left to right and spins; the camera dollies in.
    times = [0.0, 1.0, 2.0]
    cube_t = [[1.1, 0.35, 0.9], [0.2, 0.35, 0.4], [-0.6, 0.35, 1.0]]
    cube_r = [[0, math.sin(a / 2), 0, math.cos(a / 2)] for a in (0.0, math.pi / 2, math.pi)]
    cam_t = [[0.0, 1.5, 6.5], [0.0, 1.5, 6.0], [0.3, 1.6, 5.6]]
    t_acc = add_accessor(times, "SCALAR", minmax=False)
    accessors[t_acc]["min"], accessors[t_acc]["max"] = [0.0], [2.0]
    samplers = [
        {"input": t_acc, "output": add_accessor(cube_t, "VEC3"), "interpolation": "LINEAR"},
        {"input": t_acc, "output": add_accessor(cube_r, "VEC4"), "interpolation": "LINEAR"},
        {"input": t_acc, "output": add_accessor(cam_t, "VEC3"), "interpolation": "LINEAR"},
    ]
    nodes = [
        {"name": "room", "children": [1, 2, 3, 4, 5] + ([8] if glossy else []), "extras": {"motion": "static"}},
        {"name": "walls", "mesh": walls},
        {"name": "left_wall", "mesh": left},
        {"name": "right_wall", "mesh": right},
        {"name": "lamp", "mesh": panel},
        {"name": "block", "mesh": block, "rotation": [0, math.sin(0.2), 0, math.cos(0.2)]},
        {"name": "cube", "mesh": cube, "translation": cube_t[0], "extras": {"motion": "dynamic", "note": "slides and spins"}},
        {"name": "camera", "camera": 0, "translation": cam_t[0]},
    ]
    if glossy:
        nodes.append({"name": "floor", "mesh": quads_mesh("floor", [floor_quad], polished)})
    gltf = {
        "asset": {"version": "2.0", "generator": "anchorage examples/room/make_room.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "scene": 0,
        "scenes": [{"nodes": [0, 6, 7]}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "cameras": [{"type": "perspective", "perspective": {"yfov": math.radians(38.0), "znear": 0.05, "aspectRatio": 4 / 3}}],
        "animations": [{"name": "move", "samplers": samplers, "channels": [
            {"sampler": 0, "target": {"node": 6, "path": "translation"}},
            {"sampler": 1, "target": {"node": 6, "path": "rotation"}},
            {"sampler": 2, "target": {"node": 7, "path": "translation"}},
        ]}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(buf), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(buf)).decode()}],
    }
    return gltf


here = os.path.dirname(os.path.abspath(__file__))
for name, glossy in (("room.gltf", False), ("room_glossy.gltf", True)):
    with open(os.path.join(here, name), "w") as f:
        json.dump(scene(glossy), f, indent=1)
        f.write("\n")
