"""Camera model: projection against OpenCV, undistortion, centres, fundamental matrices, rig.toml."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from roomcap.calibrate.camera import CONVENTION, Camera, CameraRig, rotation_from_rvec
from roomcap.core.errors import FormatError, SchemaError

DIST_SIZES = [0, 4, 5, 8, 12, 14]


def random_camera(rng: np.random.Generator, n_dist: int, model: str = "pinhole", name: str = "c") -> Camera:
    """A camera about 4 m from the origin looking roughly at it, with realistic lens coefficients."""
    K = np.array(
        [
            [rng.uniform(600, 1500), 0, rng.uniform(600, 680)],
            [0, rng.uniform(600, 1500), rng.uniform(330, 390)],
            [0, 0, 1.0],
        ]
    )
    if model == "fisheye":
        dist = rng.normal(0, 0.05, 4)
    else:
        scale = np.array(
            [0.1, 0.05, 0.002, 0.002, 0.01, 0.05, 0.02, 0.01, 0.002, 0.002, 0.002, 0.002, 0.01, 0.01]
        )
        dist = rng.normal(0, 1, n_dist) * scale[:n_dist]
    R = rotation_from_rvec(rng.normal(0, 0.3, 3))
    t = np.array([0.0, 0.0, 4.0]) + rng.normal(0, 0.3, 3)
    return Camera(name, (1280, 720), K, dist, model, R, t)


def points_in_view(cam: Camera, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    """World points whose ideal projection lies inside the image (where a calibration is valid)."""
    X = rng.uniform(-1.5, 1.5, (4 * n, 3))
    xc = X @ cam.R.T + cam.t
    uv = xc[:, :2] / xc[:, 2:] * np.diag(cam.K)[:2] + cam.K[:2, 2]
    ok = (xc[:, 2] > 0.5) & np.all((uv > 0) & (uv < np.array(cam.size_wh)), axis=1)
    return X[ok][:n]


def ideal_px(cam: Camera, X: np.ndarray) -> np.ndarray:
    xc = X @ cam.R.T + cam.t
    return xc[:, :2] / xc[:, 2:] * np.diag(cam.K)[:2] + cam.K[:2, 2]


@pytest.mark.parametrize("n_dist", DIST_SIZES)
def test_project_matches_opencv_pinhole(rng, n_dist):
    for trial in range(5):
        cam = random_camera(rng, n_dist)
        X = points_in_view(cam, rng)
        ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist if n_dist else None)
        err = np.abs(cam.project(X) - ref.reshape(-1, 2)).max()
        assert err < 1e-6, (n_dist, trial, err)  # measured < 1e-11 px


def test_project_matches_opencv_fisheye(rng):
    for _ in range(5):
        cam = random_camera(rng, 4, "fisheye")
        X = points_in_view(cam, rng)
        ref, _ = cv2.fisheye.projectPoints(
            X.reshape(-1, 1, 3), cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist
        )
        assert np.abs(cam.project(X) - ref.reshape(-1, 2)).max() < 1e-6  # measured < 1e-12 px


def test_tilted_sensor_terms_matter(rng):
    """dist[12:14] (tau_x, tau_y) change the projection, and still match OpenCV."""
    cam = random_camera(rng, 14)
    d = cam.dist.copy()
    d[12:] = [0.02, -0.03]
    tilted = cam.replace(dist=d)
    X = points_in_view(cam, rng)
    assert np.abs(tilted.project(X) - cam.replace(dist=np.r_[d[:12], 0, 0]).project(X)).max() > 1.0
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, d)
    assert np.abs(tilted.project(X) - ref.reshape(-1, 2)).max() < 1e-6


@pytest.mark.parametrize("n_dist,model", [(n, "pinhole") for n in DIST_SIZES] + [(4, "fisheye")])
def test_undistort_inverts_project(rng, n_dist, model):
    cam = random_camera(rng, n_dist, model)
    X = points_in_view(cam, rng)
    und = cam.undistort_px(cam.project(X))
    assert np.abs(und - ideal_px(cam, X)).max() < 1e-6  # measured < 1e-9 px (100 iterations, eps 1e-12)


def test_undistort_nan_and_shapes(rng):
    cam = random_camera(rng, 5)
    xy = rng.uniform(100, 600, (3, 7, 2))
    xy[1, 2] = np.nan
    xy[2, 5, 0] = np.nan
    out = cam.undistort_px(xy)
    assert out.shape == (3, 7, 2)
    assert np.isnan(out[1, 2]).all() and np.isnan(out[2, 5]).all()
    assert np.isfinite(out).sum() == 2 * (21 - 2)
    assert np.isnan(cam.undistort_px(np.full((4, 2), np.nan))).all()
    assert cam.undistort_px(np.zeros((0, 2))).shape == (0, 2)
    # no distortion: identity (a point with one NaN coordinate is unobserved: both NaN)
    expect = np.where(np.isnan(xy).any(-1, keepdims=True), np.nan, xy)
    assert np.array_equal(cam.replace(dist=np.zeros(0)).undistort_px(xy), expect, equal_nan=True)


def test_project_nan_and_behind_camera():
    cam = Camera("c", (640, 480), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))
    X = np.array([[0, 0, 2.0], [0, 0, -2.0], [np.nan, 0, 1], [0.1, 0.2, 0.0]])
    xy = cam.project(X)
    np.testing.assert_allclose(xy[0], [320, 240])
    assert np.isnan(xy[1:]).all()  # behind, NaN in, on the camera plane


def test_center_of_a_known_camera():
    """Camera at C = (2, -1, 1.5) m looking along world +x, image x = world -y, image y = world -z."""
    C = np.array([2.0, -1.0, 1.5])
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # rows: camera axes in world
    cam = Camera("c", (640, 480), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), R=R, t=-R @ C)
    np.testing.assert_allclose(cam.center, C, atol=1e-15)
    # the Rodrigues vector's direction is the rotation axis, not the centre: (EasyMocap's slip)
    assert not np.allclose(-cv2.Rodrigues(R)[0].ravel() * np.linalg.norm(cam.t), C)
    # a point 3 m in front of it lands on the principal point; one 1 m to world -y lands right of it
    np.testing.assert_allclose(cam.project(np.array([C + [3, 0, 0]])), [[320, 240]])
    assert cam.project(np.array([C + [3, -1, 0]]))[0, 0] > 320
    # P annihilates the centre, and P projects like the undistorted camera
    np.testing.assert_allclose(cam.P @ np.r_[C, 1], 0, atol=1e-12)
    X = np.array([[5.0, 0.3, 1.0], [4.0, -2.0, 2.0]])
    h = np.c_[X, np.ones(2)] @ cam.P.T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], cam.project(X))


@pytest.mark.parametrize(
    "change,field",
    [
        (dict(R=np.diag([1.0, 1.0, -1.0])), "R"),  # reflection
        (dict(R=np.eye(3) * 1.001), "R"),  # not orthonormal
        (dict(R=np.eye(3)[:2]), "R"),  # wrong shape
        (dict(K=np.eye(2)), "K"),
        (dict(K=np.array([[500.0, 2.0, 320], [0, 500, 240], [0, 0, 1]])), "K"),  # skew
        (dict(t=np.zeros(4)), "t"),
        (dict(dist=np.zeros(6)), "dist"),
        (dict(dist=np.zeros(5), model="fisheye"), "dist"),
        (dict(model="orthographic"), "model"),
        (dict(size_wh=(640.5, 480)), "size_wh"),
        (dict(t=np.array([0, np.nan, 1.0])), "t"),
    ],
)
def test_camera_validation_names_field(change, field):
    base = dict(
        name="cam_7",
        size_wh=(640, 480),
        K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        dist=np.zeros(5),
        model="pinhole",
        R=np.eye(3),
        t=np.zeros(3),
    )
    with pytest.raises(FormatError) as ei:
        Camera(**(base | change))
    assert ei.value.field == f"camera 'cam_7'.{field}"
    assert "cam_7" in str(ei.value)


def test_rotation_error_says_what_to_do():
    with pytest.raises(FormatError, match="not a rotation.*det = -1.*transpose"):
        Camera("a", (10, 10), np.eye(3), R=np.diag([1.0, -1.0, 1.0]))


def test_camera_is_immutable():
    cam = Camera("a", (10, 10), np.eye(3))
    with pytest.raises(ValueError):
        cam.K[0, 0] = 2.0
    with pytest.raises(AttributeError):
        cam.name = "b"


# ----------------------------------------------------------------------------- rig


def make_rig(rng, n: int = 4) -> CameraRig:
    sizes = [5, 8, 14, 0, 4, 12]
    return CameraRig(tuple(random_camera(rng, sizes[i % len(sizes)], name=f"cam_{i}") for i in range(n)))


def test_rig_container(rng):
    rig = make_rig(rng, 4)
    assert len(rig) == 4 and rig.names == ["cam_0", "cam_1", "cam_2", "cam_3"]
    assert rig["cam_2"] is rig[2] and rig.index("cam_3") == 3
    sub = rig.subset(["cam_3", "cam_1"])
    assert sub.names == ["cam_3", "cam_1"] and sub[0] == rig[3]
    with pytest.raises(KeyError, match="cam_9"):
        rig.index("cam_9")
    with pytest.raises(FormatError, match="unique"):
        CameraRig((rig[0], rig[0]))


def test_rig_geometry_shapes(rng):
    rig = make_rig(rng, 3)
    X = rng.uniform(-1, 1, (50, 3))
    xy = rig.project(X)
    assert xy.shape == (3, 50, 2)
    for c in range(3):
        np.testing.assert_array_equal(xy[c], rig[c].project(X))
    assert rig.projection_matrices().shape == (3, 3, 4)
    np.testing.assert_allclose(rig.centers()[1], rig[1].center)
    und = rig.undistort_px(xy[:, None])  # (C, 1, N, 2)
    assert und.shape == (3, 1, 50, 2)
    with pytest.raises(ValueError, match="C=3"):
        rig.undistort_px(xy[:2])
    with pytest.raises(ValueError, match=r"\(N,3\)"):
        rig.project(X[:, :2])


def test_fundamental_matrices_epipolar_constraint(rng):
    """x_j^T F[i,j] x_i = 0 on undistorted pixels (Tanke eq. 3.15): epipolar distance ~ 0."""
    rig = make_rig(rng, 4)
    F = rig.fundamental_matrices()
    assert F.shape == (4, 4, 3, 3)
    assert not F[np.arange(4), np.arange(4)].any()
    X = rng.uniform(-1, 1, (200, 3))
    und = rig.undistort_px(rig.project(X))
    h = np.concatenate([und, np.ones(und.shape[:-1] + (1,))], axis=-1)
    worst = 0.0
    for i in range(4):
        for j in range(4):
            if i == j:
                continue
            lines = h[i] @ F[i, j].T  # epipolar lines in camera j
            d = np.abs(np.sum(h[j] * lines, axis=1)) / np.hypot(lines[:, 0], lines[:, 1])
            worst = max(worst, d.max())
            # F[j,i] = F[i,j]^T up to scale
            a, b = F[j, i].ravel(), F[i, j].T.ravel()
            assert min(np.abs(a - b).max(), np.abs(a + b).max()) < 1e-9
    assert worst < 1e-6  # measured ~1e-9 px
    # a wrong correspondence is far from its line
    lines = h[0] @ F[0, 1].T
    d = np.abs(np.sum(np.roll(h[1], 1, axis=0) * lines, axis=1)) / np.hypot(lines[:, 0], lines[:, 1])
    assert np.median(d) > 5


def test_rig_save_load_round_trip_every_digit(tmp_path, rng):
    rig = make_rig(rng, 5)
    p = tmp_path / "calib" / "rig.toml"
    rig.save(p, source="test")
    text = p.read_text()
    assert text.startswith("# roomcap camera rig (rig/1).")
    assert CONVENTION in text.splitlines()[1]  # the header comment
    assert f'convention = "{CONVENTION}"' in text
    back = CameraRig.load(p)
    assert back == rig  # exact: every float digit
    for a, b in zip(back, rig, strict=True):
        assert np.array_equal(a.dist, b.dist) and np.array_equal(a.R, b.R)
    assert back.sha256() == rig.sha256()
    assert not list(tmp_path.glob("calib/.rig.toml*"))  # no temporary left behind


def test_sha256_changes_with_any_digit(rng):
    rig = make_rig(rng, 2)
    h = rig.sha256()
    assert len(h) == 64 and h == make_rig(np.random.default_rng(0), 2).sha256()
    t = rig[1].t.copy()
    t[2] = np.nextafter(t[2], 10)
    assert CameraRig((rig[0], rig[1].replace(t=t))).sha256() != h
    assert rig.subset(["cam_1", "cam_0"]).sha256() != h  # order matters


def _write(tmp_path, text: str):
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


GOOD = """schema = "rig/1"
[[cameras]]
name = "a"
size_wh = [640, 480]
model = "pinhole"
K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
dist = [0.0, 0.0, 0.0, 0.0]
R = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
t = [0.0, 0.0, 2.0]
"""


@pytest.mark.parametrize(
    "edit,field,fix",
    [
        (
            lambda s: s.replace("K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]\n", ""),
            "cameras[0] ('a').K",
            "Every camera needs",
        ),
        (lambda s: s.replace("t = [0.0, 0.0, 2.0]", "t = [0.0, 2.0]"), "cameras[0] ('a').t", "metres"),
        (
            lambda s: s.replace("[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]", "[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]"),
            "cameras[0] ('a').R",
            "reflection",
        ),
        (
            lambda s: s.replace("[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]", "[0.0, 1.0], [0.0, 0.0]]"),
            "cameras[0] ('a').R",
            "3x3",
        ),
        (lambda s: s.replace("rig/1", "rig/7"), "schema", "Upgrade roomcap"),
        (lambda s: s.replace("rig/1", "tracks/1"), "schema", "right file"),
        (lambda s: s.replace("dist =", "distortion ="), "cameras[0] ('a').distortion", "Remove or rename"),
        (lambda s: s.split("[[cameras]]")[0], "cameras", "Add one [[cameras]]"),
        (
            lambda s: s.replace('schema = "rig/1"', 'schema = "rig/1"\nconvention = "world_from_cam; mm"'),
            "convention",
            "Convert the poses",
        ),
        (lambda s: s + s[s.index("[[cameras]]") :], "cameras[1].name", "unique"),
    ],
)
def test_rig_load_errors_name_file_field_fix(tmp_path, edit, field, fix):
    p = _write(tmp_path, edit(GOOD))
    with pytest.raises(FormatError) as ei:
        CameraRig.load(p)
    assert ei.value.path == str(p)
    assert ei.value.field == field, str(ei.value)
    assert fix in str(ei.value)


def test_rig_load_good_and_missing_file(tmp_path):
    rig = CameraRig.load(_write(tmp_path, GOOD))
    assert rig.names == ["a"] and rig[0].center.tolist() == [0.0, 0.0, -2.0]
    with pytest.raises(FormatError, match="does not exist"):
        CameraRig.load(tmp_path / "nope.toml")
    with pytest.raises(SchemaError):
        CameraRig.load(_write(tmp_path, GOOD.replace('schema = "rig/1"\n', "")))


def test_failed_save_leaves_previous_file(tmp_path, rng, monkeypatch):
    """Nothing is written half: a writer that dies keeps the old rig.toml and leaves no temp file."""
    rig = make_rig(rng, 2)
    p = tmp_path / "rig.toml"
    rig.save(p)
    before = p.read_bytes()
    import tomli_w

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(tomli_w, "dumps", boom)
    with pytest.raises(RuntimeError):
        make_rig(rng, 3).save(p)
    assert p.read_bytes() == before
    assert [f.name for f in tmp_path.iterdir()] == ["rig.toml"]


def test_rotation_from_rvec_matches_opencv(rng):
    for _ in range(20):
        r = rng.normal(0, 1.5, 3)
        np.testing.assert_allclose(rotation_from_rvec(r), cv2.Rodrigues(r)[0], atol=1e-12)
    np.testing.assert_array_equal(rotation_from_rvec(np.zeros(3)), np.eye(3))
    assert math.isclose(np.linalg.det(rotation_from_rvec([0, 0, np.pi])), 1.0)
