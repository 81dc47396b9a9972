"""The forecasting lab: training, datasets and their adapters, selection, metrics and benchmark protocols,
and the model families that live only in their benchmark (the CMU 8-action DCT + MLP, the characteristic-pose
model of Diller ch. 3, the behaviour model of Diller ch. 4). It builds on :mod:`roomcap.forecast.runtime`
(checkpoints are read and written by the runtime's one reader and writer); the runtime never imports it.
"""
