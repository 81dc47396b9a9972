"""Offline synchronisation of recordings made without a shared clock (``capture-run sync``).

Each camera's time offset (and, for long recordings, its drift) against a reference camera from
the cross-correlation of 2D keypoint speeds: people move at the same instants in every view, so
the per-frame keypoint speed, summed over people and normalised, is a signal that all cameras
share up to a time shift (the approach of Pose2Sim's ``synchronization`` step, made multi-person
by matching people frame to frame). Audio is the alternative when videos carry a track
(``audio_offset``; the seed's kitchen recordings were aligned by audio).

Convention written into ``session.toml`` ``[sync.cameras.<cam>]``: camera frame ``i`` shows the
instant of reference frame ``i + offset_frames``, i.e. ``t_ref_ns = t_cam_ns + offset_ns
(+ drift_ppm * 1e-6 * (t_cam_ns - t_cam0_ns))``.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from roomcap.capture.session import SESSION_SCHEMA, SESSION_VERSION, SessionLayout
from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import load_toml, save_toml
from roomcap.core.timebase import frame_rate_hz

log = logging.getLogger(__name__)


class CameraKeypoints(Protocol):
    """What the sync reads from a camera's ``keypoints/<cam>.npz``: a ``keypoints.detections.Detections``."""

    xy_px: np.ndarray  # (T,P,J,2)
    t_ns: np.ndarray  # (T,)
    frame_index: np.ndarray  # (T,)


# Reads ``keypoints/<cam>.npz``: ``keypoints.detections.Detections.load``, handed in from above (the keypoints
# stage sits above capture in the stage order).
LoadKeypoints = Callable[[Path], CameraKeypoints]


# ----------------------------------------------------------------------------- keypoint input


def read_openpose_folder(folder: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """OpenPose ``*.json`` frames in one folder -> xy (T,P,J,2) NaN-padded, score (T,P,J).

    Frames are ordered by the last number in the file name (never by directory order).
    """
    folder = Path(folder)
    files = [p for p in folder.glob("*.json")]
    if not files:
        raise FormatError(folder, None, "no OpenPose .json files in this folder.")

    def frame_no(p: Path) -> int:
        nums = re.findall(r"\d+", p.stem)
        if not nums:
            raise FormatError(p, None, "file name holds no frame number.")
        return int(nums[-1])

    files.sort(key=frame_no)
    people_per_frame = []
    J = 0
    for p in files:
        try:
            data = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise FormatError(p, None, f"is not valid JSON ({e}).") from None
        pts = []
        for person in data.get("people", []):
            k = np.asarray(person.get("pose_keypoints_2d", []), np.float64).reshape(-1, 3)
            J = max(J, len(k))
            pts.append(k)
        people_per_frame.append(pts)
    T = len(files)
    P = max(1, max(len(f) for f in people_per_frame))
    xy = np.full((T, P, J, 2), np.nan)
    score = np.zeros((T, P, J))
    for t, pts in enumerate(people_per_frame):
        for p, k in enumerate(pts):
            valid = k[:, 2] > 0
            xy[t, p, : len(k)][valid] = k[valid, :2]
            score[t, p, : len(k)] = k[:, 2]
    return xy, score


def _match_people(prev: np.ndarray, cur: np.ndarray) -> np.ndarray:
    """Reorder cur (P,J,2) so that person p continues prev's person p (Hungarian on mean joint distance)."""
    from scipy.optimize import linear_sum_assignment

    diff = np.linalg.norm(prev[:, None] - cur[None], axis=-1)  # (P,P,J)
    valid = np.isfinite(diff)
    n = valid.sum(-1)
    d = np.where(n > 0, np.where(valid, diff, 0.0).sum(-1) / np.maximum(n, 1), 1e9)
    rows, cols = linear_sum_assignment(d)
    order = np.arange(len(cur))
    order[rows] = cols
    return cur[order]


def keypoint_speed(xy: np.ndarray, smooth_sigma: float = 1.0, per_joint: bool = True) -> np.ndarray:
    """Per-frame motion signal from 2D keypoints. xy: (T,P,J,2) px, NaN = missing.

    People are matched frame to frame (Hungarian on joint distance). ``per_joint``: returns (T,J),
    each joint's speed (px/frame) summed over people, a signal that needs no identity across views;
    else (T,) the sum over people of their median joint speed. NaN where unknown.
    """
    xy = np.asarray(xy, np.float64)
    if xy.ndim != 4 or xy.shape[-1] != 2:
        raise ValueError(f"keypoint_speed: expected xy (T,P,J,2), got {xy.shape}")
    T = xy.shape[0]
    tracked = xy.copy()
    for t in range(1, T):
        if xy.shape[1] > 1:
            tracked[t] = _match_people(tracked[t - 1], xy[t])
    v = np.linalg.norm(np.diff(tracked, axis=0), axis=-1)  # (T-1,P,J)
    if per_joint:
        sig = np.nansum(v, axis=1)
        sig[np.all(np.isnan(v), axis=1)] = np.nan
        sig = np.concatenate([np.full((1, v.shape[2]), np.nan), sig])
        if smooth_sigma > 0:
            sig = np.stack([_nan_gaussian(sig[:, j], smooth_sigma) for j in range(sig.shape[1])], axis=1)
        return sig
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per_person = np.nanmedian(v, axis=2)  # (T-1,P)
            sig = np.nansum(per_person, axis=1)
            sig[np.all(np.isnan(per_person), axis=1)] = np.nan
    sig = np.concatenate([[np.nan], sig])
    if smooth_sigma > 0:
        sig = _nan_gaussian(sig, smooth_sigma)
    return sig


def _nan_gaussian(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    m = np.isfinite(x)
    num = gaussian_filter1d(np.where(m, x, 0.0), sigma, mode="constant")
    den = gaussian_filter1d(m.astype(float), sigma, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[den < 0.3] = np.nan
    return out


# ----------------------------------------------------------------------------- correlation


def lagged_correlation(ref: np.ndarray, sig: np.ndarray, max_lag: int, min_overlap: int = 10) -> np.ndarray:
    """Pearson correlation of ref[t + L] with sig[t], L in [-max_lag, max_lag] (NaN-aware) -> (2*max_lag+1,).

    ref, sig: (T,) or (T,K) multichannel (e.g. per-joint speeds): the per-channel correlations are
    averaged, weighted by their number of valid samples.
    """
    ref = np.asarray(ref, np.float64)
    sig = np.asarray(sig, np.float64)
    if ref.ndim == 2:
        if sig.ndim != 2 or sig.shape[1] != ref.shape[1]:
            raise ValueError(
                f"lagged_correlation: ref {ref.shape} and sig {sig.shape} need the same channels K"
            )
        # channel weight: how much data it has (a joint seen rarely counts little)
        w = np.minimum(np.isfinite(ref).sum(0), np.isfinite(sig).sum(0)).astype(np.float64)
        out = np.full(2 * max_lag + 1, np.nan)
        for k, L in enumerate(range(-max_lag, max_lag + 1)):
            t0, t1 = max(0, -L), min(len(sig), len(ref) - L)
            if t1 - t0 < min_overlap:
                continue
            a, b = ref[t0 + L : t1 + L], sig[t0:t1]
            m = np.isfinite(a) & np.isfinite(b)
            cnt = m.sum(0)
            a = np.where(m, a, 0.0)
            b = np.where(m, b, 0.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                ma, mb = a.sum(0) / cnt, b.sum(0) / cnt
                da, db = np.where(m, a - ma, 0.0), np.where(m, b - mb, 0.0)
                c = (da * db).sum(0) / np.sqrt((da * da).sum(0) * (db * db).sum(0))
            ok = (cnt >= min_overlap) & np.isfinite(c)
            if ok.any() and w[ok].sum() > 0:
                out[k] = float((c[ok] * w[ok]).sum() / w[ok].sum())
        return out
    out = np.full(2 * max_lag + 1, np.nan)
    for k, L in enumerate(range(-max_lag, max_lag + 1)):
        # pairs (ref[t+L], sig[t]) for all t where both exist
        t0 = max(0, -L)
        t1 = min(len(sig), len(ref) - L)
        if t1 - t0 < min_overlap:
            continue
        a = ref[t0 + L : t1 + L]
        b = sig[t0:t1]
        m = np.isfinite(a) & np.isfinite(b)
        if m.sum() < min_overlap:
            continue
        a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
        den = np.sqrt((a * a).sum() * (b * b).sum())
        if den > 0:
            out[k] = (a * b).sum() / den
    return out


# How far to trust an offset, from the correlation curve over all lags (capture-run sync prints it):
#   peak        Pearson correlation at the chosen lag (1 = the signals are the same up to the shift);
#   peak_ratio  peak / the highest other local maximum more than PEAK_LOBE_FRAMES away (how much the
#               chosen lag stands out: a ratio near 1 means another lag explains the motion as well).
# "good": peak >= 0.2 and ratio >= 2; "fair": peak >= 0.1 and ratio >= 1.3; else "poor" (do not use
# without a check: record a clap or a jump seen by all cameras, or sync by audio). The peak of 2D
# keypoint-speed correlations is low even when right (views see different 2D motion): on the Pose2Sim
# session-2024 trials peaks of 0.22-0.53 with no other positive lag recover known shifts of +7/-12
# frames exactly (tests/test_capture_offline_sync.py), so the ratio weighs more than the peak.
PEAK_LOBE_FRAMES = 3
TRUST_GOOD = (0.2, 2.0)
TRUST_FAIR = (0.1, 1.3)


@dataclass(frozen=True)
class LagEstimate:
    offset_frames: float  # camera frame i shows reference frame i + offset_frames
    correlation: float  # peak Pearson correlation
    lag_int: int
    second_peak: float = float("nan")  # highest other local maximum of the correlation curve
    overlap: int = 0  # frames correlated at the chosen lag

    @property
    def peak_ratio(self) -> float:
        """peak / second peak (inf when no other lag correlates positively)."""
        if not np.isfinite(self.second_peak) or self.second_peak <= 0:
            return float("inf")
        return float(self.correlation / self.second_peak)

    @property
    def trust(self) -> str:
        """ "good" | "fair" | "poor", see TRUST_GOOD / TRUST_FAIR."""
        for name, (c, r) in (("good", TRUST_GOOD), ("fair", TRUST_FAIR)):
            if self.correlation >= c and self.peak_ratio >= r:
                return name
        return "poor"


def second_peak(c: np.ndarray, k: int, lobe: int = PEAK_LOBE_FRAMES) -> float:
    """The highest local maximum of the curve ``c`` more than ``lobe`` samples from index ``k``."""
    c = np.where(np.isfinite(c), c, -np.inf)
    best = -np.inf
    for i in range(len(c)):
        if abs(i - k) <= lobe or not np.isfinite(c[i]):
            continue
        left = c[i - 1] if i > 0 else -np.inf
        right = c[i + 1] if i + 1 < len(c) else -np.inf
        if c[i] >= left and c[i] >= right:
            best = max(best, c[i])
    return float(best) if np.isfinite(best) else float("nan")


def estimate_lag(ref: np.ndarray, sig: np.ndarray, max_lag: int, subframe: bool = True) -> LagEstimate:
    """Offset of ``sig`` against ``ref``: peak of their lagged correlation (parabolic sub-frame fit)."""
    c = lagged_correlation(ref, sig, max_lag)
    if not np.isfinite(c).any():
        raise ValueError(
            "no overlap with enough valid samples to correlate; lengthen the recording or the "
            "keypoint tracks, or raise --max-lag-s"
        )
    k = int(np.nanargmax(c))
    lag = k - max_lag
    frac = 0.0
    if subframe and 0 < k < len(c) - 1 and np.isfinite(c[k - 1]) and np.isfinite(c[k + 1]):
        den = c[k - 1] - 2 * c[k] + c[k + 1]
        if den < 0:
            frac = float(np.clip(0.5 * (c[k - 1] - c[k + 1]) / den, -0.5, 0.5))
    overlap = min(len(sig), len(ref) - lag) - max(0, -lag)
    lobe = max(PEAK_LOBE_FRAMES, len(c) // 50)
    return LagEstimate(lag + frac, float(c[k]), lag, second_peak(c, k, lobe), int(overlap))


def estimate_offset_drift(
    ref: np.ndarray, sig: np.ndarray, max_lag: int, window: int, step: int | None = None
) -> tuple[float, float, float]:
    """Offset and drift: windowed lags fitted as offset(t) = a + b t -> (a frames, b frames/frame, corr).

    The global lag is found first; windows then search ±3 frames around it.
    """
    g = estimate_lag(ref, sig, max_lag)
    step = step or max(1, window // 2)
    ts, lags, ws = [], [], []
    for s in range(0, max(1, len(sig) - window + 1), step):
        seg = np.full_like(sig, np.nan)
        seg[s : s + window] = sig[s : s + window]
        c = lagged_correlation(ref, seg, max_lag, min_overlap=max(10, window // 2))
        lo = max(0, g.lag_int + max_lag - 3)
        hi = min(len(c), g.lag_int + max_lag + 4)
        sub = c[lo:hi]
        if not np.isfinite(sub).any():
            continue
        k = lo + int(np.nanargmax(sub))
        frac = 0.0
        if 0 < k < len(c) - 1 and np.isfinite(c[k - 1 : k + 2]).all():
            den = c[k - 1] - 2 * c[k] + c[k + 1]
            if den < 0:
                frac = float(np.clip(0.5 * (c[k - 1] - c[k + 1]) / den, -0.5, 0.5))
        ts.append(s + window / 2)
        lags.append(k - max_lag + frac)
        ws.append(max(c[k], 1e-3))
    if len(ts) < 4:
        return g.offset_frames, 0.0, g.correlation
    ts_a, lags_a = np.asarray(ts), np.asarray(lags)
    (b, a0), cov = np.polyfit(ts_a, lags_a, 1, w=np.asarray(ws), cov="unscaled")
    resid = lags_a - (a0 + b * ts_a)
    se_b = float(np.sqrt(max(cov[0, 0], 0.0)) * max(np.std(resid), 1e-3) / max(np.sqrt(np.mean(ws)), 1e-3))
    if abs(b) < 2 * se_b:  # no significant drift: keep the whole-recording estimate
        return g.offset_frames, 0.0, g.correlation
    # anchor at the whole-recording estimate (its lag holds at the middle of the overlap)
    t_mid = 0.5 * (len(sig) - 1)
    return float(g.offset_frames - b * t_mid), float(b), g.correlation


# ----------------------------------------------------------------------------- audio


def audio_offset(
    ref_path: str | os.PathLike, path: str | os.PathLike, max_lag_s: float = 2.0, env_rate: float = 1000.0
) -> tuple[float, float]:
    """Offset in seconds (t_ref = t_cam + offset, video clocks) from the audio envelopes of two videos.

    Returns (offset_s, correlation). Needs PyAV (``pip install 'roomcap[audio]'``); raises ValueError
    when a video has no audio track. The audio start of each file relative to its video is respected.
    """
    off, est = audio_estimate(ref_path, path, max_lag_s, env_rate)
    return off, est.correlation


def audio_estimate(
    ref_path: str | os.PathLike, path: str | os.PathLike, max_lag_s: float = 2.0, env_rate: float = 1000.0
) -> tuple[float, LagEstimate]:
    """:func:`audio_offset` with the whole :class:`LagEstimate` (peak, second peak, trust)."""
    env_r, a0_r = audio_envelope(ref_path, env_rate)
    env_s, a0_s = audio_envelope(path, env_rate)
    est = estimate_lag(env_r, env_s, int(max_lag_s * env_rate))
    # envelope sample i of the camera is at video time a0_s + i / rate; same for the reference
    return est.offset_frames / env_rate + a0_s - a0_r, est


def audio_envelope(
    path: str | os.PathLike, env_rate: float = 1000.0, rate: int = 16000
) -> tuple[np.ndarray, float]:
    """Mono amplitude envelope at ``env_rate`` Hz of a video's first audio track -> (envelope (N,), start_s).

    ``start_s``: audio start minus video start of the file, seconds.
    """
    try:
        import av
    except ImportError:
        raise ValueError("reading audio needs PyAV: pip install 'roomcap[audio]' (package 'av')") from None
    path = Path(path)
    try:
        container = av.open(str(path))
    except Exception as e:
        raise ValueError(f"{path}: cannot be opened for audio ({e})") from None
    with container:
        if not container.streams.audio:
            raise ValueError(f"{path}: no audio track; sync this camera by keypoints instead")
        st = container.streams.audio[0]
        v0 = 0.0
        if container.streams.video and container.streams.video[0].start_time is not None:
            vs = container.streams.video[0]
            v0 = float(vs.start_time * vs.time_base)
        a0 = float(st.start_time * st.time_base) if st.start_time is not None else 0.0
        resampler = av.AudioResampler(format="flt", layout="mono", rate=rate)
        chunks = []
        for frame in container.decode(st):
            for out in resampler.resample(frame):
                chunks.append(out.to_ndarray().reshape(-1))
        for out in resampler.resample(None):
            chunks.append(out.to_ndarray().reshape(-1))
    if not chunks:
        raise ValueError(f"{path}: the audio track is empty")
    x = np.abs(np.concatenate(chunks))
    hop = max(1, int(round(rate / env_rate)))
    n = len(x) // hop
    return x[: n * hop].reshape(n, hop).mean(axis=1), a0 - v0


def sync_audio(
    root: str | os.PathLike,
    videos: dict[str, str],
    reference: str | None = None,
    max_lag_s: float = 2.0,
    write: bool = True,
) -> dict:
    """Offsets of videos with audio tracks (camera -> video path); written into session.toml ``[sync]``."""
    names = list(videos)
    ref = reference or sorted(names)[0]
    if ref not in videos:
        raise ValueError(f"reference camera {ref!r} not in {names}")
    res = {"method": "audio-envelope-xcorr", "reference": ref, "cameras": {}}
    for n in names:
        if n == ref:
            res["cameras"][n] = {"offset_s": 0.0, "offset_ns": 0, "correlation": 1.0, "trust": "reference"}
            continue
        off_s, est = audio_estimate(videos[ref], videos[n], max_lag_s)
        res["cameras"][n] = {
            "offset_s": off_s,
            "offset_ns": int(round(off_s * 1e9)),
            "correlation": est.correlation,
            **_quality(est),
        }
    if write:
        _write_sync(root, res)
    return res


def _quality(est: LagEstimate) -> dict:
    """The trust fields written per camera into session.toml [sync.cameras.<cam>]."""
    ratio = est.peak_ratio
    return {
        "second_peak": est.second_peak if np.isfinite(est.second_peak) else -1.0,
        "peak_ratio": ratio if np.isfinite(ratio) else 99.0,
        "overlap_frames": est.overlap,
        "trust": est.trust,
    }


def _write_sync(root, res: dict) -> None:
    layout = SessionLayout(root)
    if layout.session_toml.exists():
        meta = load_toml(layout.session_toml)
    else:
        meta = {"schema": f"{SESSION_SCHEMA}/{SESSION_VERSION}", "status": "imported"}
    meta["sync"] = res
    save_toml(layout.session_toml, meta)


# ----------------------------------------------------------------------------- sessions


def estimate_offsets(
    signals: dict[str, np.ndarray],
    fps: float,
    reference: str | None = None,
    max_lag_s: float = 2.0,
    drift: bool = False,
    window_s: float = 10.0,
) -> dict:
    """Offsets of every camera against ``reference`` from per-frame speed signals (cam -> (T_c,))."""
    names = list(signals)
    ref = reference or sorted(names)[0]
    if ref not in signals:
        raise ValueError(f"reference camera {ref!r} not in {names}")
    max_lag = max(1, int(round(max_lag_s * fps)))
    out = {"method": "keypoint-speed-xcorr", "reference": ref, "fps": fps, "cameras": {}}
    for n in names:
        quality: dict = {"trust": "reference"}
        if n == ref:
            a, b, corr = 0.0, 0.0, 1.0
        else:
            e = estimate_lag(signals[ref], signals[n], max_lag)
            quality = _quality(e)
            a, b, corr = e.offset_frames, 0.0, e.correlation
            if drift:
                a, b, corr = estimate_offset_drift(signals[ref], signals[n], max_lag, int(window_s * fps))
        r = {
            "offset_frames": a,
            "offset_s": a / fps,
            "offset_ns": int(round(a / fps * 1e9)),
            "correlation": corr,
            **quality,
        }
        if drift:
            r["drift_ppm"] = b * 1e6
        if quality["trust"] == "poor":
            log.warning(
                "%s: offset %+.1f frames is poorly supported (correlation %.2f, peak ratio %.2f against %s); "
                "check it (a clap or jump seen by all cameras) before relying on it",
                n,
                a,
                corr,
                quality["peak_ratio"],
                ref,
            )
        out["cameras"][n] = r
    return out


POSE2SIM_OUTPUT = "roomcap"  # reprocess writes a foreign-layout session's outputs here (pipeline.runner)


def detections_layout(root: str | os.PathLike) -> SessionLayout:
    """The layout holding a session folder's ``keypoints/<cam>.npz``, found as ``reprocess`` places them:
    the folder itself (this project's sessions), else ``<folder>/roomcap`` (a Pose2Sim trial: ``videos/``
    + ``calibration/``, whose outputs ``reprocess`` writes beside its inputs)."""
    own = SessionLayout(root)
    nested = SessionLayout(Path(root) / POSE2SIM_OUTPUT)
    return nested if not own.detection_cameras() and nested.detection_cameras() else own


def sync_session(
    root: str | os.PathLike,
    reference: str | None = None,
    max_lag_s: float = 2.0,
    drift: bool = False,
    openpose_dirs: dict[str, str] | None = None,
    fps: float | None = None,
    write: bool = True,
    *,
    load_keypoints: LoadKeypoints | None = None,
) -> dict:
    """Estimate offsets for a session folder and write them into ``session.toml`` ``[sync]``.

    The speeds come from ``openpose_dirs`` (``{cam: folder of OpenPose JSON}``) when given, else from the
    session's ``keypoints/<cam>.npz``, read with ``load_keypoints``."""
    layout = SessionLayout(root)
    meta = load_toml(layout.session_toml) if layout.session_toml.exists() else None
    found = detections_layout(root)  # a Pose2Sim trial's detections are in <trial>/roomcap/keypoints
    signals: dict[str, np.ndarray] = {}
    if openpose_dirs:
        for cam, d in openpose_dirs.items():
            xy, _ = read_openpose_folder(d)
            signals[cam] = keypoint_speed(xy)
    else:
        if load_keypoints is None:
            raise InputError(
                "reading keypoints/<cam>.npz needs the keypoints package: run the installed `capture-run` "
                "(entry point pipeline.live:main), or pass --openpose CAM=DIR ... or --audio."
            )
        cams = found.detection_cameras()
        if len(cams) < 2:
            raise FormatError(
                layout.keypoints_dir,
                None,
                f"found {len(cams)} keypoints/<cam>.npz (nor two in "
                f"{Path(root) / POSE2SIM_OUTPUT / 'keypoints'}, where reprocess writes a Pose2Sim trial's); "
                "sync needs two or more.",
                f"Run the keypoints stage first (reprocess {root} --stages keypoints), or pass --openpose "
                "CAM=DIR ...",
            )

        for cam in cams:
            det = load_keypoints(found.detections(cam))
            signals[cam] = keypoint_speed(det.xy_px)
            if fps is None and len(det.t_ns) > 2:
                fps = frame_rate_hz(det.t_ns, det.frame_index)
    if fps is None and meta is not None:
        vals = [c.get("fps_nominal") for c in meta.get("cameras", {}).values() if c.get("fps_nominal")]
        fps = float(vals[0]) if vals else None
    if fps is None:
        raise ValueError("frame rate unknown: pass --fps")
    res = estimate_offsets(signals, fps, reference, max_lag_s, drift)
    if write:
        _write_sync(root, res)
    return res
