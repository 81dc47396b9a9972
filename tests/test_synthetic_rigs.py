"""Synthetic rigs: look-at convention, ring and kitchen geometry, rig file round trip."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.calibrate.camera import CameraRig
from roomcap.synthetic import rigs


def test_look_at_convention():
    R, t = rigs.look_at((0.0, -3.0, 1.5), (0.0, 0.0, 1.5))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    x_cam = R @ np.array([0.0, 0.0, 1.5]) + t
    assert x_cam[2] == pytest.approx(3.0) and abs(x_cam[0]) < 1e-12  # in front, on the axis
    # world up is image up (camera y points down)
    assert (R @ np.array([0.0, 0.0, 1.0]))[1] < 0
    cam = rigs.make_camera("c", (0.0, -3.0, 1.5), (0.0, 0.0, 1.5), (640, 480), 60.0)
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 1.5]]))[0], [319.5, 239.5], atol=1e-9)
    # +x in the world is to the right in this view (camera looks along +y)
    assert cam.project(np.array([[0.5, 0.0, 1.5]]))[0, 0] > 319.5


def test_ring_rig_geometry():
    rig = rigs.ring_rig(8, radius_m=4.0, height_m=2.2)
    c = rig.centers()
    np.testing.assert_allclose(np.linalg.norm(c[:, :2], axis=1), 4.0)
    np.testing.assert_allclose(c[:, 2], 2.2)
    centre_px = rig.project(np.array([[0.0, 0.0, 1.0]]))[:, 0]
    np.testing.assert_allclose(centre_px, [[639.5, 359.5]] * 8, atol=1e-9)


@pytest.mark.parametrize("linkage", ["full", "weak"])
def test_kitchen_rig_sees_the_room(linkage, tmp_path):
    rig, room = rigs.kitchen_rig(12, linkage=linkage), rigs.kitchen_room()
    assert len(rig) == 12 and len(room.boxes) >= 5
    c = rig.centers()
    x0, x1, y0, y1 = room.bounds_m
    assert np.all((c[:, 0] >= x0) & (c[:, 0] <= x1) & (c[:, 1] >= y0) & (c[:, 1] <= y1))
    assert np.all(np.abs(c[:, 2] - 2.5) < 0.2)
    assert all(np.any(cam.dist != 0) for cam in rig)  # mild distortion
    # a grid of points at chest height: each is seen by several cameras
    xs, ys = np.meshgrid(np.linspace(x0 + 0.5, x1 - 0.5, 12), np.linspace(y0 + 0.5, y1 - 0.5, 9))
    X = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 1.3)], 1)
    xy = rig.project(X)
    inside = (
        np.isfinite(xy[..., 0])
        & (xy[..., 0] >= 0)
        & (xy[..., 0] < 1280)
        & (xy[..., 1] >= 0)
        & (xy[..., 1] < 720)
    )
    views = inside.sum(0)
    west = c[:, 0] < 0
    covis = (inside[:, None] & inside[None]).sum(-1)  # (C,C) points seen by both cameras
    cross_over_within = covis[west][:, ~west].mean() / covis[west][:, west].mean()
    if linkage == "full":
        assert views.min() >= 3  # (measured min 4, median 11)
        assert cross_over_within > 0.8  # (measured 0.99)
    else:
        assert cross_over_within < 0.5  # the two halves share few views   (measured 0.31)
    rig.save(tmp_path / "rig.toml")
    assert CameraRig.load(tmp_path / "rig.toml") == rig


def test_kitchen_rig_rejects_bad_arguments():
    with pytest.raises(ValueError, match="n_cams"):
        rigs.kitchen_rig(40)
    with pytest.raises(ValueError, match="linkage"):
        rigs.kitchen_rig(4, linkage="loose")
