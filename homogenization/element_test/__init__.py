"""The element test: a loading programme applied to material points of oriented cells.

``programme`` (programmes as data: per component strain or stress control, targets, stops) and
``driver`` (one material point run from the touching state: ``run(cell_model, programme) ->
Record``) over the engine: ``points`` (the material points: orientations, trials, acceptance),
``plan`` (a stage as a plan: per component strain or stress control, targets, coupling,
stop on p), ``solver`` (the one stress-control solver, batched over points and so over parameter
sets), ``stages`` (stages in turn from the points' present state) and ``record`` (the history and
the ``Record`` of 2D and 3D runs). ``homogenization.calibration.forward`` runs a population of
parameter sets on the same engine. docs/architecture.md draws it.
"""
