"""Meso-ANN: dataset loading, network, checkpoints and training on the DEM database.

Sign convention: compression and contraction positive, as in the database.
"""
