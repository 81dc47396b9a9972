"""Board detection over all cameras of a recording, in parallel, with a cache and a diagnosis.

A recording is a folder holding one video per camera (``cam_0.mp4`` ...), one sub-folder of images
per camera, or a flat folder of images whose names start with the camera name and end with the
frame number (``left01.jpg``, ``right01.jpg``). Frames of different cameras with the same index are
taken as simultaneous (synchronised recording; image files: the number in the name).

Detections per camera: ``frames`` (F,) frame indices, ``xy_px`` (F,N,2) board points in pixels
(N = ``board.n_points``, NaN = not seen). They are cached in ``<cache_dir>/<camera>.npz`` keyed by
the source files (path, size, mtime) and the board's detection key (kind, grid, dictionary, legacy,
inverted; not the physical sizes), so a rerun after fixing a square size does not detect again, and
the diagnosis of a wrong dictionary caches the detections made with the right one.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.calibrate.boards import DICTIONARIES, Board, CalibrationError
from roomcap.core.errors import FormatError
from roomcap.core.fileio import check_schema, load_npz, npz_str, save_npz, schema_tag
from roomcap.core.progress import Progress

log = logging.getLogger(__name__)

__all__ = [
    "Source",
    "CameraDetections",
    "discover_recording",
    "detect_frame",
    "detect_all",
    "diagnose_board",
    "VIDEO_EXT",
    "IMAGE_EXT",
]

VIDEO_EXT = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")
IMAGE_EXT = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
DET_SCHEMA = "board_detections"
DET_VERSION = 1


@dataclass(frozen=True)
class Source:
    """One camera's input: a video file, or image files with their frame indices."""

    name: str
    paths: tuple[Path, ...]
    frame_ids: tuple[int, ...] | None = None  # images only

    @property
    def is_video(self) -> bool:
        return self.frame_ids is None

    def signature(self) -> str:
        parts = []
        for p in self.paths:
            try:
                st = p.stat()
                parts.append(f"{p.resolve()}:{st.st_size}:{st.st_mtime_ns}")
            except OSError:
                parts.append(f"{p}:missing")
        return "|".join(parts)


_NUM = re.compile(r"^(.*?)(\d+)$")


def _images_with_ids(files: Sequence[Path]) -> tuple[tuple[Path, ...], tuple[int, ...]]:
    files = sorted(files)
    nums = [_NUM.match(f.stem) for f in files]
    if all(nums) and len({int(m.group(2)) for m in nums}) == len(files):
        pairs = sorted(zip((int(m.group(2)) for m in nums), files, strict=False))
        return tuple(p for _, p in pairs), tuple(i for i, _ in pairs)
    return tuple(files), tuple(range(len(files)))


def discover_recording(folder: str | os.PathLike) -> list[Source]:
    """Cameras of a recording folder (see module doc), sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(
            f"Recording folder {folder} does not exist or is not a folder. Give the folder that "
            "holds one video (or one image folder) per camera."
        )
    entries = sorted(folder.iterdir())
    videos = [p for p in entries if p.is_file() and p.suffix.lower() in VIDEO_EXT]
    if videos:
        return [Source(p.stem, (p,)) for p in videos]
    sources = []
    for d in entries:
        if d.is_dir():
            imgs = [p for p in d.iterdir() if p.suffix.lower() in IMAGE_EXT]
            vids = [p for p in d.iterdir() if p.suffix.lower() in VIDEO_EXT]
            if imgs:
                paths, ids = _images_with_ids(imgs)
                sources.append(Source(d.name, paths, ids))
            elif len(vids) == 1:
                sources.append(Source(d.name, (vids[0],)))
    if sources:
        return sources
    # flat folder of images: group by the name before the trailing number (left01.jpg -> "left")
    groups: dict[str, list[tuple[int, Path]]] = {}
    skipped = []
    for p in entries:
        if p.suffix.lower() not in IMAGE_EXT:
            continue
        m = _NUM.match(p.stem)
        if not m:
            skipped.append(p.name)
            continue
        groups.setdefault(m.group(1).rstrip("_-") or "cam", []).append((int(m.group(2)), p))
    if skipped:
        log.warning("ignoring %d image(s) without a frame number in the name: %s", len(skipped), skipped[:5])
    if not groups:
        raise CalibrationError(
            f"No videos ({', '.join(VIDEO_EXT)}) or images found in {folder}. Put one video per "
            "camera in the folder (cam_0.mp4, cam_1.mp4, ...) or one image folder per camera."
        )
    return [
        Source(k, tuple(p for _, p in sorted(v)), tuple(i for i, _ in sorted(v)))
        for k, v in sorted(groups.items())
    ]


# ----------------------------------------------------------------------------- single-frame detection


def _gray(img: np.ndarray) -> np.ndarray:
    import cv2

    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _charuco_detector(board: Board):
    import cv2

    params = cv2.aruco.DetectorParameters()
    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 1
    return cv2.aruco.CharucoDetector(board.cv_board(), cp, params)


def _aruco_detector(board: Board):
    import cv2

    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX  # marker corners are the points here
    return cv2.aruco.ArucoDetector(board.cv_dictionary(), params)


def detect_frame(board: Board, image: np.ndarray, min_points: int = 6, _det=None) -> np.ndarray:
    """Board points (N,2) in pixels in one image (H,W) or (H,W,3); NaN rows where not seen.
    Fewer than ``min_points`` points (or collinear ones) count as not seen (all NaN)."""
    import cv2

    g = _gray(image)
    if board.inverted:
        g = 255 - g
    N = board.n_points
    out = np.full((N, 2), np.nan)
    if board.kind == "charuco":
        det = _det or _charuco_detector(board)
        cc, ci, _, _ = det.detectBoard(g)
        if ci is None or len(ci) < min_points:
            return out
        out[ci.ravel()] = cc.reshape(-1, 2)
    elif board.kind == "checkerboard":
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        ok, c = cv2.findChessboardCorners(g, board.grid, flags=flags)
        if ok:
            c = cv2.cornerSubPix(
                g, c, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 0.01)
            )
        else:
            ok, c = cv2.findChessboardCornersSB(
                g, board.grid, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            )
        if not ok:
            return out
        c = c.reshape(-1, 2).astype(np.float64)
        # the ordering of a checkerboard is ambiguous by 180 degrees: start at the top-left-most end
        if (c[-1] - c[0]).sum() < 0:
            c = c[::-1]
        out[:] = c
    else:
        det = _det or _aruco_detector(board)
        corners, ids, _ = det.detectMarkers(g)
        if ids is None:
            return out
        n_markers = N // 4
        for c, i in zip(corners, ids.ravel(), strict=False):
            if 0 <= i < n_markers:
                out[4 * i : 4 * i + 4] = c.reshape(4, 2)
    seen = np.isfinite(out[:, 0])
    if seen.sum() < min_points or _collinear(board.object_points()[seen]):
        out[:] = np.nan
    return out


def _collinear(obj: np.ndarray) -> bool:
    if len(obj) < 3:
        return True
    d = obj[:, :2] - obj[:, :2].mean(0)
    s = np.linalg.svd(d, compute_uv=False)
    return bool(s[1] < 1e-6 * max(s[0], 1e-12))


# ----------------------------------------------------------------------------- per-camera detection


@dataclass(frozen=True)
class CameraDetections:
    """One camera's detections. frames: (F,) frame indices; xy_px: (F,N,2), NaN = not seen."""

    name: str
    size_wh: tuple[int, int]
    frames: np.ndarray
    xy_px: np.ndarray
    n_frames_read: int = 0
    stride: int = 1

    def __post_init__(self) -> None:
        if self.xy_px.ndim != 3 or self.xy_px.shape[2] != 2 or self.xy_px.shape[0] != self.frames.shape[0]:
            raise ValueError(
                f"CameraDetections: xy_px must be (F,N,2) with F={self.frames.shape[0]}, "
                f"got {self.xy_px.shape}"
            )

    @property
    def n_points_seen(self) -> np.ndarray:
        return np.isfinite(self.xy_px[..., 0]).sum(1)

    def seen_frames(self, min_points: int = 1) -> np.ndarray:
        return self.frames[self.n_points_seen >= min_points]

    def save(self, path: Path, key: dict[str, str]) -> None:
        save_npz(
            path,
            {
                "schema": schema_tag(DET_SCHEMA, DET_VERSION),
                "name": self.name,
                "size_wh": np.array(self.size_wh),
                "frames": self.frames,
                "xy_px": self.xy_px.astype(np.float32),
                "n_frames_read": self.n_frames_read,
                "stride": self.stride,
                **{f"key_{k}": v for k, v in key.items()},
            },
        )

    @classmethod
    def load(cls, path: Path, key: dict[str, str] | None = None) -> CameraDetections | None:
        """The cached detections, or None when absent or made from other inputs."""
        if not path.exists():
            return None
        try:
            d = load_npz(path)
            check_schema(d.get("schema"), DET_SCHEMA, (DET_VERSION,), path)
        except FormatError as e:
            log.warning("ignoring detection cache %s: %s", path, e)
            return None
        if key is not None and any(
            f"key_{k}" not in d or npz_str(d, f"key_{k}") != v for k, v in key.items()
        ):
            return None
        return cls(
            npz_str(d, "name"),
            tuple(int(v) for v in d["size_wh"]),
            d["frames"].astype(np.int64),
            d["xy_px"].astype(np.float64),
            int(d["n_frames_read"]),
            int(d["stride"]),
        )


def _frames(src: Source, stride: int):
    """Yield (frame_index, image) for every stride-th frame; raise CalibrationError if unreadable."""
    import cv2

    if src.is_video:
        path = src.paths[0]
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise CalibrationError(
                f"Camera '{src.name}': cannot open video {path} (missing, corrupt or a codec OpenCV cannot "
                "read). "
                f"Check the file plays; re-encode it with `ffmpeg -i {path.name} -c:v libx264 -pix_fmt "
                "yuv420p "
                f"{path.stem}_h264.mp4`, or remove it from the recording folder to calibrate the other "
                "cameras."
            )
        i = 0
        try:
            while True:
                if i % stride:
                    if not cap.grab():
                        break
                else:
                    ok, img = cap.read()
                    if not ok:
                        break
                    yield i, img
                i += 1
        finally:
            cap.release()
        if i == 0:
            raise CalibrationError(
                f"Camera '{src.name}': video {path} opened but no frame could be decoded. "
                "Re-encode it (ffmpeg -c:v libx264) or record again."
            )
    else:
        for k, (p, fid) in enumerate(zip(src.paths, src.frame_ids or (), strict=False)):
            if k % stride:
                continue
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise CalibrationError(
                    f"Camera '{src.name}': cannot read image {p}. Remove or replace the file."
                )
            yield fid, img


def _frame_count(src: Source) -> int:
    import cv2

    if not src.is_video:
        return len(src.paths)
    cap = cv2.VideoCapture(str(src.paths[0]))
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
    cap.release()
    return max(n, 0)


def detect_camera(
    board: Board, src: Source, max_frames: int = 1000, min_points: int = 6, progress: Progress | None = None
) -> CameraDetections:
    """Detect the board in (a sample of at most ``max_frames``) frames of one camera."""
    n_total = _frame_count(src)
    stride = max(1, -(-n_total // max_frames)) if n_total else 1
    det = _charuco_detector(board) if board.kind == "charuco" else None
    if board.kind == "aruco_grid":
        det = _aruco_detector(board)
    frames, xys = [], []
    size = None
    n_read = 0
    todo = max(1, -(-n_total // stride))
    for fid, img in _frames(src, stride):
        wh = (img.shape[1], img.shape[0])
        if size is None:
            size = wh
        elif wh != size:
            raise CalibrationError(
                f"Camera '{src.name}': the resolution changed mid-recording, from {size[0]}x{size[1]} to "
                f"{wh[0]}x{wh[1]} at frame {fid} ({src.paths[0] if src.is_video else src.paths[n_read]}). "
                "Intrinsics hold for one resolution only: fix the camera's resolution and record again, or "
                "cut "
                "the recording so that each file has one resolution."
            )
        n_read += 1
        frames.append(fid)
        xys.append(detect_frame(board, img, min_points=min_points, _det=det))
        if progress is not None:
            progress(src.name, n_read, todo)
    if size is None:
        raise CalibrationError(f"Camera '{src.name}': no frames could be read from {src.paths[0]}.")
    xy = np.stack(xys) if xys else np.zeros((0, board.n_points, 2))
    return CameraDetections(src.name, size, np.asarray(frames, np.int64), xy, n_read, stride)


def cache_key(board: Board, src: Source, max_frames: int, min_points: int) -> dict[str, str]:
    return {
        "board": board.detection_key(),
        "source": src.signature(),
        "max_frames": str(max_frames),
        "min_points": str(min_points),
    }


def detect_all(
    board: Board,
    sources: Sequence[Source],
    cache_dir: str | os.PathLike | None = None,
    max_frames: int = 1000,
    min_points: int = 6,
    workers: int | None = None,
    progress: Progress | None = None,
) -> dict[str, CameraDetections]:
    """Detect the board in every camera, one thread per camera (OpenCV releases the GIL).

    Cached results are reused; each camera's result is written as soon as it is done, so an error in one
    camera (unopenable video, resolution change) loses nothing of the others. Errors of all cameras are
    collected into one CalibrationError."""
    cache = Path(cache_dir) if cache_dir is not None else None
    out: dict[str, CameraDetections] = {}
    errors: dict[str, str] = {}
    lock = threading.Lock()

    def one(src: Source) -> None:
        key = cache_key(board, src, max_frames, min_points)
        path = cache / f"{src.name}.npz" if cache else None
        if path is not None:
            hit = CameraDetections.load(path, key)
            if hit is not None:
                log.info("camera %s: detections loaded from cache %s", src.name, path)
                if progress is not None:
                    progress(src.name, 1, 1)
                with lock:
                    out[src.name] = hit
                return
        try:
            d = detect_camera(board, src, max_frames, min_points, progress)
        except CalibrationError as e:
            with lock:
                errors[src.name] = str(e)
            return
        if path is not None:
            d.save(path, key)
        log.info(
            "camera %s: board seen in %d of %d frames read", src.name, len(d.seen_frames()), d.n_frames_read
        )
        with lock:
            out[src.name] = d

    n_workers = workers or min(len(sources), max(1, os.cpu_count() or 1) * 2)
    with ThreadPoolExecutor(max_workers=max(1, n_workers)) as ex:
        list(ex.map(one, sources))
    if errors:
        done = sorted(out)
        raise CalibrationError(
            "\n".join(errors[k] for k in sorted(errors))
            + (f"\n(Detections of {done} are cached and will be reused.)" if done and cache else "")
        )
    return {s.name: out[s.name] for s in sources}


# ----------------------------------------------------------------------------- diagnosis


_DICT_TIERS = (
    (
        "DICT_4X4_50",
        "DICT_5X5_50",
        "DICT_6X6_50",
        "DICT_7X7_50",
        "DICT_APRILTAG_16h5",
        "DICT_APRILTAG_25h9",
        "DICT_ARUCO_MIP_36h12",
    ),
    ("DICT_APRILTAG_36h11", "DICT_ARUCO_ORIGINAL", "DICT_APRILTAG_36h10"),
)


@dataclass(frozen=True)
class Diagnosis:
    """Which board settings match the images. ``board`` is the suggested board (None if nothing matched)."""

    board: Board | None
    message: str
    markers_by_dictionary: dict[str, int]


def _sample_images(src: Source, n: int) -> list[np.ndarray]:
    import cv2

    imgs = []
    if src.is_video:
        cap = cv2.VideoCapture(str(src.paths[0]))
        if not cap.isOpened():
            return []
        total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or n
        for fi in np.linspace(0, max(total - 1, 0), n).astype(int):
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(fi))
            ok, img = cap.read()
            if ok:
                imgs.append(_gray(img))
        cap.release()
    else:
        for p in [
            src.paths[i] for i in np.linspace(0, len(src.paths) - 1, min(n, len(src.paths))).astype(int)
        ]:
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is not None:
                imgs.append(img)
    return imgs


def diagnose_grid(board: Board, sources: Sequence[Source], n_frames: int = 6) -> str | None:
    """A sentence when the images show markers of the board's dictionary that its declared grid cannot
    hold (the printed board has more squares than the board file says); None when they fit."""
    import cv2

    if not board.uses_markers:
        return None
    n_markers = len(board.cv_board().getIds())
    det = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)),
        cv2.aruco.DetectorParameters(),
    )
    seen: set[int] = set()
    for s in sources:
        for im in _sample_images(s, n_frames):
            _, ids, _ = det.detectMarkers(_gray(255 - im if board.inverted else im))
            seen |= set() if ids is None else {int(i) for i in ids.ravel()}
    beyond = sorted(i for i in seen if i >= n_markers)
    if len(beyond) < 2:  # one stray id can be a misread; several are markers the file does not declare
        return None
    return (
        f"markers of {board.dictionary} with ids up to {max(beyond)} are visible, but the declared "
        f"{board.grid[0]}x{board.grid[1]} squares hold only {n_markers} markers (ids 0-{n_markers - 1}): "
        "the printed board has more squares than the board file says. Count the squares (columns x rows) "
        "on the printed board and set them in the board file"
    )


def diagnose_board(board: Board, sources: Sequence[Source], n_frames: int = 6) -> Diagnosis:
    """Find the board settings that match the images when the given ones detect nothing.

    Tries every predefined ArUco dictionary in normal and inverted colours (one candidate search,
    ``detectMarkersMultiDict``), then for ChArUco the legacy-pattern switch; for checkerboards the
    inner-corner count off by one (squares given instead of corners) and inverted colours."""
    imgs = [im for s in sources for im in _sample_images(s, n_frames)]
    if not imgs:
        return Diagnosis(None, "no frame could be read for the diagnosis", {})
    if board.kind == "checkerboard":
        return _diagnose_checkerboard(board, imgs)
    found = _diagnose_switches(board, imgs)
    if found is not None:
        return found
    counts = _marker_counts(imgs)
    if not counts:
        return Diagnosis(
            None,
            f"no ArUco marker of any predefined dictionary was found in {len(imgs)} sample frames "
            "(in normal or inverted colours): the board is not visible, out of focus or too small",
            counts,
        )
    return _diagnose_dictionary(board, imgs, counts)


def _diagnose_checkerboard(board: Board, imgs: list[np.ndarray]) -> Diagnosis:
    """The checkerboard (inner corners off by one either way, normal or inverted) found in most frames."""
    cands = []
    for dx in (0, -1, 1):
        for dy in (0, -1, 1):
            for inv in (False, True):
                g = (board.grid[0] + dx, board.grid[1] + dy)
                if min(g) >= 2:
                    cands.append(board.replace(grid=g, inverted=inv))
    best, best_n = None, 0
    for b in cands:
        n = sum(np.isfinite(detect_frame(b, im)[:, 0]).any() for im in imgs[:: max(1, len(imgs) // 6)])
        if n > best_n:
            best, best_n = b, n
    if best is None:
        return Diagnosis(
            None,
            f"no checkerboard with about {board.grid} inner corners found in {len(imgs)} sample frames",
            {},
        )
    return Diagnosis(
        best,
        f"the images show a checkerboard with inner_corners = {list(best.grid)}, "
        f"inverted = {str(best.inverted).lower()}",
        {},
    )


def _diagnose_switches(board: Board, imgs: list[np.ndarray]) -> Diagnosis | None:
    """Cheap first: the declared dictionary with the colour (and ChArUco legacy-pattern) switches toggled;
    None when no switch makes the board appear."""
    if board.kind == "charuco":
        quick = [
            board.replace(inverted=i, legacy_pattern=lg)
            for i in (board.inverted, not board.inverted)
            for lg in (board.legacy_pattern, not board.legacy_pattern)
        ]
    else:
        quick = [board.replace(inverted=not board.inverted)]
    for b in quick[1:] if board.kind == "charuco" else quick:
        n = sum(np.isfinite(detect_frame(b, im)[:, 0]).any() for im in imgs)
        if n >= max(1, len(imgs) // 10):
            return Diagnosis(
                b,
                "the images match "
                + b.describe()
                + " (change: "
                + ", ".join(
                    f"{k} = {getattr(b, k)!r}".replace("True", "true").replace("False", "false")
                    for k in ("inverted", "legacy_pattern")
                    if getattr(b, k) != getattr(board, k)
                )
                + ")",
                {},
            )
    return None


def _marker_counts(imgs: list[np.ndarray]) -> dict[str, int]:
    """Markers found per ``"<dictionary>|<inverted>"``, trying the dictionaries tier by tier (see
    ``_DICT_TIERS``) on frames downscaled to at most 960 px, and stopping at the first tier that finds any."""
    import cv2

    # Within a family (DICT_5X5_50/100/250/1000) the
    # smaller dictionaries are the first markers of the larger ones, and boards number their markers
    # from 0: trying the smallest of each family finds the family cheaply; the expensive families
    # (36-bit AprilTag, ARUCO_ORIGINAL) only when the cheap ones find nothing.
    small = []
    for im in imgs:
        s = min(1.0, 960.0 / max(im.shape))
        small.append(cv2.resize(im, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else im)
    counts: dict[str, int] = {}
    for tier in _DICT_TIERS:
        for inv in (False, True):
            for name in tier:
                det = cv2.aruco.ArucoDetector(
                    cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)),
                    cv2.aruco.DetectorParameters(),
                )
                n = 0
                for im in small:
                    _, ids, _ = det.detectMarkers(255 - im if inv else im)
                    n += 0 if ids is None else len(ids)
                if n:
                    counts[f"{name}|{inv}"] = n
            if counts:
                break
        if counts:
            break
    return counts


def _diagnose_dictionary(board: Board, imgs: list[np.ndarray], counts: dict[str, int]) -> Diagnosis:
    """The board settings of the dictionary family with the most markers, the ChArUco pattern checked on the
    full frames."""
    best = max(counts, key=lambda k: counts[k])
    fam, inv_s = best.split("|")
    inv = inv_s == "True"
    prefix = fam.rsplit("_", 1)[0]
    family = [n for n in DICTIONARIES if n.rsplit("_", 1)[0] == prefix and n.rsplit("_", 1)[1].isdigit()]
    n_markers = len(board.cv_board().getIds()) if board.uses_markers else 0
    if board.dictionary in family:
        dname = board.dictionary
    elif family:
        # the smallest dictionary of the family with enough markers for the declared board
        fits = sorted((int(n.rsplit("_", 1)[1]), n) for n in family if int(n.rsplit("_", 1)[1]) >= n_markers)
        dname = fits[0][1] if fits else fam
    else:
        dname = fam
    same_bits = sorted(family) if len(family) > 1 else []
    cand = board.replace(dictionary=dname, inverted=inv)
    if board.kind == "charuco":
        scores = {}
        for legacy in (False, True):
            b = cand.replace(legacy_pattern=legacy)
            det = _charuco_detector(b)
            scores[legacy] = sum(
                int(np.isfinite(detect_frame(b, im, min_points=4, _det=det)[:, 0]).sum()) for im in imgs
            )
        cand = cand.replace(legacy_pattern=scores[True] > scores[False])
        if max(scores.values()) == 0:
            return Diagnosis(
                None,
                f"markers of {dname} (inverted={inv}) are visible but no ChArUco corner could be "
                f"interpolated with the declared {board.grid[0]}x{board.grid[1]} squares and marker/square "
                "ratio in either pattern: check squares and marker_size_m",
                counts,
            )
    changes = [
        f"{k} = {v!r}"
        for k, v in (
            ("dictionary", cand.dictionary),
            ("inverted", cand.inverted),
            ("legacy_pattern", cand.legacy_pattern),
        )
        if getattr(cand, k) != getattr(board, k)
    ]
    msg = (
        "the images match "
        + cand.describe()
        + (f" (change: {', '.join(changes)})" if changes else " (the declared settings)")
    )
    if len(same_bits) > 1:
        msg += (
            f"; {', '.join(d for d in same_bits if d != cand.dictionary)} share these first markers: "
            "use the one the board was printed with"
        )
    return Diagnosis(cand, msg, counts)
