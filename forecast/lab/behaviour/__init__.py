"""Long-horizon behaviour forecasting (Diller ch. 4, FutureHuman3D): the next M actions of a person and, for
each, its characteristic 3D pose, from observed 2D poses and action labels, learned from 2D only.

Modules: ``data`` (composite CMU activities observed in 2D), ``geometry`` (viewer frame, plane features,
eq. 4.2), ``model`` (generator, critic, rollout, checkpoint), ``training`` (eq. 4.1 and the sec. 4.5.1
evaluation), ``labels`` (a session's action-label CSV), ``sample`` (``behaviour.npz`` of a session), ``cli``
(``forecast behaviour train | eval | sample | merge``).
"""
