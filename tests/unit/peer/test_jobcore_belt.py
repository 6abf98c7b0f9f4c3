"""The job core's conveyor rules (``JobCore`` with a ``BeltLine``), against a belt simulated
here: parts at known places at count 0, each image sees the ones under the camera with a little
noise, its count latched by the link (and with the 16-bit counter's wrap). Random sequences of
images, NEXTs and PREDICTs from two robots; the rules checked on every answer: each part served
once, every pose the one its count says (never a stale pose), none past the window."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vgripd.geometry.vendors import target_from_transform, transform_from_vendor
from vgripd.peer.beltqueue import BeltLine, Latch, LatchSource, line_of
from vgripd.peer.jobcore import Admit, Command, JobCore
from vgripd.peer.registers import Reg, RegisterBank, ValueCodec
from vgripd.types import JobResult, PickInstance, Status

COUNTS_PER_MM = 4.0
BITS = 16
WINDOW = (300.0, 800.0)
CAMERA = (0.0, 250.0)  # the camera sees parts between these distances along the belt
VENDOR = "kuka"


def make_line() -> BeltLine:
    from vgripd.config import ConveyorConfig

    conveyor = ConveyorConfig(counts_per_mm=COUNTS_PER_MM, encoder_bits=BITS,
                              direction=(0.0, 1.0, 0.0), origin_mm=(100.0, -200.0, 50.0),
                              window_mm=WINDOW, trigger_distance_mm=120.0, speed_mm_s=500.0,
                              sigma_mm=0.5)
    return line_of(conveyor, VENDOR)


def truth_pose(along: float, across: float, theta_deg: float) -> np.ndarray:
    """A part ``along`` mm down the belt (direction +y from (100, -200, 50)), ``across`` to
    the left (-x), rotated ``theta_deg`` about z: written out here, not from the code."""
    t = math.radians(theta_deg + 90.0)  # the belt's x axis is the base's +y
    T = np.eye(4)
    T[:2, :2] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
    T[:3, 3] = (100.0 - across, -200.0 + along, 50.0)
    return T


class Belt:
    """The independent belt: part k at ``start[k]`` mm along at count 0."""

    def __init__(self, starts: list[float], acrosses: list[float], thetas: list[float]) -> None:
        self.starts, self.acrosses, self.thetas = starts, acrosses, thetas

    def along(self, k: int, travel_mm: float) -> float:
        return self.starts[k] + travel_mm

    def image(self, travel_mm: float, rng: np.random.Generator, job_id: int) -> JobResult:
        insts = []
        for k in range(len(self.starts)):
            a = self.along(k, travel_mm)
            if CAMERA[0] <= a <= CAMERA[1]:
                T = truth_pose(a + rng.normal(0, 0.2), self.acrosses[k], self.thetas[k])
                insts.append(PickInstance(Status.OK, target=target_from_transform(VENDOR, T),
                                          T_base_obj=T, pick_id=k + 1, score=0.9))
        if not insts:
            return JobResult(job_id=job_id, status=Status.NOT_FOUND)
        return JobResult(job_id=job_id, status=Status.OK, target=insts[0].target,
                         T_base_obj=insts[0].T_base_obj, instances=tuple(insts))


#: One step of the cell: the belt moves, maybe an image, maybe a NEXT, maybe a PREDICT ahead.
EVENTS = st.lists(st.tuples(st.sampled_from([0, 20, 40, 60, 80, 100, 120, 600]),
                            st.booleans(), st.booleans(),
                            st.one_of(st.none(), st.integers(0, 600)),
                            st.sampled_from(["a", "b"])),
                  min_size=1, max_size=50)


@settings(max_examples=100, deadline=None)
@given(EVENTS, st.lists(st.floats(30.0, 150.0), min_size=5, max_size=25),
       st.integers(0, (1 << BITS) - 1), st.integers(0, 2**31))
def test_each_part_is_served_once_at_its_own_count_never_past_the_window(
        events: list[tuple[str, int, str]], gaps: list[float], count0: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    starts = list(CAMERA[1] - np.cumsum(gaps))  # under and upstream of the camera, apart
    belt = Belt([float(s) for s in starts], list(rng.uniform(-100, 100, len(gaps))),
                list(rng.uniform(-170, 170, len(gaps))))
    line = make_line()
    core = JobCore({0: line})
    travel = 0.0
    served: dict[int, int] = {}  # part (pick_id - 1) -> times served
    last_served: dict[str, int] = {}
    job = 0

    def count_at(travel_mm: float) -> int:
        return (count0 + round(travel_mm * COUNTS_PER_MM)) % (1 << BITS)

    def check_pose(answer: JobResult, part: int, at_travel: float) -> None:
        assert answer.target is not None
        assert answer.belt is not None
        assert answer.belt.count == count_at(at_travel)
        T = transform_from_vendor(VENDOR, answer.target.values)
        expect = truth_pose(belt.along(part, at_travel), belt.acrosses[part],
                            belt.thetas[part])
        assert np.linalg.norm(T[:3, 3] - expect[:3, 3]) < 2.0  # the 0.2 mm noise, not a stale
        assert abs(answer.belt.along_mm - belt.along(part, at_travel)) < 2.0
        assert answer.belt.along_mm <= WINDOW[1]

    for move, image, want_next, ahead, link in events:
        travel += move + rng.uniform(0, 10)
        if image:
            job += 1
            result = belt.image(travel, rng, job)
            latch = line.latch(count_at(travel), None, 0, 0, None)
            assert isinstance(latch, Latch)
            assert latch.source is LatchSource.LINK
            out = core.belt_result(0, latch, result)
            assert out.belt is not None
            assert out.belt.count == count_at(travel)
            # a part seen again is the same part: once in the queue, never after it was served
            queued = [p.pick_id - 1 for p in line.queue.parts]
            assert len(queued) == len(set(queued))
            assert not set(queued) & set(served)
        if want_next:
            adm = core.trigger(link, Command.NEXT, True, busy=True, count=count_at(travel))
            assert adm.kind is Admit.NEXT
            assert adm.answer is not None
            a = adm.answer
            if a.status is Status.OK:
                assert a.belt is not None
                part = a.instances[0].pick_id - 1
                served[part] = served.get(part, 0) + 1
                assert served[part] == 1, f"part {part} served twice"
                # its pose at its own latched count, and still inside the window now
                back = ((count_at(travel) - a.belt.count) % (1 << BITS)) / COUNTS_PER_MM
                check_pose(a, part, travel - back)
                assert belt.along(part, travel) <= WINDOW[1] + 2.0
                last_served[link] = part
            else:
                assert a.status is Status.NOT_FOUND
                assert a.target is None
        if ahead is not None:
            n_travel = travel + ahead
            adm = core.trigger(link, Command.PREDICT, True, busy=False, count=count_at(n_travel))
            a = adm.answer
            assert a is not None
            if link not in last_served:
                assert a.status is Status.BAD_REQUEST
                assert a.target is None
            elif belt.along(last_served[link], n_travel) > WINDOW[1] + 2.0:
                assert a.status is Status.OUT_OF_WORKSPACE
                assert a.target is None
            elif belt.along(last_served[link], n_travel) < WINDOW[1] - 2.0:
                assert a.status is Status.OK
                check_pose(a, last_served[link], n_travel)
    stats = line.queue.stats
    assert stats.served == sum(served.values())


def test_a_job_without_its_count_ends_bad_request_and_queues_nothing() -> None:
    line = make_line()
    core = JobCore({0: line})
    T = truth_pose(100.0, 0.0, 0.0)
    result = JobResult(job_id=1, status=Status.OK, target=target_from_transform(VENDOR, T),
                       T_base_obj=T)
    why = line.latch(None, None, 0, 0, None)
    assert isinstance(why, str)
    assert "LATCH_COUNT" in why
    out = core.belt_result(0, why, result)
    assert (out.status, out.target, len(line.queue)) == (Status.BAD_REQUEST, None, 0)
    # frame id latch: a frame the PLC reported no count for is refused the same way
    line.latch_kind = LatchSource.FRAME_ID
    assert isinstance(line.latch(500, 7, 0, 0, 7), Latch)
    missing = line.latch(500, None, 0, 0, 8)
    assert isinstance(missing, str)
    assert "frame 8" in missing
    # timestamp: the count carried to the exposure, the error stated
    line.latch_kind = LatchSource.TIMESTAMP
    stamped = line.latch(1000, None, 0, 10_000_000, None)  # exposure 10 ms after the count
    assert isinstance(stamped, Latch)
    assert stamped.count == 1000 + round(500.0 * 0.010 * COUNTS_PER_MM)
    assert stamped.error_mm >= 500.0 * 2e-3


def test_predict_without_a_conveyor_is_refused() -> None:
    core = JobCore()
    adm = core.trigger("a", Command.PREDICT, True, busy=False, count=5)
    assert (adm.kind, adm.status) == (Admit.REFUSE, Status.BAD_REQUEST)


def test_map_version_4_latch_area_and_belt_result() -> None:
    codec = ValueCodec()
    bank = RegisterBank(codec, version=4)
    bank.handshake.queue = True
    assert bank.read(Reg.MAP_VERSION, 1, 0) == [4]
    bank.write(Reg.LATCH_COUNT, (*codec.u32(70000), *codec.u32(12)))
    d = bank.write(0, (1, 1, 0))
    assert (d.count, d.frame) == (70000, 12)
    bank.captured(1, 1)
    line = make_line()
    core = JobCore({0: line})
    T = truth_pose(100.0, 5.0, 30.0)
    result = core.belt_result(0, line.latch(70000 % (1 << BITS), None, 0, 0, None), JobResult(
        job_id=1, status=Status.OK, target=target_from_transform(VENDOR, T), T_base_obj=T))
    bank.publish(1, result, 0)
    w = bank.read(0, 62, 0)
    assert codec.decode_u32(w[Reg.RESULT_COUNT:Reg.RESULT_COUNT + 2]) == 70000 % (1 << BITS)
    assert w[Reg.LATCH_SOURCE] == 1
    assert abs(codec.decode_value(w[Reg.ALONG:Reg.ALONG + 2]) - 100.0) < 1e-3
    assert abs(codec.decode_value(w[Reg.ACROSS:Reg.ACROSS + 2]) - 5.0) < 1e-3
    assert abs(codec.decode_value(w[Reg.THETA:Reg.THETA + 2]) - 30.0) < 1e-3
    assert w[Reg.QUEUED] == 1
    # PREDICT needs no pick list on a conveyor link; a read-only register is named
    assert bank.write(0, (5, 2, 0)).count == 70000
    import pytest

    from vgripd.peer.registers import RegisterAccessError
    with pytest.raises(RegisterAccessError, match=r"50 \(RESULT_COUNT\) is read-only"):
        bank.write(50, (1,))
    v3 = RegisterBank(codec)
    with pytest.raises(RegisterAccessError, match="outside map version 3"):
        v3.write(46, (1,))
    assert v3.read(Reg.MAP_VERSION, 1, 0) == [3]
