"""The cases of a sweep (``hmodel sweep``, ``python -m homogenization.sweep``), apart from its command.

``plan`` (every case planned and checked before anything runs) and ``case`` (one case's test,
with the removal of the fines where it asks for one, and its summary numbers).
"""
