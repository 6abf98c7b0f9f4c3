"""Calibration toolchain: boards, intrinsics, stereo rig, hand-eye, teaching, MCT files.

Every command writes a TOML fragment that a config pulls in with ``include = [...]``
(see ``vgripd.calib.files`` and docs/calibration.md).
"""
