"""The element-test engine: a loading programme applied to material points of oriented cells.

``points`` (the material points: orientations, trials, acceptance), ``programme`` (a stage as a
plan: per component strain or stress control, targets, coupling, stop on p), ``solver`` (the one
stress-control solver, batched over points and so over parameter sets), ``run`` (stages in turn
from the points' present state) and ``record`` (the history and the ``Record`` of 2D and 3D runs).
``homogenization.driver`` runs one point from the touching state; ``homogenization.calibration.forward``
runs a population of parameter sets. docs/architecture.md draws it.
"""
