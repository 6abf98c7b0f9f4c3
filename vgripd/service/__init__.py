"""Service: the daemon (``daemon.py``, the composition root) and its rooms, bottom first:
``host/`` (the process on its host), ``links/`` (the link contract and supervision),
``worker/`` (the worker process, cameras, recorder), ``jobs/``, ``ops/`` (status, reload) and
``web/``. Each room imports only the rooms before it (README "Layout").

Uses vision, geometry, config and peer; reaches ``drivers/`` only through ``vgripd.registry``.
"""
