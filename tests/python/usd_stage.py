"""Authors a small animated USD stage with motion tags, converts it to glTF with usd2gltf,
and writes USD's own world transforms (UsdGeom.XformCache) at several frames.

    python usd_stage.py OUT_DIR

Writes OUT_DIR/stage.usda, OUT_DIR/stage.gltf (+ .bin) and OUT_DIR/xforms.json:
{"frames": [...], "fps": 24, "prims": {name: [[16 floats, row-major, row vectors] per frame]}}.
Tags are USD attributes `gltf:motion`, which usd2gltf writes as node extras {"motion": ...}.
"""
import json, os, sys

from pxr import Gf, Sdf, Usd, UsdGeom

out = sys.argv[1]
os.makedirs(out, exist_ok=True)
usda = os.path.join(out, "stage.usda")
stage = Usd.Stage.CreateNew(usda)
stage.SetTimeCodesPerSecond(24)
stage.SetStartTimeCode(1)
stage.SetEndTimeCode(24)
UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)


def tag(prim, motion):
    prim.GetPrim().CreateAttribute("gltf:motion", Sdf.ValueTypeNames.String).Set(motion)


def cube(path, size):
    m = UsdGeom.Mesh.Define(stage, path)
    s = size / 2
    pts = [(-s, -s, -s), (s, -s, -s), (s, s, -s), (-s, s, -s), (-s, -s, s), (s, -s, s), (s, s, s), (-s, s, s)]
    faces = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3)]
    m.CreatePointsAttr(pts)
    m.CreateFaceVertexCountsAttr([4] * 6)
    m.CreateFaceVertexIndicesAttr([i for f in faces for i in f])
    return m


world = UsdGeom.Xform.Define(stage, "/World")
tag(world, "static")
ground = UsdGeom.Mesh.Define(stage, "/World/Ground")
ground.CreatePointsAttr([(-5, 0, -5), (5, 0, -5), (5, 0, 5), (-5, 0, 5)])
ground.CreateFaceVertexCountsAttr([4])
ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])

mover = UsdGeom.Xform.Define(stage, "/World/Mover")
tag(mover, "dynamic")
t_op = mover.AddTranslateOp()
r_op = mover.AddRotateYOp()
s_op = mover.AddScaleOp()
for f in range(1, 25):
    t_op.Set(Gf.Vec3d(-2.0 + 4.0 * (f - 1) / 23.0, 0.5 + 0.3 * ((f - 1) % 6) / 5.0, 0.0), f)
    r_op.Set(15.0 * (f - 1), f)
    s_op.Set(Gf.Vec3f(1.0, 1.0 + 0.02 * (f - 1), 1.0), f)
cube("/World/Mover/Box", 1.0)
arm = UsdGeom.Xform.Define(stage, "/World/Mover/Arm")
arm.AddTranslateOp().Set(Gf.Vec3d(0.0, 1.0, 0.5))
arm.AddRotateXOp().Set(30.0)
cube("/World/Mover/Arm/Tip", 0.3)
stage.GetRootLayer().Save()

from usd2gltf import converter

conv = converter.Converter()
stage = conv.load_usd(usda)
conv.process(stage, os.path.join(out, "stage.gltf"))

frames = [1, 6, 12, 18, 24]
prims = {}
for name, path in [("World", "/World"), ("Ground", "/World/Ground"), ("Mover", "/World/Mover"), ("Box", "/World/Mover/Box"), ("Arm", "/World/Mover/Arm"), ("Tip", "/World/Mover/Arm/Tip")]:
    prim = stage.GetPrimAtPath(path)
    mats = []
    for f in frames:
        m = UsdGeom.XformCache(Usd.TimeCode(f)).GetLocalToWorldTransform(prim)
        mats.append([m[i][j] for i in range(4) for j in range(4)])
    prims[name] = mats
with open(os.path.join(out, "xforms.json"), "w") as fh:
    json.dump({"frames": frames, "fps": 24, "prims": prims}, fh)
