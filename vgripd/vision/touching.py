"""Marks that touch in the image: one thresholded blob holding two or more discs.

On a pallet whose plates nearly touch, a mark near one plate's edge can lie a millimetre from a
mark of the next plate. After the detection step's downscale and the lens blur the two discs
become one blob shaped like a peanut, which the circularity test rightly refuses as *one*
mark; without help both marks are lost and both plates lose a feature (a four-mark plate
becomes PARTIAL). This module finds the discs inside such a blob so that each can be refined
on its own (``features.find_circles`` with ``CircleSpec.separate_neighbours``, pick lists only;
a single-object job never gets here).

The method: the distance transform of the blob's mask peaks at the centre of each disc, at its
radius. Two discs that touch or overlap a little are separated by a neck where the distance
drops; an ellipse (a disc seen at an angle) has a ridge along its long axis instead, along
which the distance stays high. So a local maximum is a disc of its own only when the straight
path from it to every stronger accepted peak dips below ``NECK`` times the smaller of the two
peaks, and by ``MIN_DIP`` at least. Each accepted disc must also be a disc: the blob pixels
inside its rim rather than another's (the power line of the two rims) must cover about the area
of a disc of that radius (an irregular blot of dirt does not), and its diameter
must be one the spec searches for.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from vgripd.types import FloatArray

#: A valley between two peaks deeper than this share of the lower peak separates two discs
#: (two touching discs: the neck is near 0; an ellipse of axis ratio 2: the ridge stays at 1).
NECK = 0.7

#: ... and deeper than this (mask pixels) below the lower peak: the distance transform of a
#: blob a few pixels wide steps by fractions of a pixel along its ridge.
MIN_DIP = 1.0

#: The blob pixels nearest to a peak cover this range of the area of a disc of the peak's
#: radius (a disc cut by its neighbour along their bisector keeps nearly all of its area; the
#: distance transform's radius is the pixel-centre distance, so a small disc scores above 1).
AREA_RATIO = (0.6, 1.8)


def split_touching(mask: npt.NDArray[np.uint8], min_radius: float, max_radius: float
                   ) -> FloatArray:
    """The discs inside one blob's mask: (k, 3) rows of centre x, y and radius, in the mask's
    pixel coordinates (a pixel's centre at its index); empty when the blob is not two or more
    discs (one disc, a ridge, an irregular blot).

    ``min_radius``, ``max_radius``: the radii (mask pixels) a disc may have.
    """
    padded = cv2.copyMakeBorder(mask, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    dist = cv2.distanceTransform((padded > 0).astype(np.uint8), cv2.DIST_L2, 5)
    peaks_mask = (dist >= 0.5 * min_radius) & (dist >= cv2.dilate(dist, np.ones((3, 3), np.uint8)))
    ys, xs = np.nonzero(peaks_mask)
    if xs.size < 2:
        return np.zeros((0, 3))
    order = np.argsort(-dist[ys, xs], kind="stable")
    accepted: list[tuple[int, int, float]] = []
    for y, x in zip(ys[order], xs[order], strict=True):
        height = float(dist[y, x])
        if all(_valley(dist, (x, y), (ax, ay)) < min(NECK * min(height, ah),
                                                    min(height, ah) - MIN_DIP)
               for ax, ay, ah in accepted):
            accepted.append((int(x), int(y), height))
    if len(accepted) < 2:
        return np.zeros((0, 3))
    # Each blob pixel belongs to the disc whose rim it is deepest inside (the power line of
    # the two rims, as the refinement parts them): the disc's share of the blob.
    by, bx = np.nonzero(padded > 0)
    centres = np.array([(x, y, h) for x, y, h in accepted], dtype=np.float64)
    owner = np.argmin(np.hypot(bx[:, None] - centres[None, :, 0],
                               by[:, None] - centres[None, :, 1]) - centres[None, :, 2], axis=1)
    out = []
    for k, (x, y, height) in enumerate(accepted):
        area = float((owner == k).sum())
        ratio = area / (np.pi * height**2)
        if not AREA_RATIO[0] <= ratio <= AREA_RATIO[1] or not (
                min_radius <= height <= max_radius):
            return np.zeros((0, 3))  # one part is not a disc: leave the blob refused
        out.append((x - 1.0, y - 1.0, height))
    return np.array(out, dtype=np.float64)


def _valley(dist: npt.NDArray[Any], a: tuple[int, int], b: tuple[int, int]) -> float:
    """Lowest distance-transform value on the straight path from pixel a to pixel b."""
    steps = int(np.ceil(np.hypot(b[0] - a[0], b[1] - a[1]) * 2.0)) + 1
    t = np.linspace(0.0, 1.0, steps + 1)
    xs = np.rint(a[0] + t * (b[0] - a[0])).astype(np.intp)
    ys = np.rint(a[1] + t * (b[1] - a[1])).astype(np.intp)
    return float(dist[ys, xs].min())
