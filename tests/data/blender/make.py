# Regenerates blend.gltf with Blender 3.4: blender -b --python make.py -- make.py
# Tags are object custom properties "motion"; exported with Custom Properties (export_extras) on.
import bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.mesh.primitive_plane_add(size=10)
floor = bpy.context.object; floor.name = "Floor"; floor["motion"] = "static"
bpy.ops.mesh.primitive_cube_add(size=1, location=(0, 0, 1))
cube = bpy.context.object; cube.name = "Mover"; cube["motion"] = "dynamic"; cube["pipeline_note"] = "from layout"
cube.keyframe_insert("location", frame=1); cube.location = (2, 0, 1); cube.keyframe_insert("location", frame=24)
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, location=(-2, 0, 0.5))
bpy.context.object.name = "Untagged"
bpy.ops.object.camera_add(location=(0, -8, 4), rotation=(1.1, 0, 0)); bpy.context.object.name = "Cam"
bpy.ops.object.light_add(type='POINT', location=(0, 0, 4)); bpy.context.object.data.energy = 500
import os, sys
here = os.path.dirname(os.path.abspath(sys.argv[-1]))
bpy.ops.export_scene.gltf(filepath=os.path.join(here, "blend.gltf"), export_format='GLTF_SEPARATE', export_extras=True, export_lights=True, export_cameras=True)
