"""The register map of each register link as its peer reads it, decoded with the names of
``vgripd.peer.registers.Reg`` (what an integrator compares with the PLC's watch table)."""

from __future__ import annotations

import struct
import time
from collections.abc import Mapping
from typing import Any

from vgripd.peer.jobcore import Command, HandshakeState
from vgripd.peer.registers import MAX_VALUES, Reg, RegisterBank, Warnings
from vgripd.types import Status

_U32 = {Reg.CHECK_U32, Reg.VALUE_SCALE, Reg.JOB_ID, Reg.RESULT_AGE_MS, Reg.LATCH_COUNT,
        Reg.LATCH_FRAME, Reg.RESULT_COUNT}
_ENUMS: dict[Reg, Any] = {Reg.CMD: Command, Reg.STATE: HandshakeState, Reg.STATUS: Status,
                          Reg.REJECT_CODE: Status}


def _meaning(reg: Reg, value: int) -> str:
    if reg is Reg.REJECT_CODE and value == 0:
        return "none"  # no trigger refused: 0 is not the IDLE of the STATUS register
    kind = _ENUMS.get(reg)
    if kind is not None:
        try:
            return str(kind(value).name)
        except ValueError:
            return "" if value == 0 else "?"
    if reg is Reg.VALUE_FORMAT:
        return {1: "float32", 2: "int32 scaled"}.get(value, "?")
    if reg is Reg.WARNINGS:
        return " ".join(w.name or "" for w in Warnings if value & w) or "none"
    return ""


def decode(bank: RegisterBank, words: list[int]) -> list[dict[str, Any]]:
    """One row per named item: address, name, raw words, value, meaning."""
    codec = bank.image.codec
    rows: list[dict[str, Any]] = []
    for reg in Reg:
        a = int(reg)
        if a >= len(words):  # beyond this link's map version
            break
        if reg is Reg.VALUES:
            for i in range(MAX_VALUES):
                w = words[a + 2 * i: a + 2 * i + 2]
                rows.append({"address": a + 2 * i, "name": f"VALUES[{i}]", "words": w,
                             "value": codec.decode_value(w), "meaning": ""})
            continue
        if reg in (Reg.FIT_RMS, Reg.SCORE, Reg.LATCH_ERR_MM, Reg.ALONG, Reg.ACROSS, Reg.THETA):
            w = words[a:a + 2]
            value: float | int = codec.decode_value(w)
        elif reg is Reg.CHECK_F32:
            w = words[a:a + 2]
            hi_lo = w if codec.word_order == "ABCD" else w[::-1]
            value = struct.unpack(">f", struct.pack(">HH", *hi_lo))[0]
        elif reg in _U32:
            w = words[a:a + 2]
            value = codec.decode_u32(w)
        else:
            w = words[a:a + 1]
            value = int(w[0])  # the bank may hold an enum member (STATE): the PLC reads a word
        rows.append({"address": a, "name": reg.name, "words": [int(x) for x in w],
                     "value": value,
                     "meaning": _meaning(reg, int(value) if isinstance(value, int) else 0)})
    return rows


def register_views(links: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Every link holding a ``RegisterBank`` (``bank``): its decoded map, read now."""
    out = []
    for name, link in links.items():
        bank = getattr(link, "bank", None)
        if not isinstance(bank, RegisterBank):
            continue
        words = bank.read(0, bank.image.size, time.monotonic_ns())
        codec = bank.image.codec
        out.append({"link": name, "word_order": codec.word_order,
                    "value_format": codec.value_format, "rows": decode(bank, words)})
    return out
