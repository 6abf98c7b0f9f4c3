"""The worker's shared-memory image transport: the daemon's segment, images written into it
and read back (copies in the worker, read-only views in the daemon), and the sweep of segments
a killed daemon left behind. ``vgripd.service.worker.process`` has the protocol around it (module
docstring, "Images never travel through a pickle").
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
import weakref
from collections.abc import Sequence
from multiprocessing import shared_memory
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vgripd.errors import VgripError
from vgripd.types import ImagePair

#: Image offsets in the segment are aligned to this (bytes).
ALIGN = 64
SHM_DIR = Path("/dev/shm")

#: Where each image of a pair lies in the segment: (offset, shape, dtype.str), None for no image.
ImageLayout = tuple[tuple[int, tuple[int, ...], str] | None, ...]


# Raised by the transport too (a closed segment, a short read), so it is defined here;
# ``vgripd.service.worker.process`` re-exports it.
class WorkerError(VgripError):
    """The worker process did not answer a request: it died, or the request raised there."""


def _aligned(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


def images_nbytes(images: Sequence[npt.NDArray[Any] | None]) -> int:
    """Bytes a segment needs for ``images`` (each starting on an ``ALIGN`` boundary)."""
    return sum(_aligned(im.nbytes) for im in images if im is not None)


def write_images(buf: memoryview, images: Sequence[npt.NDArray[Any] | None]) -> ImageLayout:
    """Copy ``images`` into ``buf`` one after the other; the layout to read them back."""
    layout: list[tuple[int, tuple[int, ...], str] | None] = []
    offset = 0
    for image in images:
        if image is None:
            layout.append(None)
            continue
        view: npt.NDArray[Any] = np.ndarray(image.shape, image.dtype, buffer=buf, offset=offset)
        view[...] = image
        del view  # a live view would keep the segment from being closed
        layout.append((offset, tuple(image.shape), image.dtype.str))
        offset += _aligned(image.nbytes)
    return tuple(layout)


def read_images(buf: memoryview, layout: ImageLayout) -> list[npt.NDArray[Any] | None]:
    """Copies (not views) of the images described by ``layout``."""
    images: list[npt.NDArray[Any] | None] = []
    for entry in layout:
        if entry is None:
            images.append(None)
            continue
        offset, shape, dtype = entry
        view: npt.NDArray[Any] = np.ndarray(shape, np.dtype(dtype), buffer=buf, offset=offset)
        images.append(view.copy())
        del view
    return images


class ImageSegment:
    """A shared-memory segment created by the daemon; the worker attaches it by name.

    The daemon reads images from it as read-only views (``view_images``), never copying pixels
    on the event loop. Each call maps the segment afresh, and that mapping lives exactly as long
    as some array (or a slice of one) refers to it: ``in_use`` says whether images handed out
    are still alive, in which case the segment must not be written again (a new one is made).
    """

    def __init__(self, name: str, size: int) -> None:
        self.name = name
        self.size = size
        self._shm: shared_memory.SharedMemory | None = shared_memory.SharedMemory(
            name=name, create=True, size=size)
        self._views: weakref.ref[mmap.mmap] | None = None

    def in_use(self) -> bool:
        """True while arrays from ``view_images`` are still referenced somewhere."""
        return self._views is not None and self._views() is not None

    def view_images(self, layout: ImageLayout) -> list[npt.NDArray[Any] | None]:
        """Read-only views of the images described by ``layout`` (no copy)."""
        fd = os.open(SHM_DIR / self.name, os.O_RDONLY)
        try:
            mapping = mmap.mmap(fd, self.size, prot=mmap.PROT_READ)
        finally:
            os.close(fd)
        self._views = weakref.ref(mapping)
        images: list[npt.NDArray[Any] | None] = []
        for entry in layout:
            if entry is None:
                images.append(None)
                continue
            offset, shape, dtype = entry
            count = int(np.prod(shape))
            images.append(np.frombuffer(mapping, np.dtype(dtype), count, offset).reshape(shape))
        return images

    @property
    def buf(self) -> memoryview:
        if self._shm is None:
            raise WorkerError(f"shared memory {self.name} is closed")
        buf = self._shm.buf
        assert buf is not None
        return buf

    def close(self) -> None:
        """Unmap and unlink; safe to call more than once."""
        shm, self._shm = self._shm, None
        if shm is None:
            return
        try:
            shm.close()
        finally:
            with contextlib.suppress(FileNotFoundError):
                shm.unlink()

    @staticmethod
    def unlink_name(name: str) -> None:
        """Unlink a segment known only by name (one a crash left behind)."""
        seg = shared_memory.SharedMemory(name=name)
        seg.close()
        seg.unlink()


_SEGMENT_NAME = re.compile(r"vgripd-(\d+)-[0-9a-f]+-\d+")


def sweep_stale_segments() -> list[str]:
    """Unlink the segments of vgripd daemons that no longer run (killed together with their
    resource tracker, e.g. a whole process group at once); the names unlinked."""
    swept = []
    for name in segments_of("vgripd-"):
        match = _SEGMENT_NAME.fullmatch(name)
        if match is None:
            continue
        try:
            os.kill(int(match.group(1)), 0)
        except ProcessLookupError:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(SHM_DIR / name)
                swept.append(name)
        except PermissionError:
            pass  # alive, another user's
    return swept


def segments_of(prefix: str) -> list[str]:
    """Names of the shared-memory segments in /dev/shm starting with ``prefix``."""
    try:
        return sorted(p.name for p in SHM_DIR.iterdir() if p.name.startswith(prefix))
    except OSError:
        return []


def _pair_fields(pair: ImagePair) -> dict[str, Any]:
    """Everything of a pair but its pixels, picklable (mappingproxy is not)."""
    return {"t_mono_ns": pair.t_mono_ns, "source": pair.source, "meta": dict(pair.meta),
            "T_base_flange": pair.T_base_flange, "truth": dict(pair.truth)}


def _pair_of(images: Sequence[npt.NDArray[Any] | None], fields: dict[str, Any]) -> ImagePair:
    """The acquisition of ``images`` read back from shared memory (all present, camera order)."""
    views = [image for image in images if image is not None]
    if len(views) != len(images) or not views:
        raise WorkerError(f"shared memory held {len(views)} of {len(images)} images")
    return ImagePair.of_views(views, **fields)
