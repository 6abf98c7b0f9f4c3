"""Geometry: camera model, rigid transforms, stereo, orientation, vendor conventions.

Pure math on numpy arrays: no I/O, no config, nothing from the rooms above. Imports only
``vgripd.errors`` and ``vgripd.types``.
"""
