"""Property: whatever sequence of CAPTUREs (any view, also out of range) and TRIGGERs a robot
sends, the daemon answers every request exactly once, a pose only ever comes with the last view
of an uninterrupted sequence 1..N of one job, and the fit gets exactly that job's N images in
view order.

The daemon runs in-process with the synthetic camera (tiny images: only the sequencing is under
test) and a recording stand-in for the fit and for the robot link; the real links, camera
rendering and fit are tested in test_daemon_views.py.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.config import config_from_dict
from vgripd.peer.jobcore import Command
from vgripd.service.daemon import Daemon
from vgripd.service.links.protocol import LinkHealth, LinkState, RobotLink, Trigger, TriggerHandler
from vgripd.types import ImagePair, JobResult, RobotTarget, Status

N = 3
SMALL = {"fx": 150.0, "fy": 150.0, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120}
FLANGE = [{"translation_mm": [600.0 + 40.0 * k, 100.0, 700.0], "rotvec_rad": [3.1416, 0.0, 0.0]}
          for k in range(N)]


class Robot(RobotLink):
    """The robot side as the daemon sees it: every answer, in order."""

    def __init__(self) -> None:
        super().__init__("robot", None)
        self.answers: asyncio.Queue[tuple[int, str, JobResult | None]] = asyncio.Queue()

    async def open(self, on_trigger: TriggerHandler) -> None:
        self.on_trigger = on_trigger

    async def close(self) -> None:
        pass

    def health(self) -> LinkHealth:
        return LinkHealth(LinkState.UP)

    async def image_captured(self, seq: int, job_id: int) -> None:
        pass

    async def view_captured(self, seq: int, job_id: int) -> None:
        self.answers.put_nowait((seq, "view", None))

    async def publish(self, seq: int, result: JobResult) -> Status:
        self.answers.put_nowait((seq, "result", result))
        return result.status


class Fit:
    """Stands in for the pipeline: a pose for every pair, and what it was given."""

    def __init__(self) -> None:
        self.pairs: dict[int, ImagePair] = {}

    def process(self, pair: ImagePair, job_id: int) -> JobResult:
        self.pairs[job_id] = pair
        return JobResult(job_id=job_id, status=Status.OK, T_base_obj=np.eye(4),
                         target=RobotTarget("kuka", tuple("XYZABC"), (0.0,) * 6))


def config() -> Any:
    return config_from_dict({
        "camera": {"type": "synthetic", "seed": 3},
        "calibration": {"left": SMALL, "hand_eye": {
            "mounting": "robot", "T_flange_camera": {"translation_mm": [0.0, 0.0, 100.0]}}},
        "vision": {"views": N, "view_poses": FLANGE},
        "status": {"enabled": False}, "daemon": {"worker": False}})


async def run(ops: list[int | str]) -> tuple[list[tuple[Any, ...]], Fit]:
    fit = Fit()
    daemon = Daemon(config(), pipeline=fit)
    robot = Robot()
    daemon.rooms.links.links = {"robot": robot}
    await daemon.start()
    history: list[tuple[Any, ...]] = []
    try:
        for seq, op in enumerate([*ops, "trigger"], start=1):  # a TRIGGER ends any open job
            command, view = (Command.TRIGGER, 0) if op == "trigger" else (Command.CAPTURE, op)
            robot.on_trigger(Trigger("robot", seq, int(command), 0, view=int(view)))
            answer = await asyncio.wait_for(robot.answers.get(), 30)
            history.append((op, *answer))
        assert robot.answers.empty()  # one answer per request
    finally:
        await daemon.stop()
    return history, fit


@settings(max_examples=25, deadline=None)
@given(st.lists(st.one_of(st.integers(1, N + 1), st.just("trigger")), max_size=12))
def test_a_pose_only_after_an_uninterrupted_sequence_of_views(ops: list[int | str]) -> None:
    history, fit = asyncio.run(run(ops))
    for i, (op, seq, kind, result) in enumerate(history):
        assert seq == i + 1
        if kind == "view":
            assert op in range(1, N)  # only views before the last are answered "taken"
            continue
        if not result.status.pose_valid:
            assert result.target is None
            continue
        # A pose: this request is view N, the N - 1 before it were views 1..N-1, taken.
        assert op == N
        assert i >= N - 1
        assert [h[0] for h in history[i - N + 1:i + 1]] == list(range(1, N + 1))
        assert [h[2] for h in history[i - N + 1:i]] == ["view"] * (N - 1)
        # ... and the fit had exactly those N images, in view order, with their own poses.
        pair = fit.pairs[result.job_id]
        assert [m["view"] for m in pair.meta["views"]] == list(range(1, N + 1))
        assert pair.T_base_flange is not None
        np.testing.assert_allclose(pair.T_base_flange[:, 0, 3],
                                   [f["translation_mm"][0] for f in FLANGE])
