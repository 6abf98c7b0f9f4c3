"""Pick lists at 6, 12 and 24 plates: time per job and per plate, against the single-object path.

The cell is ``bench/render_independent.py``'s 5 MP stereo rig (2x 2448x2048, f = 3500 px,
200 mm baseline, 850 mm above the pallet). So that 24 plates fit its view, the plate is the
demo plate of ``config/example.toml`` at half size (marks 5 mm, 80 x 60 mm layout, bosses 6
and 10 mm). Pallets of 6, 12 and 24 plates in 6 columns, footprints touching, jittered
(``bench_picklist.pallet``), are rendered *here* with render_independent's OpenCV projection
and rasteriser (no vgripd code); the truth is the pose drawn.

Per pallet:

* **pick list** (vgripd, ``picking.max_objects = plates``): one job on the pallet's image
  pair, timed ``--repeat`` times (median); the grouping's share is the job's ``pose`` lap;
* **single-object path** (the peer: ``max_objects = 1``, one job per plate on a pair of that
  plate alone, same pose and noise): the time a cell without pick lists spends on the pallet.

Errors of every plate against the truth for both. No timed assertion anywhere; the figures are
printed, and with ``--write-results`` appended to bench/RESULTS.md.

    .venv/bin/python bench/bench_pickscale.py [--plates 6 12 24] [--repeat 3] [--write-results]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import render_independent as indep  # noqa: E402
from bench.bench_picklist import cell_config, pallet, render  # noqa: E402
from bench.results import write_section  # noqa: E402
from vgripd.geometry.transforms import pose_error  # noqa: E402
from vgripd.vision.pipeline import Pipeline  # noqa: E402

SECTION = "## Pick lists at 6, 12 and 24 plates: time per job (pickreview)"
SCALE = 0.5
COLUMNS = 6


def half_plate() -> indep.Plate:
    """The demo plate at ``SCALE``: marks, diameters and the [object] table scaled alike."""
    plate = indep.Plate.from_toml()
    obj = dict(plate.toml["object"])
    obj["features"] = [{**f, "xyz_mm": [SCALE * v for v in f["xyz_mm"]],
                        "diameter_mm": SCALE * f["diameter_mm"]} for f in obj["features"]]
    return indep.Plate(plate.names, plate.centres * SCALE, plate.diameters * SCALE, plate.dark,
                       plate.T_base_obj_ref, {"object": obj, "reference": plate.toml["reference"]})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--plates", type=int, nargs="+", default=[6, 12, 24])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=24)
    ap.add_argument("--write-results", action="store_true")
    args = ap.parse_args()

    plate = half_plate()
    cell = indep.Cell(plate)
    one = Pipeline(cell_config(plate, 1))
    rng = np.random.default_rng(args.seed)
    table = ["| plates | pickable | pick-list job ms (median) | of which grouping ms | "
             "per plate ms | single path, sum of jobs ms | ratio | error pick list max mm / "
             "deg | error single max mm / deg |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for count in args.plates:
        many = Pipeline(cell_config(plate, count))
        poses = pallet(plate, count, rng, COLUMNS)
        pair = render(cell, poses, seed=2000 + count)
        times, pose_ms = [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            result = many.process(pair, count)
            times.append((time.perf_counter() - t) * 1e3)
            pose_ms.append(result.timings_ms.get("pose", float("nan")))
        job_ms, group_ms = float(np.median(times)), float(np.median(pose_ms))
        errs, taken = [], set()
        for inst in result.instances:
            if not inst.status.pose_valid or inst.T_base_obj is None:
                continue
            e = [pose_error(inst.T_base_obj, T) for T in poses]
            k = int(np.argmin([x[0] for x in e]))
            if k not in taken and e[k][0] < 5.0:
                taken.add(k)
                errs.append(e[k])
        single_ms, single_errs = 0.0, []
        for k, T in enumerate(poses):
            alone = render(cell, [T], seed=2000 + count)
            t = time.perf_counter()
            res = one.process(alone, k)
            single_ms += (time.perf_counter() - t) * 1e3
            if res.status.pose_valid and res.T_base_obj is not None:
                single_errs.append(pose_error(res.T_base_obj, T))
        e_many = np.max(np.array(errs), axis=0) if errs else [float("nan")] * 2
        e_one = np.max(np.array(single_errs), axis=0) if single_errs else [float("nan")] * 2
        row = (f"| {count} | {len(taken)} of {count} (single: {len(single_errs)}) | {job_ms:.0f} | "
               f"{group_ms:.0f} | {job_ms / max(1, len(taken)):.1f} | {single_ms:.0f} | "
               f"{job_ms / single_ms:.2f} | {e_many[0]:.3f} / {e_many[1]:.3f} | "
               f"{e_one[0]:.3f} / {e_one[1]:.3f} |")
        table.append(row)
        print(row, flush=True)
    text = "\n".join(table)
    print(text)
    if args.write_results:
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        body = (
            f"{SECTION}\n\n"
            f"`.venv/bin/python bench/bench_pickscale.py --plates {' '.join(map(str, args.plates))}"
            f" --repeat {args.repeat} --write-results`, {datetime.date.today()}, "
            f"{os.cpu_count()} cores shared with other work (load average {load}), Python "
            f"{sys.version.split()[0]}. render_independent's 5 MP stereo cell, the demo plate at "
            f"half size (5 mm marks), one pallet per size in {COLUMNS} columns, footprints "
            "touching, rendered by the bench (no vgripd code); truth = the poses drawn. Pick "
            f"list: one job per pallet, median of {args.repeat}; grouping = the job's `pose` "
            "lap. Peer: the single-object path, one job per plate on a pair of that plate "
            "alone (same pose and noise), summed; ratio = pick-list job / that sum.\n\n"
            f"{text}\n"
        )
        write_section(SECTION, body)


if __name__ == "__main__":
    main()
