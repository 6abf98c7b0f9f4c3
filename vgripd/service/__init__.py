"""Service: the daemon, the link contract and register maps, recorder, status endpoint, sd_notify,
rate-limited logging for links facing a network.

Uses vision, geometry and config; reaches ``drivers/`` only through ``vgripd.registry``.
"""
