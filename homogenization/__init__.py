"""Homogenisation of H-cell responses over orientations, driven by loading programmes.

Sign convention: compression and contraction positive for stresses and strains, in code,
files and plots. 2D stresses are forces per unit length [N/m]. Invariants:
p = (sigma11 + sigma22) / 2, q = sigma11 - sigma22.
"""
