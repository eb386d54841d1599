"""Lists what Blender's compositor sees in an EXR: run as
`blender -b --factory-startup --python list_layers.py -- FILE.exr`. Prints one JSON line
`{"type": ..., "outputs": [...]}` after the marker `ANCHORAGE:`: the image type and the
compositor Image node's enabled outputs, i.e. the layers and passes Blender lists."""

import json
import sys

import bpy

path = sys.argv[sys.argv.index("--") + 1]
img = bpy.data.images.load(path)
scene = bpy.context.scene
scene.use_nodes = True
tree = scene.node_tree
for n in list(tree.nodes):
    tree.nodes.remove(n)
node = tree.nodes.new("CompositorNodeImage")
node.image = img
outputs = [o.name for o in node.outputs if o.enabled]
print("ANCHORAGE:" + json.dumps({"type": img.type, "outputs": outputs}))

