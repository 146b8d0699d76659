"""``python -m dipnet.rig.fake MESH``: serve a fake rig's devices over TCP (see :mod:`dipnet.rig.fake.server`)."""

from dipnet.rig.fake.server import main

main()
