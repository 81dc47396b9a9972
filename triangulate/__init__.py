"""triangulate stage: the seed's chapter 4 (Tanke 2024, sec. 4.2-4.3).

- :mod:`roomcap.triangulate.matching` -- iterative greedy epipolar matching across views (Alg. 1, eq. 4.1-4.4)
- :mod:`roomcap.triangulate.dlt` -- robust confidence-weighted DLT batched over joints and people
- :mod:`roomcap.triangulate.reconstruct` -- one frame: matching + triangulation + plausibility checks
- :mod:`roomcap.track.greedy` -- the ch. 4 tracker (sec. 4.2.2): the track stage's ``greedy`` tracker
- :mod:`roomcap.triangulate.evaluate` -- PCP, MPJPE, MOTA, IDF1 for every 3D stage
- :mod:`roomcap.triangulate.stage` -- ``triangulate_session`` / ``track_session_greedy`` on session folders
"""
