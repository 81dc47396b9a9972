"""The session report: one self-contained HTML file (no network needed to open it).

Sections: a plain-language list of problems with what to do about each; the 3D viewer of the
tracks (playback, per-person colours, cameras, forecasts as faded skeletons); per camera a
filmstrip of the video with the 2D detections and the tracks reprojected into it, coloured by
identity, on a frame slider shared with the viewer; the reprojection error per camera and per
joint as the triangulation wrote it (table, camera x joint matrix, plot over time), the views per
joint; track timelines with the frames a track was carried without observations and suspected
identity swaps; the room from above with each camera's field of view; detection rates; the
calibration (and its own figures when its report is there); the warnings the pipeline logged.

Everything is embedded: data as JSON, video frames as JPEG data URIs sized to a byte budget
(``ReportConfig``: a 4-camera, 2-minute session stays under about 30 MB; longer ones sample
frames evenly). The page is plain canvas JavaScript (``report_assets/``); script errors are
collected into ``#errors`` so tests (and people) see them.

``write_overlay_videos`` draws the same overlays on every frame of every camera's video (MP4);
``python -m roomcap.pipeline.report SESSION [--overlay]`` writes the report (and those videos) for a
session folder without running the pipeline.
"""

from roomcap.pipeline.report.figures import reprojection_figures, rig_cameras_data, track_events
from roomcap.pipeline.report.inputs import ReportConfig
from roomcap.pipeline.report.overlay_video import draw_overlay, write_overlay_videos
from roomcap.pipeline.report.page import collect, render, report_inputs, write_report
from roomcap.pipeline.report.problems import warnings_path

__all__ = [
    "ReportConfig",
    "collect",
    "draw_overlay",
    "render",
    "report_inputs",
    "reprojection_figures",
    "rig_cameras_data",
    "track_events",
    "warnings_path",
    "write_overlay_videos",
    "write_report",
]
