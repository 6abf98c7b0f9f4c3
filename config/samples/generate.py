"""Regenerate the bundled sample images of the demo cell (run from the repository root).

    .venv/bin/python config/samples/generate.py

Writes ``left_NN.png`` / ``right_NN.png`` (NN = 00..04), rendered by the synthetic camera with
the embedded demo calibration and object (empty config), and ``truth.json`` with each frame's
true ``T_base_obj`` (4x4, mm) and projected mark centres (px). Noise-free (only blur and uneven
lighting) so that the PNGs stay small; the synthetic driver adds noise when asked.
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

import cv2

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from drivers.cameras.synthetic import SyntheticCamera, SyntheticOptions  # noqa: E402
from vgripd.config import config_from_dict  # noqa: E402

FRAMES = 5
OPTIONS = SyntheticOptions(seed=2026, max_shift_mm=15.0, max_tilt_deg=4.0, blur_px=0.8,
                           noise_std=0.0, gradient=0.15)


async def main() -> None:
    camera = SyntheticCamera(OPTIONS, config_from_dict({}))
    await camera.open()
    frames = []
    try:
        for i in range(FRAMES):
            pair = await camera.grab(30.0)
            assert pair.right is not None
            for side, image in (("left", pair.left), ("right", pair.right)):
                cv2.imwrite(str(HERE / f"{side}_{i:02d}.png"), image,
                            [cv2.IMWRITE_PNG_COMPRESSION, 9])
            t = pair.truth
            frames.append({
                "left": f"left_{i:02d}.png",
                "right": f"right_{i:02d}.png",
                "T_base_obj": t["T_base_obj"].round(9).tolist(),
                "feature_names": list(t["feature_names"]),
                "pixels_left": t["pixels_left"].round(6).tolist(),
                "pixels_right": t["pixels_right"].round(6).tolist(),
            })
    finally:
        await camera.close()
    text = json.dumps({"options": OPTIONS.model_dump(mode="json"), "frames": frames}, indent=1)
    (HERE / "truth.json").write_text(text + "\n", encoding="utf-8")


if __name__ == "__main__":
    asyncio.run(main())
