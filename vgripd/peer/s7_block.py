"""The S7 link's data block, with no I/O: its size for each register map version, the bytes of
a run of map words, and the plan of writes that takes the PLC's block to the register bank's
state (docs/s7.md).

The block is the register map of ``vgripd.peer.registers``, map register ``n`` at byte
``start + 2 n``, big-endian throughout. vgripd writes only its own stretches of it (all but the
PLC's command area and, in map version 4, its latch area), and orders its writes so that the
PLC never pairs an acknowledged sequence with data of another request (``plan_db_writes``).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from vgripd.peer.registers import COMMAND_AREA, MAP_SIZE, BlockWrite, Reg, map_size

DB_BYTES = 2 * MAP_SIZE  # bytes of the block in the DB (map version 3; ``db_bytes``)


def db_bytes(version: int) -> int:
    """Bytes of the block in the DB for register map ``version`` (3: 92, 4: 124)."""
    return 2 * map_size(version)


def block_bytes(words: Sequence[int]) -> bytearray:
    """Map words as the DB holds them: 16-bit big-endian, one after the other."""
    return bytearray(struct.pack(f">{len(words)}H", *words))


def plan_db_writes(sent: Sequence[int], journal: Sequence[BlockWrite],
                   own: Sequence[range] = (range(COMMAND_AREA.stop, MAP_SIZE),),
                   ) -> list[BlockWrite]:
    """The writes (map word addresses) that take the PLC's block from ``sent`` to the end of
    the bank's ``journal``, in the journal's order.

    Only the ``own`` stretches of the block (the mirror client link's ``own_segments``: all
    but the PLC's command area, and in map version 4 its latch area) are ever written.
    Between two changes of ACK_SEQ, every word that changed travels in one write per stretch,
    spanning its first to its last changed word there (the words in between carry what the
    PLC already has, ACK_SEQ included); a change of ACK_SEQ is a write of its own at its place
    in the order. A publish is thus the data in one write (one on each side of the latch) and
    the acknowledge after it; a new job's retraction goes before its data is cleared.
    """
    image = list(sent)
    plan: list[BlockWrite] = []
    changed: set[int] = set()

    def flush_span() -> None:
        for seg in own:
            here = [a for a in changed if a in seg]
            if here:
                lo, hi = min(here), max(here)
                plan.append(BlockWrite(lo, tuple(image[lo:hi + 1])))
        changed.clear()

    for w in journal:
        ack: int | None = None
        for i, value in enumerate(w.words):
            address = w.address + i
            if address == Reg.ACK_SEQ:
                ack = value
            elif any(address in seg for seg in own) and image[address] != value:
                image[address] = value
                changed.add(address)
        if ack is not None and ack != image[Reg.ACK_SEQ]:
            flush_span()  # the data written with (before) the acknowledge goes first
            image[Reg.ACK_SEQ] = ack
            plan.append(BlockWrite(Reg.ACK_SEQ, (ack,)))
    flush_span()
    return plan
