"""The daemon judges its recipes without building a pipeline when the worker process runs
them (``vgripd.vision.readiness``), and builds each one once when it runs them itself."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

from tests.conftest import REPO
from vgripd.config import config_from_dict
from vgripd.service.daemon import Daemon
from vgripd.vision.checked import CheckedPipeline

RECIPES = {
    "1": {"name": "untaught", "object": {"features": [
        {"name": f"p{i}", "kind": "circle", "diameter_mm": 8.0, "xyz_mm": xyz}
        for i, xyz in enumerate([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 35.0, 0.0],
                                 [42.0, 47.0, 0.0]])]}},
    "2": {"name": "strict", "vision": {"min_contrast": 40.0}},
}


def test_the_worker_path_builds_no_pipeline_in_the_daemon() -> None:
    """In a fresh interpreter (the modules of the pipeline not loaded by anything else):
    ``Daemon(config)`` with the worker names the untaught recipe and imports no pipeline."""
    script = textwrap.dedent(f"""
        import json, sys
        from vgripd.config import config_from_dict
        from vgripd.service.daemon import Daemon
        daemon = Daemon(config_from_dict({{"camera": {{"type": "synthetic"}},
                                           "recipes": {RECIPES!r}}}))
        assert daemon.rooms.worker is not None
        print(json.dumps({{
            "loaded": sorted(m for m in ("vgripd.vision.pipeline", "vgripd.vision.checked",
                                         "vgripd.vision.found") if m in sys.modules),
            "problems": sorted(daemon.recipe_problems), "untaught": sorted(daemon.untaught),
            "why": daemon.recipe_problems.get(1, "")}}))
    """)
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True,
                         text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout.splitlines()[-1])
    assert seen["loaded"] == []
    assert (seen["problems"], seen["untaught"]) == ([1], [1])
    assert seen["why"].startswith("reference.T_base_obj: object 'object' has no taught")


def test_in_process_each_runnable_recipe_gets_its_own_pipeline() -> None:
    config = config_from_dict({"camera": {"type": "synthetic"}, "daemon": {"worker": False},
                               "recipes": RECIPES})
    daemon = Daemon(config)
    pipelines = daemon.rooms.jobs.pipelines
    assert daemon.rooms.worker is None
    assert sorted(pipelines) == [0, 2]
    assert all(isinstance(p, CheckedPipeline) for p in pipelines.values())
    assert pipelines[0] is not pipelines[2]
    assert pipelines[2].config.vision.min_contrast == 40.0
    assert (sorted(daemon.recipe_problems), daemon.untaught) == ([1], {1})
