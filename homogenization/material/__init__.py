"""The homogenised material: material points of oriented cells, their orientations and invariants.

``homogenised`` (``HomogenisedMaterial`` and ``HomogenisedMaterial3D``: stress and consistent
tangent of a batch of material points, one batched cell step per update), ``orientation`` (the
planar orientation sets, the localisation and averaging both dimensions share, the volume rule),
``orientation3d`` (the Lebedev rule of the 3D cell axes with their spins, the cells' kinematics)
and ``invariants`` (p, q, W2 and the 3D invariants).
"""
