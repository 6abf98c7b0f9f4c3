"""The conveyor recipes' belt lines of a config (docs/conveyor.md), kept across a reload.

The lines themselves (latch, part queue, NEXT and PREDICT) are ``vgripd.peer.beltqueue``; this
is the daemon's side: which recipes run one, which keep theirs through a reload, and the log
line that says so.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

from vgripd.config import Config
from vgripd.peer.beltqueue import BeltLine, line_of

log = logging.getLogger("vgripd.conveyor")


def belt_lines(config: Config, running: Mapping[int, BeltLine] | None = None,
               old: Config | None = None) -> dict[int, BeltLine]:
    """The conveyor recipes' lines (docs/conveyor.md), by recipe number. A reload passes the
    ``running`` lines of the ``old`` config: a recipe whose ``[conveyor]`` and ``[output]``
    are unchanged keeps its line and queue; a changed or added one starts with an empty queue
    (its parts were placed by the old belt), a removed one is gone."""
    lines: dict[int, BeltLine] = {}
    for n in config.recipe_numbers():
        c = config.for_recipe(n)
        if c.conveyor is None:
            continue
        kept = (running or {}).get(n)
        was = old.for_recipe(n) if old is not None and n in old.recipe_numbers() else None
        if kept is not None and was is not None and (was.conveyor, was.output) == (
                c.conveyor, c.output):
            lines[n] = kept
            continue
        lines[n] = line_of(c.conveyor, c.output.vendor)
        if old is not None:
            lost = len(kept.queue) if kept is not None else 0
            log.info("conveyor of recipe %d (%s): %s by the reload, its part queue starts empty%s",
                     n, config.recipe_name(n), "changed" if kept is not None else "added",
                     f" ({lost} queued parts dropped)" if lost else "")
    for n in sorted(set(running or {}) - set(lines)):
        log.info("conveyor of recipe %d: removed by the reload", n)
    return lines
