"""The learning cell with the plate (``plate = true``): the demo plate's marks are in view in
every grab, where the truth puts them (the oracle: the synthetic camera's own projection of the
demo marks at the demo reference, through the demo cell's cameras, and the mark survey of
``vgripd.vision.survey`` against the plate's base-frame points), while the board is still
found whole on the frames the operator holds it."""

from __future__ import annotations

import asyncio

import numpy as np

from drivers.cameras.board import BoardCamera, BoardOptions
from vgripd.calib.boards import Board
from vgripd.calib.capturesets import detect_or_none
from vgripd.config import Config
from vgripd.vision import scene
from vgripd.vision.survey import survey

SPEC = "chessboard:9x6:30"


def test_the_plate_stays_in_view_and_the_board_is_still_found() -> None:
    camera = BoardCamera(BoardOptions(board=SPEC, plate=True, hold_frames=2, move_frames=1),
                         Config())

    async def run() -> list:
        await camera.open()
        try:
            return [await camera.grab(30.0) for _ in range(9)]
        finally:
            await camera.close()

    pairs = asyncio.run(run())
    config = Config()  # the demo cell: the truth cameras and the plate at the demo reference
    rig = scene.stereo_rig(config)
    assert rig is not None
    T_ref = scene.T_base_obj_ref(config)
    points = scene.object_points(config) @ T_ref[:3, :3].T + T_ref[:3, 3]
    board = Board.parse(SPEC)
    held = 0
    for pair in pairs:
        np.testing.assert_allclose(pair.truth["T_base_obj"], T_ref, atol=1e-9)
        marks = survey(pair.left, pair.right, rig, scene.T_base_camera(config))
        assert len(marks) == len(points), pair.source
        found = np.array([m.xyz_base_mm for m in marks])
        nearest = np.min(np.linalg.norm(found[:, None] - points[None], axis=2), axis=0)
        assert nearest.max() < 0.5, (pair.source, nearest)
        if pair.truth["still"]:
            held += 1
            assert pair.truth["board_shown"]
            assert detect_or_none(board, pair.left, "left") is not None, pair.source
            assert detect_or_none(board, pair.right, "right") is not None, pair.source
    assert held == 6
