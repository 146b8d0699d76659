"""Everything that writes into a run directory: meshes, figures, reports.
"""
