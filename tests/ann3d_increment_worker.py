"""``relaxing_network`` for the tests that still import it from here (it lives in ``tests/other_cpus.py``)."""

from other_cpus import relaxing_network

__all__ = ["relaxing_network"]
