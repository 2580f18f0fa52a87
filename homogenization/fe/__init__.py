"""The homogenised material in finite elements: the scikit-fem solver and its output files and figures."""
