"""The bottom layer: the cell contract, parameters, CLI and file plumbing, provenance, execution.

Nothing here imports another part of the package.
"""
