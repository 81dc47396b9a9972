"""triangulate stage: the seed's chapter 4 (Tanke 2024, sec. 4.2-4.3).

- :mod:`roomcap.triangulate.matching` -- iterative greedy epipolar matching across views (Alg. 1, eq. 4.1-4.4)
- :mod:`roomcap.triangulate.dlt` -- robust confidence-weighted DLT batched over joints and people
- :mod:`roomcap.triangulate.reconstruct` -- one frame: matching + triangulation + plausibility checks
- :mod:`roomcap.triangulate.evaluate` -- PCP, MPJPE, MOTA, IDF1 for every 3D stage
- :mod:`roomcap.triangulate.stage` -- ``triangulate_session`` on a session folder
- :mod:`roomcap.triangulate.poses3d` -- the per-frame 3D poses file (CONTRACTS.md)
- :mod:`roomcap.triangulate.chunks` -- the parts layout of the 3D stages' files

The ch. 4 tracker in time (sec. 4.2.2) reads this stage's output and lives in ``track/``:
:mod:`roomcap.track.greedy` and its stage :mod:`roomcap.track.greedy_stage`.
"""
