"""Composite activities from labelled CMU clips, observed in 2D by the synthetic world (Diller ch. 4 data).

The seed learns from kitchen videos with annotated sub-actions (MPII Cooking II, IKEA-ASM). Here the same task
is built from data that ships with the project:

- **Actions.** Every CMU clip gets one action from its description (``action_of_description``: keyword
  rules over the CMU index). Only the actions that both the training subjects and the held-out subjects
  perform are used (``ACTIONS``).
- **Steps.** A step is one characteristic frame of a clip, found by the ch. 3 annotation rule
  (``forecast.characteristic.labels.annotate``; a clip where the rule finds none gives its frame of
  greatest articulation).
- **Composite activities.** A sequence of ``n_obs + M`` steps follows a fixed script of likely next actions
  (``SCRIPT``, a Markov chain without self-transitions: walk -> sit -> drink -> ...); each step draws a clip
  of its action and one of that clip's characteristic poses, placed where the person walked to (a random
  walk over the room's floor, a continuous heading). That script ("markov") gives the poses no information
  about what follows beyond the labels. The "stations" script (``compose_stations``) gives them the
  structure of a real room: its actions have fixed places, each with its routine (``STATIONS``: sit, drink,
  laugh at the table; drink, laugh, reach at the counter; wash, reach, drink at the sink; climb and reach at
  the shelf), and a person walks from place to place facing where they go, so the place of the observed
  steps (and the heading of a walk) tells what comes next where the labels alone ("walk", "drink",
  "reach") do not. Both are Markov chains over hidden states
  (``script_chain``), which gives the best possible forecast from labels alone and from labels and place.
- **2D observation.** Every step pose is rendered into one camera of a ring rig by
  ``synthetic.render.render_camera`` (pixel noise, missed joints, missed detections, lens distortion), the
  camera fixed per sequence, so training sees the kind of 2D the ``keypoints`` stage writes.
- **Subjects.** Sequences of ``train``/``val`` come from ``TRAIN_SUBJECTS`` (val: every fifth
  characteristic frame of their clips, ``split_pool``), ``test`` from ``TEST_SUBJECTS``, and the adversarial
  3D database from other subjects again (``DB_SUBJECTS``), so the critic's real poses never correspond to
  the sequences.
- **Continuous activities.** ``compose_continuous`` joins the steps into one motion (each step aligned to
  where the previous ended, the two cross-faded) with its label ranges, and ``activity_session`` writes such
  people as a session folder with a label file, the form a lab's own annotated recording takes.
"""

from __future__ import annotations

import csv
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.core.errors import InputError
from roomcap.forecast.lab import data as fdata
from roomcap.forecast.lab.characteristic.labels import annotate, articulation
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.synthetic import bvh
from roomcap.synthetic.render import RenderConfig, render, render_camera
from roomcap.synthetic.rigs import ring_rig, ring_room
from roomcap.synthetic.world import Scene, SceneConfig, write_session
from roomcap.track.trackfile import TrackFile

log = logging.getLogger(__name__)

SKELETON = "body19"
JOINTS = get_skeleton(SKELETON).joint_names
PARENTS = get_skeleton(SKELETON).parents
UPPER9 = (
    "nose",
    "neck",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "pelvis",
)  # the seed's 9 upper-body joints (head, neck, arms, hip), Table 4.13

# keyword rules, first match wins (descriptions lower case)
_RULES = (
    ("drink", ("drink", "bottlecap")),
    ("sit", ("sit on",)),
    ("climb", ("climb ladder", "climb 3 steps")),
    ("reach", ("reach for", "jump up to grab")),
    ("laugh", ("laugh",)),
    ("wash", ("wash",)),
    ("walk", ("walk",)),
)
ACTIONS = tuple(sorted({a for a, _ in _RULES}))

# the script: next-action probabilities (no action follows itself)
SCRIPT = {
    "walk": {"sit": 0.4, "climb": 0.25, "reach": 0.2, "wash": 0.15},
    "sit": {"drink": 0.6, "laugh": 0.3, "walk": 0.1},
    "drink": {"laugh": 0.4, "walk": 0.4, "sit": 0.2},
    "laugh": {"walk": 0.5, "drink": 0.3, "wash": 0.2},
    "climb": {"reach": 0.6, "walk": 0.4},
    "reach": {"walk": 0.5, "climb": 0.3, "wash": 0.2},
    "wash": {"walk": 0.6, "drink": 0.4},
}

SCRIPTS = ("markov", "stations")

# the "stations" script: a room with fixed places for its actions (room frame = the rig's world, z up,
# metres). Each place has a floor point and the heading (rad) a person there faces; a person walks from one
# place to the next, so where they are and where they head tells what they do next.
STATIONS = {
    "table": ((-1.2, 0.9), -0.6),  # sit at the kitchen table, drink, laugh
    "counter": ((-1.0, -1.2), 0.5),  # drink at the counter, laugh, reach for a glass
    "sink": ((1.3, 1.1), 0.7),  # wash, reach into the cupboard above, drink a glass of water
    "shelf": ((1.1, -1.2), -0.9),  # climb the ladder, reach onto the shelf
}
# next state from a state at a place ("leave": walk to another place, by ``LEAVE``)
STATION_SCRIPT = {
    "table:sit": {"table:drink": 0.7, "table:laugh": 0.3},
    "table:drink": {"table:laugh": 0.3, "leave": 0.7},
    "table:laugh": {"table:drink": 0.2, "leave": 0.8},
    "counter:drink": {"counter:laugh": 0.7, "counter:reach": 0.3},
    "counter:laugh": {"counter:drink": 0.3, "leave": 0.7},
    "counter:reach": {"counter:drink": 0.2, "leave": 0.8},
    "sink:wash": {"sink:reach": 0.6, "sink:drink": 0.4},
    "sink:reach": {"sink:wash": 0.3, "leave": 0.7},
    "sink:drink": {"sink:wash": 0.2, "leave": 0.8},
    "shelf:climb": {"shelf:reach": 0.8, "leave": 0.2},
    "shelf:reach": {"shelf:climb": 0.2, "leave": 0.8},
}
# where a person walks on leaving a place: any other, alike (the labels do not tell which; the walk's
# place and heading do)
LEAVE = {p: {q: 1.0 / (len(STATIONS) - 1) for q in STATIONS if q != p} for p in STATIONS}
# the first action on arriving at a place (after the walk there)
ARRIVE = {
    "table": {"table:sit": 1.0},
    "counter": {"counter:drink": 1.0},
    "sink": {"sink:wash": 0.9, "sink:drink": 0.1},
    "shelf": {"shelf:climb": 0.9, "shelf:reach": 0.1},
}
STATION_NOISE_M = 0.2  # s.d. of where a person stands at a place
STATION_TURN_RAD = 0.35  # s.d. of their heading there
WALK_PART = (0.3, 0.7)  # a walk step is this part of the way from the last place to the next
WALK_NOISE_M = 0.2
WALK_TURN_RAD = 0.25  # s.d. of the walking heading about the direction to the next place

TRAIN_SUBJECTS = (3, 7, 8, 14)
TEST_SUBJECTS = (2, 12, 13)
DB_SUBJECTS = (1, 5, 6, 9, 10, 11, 18, 19, 131)


def action_of_description(desc: str) -> str | None:
    """The action of a CMU description by the keyword rules above ('sit on high stool, stand up' -> 'sit',
    'unscrew bottlecap, drink soda' -> 'drink', 'walk on uneven terrain' -> 'walk'); None when no rule
    matches."""
    d = re.sub(r"\([^)]*\)", "", desc).strip().lower()
    for action, words in _RULES:
        if any(w in d for w in words):
            return action
    return None


@dataclass(frozen=True)
class StepClip:
    """One clip of one action: ``xyz_m (T,19,3)`` world metres (z up, floor at 0) and its characteristic
    frames ``frames (L,)``."""

    name: str
    subject: int
    action: str
    xyz_m: np.ndarray
    frames: np.ndarray


def _index() -> dict[tuple[int, int], str]:
    out = fdata.cmu_index()
    root = bvh.mocap_root()
    if root is not None:
        for f in sorted(Path(root).rglob("cmu_index.csv")):
            with open(f, newline="", encoding="utf-8", errors="replace") as fh:
                for row in csv.DictReader(fh):
                    try:
                        out.setdefault((int(row["Subject"]), int(row["Trial #"])), row["Motion Description"])
                    except (KeyError, TypeError, ValueError):
                        continue
    return out


def load_pool(fps: float = fdata.TARGET_FPS, subjects: tuple[int, ...] | None = None) -> list[StepClip]:
    """Every CMU clip under the mocap root with an action in ``ACTIONS`` (and a subject in ``subjects``),
    annotated with its characteristic frames. [] when no mocap is found."""
    idx = _index()
    names = list(JOINTS)
    out = []
    for p in bvh.list_clips():
        st = fdata.cmu_subject_trial(p.stem)
        if st is None or st not in idx or (subjects is not None and st[0] not in subjects):
            continue
        action = action_of_description(idx[st])
        if action is None:
            continue
        x = bvh.load_clip(p, fps).xyz_m
        if len(x) < 2 * fps or not np.isfinite(x).all():
            continue
        fr = annotate(x, names, fps)
        if len(fr) == 0:
            A, _ = articulation(x, names, fps)
            fr = np.array([int(np.argmax(A))])
        out.append(StepClip(p.stem, st[0], action, x.astype(np.float32), fr))
    return out


def split_pool(pool: list[StepClip]) -> dict[str, list[StepClip]]:
    """train / val / test clips. val: every fifth characteristic frame (from the third) of the training
    subjects' clips with at least two, so every action has validation steps even where one clip holds it;
    train: the other frames; test: the clips of ``TEST_SUBJECTS``."""
    out: dict[str, list[StepClip]] = {"train": [], "val": [], "test": []}
    for c in pool:
        if c.subject in TEST_SUBJECTS:
            out["test"].append(c)
        elif c.subject in TRAIN_SUBJECTS:
            i = np.arange(len(c.frames))
            val = (i % 5 == 2) if len(c.frames) >= 2 else np.zeros(len(i), bool)
            out["train"].append(StepClip(c.name, c.subject, c.action, c.xyz_m, c.frames[~val]))
            if val.any():
                out["val"].append(StepClip(c.name, c.subject, c.action, c.xyz_m, c.frames[val]))
    for a in ACTIONS:  # an action whose clips hold too few frames to split validates on its train frames
        if not any(c.action == a for c in out["val"]):
            out["val"] += [c for c in out["train"] if c.action == a]
    return out


def load_db_poses(fps: float = 25.0) -> np.ndarray:
    """The uncorrelated 3D database: every frame at ``fps`` of every clip of ``DB_SUBJECTS`` (any action),
    (N,19,3) metres, pelvis at the origin in x, y (z: height above the floor)."""
    out = []
    for p in bvh.list_clips():
        st = fdata.cmu_subject_trial(p.stem)
        if st is None or st[0] not in DB_SUBJECTS:
            continue
        x = bvh.load_clip(p, fps).xyz_m
        x = x[np.isfinite(x).all((1, 2))]
        out.append(x)
    if not out:
        raise InputError(
            "no 3D database poses: the CMU mocap of subjects "
            f"{DB_SUBJECTS} is not under the mocap root (ROOMCAP_SHARED/data/motion)"
        )
    X = np.concatenate(out).astype(np.float32)
    X[..., :2] -= X[:, JOINTS.index("pelvis"), None, :2]
    return X


# ----------------------------------------------------------------------------- composite activities


@dataclass(frozen=True)
class Composite:
    """S sequences of L steps: ``actions (S,L)`` indices into ``ACTIONS``, ``xyz_m (S,L,19,3)`` the step
    poses in the room, ``xy_px (S,L,19,2)`` their 2D detections in camera ``cam (S,)`` of ``rig`` (NaN =
    missed), ``clips (S,L)`` the clip of each step, ``states (S,L)`` the hidden state of each step in
    ``script_chain(script).states`` (None where unknown)."""

    actions: np.ndarray
    xyz_m: np.ndarray
    xy_px: np.ndarray
    cam: np.ndarray
    rig: object
    clips: np.ndarray
    states: np.ndarray | None = None


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _facing(x: np.ndarray) -> float:
    """Heading (rad) of a pose (19,3): the direction perpendicular to the hips, z up (eq. 3.8's frame)."""
    lh, rh = fdata.hip_indices(list(JOINTS))
    R, _ = fdata.norm_frame(x[None].astype(np.float64), lh, rh)
    fwd = R[0].T @ np.array([0.0, 1.0, 0.0])  # body +y in world
    return float(np.arctan2(fwd[1], fwd[0]))


@dataclass(frozen=True)
class Chain:
    """A script as a Markov chain over hidden states: ``states (S,)`` names, ``action (S,)`` the action index
    each state shows (its label), ``T (S,S)`` transition probabilities (rows sum to 1), ``pi (S,)`` the
    first step's distribution. For "markov" the states are the actions themselves; for "stations" a state is
    an action at a place ("sink:drink") or a walk to a place ("walk:sink"), so a label can stand for several
    states that place tells apart."""

    states: tuple[str, ...]
    action: np.ndarray
    T: np.ndarray
    pi: np.ndarray


def script_chain(script: str) -> Chain:
    """The chain of a script (``SCRIPTS``)."""
    if script == "markov":
        A = len(ACTIONS)
        T = np.zeros((A, A))
        for a, nxt in SCRIPT.items():
            for b, p in nxt.items():
                T[ACTIONS.index(a), ACTIONS.index(b)] = p
        return Chain(ACTIONS, np.arange(A), T / T.sum(1, keepdims=True), np.full(A, 1.0 / A))
    if script != "stations":
        raise ValueError(f"script must be one of {SCRIPTS}, got {script!r}")
    states = tuple(STATION_SCRIPT) + tuple(f"walk:{p}" for p in STATIONS)
    ix = {s: i for i, s in enumerate(states)}
    T = np.zeros((len(states), len(states)))
    for s, nxt in STATION_SCRIPT.items():
        here = s.split(":")[0]
        for t, p in nxt.items():
            if t == "leave":
                for q, pq in LEAVE[here].items():
                    T[ix[s], ix[f"walk:{q}"]] += p * pq
            else:
                T[ix[s], ix[t]] += p
    for q, nxt in ARRIVE.items():
        for t, p in nxt.items():
            T[ix[f"walk:{q}"], ix[t]] = p
    action = np.array(
        [ACTIONS.index(s.split(":")[1] if not s.startswith("walk:") else "walk") for s in states]
    )
    return Chain(states, action, T / T.sum(1, keepdims=True), np.full(len(states), 1.0 / len(states)))


def chain_forecast(
    chain: Chain, acts: np.ndarray, m: int, last_state: np.ndarray | None = None
) -> np.ndarray:
    """The best possible forecast of a script: the probabilities (S,m,A) of the next m actions after the
    observed actions ``acts (S,N)`` (forward filtering over the hidden states: from the labels alone), or,
    with ``last_state (S,)``, after that known hidden state (labels and place)."""
    A = len(ACTIONS)
    emit = np.eye(A)[chain.action]  # (states, A)
    if last_state is None:
        b = chain.pi[None] * emit[:, acts[:, 0]].T
        for k in range(1, acts.shape[1]):
            b = (b / b.sum(1, keepdims=True)) @ chain.T * emit[:, acts[:, k]].T
        b = b / b.sum(1, keepdims=True)
    else:
        b = np.eye(len(chain.states))[last_state]
    out = []
    for _ in range(m):
        b = b @ chain.T
        out.append(b @ emit)
    return np.stack(out, 1)


def _by_action(pool: list[StepClip]) -> dict[str, list[StepClip]]:
    by_action = {a: [c for c in pool if c.action == a] for a in ACTIONS}
    missing = [a for a in ACTIONS if not by_action[a]]
    if missing:
        raise InputError(
            f"compose: no clip of the actions {missing} in this pool; the CMU mocap of "
            "cmu-more (single/13, single/14) and cmu-bvh-subjects01-07 is needed"
        )
    return by_action


def _place(c: StepClip, rng: np.random.Generator, pos, heading: float) -> np.ndarray:
    """One of the clip's characteristic poses, its pelvis over ``pos`` (x, y), facing ``heading``."""
    pel = JOINTS.index("pelvis")
    x = c.xyz_m[int(c.frames[rng.integers(len(c.frames))])].astype(np.float64)
    x = x - np.array([x[pel, 0], x[pel, 1], 0.0])
    x = x @ _yaw(heading - _facing(x)).T
    return x + np.array([pos[0], pos[1], 0.0])


def compose_stations(pool: list[StepClip], n: int, length: int, seed: int = 0) -> tuple:
    """n sequences of the "stations" script -> (actions (n,L), xyz_m (n,L,19,3), clip names (n,L), states
    (n,L) indices into ``script_chain("stations").states``).

    The states follow the chain; a step at a place stands at its floor point (s.d. ``STATION_NOISE_M``) facing
    its heading (s.d. ``STATION_TURN_RAD``); a walk to a place stands ``WALK_PART`` of the way from the last
    place there (a first step that walks comes from another place drawn alike), facing the place it walks
    to (s.d. ``WALK_TURN_RAD``)."""
    rng = np.random.default_rng(seed)
    by_action = _by_action(pool)
    ch = script_chain("stations")
    acts = np.zeros((n, length), np.int64)
    states = np.zeros((n, length), np.int64)
    X = np.zeros((n, length, len(JOINTS), 3), np.float32)
    names = np.empty((n, length), dtype=object)
    for s in range(n):
        for k, (st, pos, heading, c) in enumerate(_station_walk(ch, by_action, length, rng)):
            X[s, k] = _place(c, rng, pos, heading)
            acts[s, k], states[s, k], names[s, k] = ch.action[st], st, c.name
    return acts, X, names, states


def compose(
    pool: list[StepClip], n: int, length: int, seed: int = 0, room_half_m: float = 1.8, script: str = "markov"
) -> tuple:
    """n scripted sequences of ``length`` steps -> (actions (n,L), xyz_m (n,L,19,3), clip names (n,L)).

    ``script`` "markov": the actions follow ``SCRIPT``, each step placed by a random walk over the floor
    (``room_half_m``) with a random heading, independent of what follows; "stations": ``compose_stations``."""
    if script == "stations":
        return compose_stations(pool, n, length, seed)[:3]
    if script != "markov":
        raise ValueError(f"script must be one of {SCRIPTS}, got {script!r}")
    rng = np.random.default_rng(seed)
    by_action = _by_action(pool)
    acts = np.zeros((n, length), np.int64)
    X = np.zeros((n, length, len(JOINTS), 3), np.float32)
    names = np.empty((n, length), dtype=object)
    for s in range(n):
        a = ACTIONS[rng.integers(len(ACTIONS))]
        pos = rng.uniform(-room_half_m, room_half_m, 2)
        heading = rng.uniform(-np.pi, np.pi)
        for k in range(length):
            if k:
                nxt = SCRIPT[a]
                a = str(rng.choice(list(nxt), p=np.array(list(nxt.values())) / sum(nxt.values())))
                heading += rng.normal(0, 0.6)
                pos = np.clip(pos + rng.normal(0, 0.6, 2), -room_half_m, room_half_m)
            c = by_action[a][rng.integers(len(by_action[a]))]
            X[s, k] = _place(c, rng, pos, heading)
            acts[s, k] = ACTIONS.index(a)
            names[s, k] = c.name
    return acts, X, names


def default_rig():
    """The observing rig of the composite sequences: six cameras on a 4 m ring at 2.2 m, mild distortion."""
    return ring_rig(6, 4.0, height_m=2.2, distortion=True, jitter_m=0.1, seed=3)


DEFAULT_RENDER = RenderConfig(
    noise_px=2.0,
    missed_joint_rate=0.03,
    missed_detection_rate=0.03,
    occlusion_people=True,
    occlusion_furniture=False,
    shuffle=False,
)


def observe(xyz_m: np.ndarray, rig=None, seed: int = 0, render: RenderConfig = DEFAULT_RENDER) -> tuple:
    """Render the step poses (S,L,19,3) into one camera per sequence -> (xy_px (S,L,19,2) NaN = missed,
    cam (S,)). Each step is a frame of its own (the person alone, so people occlusion is self-occlusion
    by the body's capsules)."""
    rig = rig or default_rig()
    S, L = xyz_m.shape[:2]
    rng = np.random.default_rng(seed)
    cam = rng.integers(len(rig), size=S)
    out = np.full((S, L, len(JOINTS), 2), np.nan, np.float32)
    for c in range(len(rig)):
        sel = np.flatnonzero(cam == c)
        if len(sel) == 0:
            continue
        gt = xyz_m[sel].reshape(-1, 1, len(JOINTS), 3)
        scene = Scene(
            gt, np.array([0]), 25.0, ring_room(4.0), ("composite",), SceneConfig(n_people=1, seed=seed)
        )
        det, gidx, _, _ = render_camera(scene, rig, c, render, 0.0, 0.0, np.random.default_rng([seed, c]))
        xy = np.full((len(gt), len(JOINTS), 2), np.nan, np.float32)
        rows, cols = np.nonzero(gidx == 0)
        xy[rows] = det.xy_px[rows, cols]
        out[sel] = xy.reshape(len(sel), L, len(JOINTS), 2)
    return out, cam


def make_composite(
    pool: list[StepClip], n: int, length: int, seed: int = 0, rig=None, script: str = "markov"
) -> Composite:
    rig = rig or default_rig()
    if script == "stations":
        acts, X, names, states = compose_stations(pool, n, length, seed)
    else:  # markov: the state is the action
        acts, X, names = compose(pool, n, length, seed, script=script)
        states = acts
    xy, cam = observe(X, rig, seed)
    return Composite(acts, X, xy, cam, rig, names, states)


# ----------------------------------------------------------------------------- continuous activities


@dataclass(frozen=True)
class Activity:
    """One person's continuous composite activity: ``xyz_m (T,19,3)`` at ``fps`` with its steps: ``labels``
    (L,), ``start_s``/``end_s`` (L,) the label ranges, ``char_frame`` (L,) each step's characteristic
    frame."""

    xyz_m: np.ndarray
    fps: float
    labels: tuple[str, ...]
    start_s: np.ndarray
    end_s: np.ndarray
    char_frame: np.ndarray
    states: tuple[str, ...] = ()  # "stations": each step's hidden state (script_chain("stations").states)


def compose_continuous(
    pool: list[StepClip],
    length: int,
    seed: int = 0,
    fps: float = fdata.TARGET_FPS,
    around_s: float = 1.0,
    blend_s: float = 0.4,
    start_xy: tuple[float, float] = (0.0, 0.0),
    script: str = "markov",
) -> Activity:
    """A scripted sequence of ``length`` steps as one motion: each step is its clip's frames within
    ``around_s`` of a characteristic frame. ``script`` "markov" (``SCRIPT``): each step turned and moved so
    that it starts where and facing how the previous one ended, the two cross-faded over ``blend_s``
    (linear blend of the aligned poses). "stations" (the states of ``script_chain("stations")``, placed as
    ``compose_stations`` places them): each step turned and moved so that its characteristic pose stands at
    its state's place facing its heading, and the person glides from one step's last pose to the next's
    first (``_glide``: at most ``GLIDE_SPEED_M_S``, at least ``blend_s``). A label covers its step from the
    middle of the blend (or glide) before it to the middle of the one after it."""
    if script == "stations":
        return _continuous_stations(pool, length, seed, fps, around_s, blend_s)
    if script != "markov":
        raise ValueError(f"script must be one of {SCRIPTS}, got {script!r}")
    rng = np.random.default_rng(seed)
    by_action = {a: [c for c in pool if c.action == a] for a in ACTIONS}
    pel = JOINTS.index("pelvis")
    nb = max(1, int(round(blend_s * fps)))
    a = ACTIONS[rng.integers(len(ACTIONS))]
    out = np.zeros((0, len(JOINTS), 3))
    labels, starts, chars = [], [], []
    for k in range(length):
        if k:
            nxt = SCRIPT[a]
            a = str(rng.choice(list(nxt), p=np.array(list(nxt.values())) / sum(nxt.values())))
        if not by_action[a]:
            raise InputError(f"compose_continuous: no clip of the action {a!r} in this pool")
        c = by_action[a][rng.integers(len(by_action[a]))]
        f = int(c.frames[rng.integers(len(c.frames))])
        w = int(round(around_s * fps))
        lo, hi = max(0, f - w), min(len(c.xyz_m), f + w + 1)
        seg = c.xyz_m[lo:hi].astype(np.float64)
        if len(out):
            prev = out[-1]
            turn = _facing(prev) - _facing(seg[0])
            seg = (seg - np.array([seg[0, pel, 0], seg[0, pel, 1], 0.0])) @ _yaw(turn).T
            seg = seg + np.array([prev[pel, 0], prev[pel, 1], 0.0])
            n = min(nb, len(seg) - 1, len(out) - 1)
            wgt = np.linspace(0, 1, n + 2)[1:-1][:, None, None]
            # the blended frames replace the previous tail and the segment's head
            out[-n:] = (1 - wgt) * out[-n:] + wgt * seg[:n]
            start = len(out) - n // 2
            chars.append(len(out) - n + (f - lo))
            out = np.concatenate([out, seg[n:]])
        else:
            seg = seg - np.array([seg[0, pel, 0] - start_xy[0], seg[0, pel, 1] - start_xy[1], 0.0])
            start = 0
            chars.append(f - lo)
            out = seg
        labels.append(a)
        starts.append(start)
    st = np.asarray(starts, np.float64) / fps
    en = np.append(st[1:], len(out) / fps)
    return Activity(out.astype(np.float32), fps, tuple(labels), st, en, np.asarray(chars, np.int64))


GLIDE_SPEED_M_S = 1.2  # the glide between two steps of the "stations" script (a walking pace)


def _station_target(state: str, last: str | None, rng: np.random.Generator) -> tuple:
    """Where a step of the "stations" script stands and faces (see :func:`compose_stations`) -> (pos (2,),
    heading, the last place visited)."""
    place, what = state.split(":")
    if place == "walk":
        to = np.asarray(STATIONS[what][0])
        if last is None:
            last = str(rng.choice([q for q in STATIONS if q != what]))
        frm = np.asarray(STATIONS[last][0])
        pos = frm + rng.uniform(*WALK_PART) * (to - frm) + rng.normal(0, WALK_NOISE_M, 2)
        d = to - pos
        return pos, float(np.arctan2(d[1], d[0])) + rng.normal(0, WALK_TURN_RAD), last
    xy, h = STATIONS[place]
    return np.asarray(xy) + rng.normal(0, STATION_NOISE_M, 2), h + rng.normal(0, STATION_TURN_RAD), place


def _station_walk(ch: Chain, by_action: dict, length: int, rng: np.random.Generator):
    """The stations script's steps, a walk of ``length`` states along the chain ``ch``: per step (state,
    floor point, heading, a clip of the state's action). Lazy, so the caller's own draws for a step come
    between this step's and the next's."""
    st = int(rng.choice(len(ch.states), p=ch.pi))
    last = None
    for k in range(length):
        if k:
            st = int(rng.choice(len(ch.states), p=ch.T[st]))
        pos, heading, last = _station_target(ch.states[st], last, rng)
        a = ACTIONS[int(ch.action[st])]
        yield st, pos, heading, by_action[a][rng.integers(len(by_action[a]))]


def _glide(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """n frames (n,J,3) from pose a to pose b: the pelvis along the straight line on the floor, the heading
    by the shorter turn, the body cross-faded in its own facing frame."""
    pel = JOINTS.index("pelvis")
    ha, hb = _facing(a), _facing(b)
    pa, pb = a[pel, :2], b[pel, :2]
    la = (a - np.array([pa[0], pa[1], 0.0])) @ _yaw(-ha).T
    lb = (b - np.array([pb[0], pb[1], 0.0])) @ _yaw(-hb).T
    turn = (hb - ha + np.pi) % (2 * np.pi) - np.pi
    out = []
    for w in np.linspace(0, 1, n + 2)[1:-1]:
        p = (1 - w) * pa + w * pb
        out.append(((1 - w) * la + w * lb) @ _yaw(ha + w * turn).T + np.array([p[0], p[1], 0.0]))
    return np.asarray(out).reshape(n, len(JOINTS), 3)


def _continuous_stations(
    pool, length: int, seed: int, fps: float, around_s: float, blend_s: float
) -> Activity:
    """``compose_continuous`` for the "stations" script (see there)."""
    rng = np.random.default_rng(seed)
    by_action = _by_action(pool)
    ch = script_chain("stations")
    pel = JOINTS.index("pelvis")
    nb = max(1, int(round(blend_s * fps)))
    out = np.zeros((0, len(JOINTS), 3))
    labels, states, starts, chars = [], [], [], []
    for st, pos, heading, c in _station_walk(ch, by_action, length, rng):
        a = ACTIONS[int(ch.action[st])]
        f = int(c.frames[rng.integers(len(c.frames))])
        w = int(round(around_s * fps))
        lo, hi = max(0, f - w), min(len(c.xyz_m), f + w + 1)
        seg = c.xyz_m[lo:hi].astype(np.float64)
        x = seg[f - lo]
        seg = (seg - np.array([x[pel, 0], x[pel, 1], 0.0])) @ _yaw(heading - _facing(x)).T
        seg = seg + np.array([pos[0], pos[1], 0.0])
        if len(out):
            dist = float(np.linalg.norm(seg[0, pel, :2] - out[-1, pel, :2]))
            n = max(nb, int(np.ceil(dist / GLIDE_SPEED_M_S * fps)))
            gl = _glide(out[-1], seg[0], n)
            start = len(out) + n // 2
            chars.append(len(out) + n + (f - lo))
            out = np.concatenate([out, gl, seg])
        else:
            start = 0
            chars.append(f - lo)
            out = seg
        labels.append(a)
        states.append(ch.states[st])
        starts.append(start)
    st_s = np.asarray(starts, np.float64) / fps
    en = np.append(st_s[1:], len(out) / fps)
    return Activity(
        out.astype(np.float32), fps, tuple(labels), st_s, en, np.asarray(chars, np.int64), tuple(states)
    )


def activity_session(
    pool: list[StepClip],
    root,
    n_people: int = 2,
    length: int = 8,
    seed: int = 0,
    rig=None,
    script: str = "markov",
) -> tuple[object, Path]:
    """A session folder in the layout the pipeline writes, for people doing continuous composite
    activities (``compose_continuous`` of ``script``): ``calib/rig.toml``, ``keypoints/<cam>.npz``
    (rendered with ``DEFAULT_RENDER``'s faults), ``track/tracks.npz`` (the ground truth as the track file,
    ids 0..P-1) and ``labels.csv`` (the label file of ``forecast behaviour``). "markov": each person's
    activity is centred on a ring of 1.2 m; "stations": the people move between the room's places
    (``STATIONS``, the rig's frame). -> (SessionLayout, label file path)."""
    rig = rig or default_rig()
    acts = []
    for p in range(n_people):
        a = compose_continuous(pool, length, seed * 100 + p, script=script)
        x = a.xyz_m.copy()
        if script == "markov":
            ang = 2 * np.pi * p / max(n_people, 1)
            x[..., :2] += np.array([1.2 * np.cos(ang), 1.2 * np.sin(ang)]) - x[
                :, JOINTS.index("pelvis"), :2
            ].mean(0)
        acts.append((a, x))
    T = max(len(x) for _, x in acts)
    gt = np.full((T, n_people, len(JOINTS), 3), np.nan)
    for p, (_, x) in enumerate(acts):
        gt[: len(x), p] = x
    scene = Scene(
        gt,
        np.arange(n_people),
        acts[0][0].fps,
        ring_room(4.0),
        tuple(f"activity{p}" for p in range(n_people)),
        SceneConfig(n_people=n_people, seed=seed),
    )
    lay = write_session(scene, render(scene, rig, DEFAULT_RENDER.replace(shuffle=True, seed=seed)), rig, root)
    xyz = gt.astype(np.float32)
    seen = np.isfinite(xyz[..., 0])
    tf = TrackFile(
        fps=scene.fps,
        frame_index=np.arange(T),
        t_ns=(np.arange(T) * 1e9 / scene.fps).astype(np.int64),
        track_id=np.arange(n_people),
        joint_names=JOINTS,
        parents=np.asarray(PARENTS),
        xyz_m=xyz,
        confidence=seen.astype(np.float32),
        std_m=np.where(seen, 0.0, np.nan).astype(np.float32),
        flags=seen.astype(np.uint8),
        source="forecast.behaviour.data.activity_session (ground truth)",
    )
    lay.tracks.parent.mkdir(parents=True, exist_ok=True)
    tf.save(lay.tracks)
    lines = ["track_id,start_s,end_s,label"]
    for p, (a, _) in enumerate(acts):
        lines += [
            f"{p},{s:.3f},{e:.3f},{lab}"
            for s, e, lab in zip(a.start_s, a.end_s - 1e-3, a.labels, strict=True)
        ]
    lab = Path(root) / "labels.csv"
    lab.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return lay, lab
