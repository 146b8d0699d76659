"""A fake dipping rig: a simulated tank with an object, speaking the real protocols.

One :class:`~dipnet.rig.fake.world.FakeRig` is one simulated *world*: a shape (mesh or analytic) held by a stage
with a lowering axis and two rotary axes over a tank of water. Its devices share that world,
so the water level a sensor reports follows the stage position and orientation through the
tank physics of :mod:`dipnet.simulator.physics` (``A delta = V(t_start + s + delta)``):

* controllers: ``grbl`` (GRBL 1.1) and ``marlin`` (Marlin 2.x, line numbers and checksums);
* sensors: ``level`` (ASCII line stream, or polled), ``modbus`` (Modbus RTU holding
  registers), ``ad`` (A&D balance) and ``sics`` (MT-SICS balance).

Reach them with pyserial URLs, so the real drivers run unchanged:

* in process: ``fakerig://<name>/<device>`` after ``rig.register("<name>")`` (the URL handler
  is :mod:`dipnet.rig.protocol_fakerig`);
* from another process: :func:`~dipnet.rig.fake.server.serve` (or ``python -m dipnet.rig.fake MESH``) opens TCP
  servers on 127.0.0.1 and prints ``socket://127.0.0.1:<port>`` URLs.

Geometry: the object's origin sits ``origin_height_mm`` above the resting water when the
stage is at ``lower_mm = 0`` and untilted; the rest is one :class:`~dipnet.core.geometry.RigGeometry`
(ideal by default; give a mismatched one to make a rig that needs calibration), so the water
line in the object frame is ``t = -origin_height + p (cos r - 1) + e sin r + step_scale lower + delta``
(``r`` the true tilt), the directions follow the true rig angles, the rise uses the true
cross-section and level readings drift by ``level_drift_mm_per_s`` from the world's creation
(the sensor lag is not modelled here).

Faults (:class:`~dipnet.rig.fake.world.Fault`) fire once, on the n-th motion command the controller receives:
``drop`` (the reply is lost), ``error`` (GRBL ``error:N`` / Marlin ``Error:``), ``alarm``
(GRBL ``ALARM:N`` / Marlin stopped), ``reset`` (banner mid-scan), ``disconnect`` (the link
dies; GRBL: with the move under way, as recorded in ``t4e2`` and ``t4e3``), ``resend``
(Marlin: a corrupted line, answered by ``Resend:``), ``unstable`` (the sensor is noisy and
reports "unstable" for the next ``count`` readings), and for GRBL: ``hold`` (a feed hold
lands half-way through the move), ``door`` (the safety door opens), ``late_ok`` (the next
``G4 P0`` is acknowledged ``delay_s`` late), ``corrupt_status`` / ``split_status`` (the next
status report has one byte corrupted / turned into a newline).

The fake GRBL follows the real firmware's recorded behaviour (``tests/data/grbl-traces``): it
has ``$$`` settings (:data:`~dipnet.rig.fake.world.GRBL_SETTINGS`, ``grbl_settings`` overrides them), answers ``$I``,
starts in ``Alarm`` when homing is enabled (``$22=1``) and rejects ``$H`` with ``error:5`` when
it is not; ``ALARM:1`` / ``ALARM:2`` (also from soft limits, ``$20=1``: machine space
``[-$13N, 0]``) are followed by ``[MSG:Reset to continue]`` and silence, even to ``?``, until a
soft reset; a reset while moving (or in ``Hold:1``) gives ``ALARM:3``; a held ``G4 P0`` is
acknowledged only after ``~`` or a reset.

Sensor noise is drawn from a generator keyed by the seed, the stage position and the count of
readings since the last move command, so a resumed scan reads the same noise as an
uninterrupted one.
"""
