"""Service: the daemon, the link contract and register maps, recorder, status endpoint, sd_notify.

Uses vision, geometry and config; reaches ``drivers/`` only through ``vgripd.registry``.
"""
