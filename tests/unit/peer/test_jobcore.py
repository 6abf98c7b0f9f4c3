"""The job core (``vgripd.peer.jobcore``) fed random sequences of events, without I/O.

A cell of seven links, each kind, shares one ``JobCore`` as the daemon does:

- ``plc``, ``s7``, ``mbclient``: register links (Modbus server / RTU; S7; Modbus client),
  through the ``RegisterBank`` the drivers use; its journal of block writes is replayed one
  write at a time as the peer gets them (the server's image changes, the S7 link's DB writes
  from ``plan_db_writes``, the Modbus client's from ``plan_writes``), as a PLC polling between
  two writes would see them;
- ``ua``: an OPC UA link's handshake (a request per method call); its plans are applied to an
  answer area of RequestId and result data;
- ``robot``: the robot socket's handshake (a request per frame); its answers are frames whose
  kind (RESULT or REFUSED) the plan's ACK says;
- ``ur``: the UR RTDE link's handshake (register semantics: a request is a new non-zero
  sequence) and its plans as UR register writes (``ur_wire.writes``), read as the robot
  program reads them (the answer when ``ack`` names its request; a refusal is an answer);
- ``vision``: an OPC UA link's OPC 40100 state machine (``VisionMachine``): StartSingleJob and
  the plain Next go through its states first (refused in any state but Ready), CLEAR and
  unknown commands stand for the older namespace's calls on the same link; random
  SelectModeAutomatic, PrepareRecipe, UnprepareRecipe, Halt, Reset, Stop and Abort calls move
  it (a job aborted meanwhile still ends once, ABORTED without a pose); StartContinuous starts
  a chain of jobs, each next one requested as the link does once the previous one is finished,
  until Stop (after the running job), Abort, Halt or Reset (at once) or a refusal ends it.

Random events: a request of any link (TRIGGER, CLEAR, NEXT, an unknown command; on the
register link also the same sequence again and 0, which are no requests), the running job's
image taken, the running job's end with a random result (one object, none, a pallet of n
with some not pickable, INTERNAL as when the worker died), and the daemon shutting down (every
trigger ABORTED) and taking jobs again. The rules checked on what comes out:

- each request is answered exactly once (acknowledged or refused), and only requests are;
- while an acknowledge names a request, the data is that request's (never written under the
  previous request's sequence: ACK retracted before the data changes, written last);
- never a stale or repeated pose: a pose answered is the running job's, or an instance of the
  last job's list that was not handed out yet, to the link that triggered that job;
- COUNT/INDEX: a job's answers count its pickable instances (a single object: a list of one),
  INDEX walks 1..COUNT then stays at COUNT + 1 with NOT_FOUND; no pose, no INDEX.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.links.modbus_client import plan_writes
from vgripd.peer import ur_wire
from vgripd.peer.jobcore import (
    Action,
    Admit,
    Command,
    Decision,
    Handshake,
    JobCore,
    Part,
    PickPosition,
    Step,
    ViewsAt,
    ViewStep,
    check_plans,
    next_answer,
    pick_position,
    view_admission,
)
from vgripd.peer.registers import MAP_SIZE, PICK_AREA, BlockWrite, Reg, RegisterBank, ValueCodec
from vgripd.peer.s7_block import plan_db_writes
from vgripd.peer.socket_frames import remaining
from vgripd.peer.ur_registers import URRegisterMap
from vgripd.peer.visionsm import EXECUTING, Auto, VisionMachine
from vgripd.types import JobResult, PickInstance, RobotTarget, Status

FIELDS = tuple("xyzabc")
CODEC = ValueCodec()
#: the result data of the register map (RESULT_AGE_MS is live, WARNINGS the daemon's state)
DATA = sorted(set(range(Reg.STATUS, Reg.WARNINGS)) - {Reg.RESULT_AGE_MS, Reg.RESULT_AGE_MS + 1}
              | set(PICK_AREA))


def pose(job_id: int, index: int) -> tuple[float, ...]:
    """A pose that names its job and instance (exact in float32)."""
    return (float(job_id), float(index), 0.0, 0.0, 0.0, 0.0)


def job_result(job_id: int, kind: str, n: int, bad: int) -> JobResult:
    """``kind``: ``one`` object with a pose, ``none`` found, or a ``pallet`` of ``n`` pickable
    instances followed by ``bad`` out-of-limits ones."""
    if kind == "one":
        return JobResult(job_id=job_id, status=Status.OK,
                         target=RobotTarget("kuka", FIELDS, pose(job_id, 1)))
    if kind == "died":  # the worker died (or the job timed out): the job still ends once
        return JobResult(job_id=job_id, status=Status.INTERNAL, message="worker exited")
    if kind == "none" or n + bad == 0:
        return JobResult(job_id=job_id, status=Status.NOT_FOUND, message="no marks")
    ok = tuple(PickInstance(Status.OK, target=RobotTarget("kuka", FIELDS, pose(job_id, i + 1)),
                            pick_id=i + 1, score=0.5) for i in range(n))
    rejected = tuple(PickInstance(Status.OUT_OF_LIMITS, "beyond the limit") for _ in range(bad))
    first = (ok + rejected)[0]
    return JobResult(job_id=job_id, status=first.status, message=first.message,
                     target=first.target, instances=ok + rejected)


@dataclass(frozen=True)
class Answer:
    """What a peer got for a request: refused (``code``), or acknowledged with this data."""

    seq: int
    refused: bool
    status: int = 0
    job_id: int = 0
    pose: tuple[float, ...] = ()
    count: int = 0
    index: int = 0
    frame: str = ""  # robot socket: RESULT or REFUSED


class RegisterLink:
    """A register link: the drivers' ``RegisterBank``; its writes replayed one by one as the
    peer gets them (``wire``): a server's image changes (``server``: Modbus/TCP, RTU), the S7
    link's DB writes (``plan_db_writes``) or the Modbus client link's writes (``plan_writes``)."""

    edge = True

    def __init__(self, wire: str = "server") -> None:
        self.wire = wire
        self.journal: list[BlockWrite] = []
        self.bank = RegisterBank(CODEC, self.journal)
        self.seen = [0] * MAP_SIZE  # the block as a poller sees it, write by write
        self.acked_data: list[int] | None = None
        self.answers: list[Answer] = []
        self.faults: list[str] = []
        self.last_seq = 0

    @property
    def handshake(self) -> Handshake:
        return self.bank.handshake

    def request(self, command: int, seq: int) -> Decision:
        decision = self.bank.write(Reg.CMD, [command, seq, 0])
        self._replay()
        return decision

    def captured(self, seq: int, job_id: int) -> None:
        self.bank.captured(seq, job_id)
        self._replay()

    def publish(self, seq: int, result: JobResult) -> None:
        self.bank.publish(seq, result, now_ns=0)
        self._replay()

    def _replay(self) -> None:
        writes = (self.journal if self.wire == "server" else
                  plan_db_writes(self.seen, self.journal) if self.wire == "s7" else
                  plan_writes(self.journal, image=self.bank.image.words))
        for w in writes:
            before = self.seen[Reg.ACK_SEQ]
            rejected = self.seen[Reg.REJECT_SEQ]
            self.seen[w.address:w.address + len(w.words)] = w.words
            ack = self.seen[Reg.ACK_SEQ]
            data = [self.seen[a] for a in DATA]
            if ack and ack == before and data != self.acked_data:
                self.faults.append(f"data changed while ACK_SEQ = {ack}: {w}")
            if self.seen[Reg.REJECT_SEQ] != rejected:
                self.answers.append(Answer(self.seen[Reg.REJECT_SEQ], True,
                                           self.seen[Reg.REJECT_CODE]))
            if ack != before and ack:
                self.acked_data = data
                s = self.seen
                n = s[Reg.N_VALUES]
                values = tuple(CODEC.decode_value(s[Reg.VALUES + 2 * i:Reg.VALUES + 2 * i + 2])
                               for i in range(n))
                self.answers.append(Answer(ack, False, s[Reg.STATUS],
                                           CODEC.decode_u32(s[Reg.JOB_ID:Reg.JOB_ID + 2]),
                                           values, s[Reg.COUNT], s[Reg.INDEX]))
        self.journal.clear()


class MessageLink:
    """A link whose requests are messages (OPC UA methods, socket frames): its handshake's
    plans applied to an answer area (the acknowledge and the data it names)."""

    edge = False

    def __init__(self, frames: bool) -> None:
        self.frames = frames  # robot socket: each answer is one frame, RESULT or REFUSED
        self.handshake = Handshake(edge=False)
        self.plans: list[tuple[Step, ...]] = []
        self.answers: list[Answer] = []
        self.faults: list[str] = []
        self.ack = 0
        self.data: Answer | None = None

    def request(self, command: int, seq: int) -> Decision:
        decision = self.handshake.on_request(command, seq)
        self._apply(decision.steps)
        return decision

    def captured(self, seq: int, job_id: int) -> None:
        self._apply(self.handshake.on_captured(seq, job_id))

    def publish(self, seq: int, result: JobResult) -> None:
        self._apply(self.handshake.publish(seq, result))

    def _apply(self, plan: tuple[Step, ...]) -> None:
        self.plans.append(plan)
        for step in plan:
            if step.part in (Part.CLEAR, Part.JOB_ID, Part.RESULT) and self.ack:
                self.faults.append(f"{step.part.value} while the acknowledge names {self.ack}")
            if step.part is Part.RETRACT:
                self.ack = 0
            elif step.part is Part.CLEAR:
                self.data = Answer(0, False)
            elif step.part is Part.RESULT:
                assert step.result is not None
                assert step.position is not None
                r = step.result
                values = r.target.values if r.status.pose_valid and r.target else ()
                self.data = Answer(0, False, int(r.status), r.job_id, tuple(values),
                                   step.position.count, step.position.index)
            elif step.part is Part.REJECT:
                self.answers.append(Answer(step.seq, True, step.value,
                                           frame="REFUSED" if self.frames else ""))
            elif step.part is Part.ACK:
                self.ack = step.seq
                assert self.data is not None
                frame = ("REFUSED" if step.refused else "RESULT") if self.frames else ""
                d = self.data
                self.answers.append(Answer(step.seq, False, d.status, d.job_id, d.pose,
                                           d.count, d.index, frame))


class URLink:
    """The UR RTDE link: its handshake (``ur_wire.handshake``) and its plans rendered as
    UR register writes (``ur_wire.writes``), applied one by one to the input registers
    as the robot program reads them: it takes the answer to its request when ``ack`` names
    it, reading status, job id, the pick word and both pose pages in that moment. The map has
    no retraction and no refusal registers: a refusal is an answer (status, job id 0, ack),
    and data may change under an older request's ack once the robot asked anew (it reads
    nothing before ``ack`` names its new request)."""

    edge = True

    def __init__(self) -> None:
        self.regs = URRegisterMap()
        self.handshake = ur_wire.handshake(self.regs)
        self.ints: dict[int, int] = {}
        self.doubles: dict[int, float] = {}
        self.answers: list[Answer] = []
        self.faults: list[str] = []
        self.current = 0  # the robot's request register
        self.refused_current = False  # its current request was refused by the link

    def request(self, command: int, seq: int) -> Decision:
        self.current = seq
        decision = self.handshake.on_request(command, seq)
        self.refused_current = decision.action is Action.REJECT
        self._apply(decision.steps, refused=self.refused_current)
        return decision

    def captured(self, seq: int, job_id: int) -> None:
        self._apply(self.handshake.on_captured(seq, job_id))

    def publish(self, seq: int, result: JobResult) -> None:
        self._apply(self.handshake.publish(seq, result))

    def _apply(self, plan: tuple[Step, ...], refused: bool = False) -> None:
        regs = self.regs
        for write in ur_wire.writes(regs, plan):
            acked = self.ints.get(regs.ack, 0)
            if write[0] in ("int", "double") and write[1] != regs.ack and write[1] != \
                    regs.captured and acked and acked == self.current \
                    and not self.refused_current:
                self.faults.append(f"{write} while ack names the robot's request {acked}")
            if write[0] == "int":
                self.ints[write[1]] = write[2]
            elif write[0] == "double":
                self.doubles[write[1]] = write[2]
            elif write[0] == "page":
                assert write[1] == acked  # the rotation page of the request just answered
                if write[2] is not None:
                    self.answers[-1] = dataclasses.replace(
                        self.answers[-1], pose=self.answers[-1].pose + tuple(write[2]))
            if write[0] == "int" and write[1] == regs.ack:
                pick = int(self.doubles.get(regs.pick, 0.0))
                status = self.ints.get(regs.status, 0)
                translation = (tuple(self.doubles[r] for r in regs.page)
                               if Status(status).pose_valid else ())
                self.answers.append(Answer(write[2], refused, status,
                                           self.ints.get(regs.job_id, 0), translation,
                                           pick // URRegisterMap.PICK_BASE,
                                           pick % URRegisterMap.PICK_BASE))


class VisionLink(MessageLink):
    """An OPC UA link's OPC 40100 side: requests through ``VisionMachine``'s states."""

    def __init__(self) -> None:
        super().__init__(frames=False)
        self.machine = VisionMachine()
        self.handshake = self.machine.handshake
        self.aborted: set[int] = set()  # requests whose result came ABORTED by a client's call
        self.expect_abort: set[int] = set()  # requests whose execution state a call ended
        #: what a TRIGGER is: StartSingleJob, StartContinuous, or the chain's next job
        self.mode = "single"

    def request(self, command: int, seq: int) -> Decision:
        m = self.machine
        before = m.auto
        start = {"single": lambda: m.start_single_job(seq, None),
                 "continuous": lambda: m.start_continuous(seq, None),
                 "chain": lambda: m.continue_job(seq)}[self.mode]
        verdict = (start() if command == Command.TRIGGER else
                   m.next_object(seq) if command == Command.NEXT else m.request(command, seq, 0))
        assert verdict.decision is not None
        if command == Command.TRIGGER and self.mode == "chain":
            assert before is Auto.CONTINUOUS_EXECUTION
            assert verdict.decision.action is Action.START, verdict
        elif command in (Command.TRIGGER, Command.NEXT) and before is not Auto.READY:
            assert verdict.decision.action is Action.REJECT, (before, verdict)  # Ready only
        self._apply(verdict.decision.steps)
        self._check()
        return verdict.decision

    def publish(self, seq: int, result: JobResult) -> None:
        plan, shown, _ = self.machine.publish(seq, result)
        if shown.status is Status.ABORTED and result.status is not Status.ABORTED:
            assert shown.target is None
            assert not shown.instances
            self.aborted.add(seq)
        assert (seq in self.aborted) == (seq in self.expect_abort and result.job_id != 0 and
                                         result.status is not Status.ABORTED), seq
        self._apply(plan)
        self._check()

    def call(self, method: str) -> None:
        m = self.machine
        before, running = m.auto, m.handshake.running_seq if m.busy else 0
        if method == "ready":  # the PLC's start-up: SelectModeAutomatic, PrepareRecipe
            m.select_mode_automatic()
            method = "prepare"
        {"select": m.select_mode_automatic, "prepare": lambda: m.prepare_recipe(1),
         "unprepare": lambda: m.unprepare_recipe(1), "halt": m.halt, "reset": m.reset,
         "stop": m.stop, "abort": m.abort}[method]()
        if running and before in EXECUTING and m.auto is not before:
            self.expect_abort.add(running)
        self._check()

    def _check(self) -> None:
        m = self.machine
        if m.auto is Auto.SINGLE_EXECUTION:
            assert m.busy, "SingleExecution without a running request"
        assert (m.auto is None) == (m.top.label != "Operational")


Link = RegisterLink | MessageLink | URLink


@dataclass
class Cell:
    """Three links and the daemon's rules; the daemon's part is what ``Daemon`` does with
    ``JobCore``'s admissions (refuse, answer a NEXT, run a job)."""

    links: dict[str, Link] = field(default_factory=lambda: {
        "plc": RegisterLink(), "s7": RegisterLink("s7"), "mbclient": RegisterLink("client"),
        "ua": MessageLink(frames=False), "robot": MessageLink(frames=True),
        "vision": VisionLink(), "ur": URLink()})
    core: JobCore = field(default_factory=JobCore)
    running: tuple[str, int, int, bool] | None = None  # link, seq, job id, captured
    accepting: bool = True  # False: shutting down, every trigger is refused ABORTED
    jobs: int = 0
    seqs: dict[str, int] = field(default_factory=dict)  # the last fresh sequence
    written: dict[str, int] = field(default_factory=dict)  # register link: REQ_SEQ now
    requests: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # (seq, command)
    #: the daemon's answers, by link and seq: what it was asked to publish
    told: dict[tuple[str, int], JobResult] = field(default_factory=dict)
    #: pickable instances of each job, by job id, counted here (not by ``pick_position``)
    counts: dict[int, int] = field(default_factory=dict)
    #: the link and id of the last job finished; None once another job starts
    last_finished: tuple[str, int] | None = None

    def request(self, name: str, command: int, mode: str) -> None:
        link = self.links[name]
        fresh = mode == "fresh" or not link.edge
        if fresh:
            seq = self.seqs[name] = self.seqs.get(name, 0) + 1
        else:  # the sequence written last again, or 0: no request
            seq = self.written.get(name, 0) if mode == "again" else 0
        self.written[name] = seq
        decision = link.request(command, seq)
        if fresh:
            self.requests.setdefault(name, []).append((seq, command))
        else:
            assert decision.action is Action.IGNORE, decision
        if decision.action is not Action.START:
            return
        admission = self.core.trigger(name, decision.command, accepting=self.accepting,
                                      busy=self.running is not None)
        if admission.kind is Admit.REFUSE:
            self._publish(name, seq, JobResult(job_id=0, status=admission.status))
            self.continue_chain()
        elif admission.kind is Admit.NEXT:
            assert admission.answer is not None
            self._publish(name, seq, admission.answer)
        else:
            self.core.job_started()
            self.last_finished = None
            self.jobs += 1
            self.running = (name, seq, self.jobs, False)

    def capture(self) -> None:
        if self.running is None or self.running[3]:
            return
        name, seq, job_id, _ = self.running
        self.links[name].captured(seq, job_id)
        self.running = (name, seq, job_id, True)

    def finish(self, kind: str, n: int, bad: int) -> None:
        if self.running is None:
            return
        name, seq, job_id, _ = self.running
        result = job_result(job_id, kind, n, bad)
        self.counts[job_id] = (1 if kind == "one" else
                               n if kind == "pallet" and n + bad else 0)
        self.running = None
        self.last_finished = (name, job_id)
        self._publish(name, seq, result)
        self.core.job_finished(name, seq, result, delivered=True)
        self.continue_chain()

    def continue_chain(self) -> None:
        """The vision link in ContinuousExecution requests the chain's next job once the
        daemon finished the last one (``OpcUaLink.publish``)."""
        link = self.links["vision"]
        assert isinstance(link, VisionLink)
        if not link.machine.wants_next:
            return
        mode, link.mode = link.mode, "chain"
        self.request("vision", Command.TRIGGER, "fresh")
        link.mode = mode
        # the chain runs on or has ended: never ContinuousExecution with no job running
        assert link.machine.auto is not Auto.CONTINUOUS_EXECUTION or link.machine.busy

    def _publish(self, name: str, seq: int, result: JobResult) -> None:
        self.told[(name, seq)] = result
        self.links[name].publish(seq, result)


COMMANDS = st.sampled_from([Command.TRIGGER, Command.TRIGGER, Command.NEXT, Command.NEXT,
                            Command.CLEAR, 99])
LINKS = st.sampled_from(["plc", "s7", "mbclient", "ua", "robot", "vision", "ur"])
VISION_CALLS = st.sampled_from(["ready", "ready", "ready", "select", "prepare", "unprepare",
                                "halt", "reset", "stop", "abort"])
RESULTS = st.tuples(st.sampled_from(["one", "none", "pallet", "pallet", "died"]),
                    st.integers(0, 4),
                    st.integers(0, 2))
EVENTS = st.one_of(
    st.tuples(st.just("request"), LINKS, COMMANDS,
              st.sampled_from(["fresh", "fresh", "fresh", "again", "zero"])),
    st.tuples(st.just("capture")),
    st.tuples(st.just("finish"), RESULTS),
    # whole exchanges, so that long walks of a list happen often
    st.tuples(st.just("job"), LINKS, RESULTS),
    st.tuples(st.just("next"), LINKS),
    st.tuples(st.just("accepting"), st.booleans()),  # shutdown (ABORTED) and back
    st.tuples(st.just("vision"), VISION_CALLS),  # an OPC 40100 state machine method
    # the PLC sequence of OPC 40100 on the vision link, a call perhaps in the middle of the job
    st.tuples(st.just("vjob"), RESULTS, st.sampled_from(["-", "-", "stop", "abort", "halt"]),
              st.integers(0, 3)),
    # StartContinuous: jobs one after another, a call ending the chain during the last one
    st.tuples(st.just("vcont"), st.lists(RESULTS, min_size=1, max_size=4),
              st.sampled_from(["stop", "stop", "abort", "halt", "reset"]), st.booleans()),
)


def step(cell: Cell, event: tuple) -> None:
    if event[0] == "request":
        cell.request(*event[1:])
    elif event[0] == "capture":
        cell.capture()
    elif event[0] == "finish":
        cell.finish(*event[1])
    elif event[0] == "job":
        cell.request(event[1], Command.TRIGGER, "fresh")
        cell.capture()
        cell.finish(*event[2])
    elif event[0] == "accepting":
        cell.accepting = event[1]
    elif event[0] == "vision":
        link = cell.links["vision"]
        assert isinstance(link, VisionLink)
        link.call(event[1])
    elif event[0] == "vjob":
        link = cell.links["vision"]
        assert isinstance(link, VisionLink)
        link.call("ready")
        cell.request("vision", Command.TRIGGER, "fresh")
        cell.capture()
        if event[2] != "-":
            link.call(event[2])
        cell.finish(*event[1])
        for _ in range(event[3]):  # the pick list walked by the plain Next
            cell.request("vision", Command.NEXT, "fresh")
    elif event[0] == "vcont":
        link = cell.links["vision"]
        assert isinstance(link, VisionLink)
        link.call("ready")
        link.mode = "continuous"
        cell.request("vision", Command.TRIGGER, "fresh")
        link.mode = "single"
        results, end, captured_first = event[1:]
        for result in results[:-1]:
            cell.capture()
            cell.finish(*result)  # the chain's next job starts (if the chain still runs)
        if captured_first:
            cell.capture()
        link.call(end)
        cell.capture()
        cell.finish(*results[-1])
    else:
        cell.request(event[1], Command.NEXT, "fresh")


def run(events: list[tuple]) -> Cell:
    cell = Cell()
    for event in events:
        step(cell, event)
    cell.links["vision"].call("stop")  # type: ignore[union-attr]  # a chain ends with its job
    cell.capture()
    cell.finish("one", 0, 0)  # the job still running ends, so every request is answered
    return cell


@settings(max_examples=300, deadline=None)
@given(st.lists(EVENTS, max_size=60))
def test_random_event_sequences_keep_the_handshake_rules(events: list[tuple]) -> None:
    check_rules(run(events))


#: Events of the UR link and one other (a job of either keeps the other BUSY), in sequences
#: long enough that UR's requests meet its running job, refusals, NEXT walks and shutdowns.
UR_LINKS = st.sampled_from(["ur", "ur", "plc"])
UR_EVENTS = st.one_of(
    st.tuples(st.just("request"), UR_LINKS, COMMANDS,
              st.sampled_from(["fresh", "fresh", "fresh", "again", "zero"])),
    st.tuples(st.just("capture")),
    st.tuples(st.just("finish"), RESULTS),
    st.tuples(st.just("job"), UR_LINKS, RESULTS),
    st.tuples(st.just("next"), UR_LINKS),
    st.tuples(st.just("accepting"), st.booleans()),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(UR_EVENTS, min_size=10, max_size=60))
def test_the_ur_registers_keep_the_handshake_rules(events: list[tuple]) -> None:
    check_rules(run(events))


def check_rules(cell: Cell) -> None:
    for name, link in cell.links.items():
        assert link.faults == [], name
        # each request answered exactly once, and only requests
        answered = [a.seq for a in link.answers]
        asked = [seq for seq, _ in cell.requests.get(name, [])]
        assert len(answered) == len(set(answered)), name
        assert set(answered) == set(asked), name
        if isinstance(link, MessageLink):
            check_plans(link.plans)
        commands = dict(cell.requests.get(name, []))
        for a in link.answers:
            if a.refused:
                assert (a.pose, a.job_id) == ((), 0)
                continue
            told = cell.told.get((name, a.seq))
            if commands[a.seq] == Command.CLEAR:
                assert told is None
                assert (a.status, a.job_id, a.count, a.index) == (Status.IDLE, 0, 0, 0)
                continue
            assert told is not None
            if isinstance(link, VisionLink) and a.seq in link.aborted:  # a client aborted it
                assert (a.status, a.job_id, a.pose, a.count, a.index) == (
                    Status.ABORTED, told.job_id, (), 0, 0)
                continue
            assert (a.status, a.job_id) == (told.status, told.job_id)
            assert a.count == cell.counts.get(a.job_id, 0)  # the job's, counted apart
            check_position(a, commands[a.seq])
            # docs/robot_socket.md: REFUSED is a refusal with no job (BUSY, BAD_REQUEST,
            # ABORTED at shutdown); a NEXT the daemon answers BAD_REQUEST because another
            # link's job took the list is a RESULT with job 0
            if a.frame:
                refused = a.job_id == 0 and (commands[a.seq] != Command.NEXT
                                             or a.status in (Status.BUSY, Status.ABORTED))
                assert a.frame == ("REFUSED" if refused else "RESULT"), a
    # never a stale or repeated pose
    poses = [a.pose for link in cell.links.values() for a in link.answers if a.pose]
    assert len(poses) == len(set(poses))


def check_position(a: Answer, command: int) -> None:
    """COUNT/INDEX of an acknowledged answer (a job's or a NEXT's)."""
    if a.pose:
        assert 1 <= a.index <= a.count
        assert a.pose[:2] == (a.job_id, a.index)  # the instance it says it is
    elif command == Command.NEXT and a.status == Status.NOT_FOUND:
        assert a.count >= 1
        assert a.index == a.count + 1  # past the end of the list (a single object: 1, 2)
    else:
        assert a.index == 0


@settings(max_examples=200, deadline=None)
@given(st.lists(EVENTS, max_size=60))
def test_a_next_pose_is_of_the_last_job_of_its_own_link(events: list[tuple]) -> None:
    """Replayed in order: a NEXT's pose belongs to the last job finished, triggered by the
    same link, and no job was started since."""
    cell = Cell()
    for event in [*events, ("capture",), ("finish", ("one", 0, 0))]:
        before = {name: len(link.answers) for name, link in cell.links.items()}
        last = cell.last_finished
        step(cell, event)
        if event[0] not in ("request", "next"):
            continue
        for name, link in cell.links.items():
            for a in link.answers[before[name]:]:
                if a.pose and a.pose[1] > 1:  # instance 2..n: only a NEXT hands these out
                    assert last == (name, a.job_id)
                    assert cell.last_finished == last  # no job started meanwhile


# --- three protocol defects of a security review, at the core -----------------------------


def test_clear_retracts_the_acknowledge_before_its_data_and_writes_it_last() -> None:
    journal: list[BlockWrite] = []
    bank = RegisterBank(CODEC, journal)
    bank.write(Reg.CMD, [Command.TRIGGER, 1, 0])
    bank.publish(1, job_result(5, "one", 0, 0), now_ns=0)
    journal.clear()
    assert bank.write(Reg.CMD, [Command.CLEAR, 2, 0]).action is Action.CLEAR
    ours = [w for w in journal if w.address > Reg.RECIPE]  # after the PLC's own write
    acks = [(i, w.words) for i, w in enumerate(ours) if w.address == Reg.ACK_SEQ]
    assert acks == [(0, (0,)), (len(ours) - 1, (2,))]


@pytest.mark.parametrize("kind", ["one", "pallet"])
def test_next_past_the_end_counts_the_jobs_list(kind: str) -> None:
    job = job_result(3, kind, 2, 1)
    count = 1 if kind == "one" else 2
    end = next_answer(job, count + 1)
    assert end.status is Status.NOT_FOUND
    assert pick_position(end) == PickPosition(count, count + 1)


def test_a_next_answered_bad_request_by_the_daemon_is_a_result_frame() -> None:
    robot = MessageLink(frames=True)
    robot.request(Command.TRIGGER, 1)
    robot.publish(1, job_result(1, "one", 0, 0))
    robot.request(Command.NEXT, 2)  # the daemon: another link's job took the list
    robot.publish(2, JobResult(job_id=0, status=Status.BAD_REQUEST))
    robot.request(Command.NEXT, 3)  # the link itself: no list any more
    assert [(a.seq, a.frame, a.status) for a in robot.answers] == [
        (1, "RESULT", Status.OK), (2, "RESULT", Status.BAD_REQUEST),
        (3, "REFUSED", Status.BAD_REQUEST)]


def test_order_puts_a_retraction_before_data_under_an_acknowledge() -> None:
    handshake = Handshake()
    handshake.acked = 7
    plan = handshake.order([Step(Part.CLEAR), Step(Part.ACK, 8)])
    assert [s.part for s in plan] == [Part.RETRACT, Part.CLEAR, Part.ACK]
    with pytest.raises(AssertionError):
        handshake.order([Step(Part.ACK, 9), Step(Part.STATE)])
    with pytest.raises(AssertionError):
        check_plans([(Step(Part.ACK, 1),), (Step(Part.RESULT),)])


def test_a_single_objects_next_shows_a_list_of_one_on_every_link_kind() -> None:
    """The position of the answer past the end, as each kind of link shows it: registers
    COUNT/INDEX, the UR pick register (1000 x COUNT + INDEX), the socket's remaining word."""
    end = next_answer(job_result(4, "one", 0, 0), 2)
    position = pick_position(end)
    bank = RegisterBank(CODEC)
    bank.write(Reg.CMD, [Command.NEXT, 1, 0])  # refused: no list yet
    bank.write(Reg.CMD, [Command.TRIGGER, 2, 0])
    bank.publish(2, job_result(4, "one", 0, 0), now_ns=0)
    bank.write(Reg.CMD, [Command.NEXT, 3, 0])
    bank.publish(3, end, now_ns=0)
    words = bank.read(0, MAP_SIZE, 0)
    assert (words[Reg.ACK_SEQ], words[Reg.STATUS], words[Reg.COUNT], words[Reg.INDEX]) == (
        3, Status.NOT_FOUND, 1, 2)
    assert URRegisterMap().pick_word(position) == 1002.0
    assert remaining(position) == 0


def test_job_core_admission_and_list_walk() -> None:
    core = JobCore()
    assert core.trigger("a", Command.TRIGGER, accepting=False, busy=False).status is \
        Status.ABORTED
    assert core.trigger("a", Command.NEXT, accepting=True, busy=True).status is Status.BUSY
    refused = core.trigger("a", Command.NEXT, accepting=True, busy=False)
    assert (refused.kind, refused.status) == (Admit.REFUSE, Status.BAD_REQUEST)
    assert core.trigger("a", Command.TRIGGER, accepting=True, busy=False).kind is Admit.JOB
    core.job_started()
    job = job_result(1, "pallet", 2, 1)
    core.job_finished("a", 1, job, delivered=True)
    other = core.trigger("b", Command.NEXT, accepting=True, busy=False)
    assert (other.kind, other.status) == (Admit.REFUSE, Status.BAD_REQUEST)
    assert "belongs to link a" in other.why
    walk = [core.trigger("a", Command.NEXT, accepting=True, busy=False).answer
            for _ in range(3)]
    assert [(a.status, pick_position(a).index) for a in walk if a is not None] == [
        (Status.OK, 2), (Status.NOT_FOUND, 3), (Status.NOT_FOUND, 3)]
    core.job_started()  # a new job drops the list at once
    assert core.trigger("a", Command.NEXT, accepting=True, busy=False).kind is Admit.REFUSE
    core.job_finished("a", 2, job, delivered=False)  # not delivered: no list
    assert core.pick_list is None


def test_view_admission_rules() -> None:
    """A job of several views: begun by view 1, continued in order, ended by anything else of
    its link, BUSY for other links; a CAPTURE without a job, or of a recipe of one view, is
    refused."""
    cap, trig = Command.CAPTURE, Command.TRIGGER
    waiting = ViewsAt("a", 7, next_view=2, count=3)
    cases = [
        ((cap, 1, "a", True, 3, None), ViewStep.BEGIN, Status.IDLE),
        ((cap, 2, "a", True, 3, None), ViewStep.REFUSE, Status.BAD_REQUEST),
        ((cap, 1, "a", True, 1, None), ViewStep.REFUSE, Status.BAD_REQUEST),
        ((cap, 1, "a", False, 1, None), ViewStep.JOB, Status.IDLE),
        ((trig, 0, "a", True, 3, None), ViewStep.REFUSE, Status.BAD_REQUEST),
        ((cap, 2, "a", True, 3, waiting), ViewStep.VIEW, Status.IDLE),
        ((cap, 1, "a", True, 3, waiting), ViewStep.END, Status.BAD_REQUEST),
        ((cap, 3, "a", True, 3, waiting), ViewStep.END, Status.BAD_REQUEST),
        ((trig, 0, "a", True, 3, waiting), ViewStep.END, Status.BAD_REQUEST),
        ((cap, 2, "b", True, 3, waiting), ViewStep.REFUSE, Status.BUSY),
        ((trig, 0, "b", True, 3, waiting), ViewStep.REFUSE, Status.BAD_REQUEST),
    ]
    for (command, view, link, known, count, views), step, status in cases:
        decision = view_admission(command, view, link, "1 (r)", known, count, views)
        assert (decision.step, decision.status) == (step, status), (command, view, link)
    assert "view 1 repeated" in view_admission(cap, 1, "a", "1", True, 3, waiting).why
    assert "view 3 out of order" in view_admission(cap, 3, "a", "1", True, 3, waiting).why
