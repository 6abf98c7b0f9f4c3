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

This module sits above both ``pipeline`` and ``commissioning`` (which imports the pipeline), so
neither imports the other's way round.
"""

from __future__ import annotations

from dataclasses import replace

from vgripd.types import FloatArray, ImagePair, JobResult
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
        findings = self.config_findings()
        if not findings:
            return result, points
        return replace(result, diagnosis=with_findings(d, findings)), points
