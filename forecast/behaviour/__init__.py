"""``python -m roomcap.forecast.behaviour``: the behaviour command line of
:mod:`roomcap.forecast.lab.behaviour`."""
