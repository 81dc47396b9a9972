"""The 2D stage's settings (``KeypointPipelineConfig``) and its per-image result (``FrameResult``), read by
:class:`roomcap.keypoints.pipeline.KeypointPipeline`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from roomcap.keypoints.crops import PYRAMIDS
from roomcap.keypoints.runtime import RuntimeConfig


@dataclass(frozen=True)
class KeypointPipelineConfig:
    """Settings of the 2D stage. ``skeleton``: layout of the output (``"model"`` keeps the model's own).

    What each setting gave on the Pose2Sim demos when it was chosen is in BENCHMARKS.md ("2D keypoints");
    the presets in ``keypoints/models/sets.toml`` combine them."""

    model_set: str = "default"
    skeleton: str = "body19"
    max_people: int = 20
    det_score: float = 0.0  # 0 = the detector description's threshold
    # boxes scoring between this and det_score are kept only where less than half of each lies inside a
    # stronger box (people at the image border or small in a letterboxed frame score there). 0 = off
    det_score_weak: float = 0.2
    min_box_px: float = 24.0  # ignore boxes smaller than this (height, image px)
    box_padding: float = 0.0  # 0 = the pose description's value
    pose_presence: float = 0.25  # drop people whose pose score (BlazePose: person present; else mean) below
    refine_passes: int = 2  # top-down: pose passes on the box the previous pass's keypoints span
    min_box_iou: float = 0.3  # refine passes: keep the previous pose where the new one left its box (IoU)
    rotate: bool = True  # refine passes: rotate crops so the body is upright (hips -> shoulders vertical)
    antialias: bool = True  # top-down: crops that shrink > 2x are cut from a pyramid level
    # the pyramid's filter: "gaussian" (cv2.pyrDown, 5x5), "box" (2x2 means, cv2.resize INTER_AREA: about
    # 6x cheaper per level) or "mixed" (box levels, then one pyrDown for the level the crop is cut from: the
    # Gaussian's anti-aliasing at the crop, at a third of its cost for L = 2); BENCHMARKS.md "2D keypoints"
    pyramid: str = "gaussian"
    flip_test: bool | None = None  # average with the mirrored crop (2x pose cost); None: the description's
    # flip test: joints the two crops place more than this x the crop width apart are not averaged; each
    # person takes them from the crop with the higher score (merge_hypotheses); 0 = always average
    flip_agree: float = 0.05
    flip_all_passes: bool = False  # flip test in every pose pass, not only the first and the last
    # top-down: no face points for people seen from behind (hide_face_from_behind); None: the description's
    hide_face_from_behind: bool | None = None
    back_view_facing: float = -0.15  # facing() below this = seen from behind (cos(yaw) < -0.3, yaw > 107 deg)
    model_roi: bool = False  # refine passes: the model's own ROI where it has one (BlazePose)
    # two poses of one image closer than this x the person's size (median over joints both see) are one
    # person found twice (an occluded person's crop returning the pose of the person in front); 0 = off
    duplicate_frac: float = 0.08
    # last pose pass: crop sizes (x padding) whose poses are merged (consensus: score-weighted mean of the
    # estimates near the median); (1.0,) = off
    tta_scales: tuple[float, ...] = (0.9, 1.0, 1.1)
    # duplicates: the body of one person is erased before the other is estimated again, filled with these
    # grey values (-1 = the median colour around the body); every fill is one more crop (_resolve_duplicates)
    erase_fills: tuple[float, ...] = (-1.0, 0.0)
    # top-down: people whose first-pass score is under this are estimated again on their detector box rotated
    # by 90, 180 and 270 degrees, the most confident reading placing the refine crops (_rotation_hypotheses:
    # bodies sideways or upside down). 0 = off
    rotation_weak: float = 0.5
    # tracked crops (videos: ``KeypointPipeline(images, streams)``): the detector runs every this many frames
    # of a camera (and when someone was lost, or nobody is tracked); in between, each person's crop is placed
    # by the previous frame's pose and only ``track_passes`` pose passes run (the last with tta_scales and
    # the flip test). 1 = the detector and the whole chain on every frame
    detect_every: int = 1
    track_passes: int = 1
    keep_maps: bool = False  # bottom-up: keep confidence maps + PAFs in the results
    # hands (keypoints.hand_model): the hand landmark model ("" = no hands) on a crop along each forearm, the
    # palm detector ("" = none) where the wrist is missing or the crop finds no hand; the output layout is
    # then ``<skeleton>_hands``
    hands: str = ""
    palm: str = ""
    hand_presence: float = 0.0  # the landmark model's hand presence under this = no hand; 0 = description's
    hand_joint_score: float = 0.2  # body joints (wrist, elbow, shoulder) under this score are not used
    hand_extend: float = 0.4  # the hand crop's centre: this x the forearm beyond the wrist
    hand_scale: float = 1.5  # the hand crop's side: this x the forearm (hand_model.arm_length)
    palm_region: float = 3.0  # the palm detector's region: this x the forearm, around the expected hand
    # tracked streams: the palm detector runs on a camera at most every this many frames (1 = every frame)
    palm_every: int = 1
    # tracked streams: a previous frame's hand places the crop of the hand of its side whose wrist is within
    # this x the arm's length of its root
    track_reach: float = 0.5
    # tracked streams: a wrist (within ``track_reach`` of the previous frame's) whose hand the last crops did
    # not find is cropped again after 1, 2, 4, ... frames, at most this many (exponential back-off), and the
    # palm detector looks there after 1, 2, 4, ... of its turns, at most this many; 1 = every frame / turn
    hand_retry_every: int = 1
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)

    def __post_init__(self) -> None:
        if self.pyramid not in PYRAMIDS:
            raise ValueError(
                f"KeypointPipelineConfig.pyramid must be one of {PYRAMIDS}, got {self.pyramid!r}"
            )


@dataclass
class FrameResult:
    """One image: boxes (P,5) x0,y0,x1,y1,score; xy_px (P,J,2) NaN = missing; score (P,J).

    For bottom-up models with ``keep_maps``: ``maps`` (H,W,C) float16 (confidence maps then PAF x/y pairs) and
    ``maps_to_img`` (2,3) affine from map pixels to image pixels.
    """

    boxes: np.ndarray
    xy_px: np.ndarray
    score: np.ndarray
    maps: np.ndarray | None = None
    maps_to_img: np.ndarray | None = None
