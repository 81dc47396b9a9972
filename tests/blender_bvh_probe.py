"""Run inside Blender: ``blender -b --factory-startup --python tests/blender_bvh_probe.py -- OUT.json A.bvh``.

Imports each BVH with Blender's own importer (one armature per file) and writes, per armature, the
frame range, the scene's frame rate and, for every frame, each pose bone's head in world space and
each bone's head-to-tail length. Debian's Blender 3.4 BVH importer opens files with mode 'rU', which
its Python 3.11 rejects; ``open`` is wrapped to drop the 'U' (a bug of that package, not of the file).
"""

import builtins
import json
import sys

import bpy

_open = builtins.open


def _open_no_u(file, mode="r", *args, **kwargs):
    if isinstance(mode, str) and "U" in mode:
        mode = mode.replace("U", "") or "r"
    return _open(file, mode, *args, **kwargs)


builtins.open = _open_no_u

argv = sys.argv[sys.argv.index("--") + 1 :]
out_path, files = argv[0], argv[1:]
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
result = {"armatures": []}
scene = bpy.context.scene
for f in files:
    before = set(bpy.data.objects)
    bpy.ops.import_anim.bvh(
        filepath=f,
        global_scale=1.0,
        frame_start=1,
        use_fps_scale=False,
        update_scene_fps=True,
        update_scene_duration=True,
        rotate_mode="NATIVE",
        axis_forward="-Z",
        axis_up="Y",
    )
    new = [ob for ob in bpy.data.objects if ob not in before and ob.type == "ARMATURE"]
    for arm in new:
        act = arm.animation_data.action if arm.animation_data else None
        fr = [int(v) for v in act.frame_range] if act else [scene.frame_start, scene.frame_end]
        heads, lengths = [], []
        for t in range(fr[0], fr[1] + 1):
            scene.frame_set(t)
            mw = arm.matrix_world
            heads.append({pb.name: list(mw @ pb.head) for pb in arm.pose.bones})
            lengths.append({pb.name: (pb.tail - pb.head).length for pb in arm.pose.bones})
        result["armatures"].append(
            {
                "file": f,
                "name": arm.name,
                "frame_range": fr,
                "fps": scene.render.fps / scene.render.fps_base,
                "bones": [pb.name for pb in arm.pose.bones],
                "parents": {b.name: (b.parent.name if b.parent else None) for b in arm.data.bones},
                "heads": heads,
                "lengths": lengths,
            }
        )
result["n_armatures"] = sum(1 for ob in bpy.data.objects if ob.type == "ARMATURE")
with _open(out_path, "w") as fh:
    json.dump(result, fh)
