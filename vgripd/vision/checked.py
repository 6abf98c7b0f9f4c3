"""The pipeline the daemon runs: ``Pipeline`` whose failed jobs also carry what ``vgripd check``
finds in the config (``vgripd.vision.commissioning.check_scene``).

Why: the runtime diagnosis reads one job's images, and a config that cannot work at all may
leave little there to read. With ``vision.working_distance_mm`` = [100, 400] for an object at
1 m, the marks are too small to become candidates at all, and the images alone say "no mark-like
blob" while ``vgripd check`` names the key from the geometry. So a failed job's causes start
with check's ERRORs (the config cannot find the taught reference: a fact, not a guess), then the
job's own causes, then check's WARNINGs; one cause per key. The scene check runs once, at the
first failed job (projections only, no image work), and is kept with the pipeline (a reload
builds a new one).

Images swapped between cameras (a multi-camera cell: two cables or serials exchanged, or
``calibration.cameras`` in another order than the images): each camera then sees marks its
calibration cannot explain, and the job ends NOT_FOUND "0 feature(s) matched". A failed
multi-camera job whose cameras found marks is run again with two images exchanged, for the
cameras that found marks (at most ``MAX_SWAP_PROBES`` runs, only on a failure); when one
exchange gives a valid pose, the two cameras are named first.

This module sits above both ``pipeline`` and ``commissioning`` (which imports the pipeline), so
neither imports the other's way round.
"""

from __future__ import annotations

from dataclasses import replace

from vgripd.types import FloatArray, ImagePair, JobResult, Status
from vgripd.vision.commissioning import Finding, check_scene
from vgripd.vision.diagnosis import Cause, Diagnosis
from vgripd.vision.pipeline import Pipeline


def with_findings(d: Diagnosis, findings: tuple[Finding, ...]) -> Diagnosis:
    """``d`` with check's findings among its causes: ERRORs first, WARNINGs last, one per key."""
    errors = [Cause(f.key, f"{f.message} (as vgripd check finds)")
              for f in findings if f.level == "ERROR"]
    warnings = [Cause(f.key, f"{f.message} (as vgripd check finds)")
                for f in findings if f.level == "WARNING"]
    seen: set[str] = set()
    causes = []
    for cause in (*errors, *d.causes, *warnings):
        if cause.key not in seen:
            seen.add(cause.key)
            causes.append(cause)
    return replace(d, causes=tuple(causes))


#: Exchanges of two cameras' images tried on a failed multi-camera job (each a pipeline run).
MAX_SWAP_PROBES = 10
#: Statuses whose jobs are probed for swapped images.
SWAP_PROBED = frozenset({Status.NOT_FOUND, Status.PARTIAL, Status.RESIDUAL_TOO_HIGH})


class CheckedPipeline(Pipeline):
    """``Pipeline`` plus ``vgripd check``'s scene findings in a failed job's diagnosis."""

    _findings: tuple[Finding, ...] | None = None

    def config_findings(self) -> tuple[Finding, ...]:
        """check's scene findings for this config (computed once)."""
        if self._findings is None:
            try:
                self._findings = tuple(check_scene(self))
            except Exception:  # noqa: BLE001 - explaining a failure must never fail the job
                self._findings = ()
        return self._findings

    def process_with_points(
        self, pair: ImagePair, job_id: int, *, diagnose: bool = False
    ) -> tuple[JobResult, dict[str, FloatArray]]:
        result, points = super().process_with_points(pair, job_id, diagnose=diagnose)
        d = result.diagnosis
        if d is None or result.status.pose_valid:
            return result, points
        swap = self._swapped(pair, result)
        if swap is not None:
            d = replace(d, causes=(swap, *(c for c in d.causes if c.key != swap.key)))
        findings = self.config_findings()
        if findings:
            d = with_findings(d, findings)
        return replace(result, diagnosis=d), points

    def _swapped(self, pair: ImagePair, result: JobResult) -> Cause | None:
        """The two cameras whose images, exchanged, give a valid pose (None: no such pair)."""
        multi, d = self.multi, result.diagnosis
        if multi is None or d is None or result.status not in SWAP_PROBED:
            return None
        views = list(pair.views)
        if len(views) != len(d.images):
            return None
        seeing = [j for j, st in enumerate(d.images) if st.found + st.identified >= 3]
        tries = [(a, b) for i, a in enumerate(seeing) for b in seeing[i + 1:]
                 if views[a] is not None and views[b] is not None
                 and views[a].shape == views[b].shape][:MAX_SWAP_PROBES]
        for a, b in tries:
            swapped = list(views)
            swapped[a], swapped[b] = views[b], views[a]
            probe = Pipeline.process_with_points(
                self, ImagePair.of_views(swapped, pair.t_mono_ns, source=pair.source,
                                         T_base_flange=pair.T_base_flange), result.job_id)[0]
            if probe.status.pose_valid:
                names = multi.names
                return Cause("calibration.cameras", (
                    f"the images of cameras {names[a]} and {names[b]} look swapped: with "
                    f"them exchanged the job is {probe.status.name}; check which camera is "
                    f"which (serials, cables) against the order of calibration.cameras "
                    f"({names[a]} is entry {a}, {names[b]} entry {b})"))
        return None
