"""The camera model: a typed ``Camera`` and a ``CameraRig``, and the ``rig.toml`` file (CONTRACTS.md).

Conventions (written into every rig file, see ``CONVENTION``):

- pose is ``cam_from_world``: ``x_cam = R @ x_world + t``; world and ``t`` in metres;
- pixels have their origin at the centre of the top-left pixel, as in OpenCV;
- ``K`` is the OpenCV camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (no skew: OpenCV's
  distortion functions ignore ``K[0,1]``, so a non-zero skew is rejected rather than silently dropped);
- ``dist`` is in OpenCV order. ``model = "pinhole"``: 0, 4, 5, 8, 12 or 14 coefficients
  ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])`` (radial, tangential,
  rational, thin-prism and tilted-sensor terms); ``model = "fisheye"``: 4 coefficients
  ``(k1, k2, k3, k4)`` of OpenCV's ``cv2.fisheye`` (equidistant, Kannala-Brandt) model.

Shapes: N points, C cameras. NaN means "not observed" and passes through every function.
Points behind a camera (z_cam <= 0) project to NaN (OpenCV would return a mirrored pixel).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from roomcap.calibrate.camera_fields import PINHOLE_DIST_SIZES, validated_fields
from roomcap.core.config import check_keys
from roomcap.core.errors import FormatError, UnknownNameError
from roomcap.core.fileio import check_schema, load_toml, save_toml, schema_tag

__all__ = [
    "CONVENTION",
    "RIG_SCHEMA",
    "Camera",
    "CameraRig",
    "PINHOLE_DIST_SIZES",
    "rotation_from_rvec",
    "rvec_from_rotation",
]

RIG_SCHEMA = "rig"
RIG_VERSION = 1
CONVENTION = (
    "cam_from_world: x_cam = R @ x_world + t; metres; "
    "pixels with origin at the centre of the top-left pixel as in OpenCV"
)
CAMERA_KEYS = ("name", "size_wh", "model", "K", "dist", "R", "t")

# Iterative undistortion: OpenCV's default is 5 iterations, which leaves pixel-level errors on
# strongly distorted lenses; iterate to convergence instead.
_UNDISTORT_CRITERIA = (3, 100, 1e-12)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS


def rotation_from_rvec(rvec: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rodrigues vector (3,) -> rotation matrix (3,3) (same as ``cv2.Rodrigues``).

    >>> np.round(rotation_from_rvec([0, 0, np.pi / 2]), 6) + 0.0  # a quarter turn about z
    array([[ 0., -1.,  0.],
           [ 1.,  0.,  0.],
           [ 0.,  0.,  1.]])
    """
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * Kx + (1.0 - math.cos(theta)) * (Kx @ Kx)


def rvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3,3) -> Rodrigues vector (3,) (same as ``cv2.Rodrigues``).

    >>> np.round(rvec_from_rotation(rotation_from_rvec([0.1, -0.2, 0.3])), 9)
    array([ 0.1, -0.2,  0.3])
    """
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rvec.reshape(3)


# ----------------------------------------------------------------------------- Camera


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera. K: (3,3); dist: (n,) OpenCV order; R: (3,3), t: (3,) cam_from_world, metres.

    >>> Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])  # doctest: +ELLIPSIS
    Camera(name='c0', size_wh=(640, 480), model='pinhole', ..., center=[0.0, 0.0, -2.0])
    >>> Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240]])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: <input>: field 'camera 'c0'.K': has shape (2, 3), expected (3, 3). ...
    """

    name: str
    size_wh: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    model: str = "pinhole"
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        v = validated_fields(self.name, self.size_wh, self.K, self.dist, self.model, self.R, self.t)
        for k, val in v.items():
            object.__setattr__(self, k, val)

    # ---- derived geometry

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (3,), metres: ``-R^T t``.

        >>> Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2]).center
        array([ 0.,  0., -2.])
        """
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """Projection matrix (3,4) ``K [R | t]`` for undistorted pixels.

        >>> Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2]).P
        array([[500.,   0., 320., 640.],
               [  0., 500., 240., 480.],
               [  0.,   0.,   1.,   2.]])
        """
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def rvec(self) -> np.ndarray:
        """Rodrigues vector (3,) of R (for OpenCV / aniposelib)."""
        return rvec_from_rotation(self.R)

    @property
    def width(self) -> int:
        return self.size_wh[0]

    @property
    def height(self) -> int:
        return self.size_wh[1]

    # ---- projection

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points X: (N,3) metres -> pixels (N,2) with distortion (matches cv2.projectPoints /
        cv2.fisheye.projectPoints). NaN rows and points behind the camera give NaN.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> cam.project(np.array([[0.0, 0.0, 0.0], [0.2, -0.1, 0.0], [0.0, 0.0, -3.0]]))
        array([[320., 240.],
               [370., 215.],
               [ nan,  nan]])
        >>> cam.project(np.zeros(3))
        Traceback (most recent call last):
        ValueError: Camera.project: X must be (N,3), got (3,)
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"Camera.project: X must be (N,3), got {X.shape}")
        Xc = X @ self.R.T + self.t
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            zi = np.where(z > 0, 1.0 / np.where(z > 0, z, 1.0), np.nan)
        x = Xc[:, 0] * zi
        y = Xc[:, 1] * zi
        xd, yd = self.distort_normalized(x, y)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        return np.stack([fx * xd + cx, fy * yd + cy], axis=-1)

    def distort_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply the lens model to normalised coordinates (x/z, y/z) of any equal shape.

        >>> cam = Camera("c0", (640, 480), np.diag([500.0, 500.0, 1.0]), dist=[0.1, 0.0, 0.0, 0.0])
        >>> cam.distort_normalized(np.array([0.0, 0.5]), np.array([0.0, 0.0]))  # k1 = 0.1: x (1 + k1 r^2)
        (array([0.    , 0.5125]), array([0., 0.]))
        """
        d = self.dist
        if self.model == "fisheye":
            # OpenCV fisheye (cv::fisheye::projectPoints):
            # theta_d = theta (1 + k1 th^2 + k2 th^4 + k3 th^6 + k4 th^8)
            r = np.hypot(x, y)
            th = np.arctan(r)
            th2 = th * th
            thd = th * (1 + th2 * (d[0] + th2 * (d[1] + th2 * (d[2] + th2 * d[3]))))
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(r > 1e-8, thd / np.where(r > 1e-8, r, 1.0), 1.0)
            return x * scale, y * scale
        if d.size == 0:
            return x, y
        dd = np.zeros(14)
        dd[: d.size] = d
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = dd
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        a1 = 2 * x * y
        xd = x * radial + p1 * a1 + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
        yd = y * radial + p1 * (r2 + 2 * y * y) + p2 * a1 + s3 * r2 + s4 * r4
        if tx != 0.0 or ty != 0.0:
            M = _tilt_matrix(tx, ty)
            u = M[0, 0] * xd + M[0, 1] * yd + M[0, 2]
            v = M[1, 0] * xd + M[1, 1] * yd + M[1, 2]
            w = M[2, 0] * xd + M[2, 1] * yd + M[2, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                wi = np.where(w != 0, 1.0 / np.where(w != 0, w, 1.0), 1.0)
            xd, yd = u * wi, v * wi
        return xd, yd

    def undistort_px(self, xy_px: np.ndarray) -> np.ndarray:
        """Distorted pixels (...,2) -> ideal-pinhole pixels (...,2) with the same K. NaN passes through.

        >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
        >>> cam = Camera("c0", (640, 480), K, dist=[0.1, 0.0, 0.0, 0.0])
        >>> np.round(cam.undistort_px(np.array([[576.25, 240.0], [np.nan, np.nan]])), 6)  # 320 + 500 * 0.5125
        array([[570., 240.],
               [ nan,  nan]])
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise ValueError(f"Camera.undistort_px: xy_px must be (...,2), got {xy.shape}")
        out = np.full(xy.shape, np.nan)
        flat = xy.reshape(-1, 2)
        ok = np.all(np.isfinite(flat), axis=1)
        if self.dist.size == 0 or not np.any(self.dist):
            out.reshape(-1, 2)[ok] = flat[ok]
            return out
        if not ok.any():
            return out
        import cv2

        src = np.ascontiguousarray(flat[ok]).reshape(-1, 1, 2)
        if self.model == "fisheye":
            und = cv2.fisheye.undistortPoints(
                src, self.K, self.dist, R=np.eye(3), P=self.K, criteria=_UNDISTORT_CRITERIA
            )
        else:
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x: the iterated variant has its own name
                und = cv2.undistortPointsIter(src, self.K, self.dist, None, self.K, _UNDISTORT_CRITERIA)
            else:  # OpenCV 5: undistortPoints takes the criteria
                und = cv2.undistortPoints(
                    src, self.K, self.dist, R=None, P=self.K, criteria=_UNDISTORT_CRITERIA
                )
        res = out.reshape(-1, 2)
        res[ok] = und.reshape(-1, 2)
        return res.reshape(xy.shape)

    # ---- (de)serialisation

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python dict (the rig.toml camera table); every digit kept."""
        return {
            "name": self.name,
            "size_wh": [int(self.size_wh[0]), int(self.size_wh[1])],
            "model": self.model,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(
        cls, d: Mapping[str, Any], path: str | os.PathLike[str] | None = None, where: str | None = None
    ) -> Camera:
        """Inverse of ``to_dict``; errors name ``path`` and the field (``where`` prefixes it).

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> Camera.from_dict(cam.to_dict()) == cam
        True
        >>> Camera.from_dict({"name": "c0", "size_wh": [640, 480], "K": cam.K.tolist()}, "rig.toml")
        ... # doctest: +ELLIPSIS
        Traceback (most recent call last):
        roomcap.core.errors.FormatError: rig.toml: field 'camera 'c0'.R': camera fields ['R', 't'] are ...
        """
        w = where or f"camera '{d.get('name', '?')}'"
        check_keys(d, CAMERA_KEYS, w, path, name_key=True)
        missing = [k for k in CAMERA_KEYS if k not in d and k not in ("dist", "model")]
        if missing:
            raise FormatError(
                path,
                f"{w}.{missing[0]}",
                f"camera fields {missing} are missing.",
                f"Every camera needs {list(CAMERA_KEYS)} ('dist' and 'model' may be left out).",
            )
        v = validated_fields(
            d["name"],
            d["size_wh"],
            d["K"],
            d.get("dist", []),
            d.get("model", "pinhole"),
            d["R"],
            d["t"],
            path=path,
            where=w,
        )
        return cls(**v)

    def replace(self, **changes: Any) -> Camera:
        """A copy with some fields changed (checked like a new camera).

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> cam.replace(name="c1", t=[0, 0, 3]).center
        array([ 0.,  0., -3.])
        """
        d = {k: getattr(self, k) for k in CAMERA_KEYS}
        d.update(changes)
        return Camera(**d)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))

    def __repr__(self) -> str:
        return (
            f"Camera(name={self.name!r}, size_wh={self.size_wh}, model={self.model!r}, "
            f"f=({self.K[0, 0]:.1f},{self.K[1, 1]:.1f}), c=({self.K[0, 2]:.1f},{self.K[1, 2]:.1f}), "
            f"ndist={self.dist.size}, center={np.round(self.center, 3).tolist()})"
        )


def _tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's computeTiltProjectionMatrix (tilted sensor, dist[12:14])."""
    cx, sx, cy, sy = math.cos(tau_x), math.sin(tau_x), math.cos(tau_y), math.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rxy = rot_y @ rot_x
    proj_z = np.array([[rxy[2, 2], 0, -rxy[0, 2]], [0, rxy[2, 2], -rxy[1, 2]], [0, 0, 1]])
    return proj_z @ rxy


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# ----------------------------------------------------------------------------- CameraRig


@dataclass(frozen=True, eq=False)
class CameraRig:
    """An ordered tuple of cameras with unique names (C cameras).

    >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
    >>> CameraRig.of([cam, cam.replace(name="c1")])
    CameraRig(2 cameras: ['c0', 'c1'])
    >>> CameraRig.of([cam, cam])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: <input>: field 'cameras.name': camera names must be unique; ...
    """

    cameras: tuple[Camera, ...]

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        for i, c in enumerate(cams):
            if not isinstance(c, Camera):
                raise TypeError(f"CameraRig: cameras[{i}] is {type(c).__name__}, expected Camera")
        names = [c.name for c in cams]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise FormatError(
                None,
                "cameras.name",
                f"camera names must be unique; repeated: {dup}.",
                "Rename the cameras so each name is used once.",
            )
        object.__setattr__(self, "cameras", cams)

    @classmethod
    def of(cls, cameras: Iterable[Camera]) -> CameraRig:
        return cls(tuple(cameras))

    # ---- container

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            return self.cameras[self.index(key)]
        return self.cameras[key]

    def index(self, name: str) -> int:
        """Position of the camera named ``name``.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> rig = CameraRig.of([cam, cam.replace(name="c1")])
        >>> rig.index("c1"), rig["c1"].name
        (1, 'c1')
        >>> rig.index("left")
        Traceback (most recent call last):
        roomcap.core.errors.UnknownNameError: no camera named 'left'; cameras: ['c0', 'c1']
        """
        for i, c in enumerate(self.cameras):
            if c.name == name:
                return i
        raise UnknownNameError(f"no camera named {name!r}; cameras: {self.names}")

    def subset(self, names: Sequence[str]) -> CameraRig:
        """A rig with the named cameras, in the order given.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> CameraRig.of([cam, cam.replace(name="c1"), cam.replace(name="c2")]).subset(["c2", "c0"]).names
        ['c2', 'c0']
        """
        return CameraRig(tuple(self[n] for n in names))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraRig):
            return NotImplemented
        return self.cameras == other.cameras

    def __hash__(self) -> int:
        return hash(self.sha256())

    # ---- geometry

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points X: (N,3) -> pixels (C,N,2) with distortion; NaN where behind a camera or X is NaN.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> rig = CameraRig.of([cam, cam.replace(name="c1", t=[-0.5, 0, 2])])
        >>> rig.project(np.array([[0.0, 0.0, 0.0]]))
        array([[[320., 240.]],
        <BLANKLINE>
               [[195., 240.]]])
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"CameraRig.project: X must be (N,3), got {X.shape}")
        if not self.cameras:
            return np.zeros((0, X.shape[0], 2))
        return np.stack([c.project(X) for c in self.cameras])

    def projection_matrices(self) -> np.ndarray:
        """(C,3,4) ``K [R|t]`` per camera, for undistorted pixels.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> CameraRig.of([cam, cam.replace(name="c1")]).projection_matrices().shape
        (2, 3, 4)
        """
        return np.stack([c.P for c in self.cameras]) if self.cameras else np.zeros((0, 3, 4))

    def centers(self) -> np.ndarray:
        """(C,3) camera centres in world metres.

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> CameraRig.of([cam, cam.replace(name="c1", t=[-0.5, 0, 2])]).centers() + 0.0
        array([[ 0. ,  0. , -2. ],
               [ 0.5,  0. , -2. ]])
        """
        return np.stack([c.center for c in self.cameras]) if self.cameras else np.zeros((0, 3))

    def undistort_px(self, xy_px: np.ndarray) -> np.ndarray:
        """Distorted pixels (C,...,2) -> ideal-pinhole pixels (C,...,2); NaN passes through.

        >>> rig = CameraRig.of([Camera("c0", (640, 480), np.diag([500.0, 500.0, 1.0]), t=[0, 0, 2])])
        >>> rig.undistort_px(np.array([[[100.0, 50.0]]]))
        array([[[100.,  50.]]])
        >>> rig.undistort_px(np.zeros((2, 1, 2)))
        Traceback (most recent call last):
        ValueError: CameraRig.undistort_px: expected (C=1,...,2), got (2, 1, 2)
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.ndim < 2 or xy.shape[0] != len(self) or xy.shape[-1] != 2:
            raise ValueError(f"CameraRig.undistort_px: expected (C={len(self)},...,2), got {xy.shape}")
        if not len(self):
            return xy.copy()
        return np.stack([c.undistort_px(xy[i]) for i, c in enumerate(self.cameras)])

    def fundamental_matrices(self) -> np.ndarray:
        """(C,C,3,3) F with ``x_j^T F[i,j] x_i = 0`` for undistorted homogeneous pixels of the same point
        (Tanke 2024, eq. 3.15, with x = camera i, x' = camera j). The diagonal is zero.

        F[i,j] = K_j^-T [t_ij]_x R_ij K_i^-1 with x_cj = R_ij x_ci + t_ij (Hartley & Zisserman eq. 9.2).

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> turned = cam.replace(name="c1", R=rotation_from_rvec([0, 0.4, 0]), t=[-0.5, 0, 2])
        >>> rig = CameraRig.of([cam, turned])
        >>> X = np.array([[0.1, -0.2, 0.3]])
        >>> x0, x1 = (np.append(p[0], 1.0) for p in rig.project(X))
        >>> abs(float(x1 @ rig.fundamental_matrices()[0, 1] @ x0)) < 1e-9
        True
        """
        C = len(self)
        F = np.zeros((C, C, 3, 3))
        Kinv = [np.linalg.inv(c.K) for c in self.cameras]
        for i, ci in enumerate(self.cameras):
            for j, cj in enumerate(self.cameras):
                if i == j:
                    continue
                R_ij = cj.R @ ci.R.T
                t_ij = cj.t - R_ij @ ci.t
                Fij = Kinv[j].T @ _skew(t_ij) @ R_ij @ Kinv[i]
                n = np.linalg.norm(Fij)
                F[i, j] = Fij / n if n > 0 else Fij
        return F

    # ---- files

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": schema_tag(RIG_SCHEMA, RIG_VERSION),
            "convention": CONVENTION,
            "cameras": [c.to_dict() for c in self.cameras],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], path: str | os.PathLike[str] | None = None) -> CameraRig:
        check_schema(d.get("schema"), RIG_SCHEMA, (RIG_VERSION,), path)
        check_keys(
            d,
            ("schema", "convention", "source", "cameras"),
            None,
            path,
            fix="Remove them (per-camera values go in the [[cameras]] tables).",
            name_key=True,
        )
        conv = d.get("convention")
        if conv is not None and conv != CONVENTION:
            raise FormatError(
                path,
                "convention",
                f"says {conv!r}, but rig/1 files use {CONVENTION!r}.",
                "Convert the poses to cam_from_world in metres and write the convention "
                "string as shown (calibrate-run import does this for known formats).",
            )
        cams = d.get("cameras")
        if not isinstance(cams, list) or not cams:
            raise FormatError(
                path,
                "cameras",
                "no [[cameras]] tables found.",
                "Add one [[cameras]] table per camera with " + ", ".join(CAMERA_KEYS) + ".",
            )
        out: list[Camera] = []
        for i, cd in enumerate(cams):
            if not isinstance(cd, Mapping):
                raise FormatError(
                    path, f"cameras[{i}]", "is not a table.", "Write each camera as [[cameras]]."
                )
            nm = cd.get("name")
            out.append(Camera.from_dict(cd, path=path, where=f"cameras[{i}]" + (f" ('{nm}')" if nm else "")))
            if out[-1].name in [c.name for c in out[:-1]]:
                raise FormatError(
                    path,
                    f"cameras[{i}].name",
                    f"camera name {out[-1].name!r} is used twice.",
                    "Give every camera a unique name.",
                )
        return cls(tuple(out))

    def save(self, path: str | os.PathLike[str], source: str | None = None) -> None:
        """Write ``rig.toml`` atomically (every digit kept)."""
        d = self.to_dict()
        if source:
            d["source"] = source
        save_toml(
            path,
            d,
            header=f"roomcap camera rig ({schema_tag(RIG_SCHEMA, RIG_VERSION)}).\n"
            f"Convention: {CONVENTION}.\n"
            "K = [[fx,0,cx],[0,fy,cy],[0,0,1]]; dist in OpenCV order "
            "(pinhole: k1,k2,p1,p2,k3,k4,k5,k6,s1..s4,tau_x,tau_y; fisheye: k1..k4).",
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> CameraRig:
        return cls.from_dict(load_toml(path), path=path)

    def sha256(self) -> str:
        """SHA-256 of the canonical JSON of the cameras (order, names and every float digit).

        >>> cam = Camera("c0", (640, 480), [[500, 0, 320], [0, 500, 240], [0, 0, 1]], t=[0, 0, 2])
        >>> a, b = CameraRig.of([cam]), CameraRig.of([cam.replace(t=[0, 0, 2.000001])])
        >>> a.sha256() == CameraRig.from_dict(a.to_dict()).sha256(), a.sha256() == b.sha256()
        (True, False)
        """
        canon = json.dumps([c.to_dict() for c in self.cameras], sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canon.encode("utf-8")).hexdigest()

    def __repr__(self) -> str:
        return f"CameraRig({len(self)} cameras: {self.names})"
