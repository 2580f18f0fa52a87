"""The learning loop of the meso-ANN as a library (the commands are ``hmodel certify``, ``train``, ``learn``).

``certificate`` (a model measured against the DEM on homogenised tests its database did not see:
docs/certificate.md), ``from_rest`` (the DEM started from rest in every increment: the certificate's
measure of the DEM's own reproducibility), ``envelope`` (the minimum certificate, and what a
certificate covers), ``active`` (the active-learning rounds: the DEM states where the certificate
fails become new samples, the model is retrained and certified again) and ``settings`` (the typed
settings of the certificate and the rounds, light enough for the commands' parsers).
"""
