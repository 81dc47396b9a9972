"""``python -m roomcap.forecast.behaviour``: kept for that command; the code is
:mod:`roomcap.forecast.lab.behaviour`."""
