"""Recorded or simulated readings -> :class:`~dipnet.core.measurement.DipMeasurement`: one reader entry for
every recorded format, readings repair, rise -> slabs, symmetry, validation.
"""
