"""Few-grain mesostructures: the description of one cell, its files, and the builders of the H-cell family.

Imports ``warp_hcell.core`` only.
"""
