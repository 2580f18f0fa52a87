"""The generic learning database of the meso-ANN: format, learning state, exploration, probes, generator.

Imports ``warp_hcell.core``, ``warp_hcell.mesostructures`` and ``warp_hcell.dem``.
"""
