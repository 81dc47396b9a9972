"""Small trained forecasting checkpoints shipped with the package (see forecast/preview.py)."""
