"""The vocabulary every room shares: grid, orientations, rig geometry, and the file formats (raw scans, measurements,
calibrations).

Imports no other dipnet room.
"""
