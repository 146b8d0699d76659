"""The live scan monitor: a read-only web page following a raw scan as it is written.

Rooms: :mod:`~dipnet.monitor.tail` (the scan file, followed line by line), :mod:`~dipnet.monitor.journal`
(what the scan side adds: warnings, status, the safe-stop message), :mod:`~dipnet.monitor.state` (what
the page shows), :mod:`~dipnet.monitor.worker` (the running reconstruction, a background process),
:mod:`~dipnet.monitor.replay` (a recording played back), :mod:`~dipnet.monitor.server` (FastAPI, server-sent
events) and :mod:`~dipnet.monitor.cli` (``scripts/monitor.py``). Needs the ``monitor`` extra
(``pip install -e ".[monitor]"``: fastapi, uvicorn) and plotly.
"""
