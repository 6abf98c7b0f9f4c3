"""The web view's routes are thin (``vgripd.service.web.context``): each route class is handed
the typed ``WebContext`` and reaches other objects by public names only; the history of jobs
the routes read, and the access check of an action, behave as the pages rely on."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from aiohttp import web
from aiohttp.test_utils import make_mocked_request

from tests.conftest import REPO
from vgripd.config import StatusConfig
from vgripd.service.jobs.jobrecord import JobRecord
from vgripd.service.web.access import SESSION_COOKIE, Access
from vgripd.service.web.context import JobHistory
from vgripd.types import ImagePair, JobResult, Status

WEB = REPO / "vgripd" / "service" / "web"
MODULES = sorted(WEB.glob("*.py"))


def _private_reaches(path: Path) -> list[str]:
    """``obj._name`` in ``path`` where ``obj`` is not ``self`` or ``cls`` (dunders aside)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            found.append(f"line {node.lineno}: {ast.unparse(node)}")
    return found


@pytest.mark.parametrize("path", MODULES, ids=lambda p: p.name)
def test_web_modules_reach_no_private_names(path: Path) -> None:
    bad = _private_reaches(path)
    assert not bad, f"{path.relative_to(REPO)} reaches private names:\n" + "\n".join(bad)


def _route_classes() -> list[tuple[str, ast.ClassDef]]:
    """Every class of web/ that adds routes (it has ``add(self, router)``)."""
    return [(p.name, node) for p in MODULES for node in ast.parse(p.read_text()).body
            if isinstance(node, ast.ClassDef) and any(
                isinstance(n, ast.FunctionDef) and n.name == "add"
                and [a.arg for a in n.args.args] == ["self", "router"] for n in node.body)]


#: What a route class may be handed: the context, or the setup's shared state (itself holding
#: the context) and the setup's hand-eye save.
HANDED = {"WebContext", "SetupState", "SaveHandEye"}


def test_the_route_classes_are_found() -> None:
    names = {cls.name for _, cls in _route_classes()}
    assert {"CommissionRoutes", "TeachRoutes", "PreviewRoutes", "CameraSettingsRoutes",
            "WalkRoutes", "SetupRoutes", "SetupChoices", "SetupObject",
            "SetupHandEye"} <= names


@pytest.mark.parametrize(("module", "cls"), _route_classes(), ids=lambda x: getattr(x, "name", x))
def test_route_classes_are_handed_typed_rooms(module: str, cls: ast.ClassDef) -> None:
    init = next(n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
    kinds = [ast.unparse(p.annotation) if p.annotation else "" for p in init.args.args[1:]]
    assert kinds, f"{module}: {cls.name} is handed nothing"
    assert set(kinds) <= HANDED, f"{module}: {cls.name}.__init__({ast.unparse(init.args)})"


def _record(job_id: int, recipe: int, pose: bool) -> JobRecord:
    T = np.eye(4)
    T[:3, 3] = (job_id, 0.0, 0.0)
    result = JobResult(job_id=job_id, status=Status.OK if pose else Status.NOT_FOUND,
                       T_base_obj=T if pose else None)
    return JobRecord(job_id=job_id, link="plc", seq=job_id, result=result, cycle_ms=1.0,
                     t_done_mono_ns=job_id, recipe=recipe)


def _pair() -> ImagePair:
    return ImagePair.of_views([np.zeros((4, 4), np.uint8)], 0)


def test_job_history_keeps_the_last_jobs_and_the_last_images() -> None:
    jobs = JobHistory(3)
    assert jobs.last_pair is None
    assert jobs.last_recipe() == 0
    assert jobs.last_pose() is None
    first = _pair()
    jobs.add(_record(1, 2, pose=True), {"id": 1}, first)
    jobs.add(_record(2, 5, pose=False), {"id": 2}, None)  # no images: the last pair stays
    last = jobs.last_pair
    assert last is not None
    assert last[0] == 1
    assert last[1] is first
    assert jobs.last_recipe() == 2
    assert jobs.pair_of(1) is first
    assert jobs.pair_of(2) is None
    pose = jobs.last_pose()
    assert pose is not None
    assert pose[0, 3] == 1.0  # job 2 measured none: job 1's
    jobs.add(_record(3, 0, pose=False), {"id": 3}, None)
    jobs.add(_record(4, 0, pose=False), {"id": 4}, None)
    assert jobs.summaries() == [{"id": 4}, {"id": 3}, {"id": 2}]
    assert jobs.find(1) is None
    found = jobs.find(3)
    assert found is not None
    assert found[1] == {"id": 3}
    assert jobs.last_recipe() == 0  # the images' job left the history


def _access() -> Access:
    return Access(StatusConfig.model_validate({"token": "s3cret-token-0123456789"}))


def test_an_action_disabled_is_404_naming_its_switch() -> None:
    request = make_mocked_request("POST", "/api/reload",
                                  headers={"Authorization": "Bearer s3cret-token-0123456789"})
    with pytest.raises(web.HTTPNotFound) as err:
        _access().require_action(request, False, "allow_config_edit")
    assert "status.allow_config_edit = true" in (err.value.text or "")


def test_an_action_without_the_bearer_token_is_403() -> None:
    for headers in ({}, {"Authorization": "Bearer wrong"},
                    {"Cookie": f"{SESSION_COOKIE}=s3cret-token-0123456789"}):
        request = make_mocked_request("POST", "/api/reload", headers=headers)
        with pytest.raises(web.HTTPForbidden):
            _access().require_action(request, True, "allow_config_edit")


def test_an_action_with_the_bearer_token_passes() -> None:
    request = make_mocked_request("POST", "/api/reload",
                                  headers={"Authorization": "Bearer s3cret-token-0123456789"})
    _access().require_action(request, True, "allow_config_edit")


def test_recorded_job_is_the_newest_folder_of_this_run(tmp_path: Path) -> None:
    """The recorder's folder of a job, as the image route opens an older job: this run's
    (stamped after its start), never one still being written."""
    from vgripd.service.worker.recorder import PARTIAL_PREFIX, recorded_job

    start = 1_700_000_000.0

    def stamp(t: float) -> str:
        import time

        return time.strftime("%Y%m%d-%H%M%S", time.localtime(t)) + ".000"

    (tmp_path / f"{stamp(start - 3600)}-job000007").mkdir()  # an earlier run's job 7
    assert recorded_job(tmp_path, 7, start) is None
    (tmp_path / f"{PARTIAL_PREFIX}{stamp(start + 5)}-job000007").mkdir()  # being written
    assert recorded_job(tmp_path, 7, start) is None
    (tmp_path / f"{stamp(start + 5)}-job000007").mkdir()
    (tmp_path / f"{stamp(start + 9)}-job000008").mkdir()
    assert recorded_job(tmp_path, 7, start) == str(tmp_path / f"{stamp(start + 5)}-job000007")
    assert recorded_job(tmp_path / "gone", 7, start) is None


def test_put_aside_moves_sets_out_of_the_capture(tmp_path: Path) -> None:
    import json

    from vgripd.calib.capturesets import put_aside

    sets = [{"set": n, "files": [f"left_{n:03d}.png"]} for n in (1, 2, 3)]
    for entry in sets:
        (tmp_path / entry["files"][0]).write_bytes(b"png")
    (tmp_path / "capture.json").write_text(json.dumps({"sets": sets}))
    assert put_aside(tmp_path, {2, 9}) == [2]
    assert [e["set"] for e in json.loads((tmp_path / "capture.json").read_text())["sets"]] == [
        1, 3]
    assert (tmp_path / "dropped" / "left_002.png").exists()
    assert not (tmp_path / "left_002.png").exists()
