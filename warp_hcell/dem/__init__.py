"""The batched meso-DEM in NVIDIA Warp kernels (float64) and its cell backend.

Imports ``warp_hcell.core`` and ``warp_hcell.mesostructures`` only.
"""
