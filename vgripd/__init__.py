"""vgripd: vision-guided robot gripping daemon.

Internal units are millimetres and radians; vendor units appear only in ``vgripd.geometry.vendors``.
Transforms are named ``T_a_b``: the pose of frame ``b`` expressed in frame ``a``, so that
``p_a = T_a_b @ p_b`` (see ``vgripd.geometry.transforms``).
"""

__version__ = "0.1.0"
