"""BVH motion capture: reader, vectorised forward kinematics, and mapping to the canonical ``body19``.

The reader follows the BVH format as written: ``HIERARCHY`` (ROOT/JOINT/End Site, OFFSET,
CHANNELS with the Euler order *as written* per joint) then ``MOTION`` (Frames, Frame Time,
one row of channel values per frame). Rotation channels compose left to right in the order
they are listed (``Zrotation Yrotation Xrotation`` → ``R = Rz @ Ry @ Rx``), and a joint's
world transform is ``parent_world @ [R | offset + translation]``.

``load_bvh_body19(path, fps)`` returns ``(T, 19, 3)`` metres in the world frame used
everywhere in roomcap (z up, floor at z = 0):

- **joint mapping**: hips/knees/ankles/shoulders/elbows/wrists come from the named BVH
  joints (CMU ASF names ``LeftUpLeg``/``LeftHip``…, and the iClone ``CC_Base_L_Thigh``…
  rig of ``cmu-bvh-subjects01-07``); ``pelvis`` = mid-hips and ``neck`` = mid-shoulders,
  the same definition :mod:`roomcap.keypoints.skeletons` uses to derive them from COCO detectors.
- **face points are approximations**: nose, eyes and ears are fixed offsets (see
  ``FACE_OFFSETS_M``) in a head frame rigidly attached to the BVH head joint. The head
  frame's forward/up axes are estimated once per clip as the average over frames of the
  torso's forward and the neck→head direction expressed in the head joint's local frame,
  so head turns relative to the torso are kept.
- **units** are detected from the body height (m, cm, inches, or CMU's ASF unit of
  1/0.45 in = 0.05644 m), or given; the cgspeed "Daz-friendly" skeleton (``cmu-more``) is one fixed
  skeleton for every subject, so its unit is known, not guessed (:func:`cgspeed_unit`). **Axes**: the
  vertical axis is detected from the head-above-ankles direction and rotated (a proper rotation,
  handedness kept) to +z.
- **floor**: the clip is shifted so the 5th percentile of its lowest foot point is z = 0
  (ankles then sit ~5–10 cm above the floor). The horizontal root position is kept.
- **prepended T-pose** (``cmu-bvh-subjects01-07``): the first frame is dropped when it is a
  jump far larger than the clip's typical frame-to-frame motion; for the cgspeed Daz-friendly skeleton
  frame 0 is always dropped (its README: frame 0 of each clip is a T-pose).
- **resampling** to ``fps`` is linear interpolation of joint positions.

Parsed clips are cached in memory (``functools.lru_cache``) and on disk as ``.npz`` under
``$ROOMCAP_CACHE`` or the system temp folder (keyed by path, size, mtime and reader version).
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, UnknownNameError
from roomcap.keypoints.skeletons import CANONICAL

log = logging.getLogger(__name__)

_READER_VERSION = 4
BODY19 = CANONICAL.joint_names

# Candidate BVH joint names per body19 joint, first present wins (CMU ASF exports, the iClone CC rig and
# the cgspeed "Daz-friendly" conversion of ``cmu-more``, whose feet end in ``lFoot_end``/``rFoot_end``).
_NAME_CANDIDATES: dict[str, tuple[str, ...]] = {
    "left_hip": ("LeftUpLeg", "LeftHip", "CC_Base_L_Thigh", "LeftThigh", "L_Hip", "lThigh"),
    "right_hip": ("RightUpLeg", "RightHip", "CC_Base_R_Thigh", "RightThigh", "R_Hip", "rThigh"),
    "left_knee": ("LeftLeg", "LeftKnee", "CC_Base_L_Calf", "LeftShin", "L_Knee", "lShin"),
    "right_knee": ("RightLeg", "RightKnee", "CC_Base_R_Calf", "RightShin", "R_Knee", "rShin"),
    "left_ankle": ("LeftFoot", "LeftAnkle", "CC_Base_L_Foot", "L_Ankle", "lFoot"),
    "right_ankle": ("RightFoot", "RightAnkle", "CC_Base_R_Foot", "R_Ankle", "rFoot"),
    "left_shoulder": ("LeftArm", "LeftUpArm", "LeftShoulder", "CC_Base_L_Upperarm", "L_Shoulder", "lShldr"),
    "right_shoulder": (
        "RightArm",
        "RightUpArm",
        "RightShoulder",
        "CC_Base_R_Upperarm",
        "R_Shoulder",
        "rShldr",
    ),
    "left_elbow": ("LeftForeArm", "LeftElbow", "CC_Base_L_Forearm", "LeftLowArm", "L_Elbow", "lForeArm"),
    "right_elbow": ("RightForeArm", "RightElbow", "CC_Base_R_Forearm", "RightLowArm", "R_Elbow", "rForeArm"),
    "left_wrist": ("LeftHand", "LeftWrist", "CC_Base_L_Hand", "L_Wrist", "lHand"),
    "right_wrist": ("RightHand", "RightWrist", "CC_Base_R_Hand", "R_Wrist", "rHand"),
    "head": ("Head", "CC_Base_Head", "head"),
}
_FOOT_CANDIDATES = (
    "LeftToeBase",
    "RightToeBase",
    "LeftToe",
    "RightToe",
    "CC_Base_L_ToeBase",
    "CC_Base_R_ToeBase",
    "lFoot_end",
    "rFoot_end",
)

# Face points as offsets (forward, left, up) in metres from the BVH head joint (base of the
# skull / top of the neck) in the head frame. Approximations of an adult head, not measured.
FACE_OFFSETS_M: dict[str, tuple[float, float, float]] = {
    "nose": (0.105, 0.0, 0.045),
    "left_eye": (0.085, 0.032, 0.080),
    "right_eye": (0.085, -0.032, 0.080),
    "left_ear": (0.005, 0.075, 0.060),
    "right_ear": (0.005, -0.075, 0.060),
}

# Scale candidates, metres per file unit.
UNITS_M = {"m": 1.0, "cm": 0.01, "in": 0.0254, "cmu": 0.0254 / 0.45, "mm": 0.001}


# The cgspeed "Daz-friendly" conversion of the CMU database (``cmu-more``) retargets every subject onto ONE
# skeleton (the same OFFSETs in every file): its leg, |lShin offset| + |lFoot offset| (hip -> knee -> ankle),
# is 36.827 + 45.406 = 82.233 file units. The unit is the centimetre: that leg is 0.822 m, against 0.827 m
# (subject 01) and 0.849 m (subject 18) through CMU's ASF unit, and the T-pose stands about 1.5 m from the
# soles to the eyes.
# The salsa takes of ``cmu-more/two-person`` are the same skeleton written at 1/128 of that scale.
CGSPEED_JOINTS = ("hip", "abdomen", "chest", "neck", "head", "lThigh", "lShin", "lFoot", "rThigh", "rShin")
CGSPEED_LEG_UNITS = 82.233
CGSPEED_SCALES = {"cm": 0.01, "cgspeed/128": 1.28}  # metres per file unit of the two known writings


class BvhError(FormatError):
    pass


@dataclass(frozen=True)
class Bvh:
    """A parsed BVH file.

    ``names (J,)``, ``parents (J,)`` (-1 root), ``offsets (J,3)`` file units; End Sites are
    joints named ``<parent>_end`` without channels. ``channels[j]`` lists the channel names
    as written; ``channel_start[j]`` is the column of its first channel in ``motion (F,C)``.
    """

    path: str
    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    channel_start: np.ndarray
    motion: np.ndarray
    frame_time_s: float

    @property
    def n_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time_s

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownNameError(f"{self.path}: no joint '{name}'; joints: {list(self.names)}") from None

    def ancestors(self, joints) -> np.ndarray:
        """Sorted indices of ``joints`` and all their ancestors."""
        keep = set()
        for j in joints:
            while j >= 0 and j not in keep:
                keep.add(int(j))
                j = int(self.parents[j])
        return np.array(sorted(keep), dtype=np.int64)

    def forward_kinematics(self, joints=None, frames=None) -> tuple[np.ndarray, np.ndarray]:
        """World positions ``(F,K,3)`` (file units and axes) and rotations ``(F,K,3,3)`` of ``joints``.

        ``joints``: indices (default all); only they and their ancestors are computed.
        ``frames``: index array or slice into the motion (default all). Vectorised over frames;
        one small loop over the needed joints in topological order (parents precede children).
        """
        motion = self.motion if frames is None else self.motion[frames]
        F = motion.shape[0]
        want = np.arange(len(self.names)) if joints is None else np.asarray(joints, dtype=np.int64)
        need = self.ancestors(want)
        pos: dict[int, np.ndarray] = {}
        rot: dict[int, np.ndarray] = {}
        for j in need:  # file order is topological: a parent is written before its children
            local_t = np.broadcast_to(self.offsets[j], (F, 3)).copy()
            R = None
            c0 = int(self.channel_start[j])
            for k, ch in enumerate(self.channels[j]):
                v = motion[:, c0 + k]
                axis = "XYZ".index(ch[0].upper())
                if ch[1:].lower() == "position":
                    local_t[:, axis] += v
                else:
                    Rk = _axis_rotation(axis, np.deg2rad(v))
                    R = Rk if R is None else R @ Rk
            p = int(self.parents[j])
            if p < 0:
                pos[j] = local_t
                rot[j] = R if R is not None else np.broadcast_to(np.eye(3), (F, 3, 3))
            else:
                pos[j] = pos[p] + np.einsum("fab,fb->fa", rot[p], local_t)
                rot[j] = rot[p] if R is None else rot[p] @ R
        return np.stack([pos[int(j)] for j in want], 1), np.stack([rot[int(j)] for j in want], 1)


def _axis_rotation(axis: int, a: np.ndarray) -> np.ndarray:
    """Rotation matrices (F,3,3) about the x/y/z axis by angles ``a`` (F,) radians."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def read_bvh(path: str | os.PathLike) -> Bvh:
    """Parse a BVH file (hierarchy + motion). Raises :class:`BvhError` naming the problem."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as e:
        raise BvhError(path, None, f"cannot read: {e}", "Check the path and permissions.") from e
    head, sep, motion_text = text.partition("MOTION")
    if not sep:
        raise BvhError(path, "MOTION", "no MOTION section.", "The file is truncated or not a BVH file.")
    tok = head.split()
    if not tok or tok[0] != "HIERARCHY":
        raise BvhError(path, "HIERARCHY", "the file does not start with HIERARCHY.", "Is this a BVH file?")
    names, parents, offsets, channels = _hierarchy(tok, path)
    motion, frame_time_s = _motion(motion_text, sum(len(c) for c in channels), path)
    starts = np.cumsum([0] + [len(c) for c in channels[:-1]])
    return Bvh(
        str(path),
        tuple(names),
        np.asarray(parents, dtype=np.int64),
        np.asarray(offsets, dtype=np.float64),
        tuple(channels),
        np.asarray(starts, dtype=np.int64),
        motion,
        frame_time_s,
    )


def _hierarchy(
    tok: list[str], path: Path
) -> tuple[list[str], list[int], list[list[float]], list[tuple[str, ...]]]:
    """The header's tokens (``tok[0]`` is HIERARCHY) -> joint names (End Sites as ``<parent>_end``), parent
    indices (-1: the root), offsets and channels, in file order."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    stack: list[int] = []
    pending: int | None = None  # joint whose '{' is expected
    i = 1
    try:
        while i < len(tok):
            t = tok[i]
            if t in ("ROOT", "JOINT"):
                name = tok[i + 1]
                names.append(name)
                parents.append(stack[-1] if stack else -1)
                offsets.append([0.0, 0.0, 0.0])
                channels.append(())
                pending = len(names) - 1
                i += 2
            elif t == "End":  # End Site
                p = stack[-1]
                names.append(f"{names[p]}_end")
                parents.append(p)
                offsets.append([0.0, 0.0, 0.0])
                channels.append(())
                pending = len(names) - 1
                i += 2
            elif t == "{":
                if pending is None:
                    raise ValueError("'{' without a joint")
                stack.append(pending)
                pending = None
                i += 1
            elif t == "}":
                stack.pop()
                i += 1
            elif t == "OFFSET":
                offsets[stack[-1]] = [float(v) for v in tok[i + 1 : i + 4]]
                i += 4
            elif t == "CHANNELS":
                n = int(tok[i + 1])
                chans = tuple(tok[i + 2 : i + 2 + n])
                for c in chans:
                    if c[0].upper() not in "XYZ" or c[1:].lower() not in ("position", "rotation"):
                        raise ValueError(f"unknown channel '{c}'")
                channels[stack[-1]] = chans
                i += 2 + n
            else:
                raise ValueError(f"unexpected token '{t}'")
    except (ValueError, IndexError) as e:
        raise BvhError(
            path,
            "HIERARCHY",
            f"cannot parse near token {i}: {e}",
            "The hierarchy is malformed; re-export the file.",
        ) from e
    return names, parents, offsets, channels


def _motion(motion_text: str, n_ch: int, path: Path) -> tuple[np.ndarray, float]:
    """The MOTION section -> the complete frames (T, n_ch) (at most the header's count) and the frame time."""
    lines = motion_text.lstrip().split("\n", 2)
    try:
        n_frames = int(lines[0].split(":")[1])
        frame_time_s = float(lines[1].split(":")[1])
    except (IndexError, ValueError) as e:
        raise BvhError(path, "MOTION", "cannot read 'Frames:' / 'Frame Time:'.", "Re-export the file.") from e
    values = np.array(lines[2].split(), dtype=np.float64) if len(lines) > 2 else np.zeros(0)
    n_full = len(values) // n_ch if n_ch else 0
    if n_full < n_frames:
        log.warning("%s: header says %d frames, %d complete rows found; using those", path, n_frames, n_full)
    if n_full == 0:
        raise BvhError(
            path, "MOTION", f"no complete frame of {n_ch} channel values.", "The file is truncated."
        )
    n_use = min(n_full, n_frames) if n_frames > 0 else n_full
    motion = values[: n_use * n_ch].reshape(n_use, n_ch)
    if not (frame_time_s > 0):
        raise BvhError(path, "Frame Time", f"must be > 0, got {frame_time_s}.", "Fix the MOTION header.")
    return motion, frame_time_s


# ---------------------------------------------------------------------------------------------
# body19 extraction


def _pick(bvh: Bvh, candidates: tuple[str, ...]) -> int | None:
    lower = {n.lower(): i for i, n in enumerate(bvh.names)}
    for c in candidates:
        if c in bvh.names:
            return bvh.names.index(c)
    for c in candidates:
        if c.lower() in lower:
            return lower[c.lower()]
    return None


def is_cgspeed(bvh: Bvh) -> bool:
    """True for the cgspeed "Daz-friendly" skeleton (its joint names, ``CGSPEED_JOINTS``)."""
    return all(n in bvh.names for n in CGSPEED_JOINTS)


def cgspeed_unit(bvh: Bvh) -> tuple[str, float] | None:
    """(unit name, metres per file unit) of a cgspeed Daz-friendly file, None for other skeletons.

    The skeleton is fixed (``CGSPEED_LEG_UNITS`` at centimetres), so the file's leg offsets say at which of
    the known scales (``CGSPEED_SCALES``) it is written; any other uniform scale is taken relative to the
    centimetre skeleton and logged."""
    if not is_cgspeed(bvh):
        return None
    leg = float(
        np.linalg.norm(bvh.offsets[bvh.index("lShin")]) + np.linalg.norm(bvh.offsets[bvh.index("lFoot")])
    )
    if leg <= 0:
        raise BvhError(bvh.path, "lShin", "the leg offsets are zero.", "Re-export the file.")
    for unit, m in CGSPEED_SCALES.items():
        if abs(leg * m / (CGSPEED_LEG_UNITS * 0.01) - 1.0) < 0.01:
            return unit, m
    m = CGSPEED_LEG_UNITS * 0.01 / leg
    log.warning(
        "%s: cgspeed skeleton at an unknown scale (leg %.4g units); %.4g m per unit", bvh.path, leg, m
    )
    return f"cgspeed x{m:.4g}", m


def _up_rotation(up_axis: int, sign: float) -> np.ndarray:
    """Proper rotation (det +1, axis permutation with signs) taking the file's up axis to +z."""
    a = up_axis
    b, c = (a + 1) % 3, (a + 2) % 3
    M = np.zeros((3, 3))
    M[0, b] = 1.0
    M[1, c] = sign
    M[2, a] = sign
    return M


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


@dataclass(frozen=True)
class MocapClip:
    """A clip on the canonical skeleton: ``xyz_m (T,19,3)`` metres, z up, floor at 0, at ``fps``."""

    name: str
    xyz_m: np.ndarray
    fps: float
    unit: str
    source: str

    @property
    def n_frames(self) -> int:
        return self.xyz_m.shape[0]

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.fps

    def resample(self, fps: float) -> MocapClip:
        return MocapClip(self.name, resample(self.xyz_m, self.fps, fps), float(fps), self.unit, self.source)


def resample(xyz: np.ndarray, fps_in: float, fps_out: float) -> np.ndarray:
    """Linear resampling of ``(T,...)`` positions from ``fps_in`` to ``fps_out`` (same start time)."""
    T = xyz.shape[0]
    if abs(fps_in - fps_out) < 1e-9 or T < 2:
        return xyz.copy()
    t_out = np.arange(0.0, (T - 1) / fps_in + 1e-9, 1.0 / fps_out) * fps_in  # in input-frame units
    i0 = np.clip(np.floor(t_out).astype(np.int64), 0, T - 2)
    w = (t_out - i0).reshape((-1,) + (1,) * (xyz.ndim - 1))
    return (1.0 - w) * xyz[i0] + w * xyz[i0 + 1]


def bvh_to_body19(
    bvh: Bvh, unit_m: float | str | None = None, drop_tpose: bool | None = None
) -> tuple[np.ndarray, str]:
    """Canonical ``(F,19,3)`` metres z-up at the file's frame rate, and the unit name used.

    See the module docstring for the mapping, unit/axis detection and face approximation.
    """
    body, neck_joint, foot_pts, R_head = _joint_tracks(bvh)

    cg = cgspeed_unit(bvh)
    if cg is not None and drop_tpose is None:
        drop_tpose = bvh.n_frames > 1  # frame 0 of every cgspeed Daz-friendly clip is a T-pose
    if cg is not None and unit_m is None:
        unit_m = cg[1]
    # Drop a prepended T-pose: frame 0 far from frame 1 compared with the clip's typical step.
    if drop_tpose is None and bvh.n_frames > 3:
        stack = np.stack(list(body.values()), 1)
        rel = stack - stack[:, :1]
        step = np.linalg.norm(np.diff(rel, axis=0), axis=-1).mean(-1)
        drop_tpose = bool(step[0] > 10.0 * max(np.median(step[1:]), 1e-9))
    if drop_tpose:
        body = {k: v[1:] for k, v in body.items()}
        neck_joint, foot_pts, R_head = neck_joint[1:], foot_pts[1:], R_head[1:]

    # Up axis: the head-above-ankles direction.
    mid_ankle = 0.5 * (body["left_ankle"] + body["right_ankle"])
    vert = np.median(body["head"] - mid_ankle, axis=0)
    up_axis = int(np.argmax(np.abs(vert)))
    M = _up_rotation(up_axis, float(np.sign(vert[up_axis])))

    # Units from height (head joint above the ankles, ~1.45-1.6 m for adults).
    h = float(np.percentile(np.abs((body["head"] - mid_ankle)[:, up_axis]), 90))
    unit, scale = _unit(unit_m, h, cg)

    def to_world(x: np.ndarray) -> np.ndarray:
        return scale * (x @ M.T)

    out = np.full((len(next(iter(body.values()))), len(BODY19), 3), np.nan)
    J = {n: i for i, n in enumerate(BODY19)}
    for n in (
        "left_hip",
        "right_hip",
        "left_knee",
        "right_knee",
        "left_ankle",
        "right_ankle",
        "left_shoulder",
        "right_shoulder",
        "left_elbow",
        "right_elbow",
        "left_wrist",
        "right_wrist",
    ):
        out[:, J[n]] = to_world(body[n])
    out[:, J["pelvis"]] = 0.5 * (out[:, J["left_hip"]] + out[:, J["right_hip"]])
    out[:, J["neck"]] = 0.5 * (out[:, J["left_shoulder"]] + out[:, J["right_shoulder"]])

    # the face points from the head joint's frame
    _add_face(out, J, to_world(body["head"]), to_world(neck_joint), R_head, M)

    # Floor at z = 0: 5th percentile of the lowest foot point per frame.
    feet_z = to_world(foot_pts)[..., 2].min(1)
    out[..., 2] -= np.percentile(feet_z, 5)
    return out, unit


def _joint_tracks(bvh: Bvh) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """In the file's units and axes: each named body joint's positions (F,3), the head's parent joint's,
    the foot points (F,K,3) and the head joint's rotation (F,3,3)."""
    idx = {}
    for name, cands in _NAME_CANDIDATES.items():
        j = _pick(bvh, cands)
        if j is None:
            raise BvhError(
                bvh.path,
                name,
                f"no BVH joint for '{name}' (tried {list(cands)}).",
                "Add the rig's joint name to synthetic.bvh._NAME_CANDIDATES.",
            )
        idx[name] = j
    head = idx["head"]
    head_parent = int(bvh.parents[head])
    feet = [j for j in (_pick(bvh, (c,)) for c in _FOOT_CANDIDATES) if j is not None]
    feet += [i for i, n in enumerate(bvh.names) if n.endswith("_end") and bvh.parents[i] in feet]
    order = [idx[n] for n in _NAME_CANDIDATES] + [head_parent] + feet
    P, R = bvh.forward_kinematics(order)
    body = {n: P[:, k] for k, n in enumerate(_NAME_CANDIDATES)}
    neck_joint = P[:, len(_NAME_CANDIDATES)]
    foot_pts = np.concatenate(
        [
            P[:, len(_NAME_CANDIDATES) + 1 :],
            P[:, [order.index(idx["left_ankle"]), order.index(idx["right_ankle"])]],
        ],
        1,
    )
    R_head = R[:, list(_NAME_CANDIDATES).index("head")]
    return body, neck_joint, foot_pts, R_head


def _unit(unit_m: float | str | None, h: float, cg: tuple[str, float] | None) -> tuple[str, float]:
    """The unit's name and metres per unit: given, cgspeed's, or the one that makes ``h`` (the head's height
    above the ankles in file units) about 1.5 m."""
    if unit_m is None:
        unit = min(UNITS_M, key=lambda u: abs(np.log(max(h, 1e-9) * UNITS_M[u] / 1.5)))
        scale = UNITS_M[unit]
    elif isinstance(unit_m, str):
        unit, scale = unit_m, UNITS_M[unit_m]
    elif cg is not None and float(unit_m) == cg[1]:
        unit, scale = cg
    else:
        unit, scale = f"{unit_m:g} m", float(unit_m)
    return unit, scale


def _add_face(
    out: np.ndarray,
    J: dict[str, int],
    head_w: np.ndarray,
    neck_w: np.ndarray,
    R_head: np.ndarray,
    M: np.ndarray,
) -> None:
    """Write the face points (``FACE_OFFSETS_M``) into ``out``: the head frame in head-joint-local axes,
    averaged over the clip, placed at each frame's head joint."""
    Rh = np.einsum("ab,fbc->fac", M, R_head)  # head joint rotation, world axes
    left_w = _normalize(
        out[:, J["left_shoulder"]]
        - out[:, J["right_shoulder"]]
        + out[:, J["left_hip"]]
        - out[:, J["right_hip"]]
    )
    up_w = _normalize(head_w - neck_w)
    fwd_w = _normalize(np.cross(left_w, up_w))  # facing direction (z up: forward = left x up)
    up_l = _normalize(np.einsum("fba,fb->fa", Rh, up_w).mean(0))
    fwd_l = np.einsum("fba,fb->fa", Rh, fwd_w).mean(0)
    fwd_l = _normalize(fwd_l - up_l * (fwd_l @ up_l))
    left_l = np.cross(up_l, fwd_l)
    basis_l = np.stack([fwd_l, left_l, up_l], 1)  # columns: forward, left, up in head-local axes
    for n, off in FACE_OFFSETS_M.items():
        d_l = basis_l @ np.asarray(off)
        out[:, J[n]] = head_w + np.einsum("fab,b->fa", Rh, d_l)


# ---------------------------------------------------------------------------------------------
# loading with caches


def _cache_dir() -> Path:
    return Path(os.environ.get("ROOMCAP_CACHE", Path(tempfile.gettempdir()) / "roomcap-cache")) / "bvh"


def _cache_key(path: Path, unit_m, drop_tpose) -> str:
    st = path.stat()
    key = f"{_READER_VERSION}|{path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{unit_m}|{drop_tpose}"
    return hashlib.sha1(key.encode()).hexdigest()[:20]


@lru_cache(maxsize=256)
def _load_native(path: str, unit_m, drop_tpose) -> tuple[np.ndarray, float, str]:
    p = Path(path)
    cache = _cache_dir() / f"{p.stem}-{_cache_key(p, unit_m, drop_tpose)}.npz"
    if cache.exists():
        try:
            with np.load(cache, allow_pickle=False) as z:
                return z["xyz_m"], float(z["fps"]), str(z["unit"])
        except (OSError, ValueError, KeyError):
            log.warning("ignoring unreadable cache %s", cache)
    bvh = read_bvh(p)
    xyz, unit = bvh_to_body19(bvh, unit_m=unit_m, drop_tpose=drop_tpose)
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(cache.name + f".{os.getpid()}.tmp.npz")
        np.savez(tmp, xyz_m=xyz, fps=bvh.fps, unit=unit)
        os.replace(tmp, cache)
    except OSError as e:  # a cache is an optimisation only
        log.debug("cannot write cache %s: %s", cache, e)
    xyz.setflags(write=False)
    return xyz, bvh.fps, unit


def load_clip(
    path: str | os.PathLike,
    fps: float | None = None,
    unit_m: float | str | None = None,
    drop_tpose: bool | None = None,
) -> MocapClip:
    """Load a BVH file as a :class:`MocapClip` (body19, metres, z up), resampled to ``fps`` if given."""
    path = Path(path)
    xyz, native_fps, unit = _load_native(str(path.resolve()), unit_m, drop_tpose)
    clip = MocapClip(path.stem, np.array(xyz), native_fps, unit, str(path))
    return clip if fps is None else clip.resample(fps)


def load_bvh_body19(
    path: str | os.PathLike,
    fps: float | None = None,
    unit_m: float | str | None = None,
    drop_tpose: bool | None = None,
) -> np.ndarray:
    """``(T,19,3)`` metres, z up, floor at z = 0, at ``fps`` (default: the file's rate)."""
    return load_clip(path, fps, unit_m, drop_tpose).xyz_m


def mocap_root(root: str | os.PathLike | None = None) -> Path | None:
    """The mocap folder: ``root``, else ``$ROOMCAP_MOCAP``, else ``$ROOMCAP_SHARED/data/motion``
    (``ROOMCAP_SHARED`` defaults to ``../shared`` beside the repository). None when absent."""
    if root is not None:
        p = Path(root)
    elif os.environ.get("ROOMCAP_MOCAP"):
        p = Path(os.environ["ROOMCAP_MOCAP"])
    else:
        shared = os.environ.get("ROOMCAP_SHARED", Path(__file__).resolve().parents[2] / "shared")
        p = Path(shared) / "data" / "motion"
    return p if p.is_dir() else None


def list_clips(root: str | os.PathLike | None = None, exclude_raw_duplicates: bool = True) -> list[Path]:
    """Sorted BVH files under the mocap root (recursive); [] when the folder is absent.

    With ``exclude_raw_duplicates``, a raw file with a ``scaled_`` twin beside it is left out
    (``cmu-bvh-131`` ships both), so each motion appears once.
    """
    r = mocap_root(root)
    if r is None:
        return []
    files = sorted(r.rglob("*.bvh"))
    if exclude_raw_duplicates:
        names = {f.parent / f.name for f in files}
        files = [f for f in files if f.parent / f"scaled_{f.name}" not in names]
    return files


@lru_cache(maxsize=1024)
def _header_duration(path: str, size: int, mtime_ns: int) -> float:
    with open(path, "rb") as f:
        data = f.read()
    i = data.find(b"MOTION")
    if i < 0:
        return 0.0
    n, ft = 0, 0.0
    for line in data[i : i + 200].splitlines()[1:3]:
        key, _, val = line.decode(errors="replace").partition(":")
        if key.strip().lower() == "frames":
            n = int(val)
        elif key.strip().lower() == "frame time":
            ft = float(val)
    return n * ft


def clip_duration_s(path: str | os.PathLike) -> float:
    """Duration from the BVH header (``Frames`` × ``Frame Time``) without parsing the motion.

    0 when the file cannot be read."""
    p = Path(path)
    try:
        st = p.stat()
        return _header_duration(str(p), st.st_size, st.st_mtime_ns)
    except (OSError, ValueError):
        return 0.0


def load_clips(fps: float, root: str | os.PathLike | None = None, min_frames: int = 0) -> list[MocapClip]:
    """Every clip under the mocap root (see :func:`list_clips`) at ``fps``, skipping clips shorter
    than ``min_frames`` frames; [] when the folder is absent."""
    out = []
    for p in list_clips(root):
        c = load_clip(p, fps)
        if c.n_frames >= min_frames:
            out.append(c)
    return out
