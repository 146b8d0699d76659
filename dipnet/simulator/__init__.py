"""The physics of a dip: tank, sensor model, protocol; a shape becomes a :class:`~dipnet.core.rawscan.RawScan`.

Uses core and shapes; never imports the rig.
"""
