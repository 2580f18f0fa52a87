"""Few-grain mesostructures and their batched meso-DEM in NVIDIA Warp kernels (float64).

Sign convention at the package interface: compression and contraction positive; the
DEM's internal tension-positive quantities are converted in one named function.
"""
