"""The daemon's heap after start-up: out of the cyclic garbage collector's way.

A full (generation 2) collection walks every object the interpreter tracks; after start-up that
is the whole of vgripd, pydantic, aiohttp, numpy and the link libraries, and one such pass took
130-150 ms on the 2-core bench machine. Run on the event loop at an unlucky moment it would hold
a PLC's poll that long. :func:`freeze_start_up_heap` collects once while nothing is waiting yet,
then moves everything still alive into the permanent generation (``gc.freeze``), so later
collections walk only what was made since; and it raises the first generation's threshold so
that the short-lived objects of each poll are swept in fewer, equally short passes.
"""

from __future__ import annotations

import gc

#: Allocations (net of deallocations) between two young-generation collections (CPython's
#: default is 700; each such pass stays well under a millisecond at this size).
GEN0_THRESHOLD = 5000


def freeze_start_up_heap() -> int:
    """Collect, freeze what is left and raise the young threshold; the number of objects
    frozen. Call once, when start-up is done and before the first request is served."""
    gc.collect()
    gc.freeze()
    _, gen1, gen2 = gc.get_threshold()
    gc.set_threshold(GEN0_THRESHOLD, gen1, gen2)
    return gc.get_freeze_count()
