"""roomcap: markerless multi-camera, multi-person 3D motion capture with a forecasting back-end.

The one installed top-level name. Its stage packages are the folders beside this file, mapped into the
namespace by the packaging (``pyproject.toml`` ``[tool.setuptools] package-dir``): ``roomcap.capture``,
``roomcap.calibrate``, ``roomcap.keypoints``, ``roomcap.triangulate``, ``roomcap.track``,
``roomcap.forecast``, ``roomcap.pipeline`` on top, ``roomcap.core`` below them all and ``roomcap.synthetic``
as the test world.
"""
