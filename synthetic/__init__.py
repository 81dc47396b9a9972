"""The synthetic world: rigs, rooms, multi-person scenes from CMU mocap, rendering to detections.

Quick start::

    from roomcap.synthetic import kitchen, make_scene, render_scene, SceneConfig, RenderConfig
    rig, room = kitchen(12)
    scene = make_scene(room, SceneConfig(n_people=8, duration_s=10, fps=25, seed=0))
    r = render_scene(scene, rig, RenderConfig(noise_px=3, missed_joint_rate=0.1, flip_rate=0.02))
    r.detections[c]   # keypoints.detections.Detections of camera c
    r.gt_index[c]     # (T,P_c) scene person per detection row, -1 false positive, -2 padding
    scene.gt_xyz_m    # (T,P,19,3) metres, NaN while absent
"""

from roomcap.synthetic.bvh import list_clips, load_bvh_body19, load_clip, mocap_root, read_bvh
from roomcap.synthetic.render import RenderConfig, Rendering, render_scene
from roomcap.synthetic.rigs import Box, Room, kitchen, kitchen_rig, kitchen_room, ring_rig, ring_room
from roomcap.synthetic.world import Scene, SceneConfig, load_gt, make_scene, write_session

__all__ = [
    "Box",
    "RenderConfig",
    "Rendering",
    "Room",
    "Scene",
    "SceneConfig",
    "kitchen",
    "kitchen_rig",
    "kitchen_room",
    "list_clips",
    "load_bvh_body19",
    "load_clip",
    "load_gt",
    "make_scene",
    "mocap_root",
    "read_bvh",
    "render_scene",
    "ring_rig",
    "ring_room",
    "write_session",
]
