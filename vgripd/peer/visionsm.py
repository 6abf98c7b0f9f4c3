"""OPC 40100's vision state machine as rules without I/O, on top of the link's ``Handshake``.

OPC 40100-1 (OPC UA for Machine Vision) gives a vision system two nested state machines:
``VisionStateMachine`` (Preoperational, Halted, Error, Operational; methods Halt, Reset,
SelectModeAutomatic, ConfirmAll) and, inside Operational, the automatic mode (Initialized,
Ready, SingleExecution, ContinuousExecution; methods StartSingleJob, StartContinuous, Stop,
Abort, SimulationMode), plus recipe preparation (Initialized -> Ready). ``VisionMachine`` keeps
both and answers each method call with a ``Verdict``: refused (the OPC UA status code's name,
e.g. ``BadInvalidState`` for a call the current state does not allow) or done, with the
transitions it fired (the NodeSet's transition names, e.g. ``ReadyToSingleExecution``).

A job request (StartSingleJob, the plain ``Next`` of the pick list and a conveyor's plain
``Predict``) goes through the link's ``Handshake`` (``vgripd.peer.jobcore``), so the
register contract's promises hold for the standard's methods too: each request answered
once, no stale or repeated pose, COUNT/INDEX. The property test
(``tests/unit/peer/test_jobcore.py``) drives this machine among the other link kinds.
Halt, Reset, Stop or Abort while a job runs cannot take the job back from the daemon: its
result still comes, once, but as ``ABORTED`` without a pose (``VisionMachine.publish``), and
the state machine has already left SingleExecution.

ContinuousExecution (StartContinuous) is a chain of such requests: one at a time, each with a
sequence of its own, the next one started by the link (``continue_job``) once the previous
result is published. Stop ends the chain after the running job (its result is a normal one),
Abort at once (the running job's result ABORTED, as Halt and Reset do); a result the daemon
gives without a job (another link's job runs: BUSY; shutdown: ABORTED) ends it too, so a
chain never spins on refusals, and a system fault moves to Error as in SingleExecution.

The numbers of the states are OPC 40100's ``StateNumber`` values (NodeSet 1.0.0).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from vgripd.peer.jobcore import Action, Command, Decision, Handshake, Part, Step
from vgripd.types import JobResult, Status


class _Numbered(enum.Enum):
    """A state of the standard's machines: its name and StateNumber."""

    @property
    def label(self) -> str:
        return self.value[0]

    @property
    def number(self) -> int:
        return self.value[1]


class Top(_Numbered):
    """``VisionStateMachineType`` states: name and StateNumber."""

    PREOPERATIONAL = ("Preoperational", 1)
    HALTED = ("Halted", 2)
    ERROR = ("Error", 3)
    OPERATIONAL = ("Operational", 4)


class Auto(_Numbered):
    """``VisionAutomaticModeStateMachineType`` states (only while Operational)."""

    INITIALIZED = ("Initialized", 5)
    READY = ("Ready", 6)
    SINGLE_EXECUTION = ("SingleExecution", 7)
    CONTINUOUS_EXECUTION = ("ContinuousExecution", 8)


#: Results with these statuses mean the vision system itself failed (not the part): the
#: machine goes to Error (OperationalToErrorAuto); Reset brings it back to Preoperational.
SYSTEM_FAULTS = frozenset({Status.CAMERA_ERROR, Status.NOT_CALIBRATED, Status.INTERNAL})

#: ResultStateDataType (OPC 40100-1 12.19): an Int32, 1 Completed, 3 Aborted, 4 Failed.
RESULT_COMPLETED, RESULT_ABORTED, RESULT_FAILED = 1, 3, 4
#: Statuses whose result is "Failed": the job did not produce an answer about the part.
FAILED_STATUSES = SYSTEM_FAULTS | {Status.BUSY, Status.BAD_REQUEST}

#: the automatic mode's states in which a job of the state machine runs
EXECUTING = (Auto.SINGLE_EXECUTION, Auto.CONTINUOUS_EXECUTION)

BAD_STATE = "BadInvalidState"
BAD_ARGUMENT = "BadInvalidArgument"
BAD_NO_DATA = "BadNoData"
NOT_SUPPORTED = "BadNotSupported"


def result_state(status: Status) -> int:
    """The ResultState of a result with vgripd status ``status``."""
    if status is Status.ABORTED:
        return RESULT_ABORTED
    return RESULT_FAILED if status in FAILED_STATUSES else RESULT_COMPLETED


@dataclass(frozen=True)
class Verdict:
    """The answer to one method call: ``refused`` is the OPC UA status code's name ("" when
    the call is done); ``why`` says why, for the log; ``transitions`` fired, in order;
    ``decision`` the handshake's, for a job request."""

    refused: str = ""
    why: str = ""
    transitions: tuple[str, ...] = ()
    decision: Decision | None = None

    @property
    def ok(self) -> bool:
        return not self.refused


def _refuse(code: str, why: str, seq: int = 0, command: int = 0,
            status: Status = Status.BAD_REQUEST) -> Verdict:
    """A refusal; a job request's refusal is the handshake's REJECT step (answered once)."""
    decision = (Decision(Action.REJECT, seq, command, 0, status,
                         steps=(Step(Part.REJECT, seq, int(status)),)) if seq else None)
    return Verdict(code, why, decision=decision)


class VisionMachine:
    """One link's OPC 40100 state: the two state machines, the prepared recipe, the running
    request (through ``handshake``) and what becomes of its result."""

    def __init__(self) -> None:
        self.handshake = Handshake(edge=False)
        self.top = Top.PREOPERATIONAL
        self.auto: Auto | None = None
        self.recipe: int | None = None  # the prepared recipe (number)
        self.simulation = False
        #: the running request was aborted (Halt, Reset, Stop, Abort): its result is ABORTED
        self.aborted = False
        #: Stop was called in ContinuousExecution: the chain ends with the running job
        self.stopping = False

    # -- what clients see ------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        return self.handshake.busy

    @property
    def state_path(self) -> str:
        """``Operational.Ready`` or ``Halted``: the state as one string."""
        return self.top.label + (f".{self.auto.label}" if self.auto is not None else "")

    def _go(self, top: Top, auto: Auto | None, name: str) -> tuple[str, ...]:
        """Move to ``top``/``auto`` by the transition ``name``. Leaving SingleExecution other
        than by the result aborts the running job (a request of the older namespace, started
        outside Ready, is not the state machine's and runs on)."""
        if self.busy and self.auto in EXECUTING and auto is not self.auto:
            self.aborted = True
        if auto is not Auto.CONTINUOUS_EXECUTION:
            self.stopping = False
        self.top, self.auto = top, auto
        return (name,)

    # -- VisionStateMachine ----------------------------------------------------------------

    def select_mode_automatic(self) -> Verdict:
        if self.top is Top.OPERATIONAL:
            return Verdict()  # automatic is the only mode: nothing to change
        if self.top is not Top.PREOPERATIONAL:
            return _refuse(BAD_STATE, f"SelectModeAutomatic in {self.top.label} (Reset first)")
        return Verdict(transitions=self._go(Top.OPERATIONAL, Auto.INITIALIZED,
                                            "PreoperationalToOperational")
                       + (("InitializedToReadyRecipe",) if self._ready() else ()))

    def _ready(self) -> bool:
        """A recipe is prepared already: Initialized moves on to Ready."""
        if self.recipe is not None and self.auto is Auto.INITIALIZED:
            self.auto = Auto.READY
            return True
        return False

    def halt(self) -> Verdict:
        """Halt is allowed in every state (Halted: nothing changes)."""
        if self.top is Top.HALTED:
            return Verdict()
        return Verdict(transitions=self._go(Top.HALTED, None, f"{self.top.label}ToHalted"))

    def reset(self) -> Verdict:
        """Reset is always executable: back to Preoperational (the prepared recipe stays)."""
        if self.top is Top.PREOPERATIONAL:
            return Verdict()
        return Verdict(transitions=self._go(Top.PREOPERATIONAL, None,
                                            f"{self.top.label}ToPreoperational"))

    def fault(self) -> tuple[str, ...]:
        """The vision system failed (a result with a ``SYSTEM_FAULTS`` status)."""
        if self.top is Top.ERROR:
            return ()
        return self._go(Top.ERROR, None, f"{self.top.label}ToErrorAuto")

    # -- recipes -----------------------------------------------------------------------------

    def prepare_recipe(self, number: int) -> Verdict:
        """Prepare recipe ``number`` (already judged to exist): in Preoperational, Initialized
        and Ready; not while a job runs or in Halted / Error."""
        if self.auto in (Auto.SINGLE_EXECUTION, Auto.CONTINUOUS_EXECUTION) or self.top in (
                Top.HALTED, Top.ERROR):
            return _refuse(BAD_STATE, f"PrepareRecipe in {self.state_path}")
        self.recipe = number
        return Verdict(transitions=("InitializedToReadyRecipe",) if self._ready() else ())

    def unprepare_recipe(self, number: int) -> Verdict:
        if self.auto in (Auto.SINGLE_EXECUTION, Auto.CONTINUOUS_EXECUTION) or self.top in (
                Top.HALTED, Top.ERROR):
            return _refuse(BAD_STATE, f"UnprepareRecipe in {self.state_path}")
        if self.recipe != number:
            return _refuse(BAD_ARGUMENT, f"UnprepareRecipe: recipe {number} is not prepared")
        self.recipe = None
        if self.auto is Auto.READY:
            self.auto = Auto.INITIALIZED
            return Verdict(transitions=("ReadyToInitializedRecipe",))
        return Verdict()

    # -- automatic mode ----------------------------------------------------------------------

    def start_single_job(self, seq: int, recipe: int | None) -> Verdict:
        """StartSingleJob as request ``seq`` (``recipe``: the one the call names, already
        judged to exist; None: the prepared one). Only in Ready."""
        return self._start("StartSingleJob", seq, recipe, Auto.SINGLE_EXECUTION)

    def start_continuous(self, seq: int, recipe: int | None) -> Verdict:
        """StartContinuous: request ``seq`` is the first job of a chain (``continue_job``
        starts each next one). Only in Ready."""
        return self._start("StartContinuous", seq, recipe, Auto.CONTINUOUS_EXECUTION)

    def _start(self, method: str, seq: int, recipe: int | None, to: Auto) -> Verdict:
        if self.auto is not Auto.READY:
            status = Status.BUSY if self.busy else Status.BAD_REQUEST
            return _refuse(BAD_STATE, f"{method} in {self.state_path} (Ready needed: "
                           "SelectModeAutomatic, then PrepareRecipe)", seq, Command.TRIGGER,
                           status)
        if recipe is not None and recipe != self.recipe:
            return _refuse(BAD_ARGUMENT, f"{method}: recipe {recipe} is not the prepared "
                           f"one ({self.recipe})", seq, Command.TRIGGER)
        assert self.recipe is not None
        verdict = self.request(Command.TRIGGER, seq, self.recipe)
        if verdict.ok and to is Auto.CONTINUOUS_EXECUTION:
            self.auto, self.stopping = to, False
            return Verdict(transitions=("ReadyToContinuousExecution",),
                           decision=verdict.decision)
        return verdict

    @property
    def wants_next(self) -> bool:
        """ContinuousExecution goes on and no request runs: the link starts the next job."""
        return self.auto is Auto.CONTINUOUS_EXECUTION and not self.busy and not self.stopping

    def continue_job(self, seq: int) -> Verdict:
        """The next job of ContinuousExecution as request ``seq``."""
        if not self.wants_next:
            return _refuse(BAD_STATE, f"next continuous job in {self.state_path}", seq,
                           Command.TRIGGER, Status.BUSY if self.busy else Status.BAD_REQUEST)
        assert self.recipe is not None
        return self.request(Command.TRIGGER, seq, self.recipe)

    def next_object(self, seq: int) -> Verdict:
        """The plain ``Next`` (the next object of the last job's pick list, or a conveyor's
        next part): in Ready."""
        return self._answer("Next", Command.NEXT, seq)

    def predict(self, seq: int) -> Verdict:
        """The plain ``Predict`` (where a conveyor's part last served will be at a later
        count): in Ready, like Next; ``BadNotSupported`` when no recipe has a conveyor."""
        return self._answer("Predict", Command.PREDICT, seq)

    def _answer(self, method: str, command: Command, seq: int) -> Verdict:
        """A request answered without an image (NEXT, PREDICT) with the prepared recipe."""
        if self.auto is not Auto.READY:
            status = Status.BUSY if self.busy else Status.BAD_REQUEST
            return _refuse(BAD_STATE, f"{method} in {self.state_path}", seq, command, status)
        return self.request(command, seq, self.recipe or 0)

    def request(self, command: int, seq: int, recipe: int) -> Verdict:
        """A request through the handshake; a started job moves Ready to SingleExecution.
        The link's older namespace calls this directly (its own rules, any state)."""
        decision = self.handshake.on_request(command, seq, recipe)
        if decision.action is not Action.START:
            code = (BAD_STATE if decision.code is Status.BUSY else
                    NOT_SUPPORTED if command == Command.PREDICT else BAD_NO_DATA)
            return Verdict(code, f"request {seq} refused {decision.code.name}",
                           decision=decision)
        self.aborted = False
        moves: tuple[str, ...] = ()
        if command == Command.TRIGGER and self.auto is Auto.READY:
            self.auto = Auto.SINGLE_EXECUTION
            moves = ("ReadyToSingleExecution",)
        return Verdict(transitions=moves, decision=decision)

    def stop(self) -> Verdict:
        """Stop: in an execution state, back to Ready; the running job's result is ABORTED."""
        return self._end_execution("Stop")

    def abort(self) -> Verdict:
        return self._end_execution("Abort")

    def _end_execution(self, how: str) -> Verdict:
        if self.auto not in EXECUTING:
            return _refuse(BAD_STATE, f"{how} in {self.state_path} (no job runs)")
        if self.auto is Auto.CONTINUOUS_EXECUTION and how == "Stop" and self.busy:
            self.stopping = True  # the running job ends normally, then Ready (publish)
            return Verdict()
        assert self.auto is not None
        name = f"{self.auto.label}ToReady{how}"
        self.aborted = self.busy
        self.auto, self.stopping = Auto.READY, False
        return Verdict(transitions=(name,))

    def set_simulation(self, active: bool) -> Verdict:
        if self.top is not Top.OPERATIONAL:
            return _refuse(BAD_STATE, f"SimulationMode in {self.state_path}")
        self.simulation = active
        return Verdict()

    # -- the daemon's side -----------------------------------------------------------------

    def captured(self, seq: int, job_id: int) -> tuple[Step, ...]:
        return self.handshake.on_captured(seq, job_id)

    def publish(self, seq: int, result: JobResult) -> tuple[tuple[Step, ...], JobResult,
                                                            tuple[str, ...]]:
        """The running request's result: the handshake's plan, the result as it is published
        (``ABORTED`` without a pose when the request was aborted meanwhile) and the
        transitions (SingleExecution back to Ready, or to Error for a system fault)."""
        if self.aborted and result.job_id and result.status is not Status.ABORTED:
            result = JobResult(job_id=result.job_id, status=Status.ABORTED,
                               message="aborted by the OPC UA client (Halt, Reset, Stop or "
                                       "Abort) before its result", recipe=result.recipe,
                               t_capture_mono_ns=result.t_capture_mono_ns,
                               t_done_mono_ns=result.t_done_mono_ns)
        plan = self.handshake.publish(seq, result)
        self.aborted = False
        moves: tuple[str, ...] = ()
        if result.status in SYSTEM_FAULTS and self.top is Top.OPERATIONAL:
            moves = self.fault()
        elif self.auto is Auto.SINGLE_EXECUTION:
            self.auto = Auto.READY
            moves = ("SingleExecutionToReadyAuto",)
        elif self.auto is Auto.CONTINUOUS_EXECUTION and (self.stopping or not result.job_id):
            # Stop was called, or the daemon gave no job (BUSY, ABORTED): the chain ends
            moves = ("ContinuousExecutionToReadyStop" if self.stopping
                     else "ContinuousExecutionToReadyAuto",)
            self.auto, self.stopping = Auto.READY, False
        return plan, result, moves
