"""Grouping triangulated marks into object instances (``vision.instances``), on points.

The scenes are built here from the demo plate's model and known poses (scipy's rotations), so
every point's true owner is known: an instance must hold exactly the marks of one plate, two
plates are never merged, a blob is never used twice, a plate with missing marks is still found
with what it shows.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from vgripd.config import config_from_dict
from vgripd.vision import scene
from vgripd.vision.instances import find_instances

MODEL = scene.object_points(config_from_dict({}))
TOL, MAX_RMS = 3.0, 1.0


def _pose(x: float, y: float, yaw_deg: float, z: float = 700.0, tilt_deg: float = 0.0
          ) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zx", [yaw_deg, tilt_deg], degrees=True).as_matrix()
    T[:3, 3] = (x, y, z)
    return T


def _scene(poses: list[np.ndarray], noise_mm: float = 0.05, seed: int = 0,
           drop: dict[int, list[int]] | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shuffled points of every plate, with their owner (plate index) and model index."""
    rng = np.random.default_rng(seed)
    pts, owner, index = [], [], []
    for k, T in enumerate(poses):
        for i, p in enumerate(MODEL):
            if i in (drop or {}).get(k, []):
                continue
            pts.append(T[:3, :3] @ p + T[:3, 3] + rng.normal(0.0, noise_mm, 3))
            owner.append(k)
            index.append(i)
    perm = rng.permutation(len(pts))
    return np.array(pts)[perm], np.array(owner)[perm], np.array(index)[perm]


def _check(found: list, owner: np.ndarray, index: np.ndarray, poses: list[np.ndarray]
           ) -> dict[int, int]:
    """Each instance is one plate's marks, each assigned to its own model point, its pose that
    plate's; returns plate -> number of marks found."""
    seen: dict[int, int] = {}
    used: set[int] = set()
    for inst in found:
        rows = inst.assignment[inst.assignment >= 0]
        assert not used & set(rows.tolist()), "a point used by two instances"
        used |= set(rows.tolist())
        plates = set(owner[rows].tolist())
        assert len(plates) == 1, f"instance merges plates {plates}"
        plate = plates.pop()
        assert plate not in seen, f"plate {plate} found twice"
        feats = np.flatnonzero(inst.assignment >= 0)
        np.testing.assert_array_equal(index[inst.assignment[feats]], feats)
        np.testing.assert_allclose(inst.T_points_model[:3, 3], poses[plate][:3, 3], atol=0.5)
        seen[plate] = len(rows)
    return seen


def test_touching_plates_on_a_grid_are_each_found_whole() -> None:
    # Pitch = the marks' box (123 x 90 mm) plus one 10 mm mark: the footprints touch.
    poses = [_pose(c * 133.0, r * 100.0, yaw) for r in range(2) for c in range(3)
             for yaw in [(-2.0, 3.0, 1.0, -3.0, 2.5, 0.0)[3 * r + c]]]
    pts, owner, index = _scene(poses)
    grouping = find_instances(MODEL, pts, TOL, max_rms_mm=MAX_RMS)
    assert grouping.complete
    assert _check(list(grouping.instances), owner, index, poses) == {k: 6 for k in range(6)}
    assert not any(i.ambiguous for i in grouping.instances)
    assert all(i.score > 5.9 for i in grouping.instances)


def test_interleaved_plates_sharing_their_area_are_resolved_not_merged() -> None:
    # Two plates overlapping by half (one lies on the other, a few mm higher; the marks of
    # both are visible): every mark lies among the other plate's marks.
    poses = [_pose(0.0, 0.0, 0.0), _pose(35.0, 12.0, 90.0, z=690.0)]
    pts, owner, index = _scene(poses, seed=3)
    gaps = np.linalg.norm(pts[owner == 0][:, None] - pts[owner == 1][None], axis=2)
    assert gaps.min() < 30.0  # the scene really interleaves (marks are 10 mm)
    grouping = find_instances(MODEL, pts, TOL, max_rms_mm=MAX_RMS)
    assert _check(list(grouping.instances), owner, index, poses) == {0: 6, 1: 6}


def test_missing_marks_a_plate_with_three_is_reported_one_with_two_is_not() -> None:
    poses = [_pose(0.0, 0.0, 0.0), _pose(133.0, 0.0, 2.0), _pose(266.0, 0.0, -2.0),
             _pose(0.0, 100.0, 1.0)]
    drop = {1: [2], 2: [0, 3, 4], 3: [1, 2, 3, 5]}  # 5, 3 and 2 marks left
    pts, owner, index = _scene(poses, drop=drop, seed=5)
    grouping = find_instances(MODEL, pts, TOL, max_rms_mm=MAX_RMS)
    seen = _check(list(grouping.instances), owner, index, poses)
    assert seen == {0: 6, 1: 5, 2: 3}


def test_alternative_pairings_of_one_blob_are_never_both_used() -> None:
    """An epipolar pairing of a left blob with the wrong right blob is a point of its own
    sharing the left blob's key: the grouping takes the right one and drops the other."""
    poses = [_pose(0.0, 0.0, 0.0), _pose(133.0, 0.0, 3.0)]
    pts, owner, index = _scene(poses, seed=7)
    keys = [(2 * r, 2 * r + 1) for r in range(len(pts))]
    # Each plate's m1 also paired wrongly: 40 mm deeper, sharing m1's left blob.
    extra, extra_keys = [], []
    for k in (0, 1):
        row = int(np.flatnonzero((owner == k) & (index == 0))[0])
        extra.append(pts[row] + [0.0, 0.0, 40.0])
        extra_keys.append((2 * row, 1000 + k))
    all_pts = np.vstack([pts, extra])
    grouping = find_instances(MODEL, all_pts, TOL, keys + extra_keys, max_rms_mm=MAX_RMS)
    owner2 = np.r_[owner, [-1, -2]]
    index2 = np.r_[index, [-1, -1]]
    assert _check(list(grouping.instances), owner2, index2, poses) == {0: 6, 1: 6}


def test_a_symmetric_subset_of_marks_makes_that_instance_ambiguous() -> None:
    """A rectangle of four marks matches itself turned by 180 deg: the instance is found but
    flagged ambiguous; an asymmetric plate next to it is not."""
    rect = np.array([[-40.0, -25.0, 0.0], [40.0, -25.0, 0.0], [40.0, 25.0, 0.0],
                     [-40.0, 25.0, 0.0]])
    T = _pose(0.0, 0.0, 10.0)
    pts = rect @ T[:3, :3].T + T[:3, 3]
    grouping = find_instances(rect, pts, TOL, max_rms_mm=MAX_RMS)
    assert len(grouping.instances) == 1
    assert grouping.instances[0].ambiguous
    assert grouping.instances[0].rival == pytest.approx(grouping.instances[0].score, abs=0.1)
    pts2, owner, index = _scene([_pose(0.0, 0.0, 0.0)])
    (inst,) = find_instances(MODEL, pts2, TOL, max_rms_mm=MAX_RMS).instances
    assert not inst.ambiguous


def test_degenerate_inputs() -> None:
    assert find_instances(MODEL, np.zeros((0, 3)), TOL).instances == ()
    assert find_instances(MODEL, MODEL[:2], TOL).instances == ()
    # All points on one spot: no seed triangle has the model's distances.
    assert find_instances(MODEL, np.zeros((10, 3)), TOL).instances == ()


def test_the_work_bound_is_reported() -> None:
    poses = [_pose(c * 133.0, 0.0, 0.0) for c in range(3)]
    pts, _, _ = _scene(poses)
    grouping = find_instances(MODEL, pts, TOL, max_rms_mm=MAX_RMS, max_verified=1)
    assert not grouping.complete


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(count=st.integers(1, 6), seed=st.integers(0, 10_000),
       yaw=st.floats(-180.0, 180.0), tilt=st.floats(0.0, 20.0))
def test_random_pallets_every_plate_found_once(count: int, seed: int, yaw: float,
                                               tilt: float) -> None:
    """Property: any grid of plates (one common yaw and tilt, jitter of each, footprints
    touching) gives each plate exactly once, whole, and nothing else."""
    rng = np.random.default_rng(seed)
    R = Rotation.from_euler("zx", [yaw, tilt], degrees=True).as_matrix()
    poses = []
    for k in range(count):
        r, c = divmod(k, 3)
        T = _pose(*rng.uniform(-2.0, 2.0, 2), float(rng.uniform(-3.0, 3.0)))
        T[:3, 3] += (c * 140.0, r * 105.0, 0.0)
        G = np.eye(4)
        G[:3, :3] = R
        G[:3, 3] = (0.0, 0.0, 700.0)
        T[:3, 3] -= (0.0, 0.0, 700.0)  # the grid is laid out in the tilted plane
        poses.append(G @ T)
    pts, owner, index = _scene(poses, seed=seed)
    grouping = find_instances(MODEL, pts, TOL, max_rms_mm=MAX_RMS)
    assert _check(list(grouping.instances), owner, index, poses) == {k: 6 for k in range(count)}


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(count=st.integers(1, 6), seed=st.integers(0, 10_000), clutter=st.integers(0, 12),
       hidden=st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5)), max_size=6))
def test_random_pallets_with_clutter_and_hidden_marks(count: int, seed: int, clutter: int,
                                                      hidden: list[tuple[int, int]]) -> None:
    """Property: with spurious points (away from every mark's place, hidden ones included)
    and up to two hidden marks per plate, every plate is found once with exactly its visible
    marks, and no spurious point joins an instance."""
    rng = np.random.default_rng(seed)
    poses = []
    for k in range(count):
        r, c = divmod(k, 3)
        poses.append(_pose(c * 135.0 + rng.uniform(-2, 2), r * 102.0 + rng.uniform(-2, 2),
                           float(rng.uniform(-4.0, 4.0))))
    drop: dict[int, list[int]] = {}
    for plate, mark in hidden:
        if plate < count and len(drop.get(plate, [])) < 2 and mark not in drop.get(plate, []):
            drop.setdefault(plate, []).append(mark)
    pts, owner, index = _scene(poses, seed=seed, drop=drop)
    places = np.vstack([MODEL @ T[:3, :3].T + T[:3, 3] for T in poses])
    extra: list[np.ndarray] = []
    while len(extra) < clutter:
        p = rng.uniform(places.min(axis=0) - 40.0, places.max(axis=0) + 40.0)
        if np.linalg.norm(places - p, axis=1).min() > 3.0 * TOL:
            extra.append(p)
    all_pts = np.vstack([pts, *extra]) if extra else pts
    owner2 = np.r_[owner, -np.arange(1, clutter + 1)]
    index2 = np.r_[index, -np.ones(clutter, dtype=int)]
    grouping = find_instances(MODEL, all_pts, TOL, max_rms_mm=MAX_RMS)
    full = [i for i in grouping.instances if i.count >= 4]
    seen = _check(full, owner2, index2, poses)
    assert seen == {k: 6 - len(drop.get(k, [])) for k in range(count)}
