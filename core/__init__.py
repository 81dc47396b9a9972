"""The shared core below every stage: the project's error base and the command-line guard.

Nothing here imports a stage package; every stage may import from here.
"""
