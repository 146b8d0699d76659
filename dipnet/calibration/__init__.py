"""Rig calibration: estimate a :class:`~dipnet.core.geometry.RigGeometry` from dips.

Calibration is an estimation problem like reconstruction, and reuses its parts (the readers'
readings -> slabs map, the dip operator, any solver). It runs in two stages, the first of
which needs no grid and no shape, so nothing that depends on the geometry (the grid's
working ball, validation, a solver's support hull) sees the data before the geometry is
estimated:

1. **Moments** (:mod:`dipnet.calibration.moments`): the level drift from the rest level of
   every dip, then the pivot, tilt-axis offset, tilt zero (and for a reference object the
   step scale and spin zero) from the first two moments of every dip, which a rigid object
   fixes whatever its shape. A grid search over the angles and the step scale comes first,
   the heights are solved in closed form, so start heights 50+ mm off are no trap. 90%
   intervals from a bootstrap over dips (model error included), widened by a floor
   (:data:`MODEL_FLOOR`) measured over the random rigs of ``scripts/bench_calibration.py``.
2. **Volume**: a reference object's known volume gives the cross-section directly; without
   one (:func:`self_calibrate`) it is fitted as one volume gain jointly with the shape (the
   solver's ``fit_gain``), its interval widened by the shape prior's bias.

What cannot be estimated is named with the reason and how far the shape could move
(:attr:`CalibrationReport.undetermined`, :attr:`CalibrationReport.shape_motion`) and kept at
its configured value: for an unknown object the spin zero (the object's own rotation) and the
step scale (the scale of the whole scene; only section / step_scale^3 is fixed); for a
centred ball the spin zero (its symmetry) and, when its height is not known well enough for
the rig's offset, the tilt zero. A parameter known only loosely is shrunk toward its configured
value and named under :attr:`CalibrationReport.caveats` (``reference._hold_undetermined``).
The sensor lag is never estimated: at the simulator's 2 s settle time a lag shifts every
profile alike, which self-calibration's pivot absorbs (a reference ball's intervals carry it
as a height error).
"""
