"""The environment the project runs in: exactly one OpenCV build.

The OpenCV wheels (``opencv-python``, ``opencv-contrib-python``, their ``-headless`` twins) all install
into the same ``cv2`` folder, so a second one silently replaces the project's build (aniposelib
pulled ``opencv-contrib-python`` 5.1 over the headless 5.0 and a keypoint test changed its result).
"""

from __future__ import annotations

from importlib import metadata


def test_exactly_one_opencv_distribution_is_installed():
    every = {(d.metadata["Name"] or "").lower().replace("_", "-") for d in metadata.distributions()}
    names = sorted(n for n in every if n.startswith("opencv"))
    assert names == ["opencv-contrib-python-headless"], (
        f"OpenCV distributions installed: {names}. Exactly one, opencv-contrib-python-headless, must be: "
        "uninstall the others (pip uninstall <name>) and reinstall opencv-contrib-python-headless "
        "(pip install --force-reinstall --no-deps opencv-contrib-python-headless)."
    )
