"""What a run leaves behind: its run files, their figures and the labels and look those share.

``io`` (``run.h5`` and ``curve.csv``: write and read a run), ``figures`` (the biaxial figure of
several runs and the side-by-side panels), ``figure_style`` (the look of every figure: ticks,
axis labels, numbers), ``run_labels`` (titles and legend labels from a run's metadata) and
``oedometer`` (oedometer.csv, the table of a K0 test).
"""
