"""``python -m roomcap.forecast.characteristic``: the characteristic-pose command line of
:mod:`roomcap.forecast.lab.characteristic` (the command the shipped checkpoints' cards record)."""
