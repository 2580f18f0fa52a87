"""Bayesian calibration of the H-model's micro-parameters on measured curves (``hmodel calibrate``).

``data`` reads the measured curves, ``forward`` runs a population of parameter sets as one
batch of cells, ``bayes`` holds the prior, the likelihood and the sampling helpers (emcee),
``report`` writes the outputs. docs/calibration.md has a worked example.
"""
