"""The job core: the rules every link and the daemon obey, as state machines without I/O.

Nothing here awaits, reads a clock or touches a socket: each object takes an event (a peer's
request, an image taken, a result, a NEXT, a CLEAR) and returns a decision (refuse with a code,
start a job, write these parts of the answer area in this order, answer the NEXT with this
instance). The links (``drivers/links/*``) and the daemon carry the decisions out; the tests
feed the machines random sequences of events and check the rules on what comes out
(``tests/unit/peer/test_jobcore.py``), so the rules hold for every link kind at once.

Two machines:

``Handshake`` (one per link): a link's side of the request/answer exchange. A peer request
(``on_request``) is ignored (not a new request), refused (``REJECT``: BUSY while a request of
this link runs, BAD_REQUEST for an unknown command or a NEXT without a list), answered at once
(``CLEAR``) or started (``START``: the daemon gets a trigger). Every decision carries its
``steps``: the parts of the link's answer area to write, in order. The order is the promise a
PLC relies on, the same for every command on every link:

- ``RETRACT`` (the acknowledge names no request: ACK_SEQ 0, OPC UA RequestId 0) comes before
  any data of the answer area changes (``CLEAR``, ``JOB_ID``, ``RESULT``);
- ``ACK`` (the acknowledge names the request: ACK_SEQ = seq, RequestId, the socket's final
  frame) is the last step of its plan, after every data step;
- ``REJECT`` answers a refused request and touches nothing else.

``Handshake.order`` enforces both rules on every plan it hands out (a plan that changes data
while a request is acknowledged gets its retraction in front), so no link can write CLEAR's
data under the previous request's sequence again. A link renders each step in its own terms:
register links (Modbus server/RTU/client, S7) as block writes of the register map
(``protocol.RegisterBank``), OPC UA as variable writes (``opcua_space.Space``), the robot
socket as frames. ``STATE`` (the register map's STATE, OPC UA's state machine) is no data of
the answer and may go anywhere.

``JobCore`` (one per daemon): admission of a trigger (refused ABORTED when not accepting, BUSY
while a job runs), and the pick list of the last job (``PickCursor``): kept for the link that
triggered it when its result was delivered and has a pickable instance, dropped by any new job,
walked by NEXT (``next_answer``), past the end ``NOT_FOUND`` with INDEX = COUNT + 1; a NEXT of a
link that does not hold the list answered BAD_REQUEST with job id 0. ``view_admission``: the
rules of a job of several views (begin, next view, end, BUSY for others, refusals).

Events without a decision of their own: a job that ends by a dead worker, a timeout or
shutdown ends with a result (INTERNAL, CAMERA_ERROR, ABORTED) like any other, through
``JobCore.job_finished`` and the link's ``Handshake.publish``; a link that goes down keeps its
handshake and its image (a client link writes the answer at the reconnect); a recipe travels
with the trigger and the daemon judges it (an unknown one is the job's BAD_REQUEST result).

Pick list fields (COUNT, INDEX, PICK_ID, SCORE; ``pick_position``): COUNT counts the pickable
instances of the *job* (a single-object job is a list of one: 1 with a pose, 0 without), INDEX
the instance shown (1-based; 0 = none shown; COUNT + 1 = past the end, after NEXT).
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

from vgripd.errors import LinkError
from vgripd.peer.beltqueue import BeltLine, Latch
from vgripd.types import JobResult, Status


class Command(enum.IntEnum):
    TRIGGER = 1
    CLEAR = 2
    NEXT = 3  # the next instance of the last job's pick list (map version 3)
    CAPTURE = 4  # one view of a several-view job (``vision.views``); the view in the high byte
    PREDICT = 5  # a conveyor part's pose at a later encoder count (map version 4)


#: Views one job may have (``vision.views``), and so the largest view index of a CAPTURE.
MAX_VIEWS = 8


def capture_word(view: int) -> int:
    """The CMD word of a CAPTURE of view ``view`` (1-based): ``view * 256 + 4``.

    The low byte is the command, the high byte the view: one register, so the view and the
    request arrive in the same write and no spare register (nor a new map version) is needed.
    """
    if not 1 <= view <= MAX_VIEWS:
        raise ValueError(f"view {view}: views are 1..{MAX_VIEWS}")
    return view << 8 | Command.CAPTURE


def split_command(word: int) -> tuple[int, int]:
    """``(command, view)`` of a CMD word: a CAPTURE carries its view in the high byte; any
    other command keeps the whole word (so a high byte there stays an unknown command)."""
    if word & 0xFF == Command.CAPTURE:
        return int(Command.CAPTURE), word >> 8
    return word, 0


class HandshakeState(enum.IntEnum):
    IDLE = 0
    TRIGGERED = 1  # request accepted, waiting for the image
    BUSY = 2  # image captured, processing
    DONE = 3  # result acknowledged
    VIEWS = 4  # a view of a several-view job taken: the robot moves on to the next view


# --- pick lists ----------------------------------------------------------------------------

UNKNOWN_SCORE = -1.0  # SCORE when no instance (or a single object without a score) is shown


@dataclass(frozen=True)
class NextAnswer(JobResult):
    """The daemon's answer to a NEXT request: the job's result with the top-level fields
    describing the instance at ``index`` (1-based, among ``instances``) instead of the first.

    ``index`` = pickable count + 1 is the answer past the end of the list (``NOT_FOUND``, no
    pose). ``count`` is the job's pickable count (the answer past the end has no pose of its
    own to count from). ``job_id``, ``recipe``, ``t_capture_mono_ns`` and ``t_done_mono_ns``
    are the job's own: the images are as old as the original result, and RESULT_AGE_MS says so.
    """

    index: int = 1
    count: int = 0


@dataclass(frozen=True)
class PickPosition:
    """Where a published result stands in its job's pick list (COUNT, INDEX, PICK_ID, SCORE).

    ``count``: pickable instances (a single-object job counts 1 with a pose, 0 without);
    ``index``: 1-based index of the instance shown, 0 when no pose is shown, ``count + 1``
    past the end; ``pick_id`` and ``score`` of the instance shown (0 and ``UNKNOWN_SCORE``
    when none is, or for a single-object job, which has no score).
    """

    count: int
    index: int
    pick_id: int = 0
    score: float = UNKNOWN_SCORE

    @property
    def listed(self) -> bool:
        """True when NEXT may follow: the result belongs to a job with a pickable instance."""
        return self.count > 0


def pickable_count(result: JobResult) -> int:
    """Pickable instances of ``result``'s job (``JobResult.instances`` are in pick order, the
    pickable ones first); a single-object job: 1 with a pose, 0 without. A NEXT answer
    carries its job's count."""
    if isinstance(result, NextAnswer):
        return result.count
    if result.instances:
        return sum(i.status.pose_valid for i in result.instances)
    return int(result.status.pose_valid and result.target is not None)


def pick_position(result: JobResult) -> PickPosition:
    """The pick-list fields of a result to publish (a job's own result or a ``NextAnswer``).

    Refusals and failures that never had a list (BUSY, BAD_REQUEST, a failed single-object
    job) are ``count`` 0: NEXT cannot follow them. A NEXT answer counts its job's list, also
    past the end (a single-object job: COUNT 1, INDEX 2).
    """
    count = pickable_count(result)
    if isinstance(result, NextAnswer):
        index = result.index
    else:
        index = 1 if count and result.status.pose_valid else 0
    if result.instances and 1 <= index <= count:
        shown = result.instances[index - 1]
        return PickPosition(count, index, shown.pick_id, shown.score)
    return PickPosition(count, index)


def next_answer(result: JobResult, index: int) -> NextAnswer:
    """The answer showing instance ``index`` (1-based) of job ``result``'s pick list; past the
    end (``index > count``) a ``NOT_FOUND`` answer without a pose at ``count + 1``.

    ``result`` is the job's own published result (the top-level fields of instance 1). Raises
    ``ValueError`` for an index below 1 or a result without a list (the daemon refuses NEXT
    before it gets here).
    """
    count = pickable_count(result)
    if count == 0 or index < 1:
        raise ValueError(f"job {result.job_id}: no pick list instance {index} "
                         f"({count} pickable)")
    end = NextAnswer(job_id=result.job_id, status=Status.NOT_FOUND, index=count + 1,
                     count=count,
                     message=f"pick list of job {result.job_id} exhausted: all {count} "
                             "pickable instances were handed out",
                     t_capture_mono_ns=result.t_capture_mono_ns,
                     t_done_mono_ns=result.t_done_mono_ns, instances=result.instances,
                     recipe=result.recipe)
    if index > count:
        return end
    if not result.instances:  # a single object: instance 1 is the job's own result
        own = {f.name: getattr(result, f.name) for f in dataclasses.fields(result)
               if f.name not in ("index", "count")}
        return NextAnswer(**own, index=1, count=count)
    inst = result.instances[index - 1]
    return dataclasses.replace(end, status=inst.status, message=inst.message, target=inst.target,
                               T_base_obj=inst.T_base_obj, offset=inst.offset,
                               residuals=inst.residuals, features_used=inst.features_used,
                               index=index)


# --- a link's handshake --------------------------------------------------------------------


class Part(enum.Enum):
    """A part of a link's answer area (what a ``Step`` writes)."""

    RETRACT = "retract"  # the acknowledge names no request (ACK_SEQ 0, RequestId 0)
    CLEAR = "clear"  # the result area emptied (data)
    JOB_ID = "job_id"  # the job's id, at image capture (data)
    RESULT = "result"  # a result and its pick-list position (data)
    STATE = "state"  # the handshake state (not data: any time)
    CAPTURED = "captured"  # the request whose image is taken (CAPTURED_SEQ)
    REJECT = "reject"  # the request refused, and why (REJECT_CODE, then REJECT_SEQ)
    ACK = "ack"  # the acknowledge names the request: written last


#: Parts that change the answer's data: only while no request is acknowledged.
DATA_PARTS = frozenset({Part.CLEAR, Part.JOB_ID, Part.RESULT})


@dataclass(frozen=True)
class Step:
    """One write of a plan. ``seq``: the request (CAPTURED, REJECT, ACK); ``value``: the
    state (STATE), job id (JOB_ID) or refusal code (REJECT); ``result`` and ``position``: what
    RESULT shows; ``refused`` (ACK): the answer is a refusal without a job (the robot socket
    sends it as a REFUSED frame, the others need not care)."""

    part: Part
    seq: int = 0
    value: int = 0
    result: JobResult | None = None
    position: PickPosition | None = None
    refused: bool = False


class Action(enum.Enum):
    IGNORE = "ignore"  # not a new request
    START = "start"  # run a job: hand a Trigger to the daemon
    CLEAR = "clear"  # reset the result area and acknowledge
    REJECT = "reject"  # refused: REJECT_SEQ / REJECT_CODE


@dataclass(frozen=True)
class Decision:
    action: Action
    seq: int = 0
    command: int = 0
    recipe: int = 0
    code: Status = Status.IDLE
    view: int = 0  # CAPTURE: the view (1-based)
    #: Map version 4: LATCH_COUNT and LATCH_FRAME as the request found them (None: not read).
    count: int | None = None
    frame: int | None = None
    #: The writes that carry the decision out, in order (``Handshake.order``).
    steps: tuple[Step, ...] = ()


def answer_refused(command: int, result: JobResult, captured: bool) -> bool:
    """True when the answer to a request is a refusal without a job (the robot socket's
    REFUSED frame): no image was taken and no job created (job id 0), and the request was not a
    NEXT, whose answers are results (docs/robot_socket.md: a NEXT whose list another link's job
    took is answered RESULT BAD_REQUEST with job 0) unless it was BUSY or ABORTED."""
    if captured or result.job_id:
        return False
    if command in (Command.NEXT, Command.PREDICT):
        return result.status in (Status.BUSY, Status.ABORTED)
    return True


class Handshake:
    """A link's request/answer state machine: idle -> triggered -> busy -> done -> ...

    ``edge`` (register links): a request is a change of the request sequence to a non-zero
    value; 0 is the power-on value and never a request (a restarted PLC may write 0 and then
    start again at 1), and the same sequence again is not a new request. Without ``edge``
    (message links: OPC UA methods, socket frames) every call is a request.

    ``acked``: the request the answer area acknowledges now (0: retracted, or none yet).
    """

    def __init__(self, edge: bool = True) -> None:
        self.edge = edge
        self.state = HandshakeState.IDLE
        self.running_seq = 0
        self.running_command = 0
        self.last_req_seq = 0
        self.acked = 0
        self.captured = False  # the running request's image is taken
        #: The result shown belongs to a job with a pick list (``PickPosition.listed``): NEXT
        #: may follow. Set by ``on_published``; a new TRIGGER and CLEAR reset it.
        self.listed = False
        #: A conveyor's part queue answers NEXT and PREDICT (the daemon judges them): they
        #: need no list here. Without it PREDICT is refused like a NEXT without a list.
        self.queue = False
        #: The commands this link's peer may send (None: every one above); any other is
        #: refused BAD_REQUEST like an unknown one (the UR registers carry no CLEAR).
        self.commands: frozenset[int] | None = None

    @property
    def busy(self) -> bool:
        return self.state in (HandshakeState.TRIGGERED, HandshakeState.BUSY)

    # -- events ------------------------------------------------------------------------------

    def on_request(self, command: int, seq: int, recipe: int = 0) -> Decision:
        """A peer's request; the decision says what to do and what to write."""
        if self.edge:
            if seq == self.last_req_seq:
                return Decision(Action.IGNORE, seq)
            self.last_req_seq = seq
            if seq == 0:
                return Decision(Action.IGNORE, seq)
        command, view = split_command(command)
        if (command not in (Command.TRIGGER, Command.CLEAR, Command.NEXT, Command.CAPTURE,
                            Command.PREDICT)
                or (command == Command.CAPTURE and not 1 <= view <= MAX_VIEWS)
                or (self.commands is not None and command not in self.commands)):
            return self._reject(seq, command, recipe, Status.BAD_REQUEST, view)
        if self.busy:
            return self._reject(seq, command, recipe, Status.BUSY, view)
        if command == Command.PREDICT and not self.queue:
            return self._reject(seq, command, recipe, Status.BAD_REQUEST, 0)
        if command == Command.NEXT and not (self.listed or self.queue):  # nothing to go on
            return self._reject(seq, command, recipe, Status.BAD_REQUEST, 0)
        if command == Command.CLEAR:
            self.state = HandshakeState.IDLE
            self.listed = False
            steps = self.order([Step(Part.RETRACT), Step(Part.CLEAR),
                                Step(Part.STATE, value=HandshakeState.IDLE),
                                Step(Part.ACK, seq)])
            return Decision(Action.CLEAR, seq, command, recipe, steps=steps)
        if command in (Command.TRIGGER, Command.CAPTURE):
            self.listed = False  # the old list is not this job's
        self.state = HandshakeState.TRIGGERED
        self.running_seq = seq
        self.running_command = command
        self.captured = False
        steps = self.order([Step(Part.RETRACT), Step(Part.CLEAR),
                            Step(Part.STATE, value=HandshakeState.TRIGGERED)])
        return Decision(Action.START, seq, command, recipe, view=view, steps=steps)

    def on_captured(self, seq: int, job_id: int = 0) -> tuple[Step, ...]:
        """The image of the running request is taken: JOB_ID, STATE, then CAPTURED."""
        self.check_running(seq, "image_captured")
        self.state = HandshakeState.BUSY
        self.captured = True
        return self.order([Step(Part.JOB_ID, value=job_id),
                           Step(Part.STATE, value=HandshakeState.BUSY),
                           Step(Part.CAPTURED, seq)])

    def on_view_captured(self, seq: int, job_id: int = 0) -> tuple[Step, ...]:
        """A view (not the last) is taken: the request is over, the next may come. The job
        may still end under this sequence (the next view timed out): ``check_running``
        accepts a publish for it until a new request runs."""
        self.check_running(seq, "view_captured")
        self.state = HandshakeState.VIEWS
        self.captured = True
        return self.order([Step(Part.JOB_ID, value=job_id),
                           Step(Part.STATE, value=HandshakeState.VIEWS),
                           Step(Part.CAPTURED, seq)])

    def on_published(self, seq: int, listed: bool = False) -> None:
        """``listed``: the published result has a pick list (NEXT may follow)."""
        self.check_running(seq, "publish")
        self.state = HandshakeState.DONE
        self.listed = listed

    def publish(self, seq: int, result: JobResult,
                position: PickPosition | None = None) -> tuple[Step, ...]:
        """The running request's answer: RESULT (with ``position``, by default
        ``pick_position(result)``), STATE DONE, then ACK. ``LinkError`` when ``seq`` is not the
        running request."""
        self.check_running(seq, "publish")
        position = pick_position(result) if position is None else position
        refused = answer_refused(self.running_command, result, self.captured)
        self.on_published(seq, position.listed)
        return self.order([Step(Part.RESULT, seq, result=result, position=position),
                           Step(Part.STATE, value=HandshakeState.DONE),
                           Step(Part.ACK, seq, refused=refused)])

    def check_running(self, seq: int, what: str) -> None:
        waiting = self.state is HandshakeState.VIEWS and what == "publish"
        if not (self.busy or waiting) or seq != self.running_seq:
            running = self.running_seq if self.busy else "none"
            raise LinkError(f"{what} for request {seq}, but the running request is {running}")

    # -- ordering ----------------------------------------------------------------------------

    def order(self, steps: list[Step]) -> tuple[Step, ...]:
        """``steps`` as a plan that keeps the ordering rules, and ``acked`` updated.

        A data step while a request is acknowledged gets a RETRACT in front of it; a RETRACT
        when nothing is acknowledged is dropped only if it is not the plan's first step (a
        leading one stays: a link may write it anyway, it is harmless); an ACK anywhere but
        last is a bug of this module and raises ``AssertionError``.
        """
        out: list[Step] = []
        acked = self.acked
        for i, step in enumerate(steps):
            if step.part is Part.ACK:
                assert i == len(steps) - 1, f"ACK must be the last step: {steps}"
                acked = step.seq
            elif step.part is Part.RETRACT:
                if acked == 0 and out:
                    continue
                acked = 0
            elif step.part in DATA_PARTS and acked != 0:
                out.append(Step(Part.RETRACT))
                acked = 0
            out.append(step)
        self.acked = acked
        return tuple(out)

    def _reject(self, seq: int, command: int, recipe: int, code: Status,
                view: int) -> Decision:
        return Decision(Action.REJECT, seq, command, recipe, code, view,
                        steps=(Step(Part.REJECT, seq, int(code)),))


def check_plans(plans: list[tuple[Step, ...]]) -> None:
    """``AssertionError`` unless the plans, written one after another, keep the ordering rules:
    no data step while a request is acknowledged, every ACK the last step of its plan, and
    each request acknowledged or refused at most once. For tests and for links that want to
    check what they were handed."""
    acked = 0
    answered: set[int] = set()
    for plan in plans:
        for i, step in enumerate(plan):
            if step.part in DATA_PARTS:
                assert acked == 0, f"{step.part.value} written while ACK names {acked}: {plan}"
            elif step.part is Part.RETRACT:
                acked = 0
            elif step.part is Part.ACK:
                assert i == len(plan) - 1, f"ACK not last: {plan}"
                acked = step.seq
            if step.part in (Part.ACK, Part.REJECT):
                assert step.seq not in answered, f"request {step.seq} answered twice: {plan}"
                answered.add(step.seq)


# --- the daemon's admission and pick list -------------------------------------------------


@dataclass
class PickCursor:
    """The last job's pick list, as far as NEXT has walked it.

    ``link``: the link that triggered the job (only it may walk the list); ``result``: the
    job's result as published (the top level shows instance 1); ``index``: the 1-based index
    last handed out (``count + 1`` once past the end).
    """

    link: str
    seq: int
    result: JobResult
    index: int = 1

    @property
    def count(self) -> int:
        return pickable_count(self.result)


class Admit(enum.Enum):
    REFUSE = "refuse"  # answer ``status`` without a job (job id 0)
    NEXT = "next"  # answer ``answer`` from the pick list (no acquisition)
    JOB = "job"  # start a job (the daemon decides how: one image or several views)


@dataclass(frozen=True)
class Admission:
    kind: Admit
    status: Status = Status.IDLE
    why: str = ""
    answer: JobResult | None = None


class JobCore:
    """The daemon's job rules: admission of triggers and the last job's pick list.

    The daemon owns the running job (its task) and its run state; it tells the core whether
    it takes jobs (``accepting``: start-up or running; at shutdown every trigger is refused
    ABORTED) and whether a job runs (``busy``), and the core decides.
    """

    def __init__(self, lines: dict[int, BeltLine] | None = None) -> None:
        self.pick_list: PickCursor | None = None
        #: Conveyor recipes (docs/conveyor.md) by number: their NEXT and PREDICT are answered
        #: from the recipe's part queue, also while a job runs.
        self.lines: dict[int, BeltLine] = lines or {}

    def trigger(self, link: str, command: int, accepting: bool, busy: bool, recipe: int = 0,
                count: int | None = None, now_ns: int = 0) -> Admission:
        """A link's request reaches the daemon: refuse, answer from the list (or a conveyor
        recipe's queue: ``count`` is the request's encoder count), or run a job (which must
        call ``job_started``, so a NEXT can never get a pose of an earlier job)."""
        line = self.lines.get(recipe)
        if accepting and command in (Command.NEXT, Command.PREDICT) and line is not None:
            answer = (line.next(link, count, now_ns) if command == Command.NEXT
                      else line.predict(link, count, now_ns))
            return Admission(Admit.NEXT, answer=dataclasses.replace(answer, recipe=recipe))
        if command == Command.PREDICT and accepting and not busy:
            return Admission(Admit.REFUSE, Status.BAD_REQUEST,
                             f"PREDICT: recipe {recipe} has no conveyor")
        if not accepting or busy:
            return Admission(Admit.REFUSE, Status.BUSY if accepting else Status.ABORTED)
        if command == Command.NEXT:
            cursor = self.pick_list
            if cursor is None or cursor.link != link:
                why = ("no pick list: no job since start, or the last one found nothing pickable"
                       if cursor is None else
                       f"the last job's pick list belongs to link {cursor.link}")
                return Admission(Admit.REFUSE, Status.BAD_REQUEST, why)
            # The cursor moves here, at the request, so two NEXTs in a row get two instances.
            cursor.index = min(cursor.index + 1, cursor.count + 1)
            return Admission(Admit.NEXT, answer=next_answer(cursor.result, cursor.index))
        return Admission(Admit.JOB)

    def job_started(self) -> None:
        """A job (or the first view of a several-view job) starts: the old list is nobody's."""
        self.pick_list = None

    def job_finished(self, link: str, seq: int, result: JobResult, delivered: bool) -> None:
        """The job's answer went out (``delivered``) or not: a delivered result with a pickable
        instance becomes the pick list of ``link`` (not on a conveyor: its queue serves)."""
        if delivered and pickable_count(result) and result.recipe not in self.lines:
            self.pick_list = PickCursor(link, seq, result)

    def belt_result(self, recipe: int, latch: Latch | str | None,
                    result: JobResult) -> JobResult:
        """A conveyor recipe's job result before it is published: with its ``latch`` its
        parts go into the queue and the answer carries the count; without one (``latch`` the
        reason) the job ends ``BAD_REQUEST`` and nothing is queued, so no pose without its
        count reaches a peer. Other recipes' results pass unchanged."""
        line = self.lines.get(recipe)
        if line is None or latch is None:
            return result
        if isinstance(latch, str):
            return JobResult(job_id=result.job_id, status=Status.BAD_REQUEST, message=latch,
                             t_capture_mono_ns=result.t_capture_mono_ns,
                             t_done_mono_ns=result.t_done_mono_ns, recipe=result.recipe)
        return line.add(latch, result)


# --- several views per job (``vision.views``) -----------------------------------------------


@dataclass(frozen=True)
class ViewsAt:
    """A several-view job as the rules see it: its link, id, the view it waits for next and
    how many it takes."""

    link: str
    job_id: int
    next_view: int
    count: int


class ViewStep(enum.Enum):
    REFUSE = "refuse"  # answer ``status`` (``why``) without a job
    END = "end"  # end the views job BAD_REQUEST (``why``), answered to this request
    JOB = "job"  # a job of one acquisition (an unknown recipe: its result says BAD_REQUEST)
    BEGIN = "begin"  # view 1 of a new several-view job
    VIEW = "view"  # the next view of the views job


@dataclass(frozen=True)
class ViewDecision:
    step: ViewStep
    status: Status = Status.IDLE
    why: str = ""


def view_admission(command: int, view: int, link: str, recipe: str, known: bool, count: int,
                   views: ViewsAt | None) -> ViewDecision:
    """What a CAPTURE (or a TRIGGER of a recipe of several views) does, once the daemon has
    admitted it (``JobCore.trigger``: not busy). ``recipe``: the recipe's label for messages;
    ``known``: it is configured; ``count``: its ``vision.views`` (1 when not configured).

    A TRIGGER of a recipe of several views ends the link's own views job or is refused
    BAD_REQUEST; a CAPTURE of another link while a views job waits is BUSY; view 1 of a recipe
    of several views begins a job; views out of order or repeated end the job (BAD_REQUEST, so
    no pose mixes two jobs); any other CAPTURE is refused BAD_REQUEST.
    """
    if command != Command.CAPTURE:
        why = (f"recipe {recipe} takes {count} views per job: CAPTURE views 1..N "
               "(CMD = view * 256 + 4), not TRIGGER")
        if views is not None and views.link == link:
            return ViewDecision(ViewStep.END, Status.BAD_REQUEST, why)
        return ViewDecision(ViewStep.REFUSE, Status.BAD_REQUEST, why)
    if views is not None and views.link != link:
        return ViewDecision(ViewStep.REFUSE, Status.BUSY,
                            f"link {views.link}'s views job {views.job_id} is at view "
                            f"{views.next_view - 1}")
    if views is None:
        if not known:
            return ViewDecision(ViewStep.JOB)
        if view == 1 and count > 1:
            return ViewDecision(ViewStep.BEGIN)
        why = (f"recipe {recipe} takes one view per job: TRIGGER, not CAPTURE" if count == 1
               else f"no views job running: CAPTURE view 1 first, not view {view}")
        return ViewDecision(ViewStep.REFUSE, Status.BAD_REQUEST, why)
    if view != views.next_view:
        what = "repeated" if view < views.next_view else "out of order"
        return ViewDecision(ViewStep.END, Status.BAD_REQUEST,
                            f"view {view} {what}: view {views.next_view} of {views.count} "
                            "expected; start again at view 1")
    return ViewDecision(ViewStep.VIEW)
