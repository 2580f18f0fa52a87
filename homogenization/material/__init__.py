"""The homogenised material: material points of oriented cells, their orientations and invariants.

``homogenised`` (``HomogenisedMaterial`` of either dimension: stress and consistent
tangent of a batch of material points, one batched cell step per update), ``orientation`` (the
orientation sets of both dimensions: the planar rule, the Lebedev rule of the 3D cell axes with
their spins and the cells' kinematics; the localisation, averaging and volume rule they share)
and ``invariants`` (p, q, W2 and the 3D invariants).
"""
