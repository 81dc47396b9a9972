"""``python -m roomcap.forecast.characteristic``: kept for that command (the shipped checkpoints record it);
the code is :mod:`roomcap.forecast.lab.characteristic`."""
