"""``Rooms``: the daemon's rooms by name, the one handle the web view, the reload and the tests
take them by (``Daemon.rooms``), instead of the daemon passing each room's state on.

It lives here, the room just below the web view, because it names every room beneath it; the
daemon (the composition root) builds the rooms and hands this handle out.
"""

from __future__ import annotations

from dataclasses import dataclass

from vgripd.service.jobs.runner import JobRunner
from vgripd.service.jobs.travel import BeltTravel
from vgripd.service.jobs.walkmode import WalkMode
from vgripd.service.links.supervision import LinkSupervisor
from vgripd.service.ops.status import StatusBoard
from vgripd.service.worker.cameras import CameraSupervisor
from vgripd.service.worker.process import WorkerClient


@dataclass(frozen=True)
class Rooms:
    """Each room of one daemon (the rooms themselves change; which ones they are does not).

    - ``links``: the robot links (``links.links``, by name) and the file budget;
    - ``cameras``: the camera (``cameras.camera``), whether it is open, down or faulty;
    - ``jobs``: the job state, admission (``jobs.core``), the counters, the last job, the
      recorder and the job listeners;
    - ``walks``: a walked hand-eye calibration; ``travel``: triggering by belt travel;
    - ``status``: the status line and snapshot;
    - ``worker``: the worker process (None: the pipeline runs in the daemon's process).
    """

    links: LinkSupervisor
    cameras: CameraSupervisor
    jobs: JobRunner
    walks: WalkMode
    travel: BeltTravel
    status: StatusBoard
    worker: WorkerClient | None
