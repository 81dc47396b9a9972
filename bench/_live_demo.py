"""The Pose2Sim multi-person demo as live cameras, for the live benches: its calibration and its 4 videos as
looping, real-time file cameras in a ``cams.yaml``."""

from __future__ import annotations

from pathlib import Path

from roomcap.calibrate.formats import import_rig

CAMS = ("cam01", "cam02", "cam03", "cam04")


def write_looping_cams(demo: Path, folder: Path) -> Path:
    """``folder/rig.toml`` from the demo's Qualisys calibration and ``folder/cams.yaml`` naming its videos as
    looping file cameras replayed at their own rate; returns the cams.yaml."""
    import_rig(demo / "calibration" / "Calib.qca.txt").save(folder / "rig.toml")
    cams = folder / "cams.yaml"
    cams.write_text(
        "calibration: rig.toml\ncameras:\n"
        + "".join(
            f"  - {{name: {c}, source: '{demo / 'videos' / (c + '.mp4')}', loop: true, realtime: true}}\n"
            for c in CAMS
        )
    )
    return cams
