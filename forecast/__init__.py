"""Forecasting, in two parts: :mod:`roomcap.forecast.runtime` (loading a checkpoint and forecasting a track:
the registry, the one checkpoint reader and writer, the models, normalisation (Tanke eq. 3.8), the preview)
and :mod:`roomcap.forecast.lab` (training, datasets and their adapters, metrics, selection and the benchmark
protocols). The runtime imports nothing of the lab. ``cli`` (the command line) and ``commands`` (what it runs)
sit above both. Importing ``forecast`` itself does not import torch.
"""
