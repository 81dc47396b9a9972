"""Forecasting: datasets over track files (and CMU BVH / Humans-in-Kitchens adapters), normalisation
(Tanke eq. 3.8), models (zero/constant velocity, seq2seq GRU, the ch. 6 intention model, ch. 7 Social
Diffusion), metrics (MPJPE, NDMS, APD, ADE, FDE, NPSS, SSCP) and ``forecast train|sample|eval``.

Modules: ``data`` (clips, windows, normalisation, adapters; numpy only), ``metrics`` (numpy only),
``models`` (torch), ``predict`` (world-space forecasting and long rollouts), ``train`` (configs, loops,
checkpoints), ``evaluate`` (protocols and the report), ``preview`` (the pipeline's forecast preview;
``track_forecast`` its model part), ``cli`` (the command line) and ``commands`` (what it runs). Importing
``forecast`` itself does not import torch.
"""
