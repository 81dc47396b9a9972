"""Run inside Blender: ``blender -b --factory-startup --python tests/blender_bvh_render.py -- OUT.png A.bvh
[FRAME] [HAND]``.

Imports the BVH with Blender's own importer and renders (Cycles, CPU) the armature's bones as tubes
(one 8-sided tube per posed bone, head to tail) at FRAME: the whole body, and with HAND
(``left`` or ``right``) a close-up of that hand's bones as well, OUT.png with ``_hand`` before the suffix.
Debian's Blender 3.4 importer opens with mode 'rU'; ``open`` is wrapped as in blender_bvh_probe.py.
"""

import builtins
import math
import sys

import bpy
from mathutils import Vector

_open = builtins.open


def _open_no_u(file, mode="r", *args, **kwargs):
    if isinstance(mode, str) and "U" in mode:
        mode = mode.replace("U", "") or "r"
    return _open(file, mode, *args, **kwargs)


builtins.open = _open_no_u
argv = sys.argv[sys.argv.index("--") + 1 :]
out_png, bvh = argv[0], argv[1]
frame = int(argv[2]) if len(argv) > 2 else 1
hand = argv[3] if len(argv) > 3 else ""
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
bpy.ops.import_anim.bvh(filepath=bvh, global_scale=1.0, frame_start=1, use_fps_scale=False,
                        update_scene_fps=True, update_scene_duration=True, rotate_mode="NATIVE",
                        axis_forward="-Z", axis_up="Y")  # fmt: skip
arm = next(ob for ob in bpy.data.objects if ob.type == "ARMATURE")
scene = bpy.context.scene
scene.frame_set(frame)
mw = arm.matrix_world
verts, edges, radius = [], [], []
for pb in arm.pose.bones:
    h, t = mw @ pb.head, mw @ pb.tail
    finger = any(k in pb.name for k in ("thumb", "finger", "hand_root"))
    verts += [h, t]
    edges.append((len(verts) - 2, len(verts) - 1))
    radius += [0.004 if finger else 0.015] * 2

V, Fc = [], []
for (i, k), r in zip(edges, radius[::2], strict=True):  # one 8-sided tube per bone
    h, t = verts[i], verts[k]
    axis = t - h
    if axis.length < 1e-6:
        continue
    u = axis.orthogonal().normalized()
    w = axis.normalized().cross(u)
    base = len(V)
    for end in (h, t):
        for a in range(8):
            ang = 2 * math.pi * a / 8
            V.append(tuple(end + r * (math.cos(ang) * u + math.sin(ang) * w)))
    Fc += [(base + a, base + (a + 1) % 8, base + 8 + (a + 1) % 8, base + 8 + a) for a in range(8)]
    Fc += [tuple(base + a for a in range(8)), tuple(base + 8 + a for a in range(8))]
mesh = bpy.data.meshes.new("bones")
mesh.from_pydata(V, [], Fc)
ob = bpy.data.objects.new("bones", mesh)
scene.collection.objects.link(ob)
mat = bpy.data.materials.new("m")
mat.use_nodes = True
mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.8, 0.35, 0.1, 1.0)
ob.data.materials.append(mat)
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.rotation_euler = (0.6, 0.2, 0.8)
scene.collection.objects.link(sun)
world = bpy.data.worlds.new("w")
world.color = (0.6, 0.6, 0.65)
sun.data.energy = 4.0
scene.world = world
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = 16
scene.cycles.use_denoising = False
scene.render.resolution_x, scene.render.resolution_y = 800, 800
cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
scene.collection.objects.link(cam)
scene.camera = cam


def shoot(center: Vector, dist: float, path: str) -> None:
    cam.location = center + Vector((dist * 0.8, -dist, dist * 0.35))
    cam.rotation_euler = (center - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


pts = [v for v in verts]
c = sum(pts, Vector()) / len(pts)
shoot(c, 2.6, out_png)
if hand:
    hp = [mw @ pb.head for pb in arm.pose.bones if pb.name.startswith(hand) and "finger" in pb.name]
    hc = sum(hp, Vector()) / len(hp)
    shoot(hc, 0.35, out_png.replace(".png", "_hand.png"))
