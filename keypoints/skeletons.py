"""Skeletons as data: joint names, parents, limbs, and mappings between layouts.

Skeleton ids (CONTRACTS.md): ``coco17``, ``coco18`` (OpenPose COCO), ``body25``,
``body25b`` (OpenPose BODY_25B, used by Pose2Sim's demo), ``blazepose33``,
``halpe26``, ``smpl29`` (Humans-in-Kitchens: SMPL's 22 body joints + 7 head
points) and the canonical ``body19`` (COCO-17 plus pelvis and neck) used for
every 3D file. Joint names are lower snake case.

Hands: 21 joints per hand in MediaPipe's (and OpenPose's) landmark order, named as COCO-WholeBody names
them (mmpose's ``coco_wholebody`` metainfo): ``left_hand_root`` (the hand's wrist point), then
``left_thumb1``..``left_thumb4``, ``left_forefinger1``..4, ``left_middle_finger1``..4,
``left_ring_finger1``..4, ``left_pinky_finger1``..4, and ``right_`` likewise (:data:`HAND_LEFT`,
:data:`HAND_RIGHT`). Every layout above has a ``<id>_hands`` variant with both hands appended
(``blazepose33_hands`` is MediaPipe Holistic's body and hands, ``body19_hands`` the whole-body 3D
layout with hands); :data:`HAND_BONES` are the bones drawn and measured.

The 3D stages can also use ``whole_body`` (:func:`whole_body`: body19 plus the feet, hand
points, upper neck and head top a 2D layout provides) or a skeleton declared in a TOML
(:func:`load_skeleton_toml`).

``convert`` maps keypoints between layouts by joint name; joints the source
lacks but can be derived (pelvis = mid-hips, neck = mid-shoulders) are
computed, everything else is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np

from roomcap.core.errors import FormatError, UnknownNameError
from roomcap.core.fileio import load_toml

_COCO17 = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)
_BODY19 = _COCO17 + ("pelvis", "neck")
_COCO18 = (
    "nose",
    "neck",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_hip",
    "right_knee",
    "right_ankle",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_eye",
    "left_eye",
    "right_ear",
    "left_ear",
)
_FEET = ("left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel")
_BODY25 = (
    "nose",
    "neck",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "pelvis",
    "right_hip",
    "right_knee",
    "right_ankle",
    "left_hip",
    "left_knee",
    "left_ankle",
    "right_eye",
    "left_eye",
    "right_ear",
    "left_ear",
) + _FEET
_BODY25B = _COCO17 + ("upper_neck", "head_top") + _FEET
_HALPE26 = _COCO17 + (
    "head",
    "neck",
    "pelvis",
    "left_big_toe",
    "right_big_toe",
    "left_small_toe",
    "right_small_toe",
    "left_heel",
    "right_heel",
)
_BLAZEPOSE33 = (
    "nose",
    "left_eye_inner",
    "left_eye",
    "left_eye_outer",
    "right_eye_inner",
    "right_eye",
    "right_eye_outer",
    "left_ear",
    "right_ear",
    "mouth_left",
    "mouth_right",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_heel",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
)
# Humans-in-Kitchens / SMPL order (Tanke ch. 8): 22 body joints, then 7 head points.
_SMPL29 = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "head_point_0",
    "head_point_1",
    "head_point_2",
    "head_point_3",
    "head_point_4",
    "head_point_5",
    "head_point_6",
)

# Hands (COCO-WholeBody names, MediaPipe landmark order: 0 wrist, 1-4 thumb CMC..tip, 5-8 index MCP..tip,
# 9-12 middle, 13-16 ring, 17-20 little finger).
FINGERS = ("thumb", "forefinger", "middle_finger", "ring_finger", "pinky_finger")


def hand_joints(side: str) -> tuple[str, ...]:
    """The 21 joint names of the ``side`` ("left" or "right") hand, in MediaPipe's landmark order."""
    return (f"{side}_hand_root",) + tuple(f"{side}_{f}{k}" for f in FINGERS for k in range(1, 5))


HAND_LEFT = hand_joints("left")
HAND_RIGHT = hand_joints("right")
HANDS = HAND_LEFT + HAND_RIGHT
_HAND_PARENT = {
    f"{side}_{f}{k}": f"{side}_hand_root" if k == 1 else f"{side}_{f}{k - 1}"
    for side in ("left", "right")
    for f in FINGERS
    for k in range(1, 5)
}
# (parent, child) joint names of every hand bone: per finger root->1, 1->2, 2->3, 3->4 (the first is a
# palm bone, the metacarpal; the thumb's is the CMC-MCP segment), 20 per hand.
HAND_BONES = tuple((p, c) for c, p in _HAND_PARENT.items())

# Kinematic parent of every joint, by name (a joint absent from a layout is skipped
# when walking up to the nearest present ancestor).
_PARENT = {
    "pelvis": None,
    "left_hip": "pelvis",
    "right_hip": "pelvis",
    "neck": "pelvis",
    "left_knee": "left_hip",
    "right_knee": "right_hip",
    "left_ankle": "left_knee",
    "right_ankle": "right_knee",
    "left_shoulder": "neck",
    "right_shoulder": "neck",
    "left_elbow": "left_shoulder",
    "right_elbow": "right_shoulder",
    "left_wrist": "left_elbow",
    "right_wrist": "right_elbow",
    "nose": "neck",
    "left_eye": "nose",
    "right_eye": "nose",
    "left_ear": "left_eye",
    "right_ear": "right_eye",
    "upper_neck": "neck",
    "head_top": "upper_neck",
    "head": "neck",
    "left_big_toe": "left_ankle",
    "left_small_toe": "left_ankle",
    "left_heel": "left_ankle",
    "right_big_toe": "right_ankle",
    "right_small_toe": "right_ankle",
    "right_heel": "right_ankle",
    "left_eye_inner": "nose",
    "left_eye_outer": "left_eye",
    "right_eye_inner": "nose",
    "right_eye_outer": "right_eye",
    "mouth_left": "nose",
    "mouth_right": "nose",
    "left_pinky": "left_wrist",
    "right_pinky": "right_wrist",
    "left_index": "left_wrist",
    "right_index": "right_wrist",
    "left_thumb": "left_wrist",
    "right_thumb": "right_wrist",
    "left_foot_index": "left_ankle",
    "right_foot_index": "right_ankle",
    "spine1": "pelvis",
    "spine2": "spine1",
    "spine3": "spine2",
    "left_foot": "left_ankle",
    "right_foot": "right_ankle",
    "left_collar": "spine3",
    "right_collar": "spine3",
    **{f"head_point_{i}": "head" for i in range(7)},
    "left_hand_root": "left_wrist",
    "right_hand_root": "right_wrist",
    **_HAND_PARENT,
}
# SMPL's tree differs from the COCO-style one above in the upper body.
_PARENT_SMPL = {
    "neck": "spine3",
    "head": "neck",
    "left_shoulder": "left_collar",
    "right_shoulder": "right_collar",
}

# Joints that can be derived as the midpoint of two others when a layout lacks them.
DERIVED = {"pelvis": ("left_hip", "right_hip"), "neck": ("left_shoulder", "right_shoulder")}

# The four limb pairs PCP scores (seed ch. 4.3; Shelf/Campus protocol), by name.
PCP_LIMBS = {
    "upper_arm": (("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow")),
    "lower_arm": (("left_elbow", "left_wrist"), ("right_elbow", "right_wrist")),
    "upper_leg": (("left_hip", "left_knee"), ("right_hip", "right_knee")),
    "lower_leg": (("left_knee", "left_ankle"), ("right_knee", "right_ankle")),
}


@dataclass(frozen=True)
class Skeleton:
    """A keypoint layout. ``parents[j]`` is -1 for roots; ``limbs`` are (parent, child) index pairs."""

    id: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        table = dict(_PARENT, **_PARENT_SMPL) if self.id == "smpl29" else _PARENT
        idx = {n: i for i, n in enumerate(self.joint_names)}
        # One root: the first of these the layout has; joints whose ancestors are all
        # missing (hips and shoulders of COCO-17, say) hang from it.
        root = next(idx[n] for n in ("pelvis", "neck", "left_hip", *self.joint_names) if n in idx)
        parents = []
        for j, name in enumerate(self.joint_names):
            p = table.get(name)
            while p is not None and p not in idx:  # walk up to the nearest ancestor the layout has
                p = table.get(p)
            parents.append(-1 if j == root else (root if p is None else idx[p]))
        object.__setattr__(self, "parents", tuple(parents))

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def limbs(self) -> tuple[tuple[int, int], ...]:
        return tuple((p, c) for c, p in enumerate(self.parents) if p >= 0)

    def index(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise UnknownNameError(
                f"skeleton '{self.id}' has no joint '{name}'; joints: {list(self.joint_names)}"
            ) from None

    @property
    def flip_index(self) -> np.ndarray:
        """Index permutation that swaps left and right joints."""
        idx = {n: i for i, n in enumerate(self.joint_names)}
        out = []
        for n in self.joint_names:
            m = n.replace("left_", "\0").replace("right_", "left_").replace("\0", "right_")
            out.append(idx.get(m, idx[n]))
        return np.asarray(out)

    def pcp_limbs(self) -> dict[str, tuple[tuple[int, int], ...]]:
        return {k: tuple((self.index(a), self.index(b)) for a, b in pairs) for k, pairs in PCP_LIMBS.items()}


SKELETONS: dict[str, Skeleton] = {
    s.id: s
    for s in (
        Skeleton("body19", _BODY19),
        Skeleton("coco17", _COCO17),
        Skeleton("coco18", _COCO18),
        Skeleton("body25", _BODY25),
        Skeleton("body25b", _BODY25B),
        Skeleton("halpe26", _HALPE26),
        Skeleton("blazepose33", _BLAZEPOSE33),
        Skeleton("smpl29", _SMPL29),
    )
}
CANONICAL = SKELETONS["body19"]
# every layout with both hands appended: ``<id>_hands`` (MediaPipe Holistic = ``blazepose33_hands``;
# OpenPose with ``--hand``: ``body25_hands``, ...; the 3D whole body with hands: ``body19_hands``)
SKELETONS.update(
    {f"{k}_hands": Skeleton(f"{k}_hands", v.joint_names + HANDS) for k, v in list(SKELETONS.items())}
)

# Joints a 3D skeleton carries beyond body19 when a 2D layout provides them (``whole_body``).
WHOLE_BODY_EXTRAS = (
    "left_big_toe",
    "left_small_toe",
    "left_heel",
    "right_big_toe",
    "right_small_toe",
    "right_heel",
    "left_foot_index",
    "right_foot_index",
    "upper_neck",
    "head_top",
    "head",
    "left_pinky",
    "right_pinky",
    "left_index",
    "right_index",
    "left_thumb",
    "right_thumb",
) + HANDS


def whole_body(sources) -> Skeleton:
    """The 3D skeleton for detections in the 2D layouts ``sources``: ``body19`` plus every joint of
    :data:`WHOLE_BODY_EXTRAS` that one of them provides (feet of BODY_25/BODY_25B/HALPE-26/BlazePose,
    BlazePose's hand points, BODY_25B's upper neck and head top, the 42 hand joints of a ``*_hands``
    layout), in that order. Id ``whole_body``
    (``body19`` itself when no layout adds a joint)."""
    have = set()
    for src in sources:
        have |= set(get_skeleton(src).joint_names)
    extra = tuple(n for n in WHOLE_BODY_EXTRAS if n in have)
    return CANONICAL if not extra else Skeleton("whole_body", _BODY19 + extra)


def finger_bones(joint_names) -> dict[str, tuple[tuple[int, int], ...]]:
    """Index pairs (parent, child) of the :data:`HAND_BONES` a layout has, by ``<side>_<finger>``
    (e.g. ``left_thumb``: 4 bones from the hand root to the tip); fingers it lacks are left out."""
    idx = {n: i for i, n in enumerate(joint_names)}
    out: dict[str, tuple[tuple[int, int], ...]] = {}
    for side in ("left", "right"):
        for f in FINGERS:
            key = f"{side}_{f}"
            bones = tuple(
                (idx[p], idx[c]) for p, c in HAND_BONES if c.startswith(key) and p in idx and c in idx
            )
            if bones:
                out[key] = bones
    return out


def custom_skeleton(id: str, joint_names, parents) -> Skeleton:
    """A skeleton with its own tree: ``parents`` are joint names (``""`` for the root) or indices (-1)."""
    names = tuple(str(n) for n in joint_names)
    if len(set(names)) != len(names):
        raise ValueError(f"skeleton '{id}': joint names repeat: {list(names)}")
    if len(parents) != len(names):
        raise ValueError(f"skeleton '{id}': {len(names)} joints but {len(parents)} parents")
    idx = {n: i for i, n in enumerate(names)}
    par = []
    for n, p in zip(names, parents, strict=True):
        if isinstance(p, str):
            if p and p not in idx:
                raise ValueError(
                    f"skeleton '{id}': the parent '{p}' of '{n}' is not a joint; joints: {list(names)}"
                )
            par.append(idx[p] if p else -1)
        else:
            par.append(int(p))
    if sum(1 for p in par if p < 0) != 1:
        raise ValueError(f"skeleton '{id}': exactly one joint must be the root (parent \"\"), got {par}")
    sk = Skeleton(id, names)
    object.__setattr__(sk, "parents", tuple(par))
    return sk


def load_skeleton_toml(path) -> Skeleton:
    """A skeleton the project does not know, declared in a small TOML, for the 3D stages::

        [skeleton]
        id = "mouse"
        joints = ["snout", "left_ear", "right_ear", "neck", "tail_base"]
        parents = ["neck", "snout", "snout", "", "neck"]      # "" = the root

        [layouts.dlc_mouse]                 # a 2D layout: the ``skeleton`` id of the detections files
        joints = ["nose", "earL", "earR", "neck", "tailbase"]
        map = { snout = "nose", left_ear = "earL", right_ear = "earR", tail_base = "tailbase" }

    The 3D joints take the 2D joints of the same name, or the one ``map`` names (3D = 2D). Each
    layout is registered (so its detections files load) with its joints renamed to the 3D names.
    Returns the 3D skeleton."""
    from pathlib import Path

    path = Path(path)
    data = load_toml(path)
    try:
        sk = data["skeleton"]
        skel = custom_skeleton(str(sk["id"]), sk["joints"], sk["parents"])
        for lid, lay in data.get("layouts", {}).items():
            m = {str(v): str(k) for k, v in lay.get("map", {}).items()}
            bad = [v for v in m if v not in lay["joints"]]
            if bad:
                raise ValueError(f"layout '{lid}': map names 2D joints {bad} it does not have")
            names = tuple(m.get(n, n) for n in lay["joints"])
            if not set(names) & set(skel.joint_names):
                raise ValueError(f"layout '{lid}' shares no joint with skeleton '{skel.id}'")
            SKELETONS[str(lid)] = Skeleton(str(lid), names)
        unknown = set(data) - {"skeleton", "layouts"}
        if unknown:
            raise ValueError(f"unknown sections {sorted(unknown)}; valid: skeleton, layouts")
    except (KeyError, TypeError, ValueError) as e:
        raise FormatError(
            path, None, f"not a skeleton declaration ({e}).", "See keypoints.skeletons.load_skeleton_toml."
        ) from None
    return skel


def skeleton_from_names(joint_names) -> Skeleton:
    """The skeleton of a 3D file from its joint names (a known layout when the names are one's)."""
    names = tuple(str(n) for n in joint_names)
    for sk in SKELETONS.values():
        if sk.joint_names == names:
            return sk
    return Skeleton("whole_body" if names[: len(_BODY19)] == _BODY19 else "custom", names)


def get_skeleton(skeleton: str | Skeleton) -> Skeleton:
    if isinstance(skeleton, Skeleton):
        return skeleton
    try:
        return SKELETONS[str(skeleton)]
    except KeyError:
        raise UnknownNameError(f"unknown skeleton id '{skeleton}'; known: {sorted(SKELETONS)}") from None


@cache
def mapping(src: str | Skeleton, dst: str | Skeleton) -> tuple[np.ndarray, tuple[tuple[int, int, int], ...]]:
    """Index map from ``src`` to ``dst`` layout.

    Returns ``take`` (J_dst,) with the source index of each destination joint or -1,
    and ``derived``: (dst_index, src_a, src_b) for joints computed as a midpoint.
    """
    s, d = get_skeleton(src), get_skeleton(dst)  # ids or Skeleton objects (hashable)
    src_idx = {n: i for i, n in enumerate(s.joint_names)}
    take = np.full(d.n_joints, -1, dtype=np.int64)
    derived = []
    for j, name in enumerate(d.joint_names):
        if name in src_idx:
            take[j] = src_idx[name]
        elif name in DERIVED and all(p in src_idx for p in DERIVED[name]):
            a, b = DERIVED[name]
            derived.append((j, src_idx[a], src_idx[b]))
    return take, tuple(derived)


def convert(xy: np.ndarray, score: np.ndarray | None, src: str | Skeleton, dst: str | Skeleton = "body19"):
    """Map keypoints (..., J_src, D) and scores (..., J_src) to layout ``dst``.

    Joints the source cannot provide are NaN with score 0. Derived joints are the
    midpoint of their two sources (NaN if either is NaN), with the smaller score.
    """
    xy = np.asarray(xy, dtype=np.float64)
    s = get_skeleton(src)
    if xy.shape[-2] != s.n_joints:
        raise ValueError(f"convert: expected (..., {s.n_joints}, D) for '{src}', got {xy.shape}")
    take, derived = mapping(s, get_skeleton(dst))
    out_shape = xy.shape[:-2] + (len(take), xy.shape[-1])
    out = np.full(out_shape, np.nan)
    ok = take >= 0
    out[..., ok, :] = xy[..., take[ok], :]
    sc = None
    if score is not None:
        score = np.asarray(score, dtype=np.float64)
        sc = np.zeros(out_shape[:-1])
        sc[..., ok] = score[..., take[ok]]
    for j, a, b in derived:
        out[..., j, :] = 0.5 * (xy[..., a, :] + xy[..., b, :])
        if sc is not None:
            sc[..., j] = np.minimum(score[..., a], score[..., b])
    if sc is not None:
        sc = np.where(np.isnan(out[..., 0]), 0.0, sc)
    return out, sc
