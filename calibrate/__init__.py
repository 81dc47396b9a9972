"""calibrate stage: the camera model (``Camera``, ``CameraRig``, ``rig.toml``), calibration
importers/exporters, and board calibration.

Never imports torch or depthai (tests/test_import_boundaries.py checks this).
"""

from roomcap.calibrate.camera import CONVENTION, Camera, CameraRig
from roomcap.calibrate.formats import ImportOptions, detect_format, export_rig, import_rig

__all__ = ["CONVENTION", "Camera", "CameraRig", "ImportOptions", "detect_format", "export_rig", "import_rig"]
