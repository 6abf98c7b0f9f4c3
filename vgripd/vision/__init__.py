"""Vision: feature finders, correspondence, the locate pipeline, annotation.

Builds on ``vgripd.geometry`` and ``vgripd.config``; knows nothing about links or the daemon.
"""
