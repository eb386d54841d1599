"""Renders one frame of a glTF scene with Blender's Cycles, for benches/cycles.py: run as

    blender -b --factory-startup --python benches/cycles_render.py -- \
        OUT.exr FRAME WIDTH HEIGHT SAMPLES THREADS LAYERS.json

LAYERS.json is a list of `{"path": SCENE.gltf, "matrix": M}`, M the layer's transform (a
job's `transform`, 16 numbers, row-major, in glTF's Y-up space) or null. Imports the glTF
files, each under an empty that carries its transform (so that animated nodes keep their
animation, relative to it; the first camera found becomes the scene camera), renders FRAME on
the CPU with SAMPLES samples per pixel (no adaptive sampling, no denoiser, a fixed seed) and
writes a multilayer EXR with the Combined pass and the diffuse and glossy indirect light and
colour passes. Prints `ANCHORAGE: {"seconds": S}` with the render's own time (scene import
and EXR writing excluded).
"""

import json
import sys
import time

import bpy
import mathutils

args = sys.argv[sys.argv.index("--") + 1 :]
out, frame, width, height, samples, threads = args[:6]
layers = json.load(open(args[6]))

for obj in list(bpy.data.objects):
    bpy.data.objects.remove(obj, do_unlink=True)
# glTF's Y-up axes to Blender's Z-up ones, as the importer converts them.
Y_UP = mathutils.Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
for layer in layers:
    before = set(bpy.data.objects)
    bpy.ops.import_scene.gltf(filepath=layer["path"])
    roots = [obj for obj in set(bpy.data.objects) - before if obj.parent is None]
    if layer.get("matrix") is None:
        continue
    m = layer["matrix"]
    empty = bpy.data.objects.new("layer transform", None)
    bpy.context.scene.collection.objects.link(empty)
    empty.matrix_world = Y_UP @ mathutils.Matrix([m[4 * r:4 * r + 4] for r in range(4)]) @ Y_UP.inverted()
    for obj in sorted(roots, key=lambda o: o.name):
        obj.parent = empty

scene = bpy.context.scene
cameras = [o for o in scene.objects if o.type == "CAMERA"]
if not cameras:
    sys.exit("no camera in the scene")
scene.camera = cameras[0]
scene.frame_set(int(frame))
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = int(samples)
scene.cycles.use_adaptive_sampling = False
scene.cycles.use_denoising = False
scene.cycles.seed = 1
scene.render.threads_mode = "FIXED"
scene.render.threads = int(threads)
scene.render.resolution_x = int(width)
scene.render.resolution_y = int(height)
scene.render.resolution_percentage = 100
scene.render.film_transparent = False
# No world light: the scene's own lights only, as anchorage renders them.
if scene.world is None:
    scene.world = bpy.data.worlds.new("World")
scene.world.use_nodes = True
bg = scene.world.node_tree.nodes.get("Background")
if bg is not None:
    bg.inputs["Strength"].default_value = 0.0
layer = scene.view_layers[0]
for p in ("use_pass_diffuse_indirect", "use_pass_diffuse_color", "use_pass_glossy_indirect",
          "use_pass_glossy_color", "use_pass_diffuse_direct", "use_pass_glossy_direct"):
    setattr(layer, p, True)
settings = scene.render.image_settings
settings.file_format = "OPEN_EXR_MULTILAYER"
settings.color_depth = "32"
settings.exr_codec = "ZIP"
scene.render.filepath = out
scene.render.use_file_extension = False

t = time.time()
bpy.ops.render.render(write_still=True)
print("ANCHORAGE: " + json.dumps({"seconds": time.time() - t}))
