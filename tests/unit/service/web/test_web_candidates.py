"""The web view's pictures of a good job show every candidate blob with its fate (as ``replay
--annotate`` draws a failed one): the finders run again in the image helper."""

from __future__ import annotations

from collections import Counter

import pytest

from tests.unit.vision.test_diagnosis import grab
from vgripd.config import config_from_dict
from vgripd.service.web import images
from vgripd.types import Status
from vgripd.vision.pipeline import Pipeline


async def test_a_good_jobs_images_carry_its_dropped_candidates(
        monkeypatch: pytest.MonkeyPatch) -> None:
    config = config_from_dict({"camera": {"type": "synthetic", "seed": 3, "extra_blobs": 12}})
    pair = await grab(config)
    pipeline = Pipeline(config)
    result = pipeline.process(pair, 7)
    assert result.status is Status.OK
    assert result.diagnosis is None  # a good job carries none: nothing to draw from
    monkeypatch.setattr(images, "_pipeline", pipeline)  # what the helper process holds
    drawn = images._with_candidates(pair, result)
    assert drawn.diagnosis is not None
    assert drawn.status is result.status
    assert drawn.T_base_obj is result.T_base_obj  # the job's own figures, not the rerun's
    fates = Counter(c.reason for st in drawn.diagnosis.images for c in st.candidates)
    assert fates["used"] == 12  # six marks in each image
    dropped = {r for r in fates if r not in ("used", "kept")}
    assert dropped, fates  # the clutter, each with its reason
    assert drawn.diagnosis.causes == ()  # no "likely cause" line on a good job
    jpegs = images.render(pair, result)
    assert len(jpegs) == 2
