"""The track file, ``<session>/track/tracks.npz``: the contract with forecasting and with users.

Its format is defined in :mod:`triangulate.trackfile`, the lowest stage that writes it (the chapter-4
tracker in ``triangulate`` writes it as well as the particle tracker here), so both trackers import
it without going up the stage order. This module is its public name: ``from track.trackfile import
TrackFile`` keeps working.
"""

from triangulate.trackfile import *  # noqa: F403
