"""What consumes a track file (``track/tracks.npz``): files for other tools, the skeleton fit, live streams.

- :mod:`roomcap.outputs.export` -- ``tracks export``: one file per person and format through a registry of
  exporters (TRC, C3D, CSV, JSON, BVH), Pose2Sim's Butterworth low-pass
- :mod:`roomcap.outputs.skeleton_fit` / :mod:`roomcap.outputs.skeleton_fit_file` -- one skeleton per person
  (``track/skeleton_fit.npz``); :mod:`roomcap.outputs.bvh` writes it as BVH
- :mod:`roomcap.outputs.opensim_ik` -- OpenSim scaling and inverse kinematics with Pose2Sim's model
- :mod:`roomcap.outputs.lsl_osc` -- tracks to the Lab Streaming Layer and OSC, live or replayed
- :mod:`roomcap.outputs.rerun_recording` -- the session as a Rerun recording, written or live
- :mod:`roomcap.outputs.cli` -- the ``tracks`` command

The layer sits above ``track`` (it reads the track file and the detections) and beside ``forecast``;
``pipeline`` uses it.
"""
