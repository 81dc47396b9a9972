"""The forecasting runtime: what loading a checkpoint and forecasting a track needs, and nothing of training,
datasets or benchmarks (the import-linter contract in pyproject.toml keeps it so; the pipeline's preview and
users' code import only this part).

Modules: ``registry`` (model name -> config class, build, how it forecasts), ``config`` (the models' configs),
``checkpoint`` (the one checkpoint reader and writer, model cards inside), ``normalise`` (Tanke eq. 3.8),
``models`` (the networks and baselines; torch), ``predict`` (world-space forecasting and long rollouts),
``track_forecast`` and ``preview`` (forecasting a track; the pipeline's preview), ``baselines`` (the
checkpoint-free previews), ``cards`` (``forecast models``), ``samples`` and ``sample_plot`` (what ``forecast
sample`` writes). Importing the runtime does not import torch: building a model does.
"""
