"""The BVH file of a skeleton fit (:mod:`roomcap.outputs.skeleton_fit`).

Metres, y up like the TRC: world (x, y, z) -> (x, z, -y); joint names as in the track file; every joint
is a BVH JOINT with ``Zrotation Xrotation Yrotation`` channels, and leaves end in a short End Site so
every joint is a bone head in Blender. A whole-body fit's hands are joints like any other:
``<side>_hand_root`` under the wrist, then ``<side>_thumb1``..4, ``<side>_forefinger1``..4, ... each finger
a chain of 4.
"""

from __future__ import annotations

import os

import numpy as np
from scipy.spatial.transform import Rotation

from roomcap.core.fileio import atomic_write_text
from roomcap.outputs.skeleton_fit import YUP, _children
from roomcap.outputs.skeleton_fit_file import FitError, SkeletonFit


def write_bvh(fit: SkeletonFit, path: str | os.PathLike, track_ids: list[int] | None = None) -> None:
    """BVH of the fitted skeleton of one person, or several (one ROOT each, joint names suffixed
    ``_<id>``). Frames: the persons' span; frames where a person of several is absent hold its nearest
    fitted pose."""
    ids = fit.track_id.tolist() if track_ids is None else [int(i) for i in track_ids]
    ks = [int(np.flatnonzero(fit.track_id == i)[0]) for i in ids]
    span = fit.span[:, ks].any(-1)
    rows = np.flatnonzero(span)
    if not len(rows):
        raise FitError(f"tracks {ids} have no fitted frame.")
    rows = np.arange(rows[0], rows[-1] + 1)
    names, parents = fit.joint_names, fit.parents
    children = _children(parents)
    multi = len(ids) > 1
    lines = ["HIERARCHY"]
    motion_cols = []
    for k, tid in zip(ks, ids, strict=True):
        sfx = f"_{tid}" if multi else ""
        off = fit.rest_offset_m[k] @ YUP.T
        root = int(np.flatnonzero(parents < 0)[0])
        # hold the nearest fitted pose outside this person's span
        have = np.flatnonzero(fit.span[rows, k])
        near = have[np.clip(np.searchsorted(have, np.arange(len(rows))), 0, len(have) - 1)]
        prev = have[np.clip(np.searchsorted(have, np.arange(len(rows)), side="right") - 1, 0, len(have) - 1)]
        pick = np.where(np.abs(near - np.arange(len(rows))) < np.abs(prev - np.arange(len(rows))), near, prev)
        src = rows[pick]
        root_p = fit.root_xyz_m[src, k] @ YUP.T
        q = fit.rotation_xyzw[src, k]
        Lm = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(len(rows), len(names), 3, 3)
        Lm = YUP @ Lm @ YUP.T
        eul = (
            Rotation.from_matrix(Lm.reshape(-1, 3, 3)).as_euler("ZXY", degrees=True).reshape(len(rows), -1, 3)
        )
        order: list[int] = []

        def emit(j: int, depth: int, sfx=sfx, off=off, order=order) -> None:
            ind = "\t" * depth
            kind = "ROOT" if parents[j] < 0 else "JOINT"
            lines.append(f"{ind}{kind} {names[j]}{sfx}")
            lines.append(f"{ind}{{")
            o = np.zeros(3) if parents[j] < 0 else off[j]
            lines.append(f"{ind}\tOFFSET {o[0]:.6f} {o[1]:.6f} {o[2]:.6f}")
            if parents[j] < 0:
                lines.append(f"{ind}\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
            else:
                lines.append(f"{ind}\tCHANNELS 3 Zrotation Xrotation Yrotation")
            order.append(j)
            if children[j]:
                for c in children[j]:
                    emit(c, depth + 1, sfx, off, order)
            else:  # End Site continuing the bone by a quarter of its length (5 cm for a root leaf)
                e = 0.25 * off[j] if np.linalg.norm(off[j]) > 0 else np.array([0.0, 0.05, 0.0])
                lines.append(f"{ind}\tEnd Site")
                lines.append(f"{ind}\t{{")
                lines.append(f"{ind}\t\tOFFSET {e[0]:.6f} {e[1]:.6f} {e[2]:.6f}")
                lines.append(f"{ind}\t}}")
            lines.append(f"{ind}}}")

        emit(root, 0)
        cols = [root_p]
        cols += [eul[:, j] for j in order]
        motion_cols.append(np.concatenate(cols, 1))
    M = np.concatenate(motion_cols, 1)
    lines += ["MOTION", f"Frames: {len(rows)}", f"Frame Time: {1.0 / fit.fps:.8f}"]
    lines += [" ".join(f"{v:.6f}" for v in r) for r in M]
    atomic_write_text(path, "\n".join(lines) + "\n")
