"""The OPC UA address space of the ``opcua`` link, shaped after OPC 40100 (Machine Vision).

Everything vgripd serves lives under ``Objects/VisionSystem`` in the namespace
``options.namespace_uri`` (index 2 on a fresh server; clients should look the URI up in the
``NamespaceArray``). Own nodes have string node ids named by their browse path
(``ns=2;s=VisionSystem.Result.RequestId``), so a PLC program can hard-code them; the state
machine is built by asyncua's ``FiniteStateMachine`` helper (a subtype of the standard
``FiniteStateMachineType``, numeric ids: browse to it) and its ``CurrentState`` written
directly. docs/opcua.md has the table and what of OPC 40100 is left out.

Writes go through ``Space.write`` in the order the caller gives; ``publish`` orders them so that
a client never pairs a request id with another request's data (``Space.publish_result``).
"""

from __future__ import annotations

import contextlib
import datetime
import gc
import math
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.statemachine import FiniteStateMachine, State
from asyncua.server.event_generator import EventGenerator

from drivers.links.opcua_belt import (
    BELT_RESULT,
    LATCH_INPUTS,
    belt_finite,
    belt_values,
    read_latch,
)
from vgripd.peer.jobcore import UNKNOWN_SCORE, PickPosition, pick_position
from vgripd.types import BeltPose, JobResult, Status

#: ``VisionStateMachine`` states: name -> number (vgripd's numbers; OPC 40100 names).
STATES = {"Ready": 1, "SingleExecution": 2, "Error": 3}
#: A result with one of these statuses leaves the state machine in ``Error`` (the vision system
#: itself failed, as opposed to a part that was not found): OPC 40100's error state. A new
#: StartSingleJob is still accepted there (the register map also allows a new trigger).
ERROR_STATUSES = frozenset({Status.CAMERA_ERROR, Status.NOT_CALIBRATED, Status.INTERNAL})

MethodHandler = Callable[..., Awaitable[Any]]
#: ``Result.Timestamp`` before the first result: OPC UA's null DateTime (encoded as 0). A value
#: of None made every Read that named the variable fail with BadInternalError.
NO_TIME = datetime.datetime(1601, 1, 1, tzinfo=datetime.UTC)


def node_id(idx: int, path: str) -> ua.NodeId:
    """The string node id of vgripd's node at browse path ``path`` (dots between names)."""
    return ua.NodeId(ua.String(path), ua.Int16(idx))


@dataclass(frozen=True)
class ResultValues:
    """What one result shows, already checked: the finite pose or none."""

    request_id: int
    job_id: int
    recipe: int
    status: Status
    message: str
    vendor: str
    value_names: list[str]
    values: list[float]
    pose: list[float]  # T_offset row-major (16), mm; empty without a pose
    fit_rms_mm: float
    residual_names: list[str]
    residuals: list[float]
    timestamp: datetime.datetime
    pick: PickPosition = PickPosition(0, 0)  # Count, Index, PickId, Score
    belt: BeltPose | None = None  # a conveyor answer's count and pose in belt terms

    @property
    def status_name(self) -> str:
        return self.status.name


def result_values(request_id: int, recipe: int, result: JobResult,
                  timestamp: datetime.datetime) -> tuple[ResultValues, JobResult]:
    """The variables' values for ``result`` and the result as it is published.

    A pose is shown only with a pose-valid status; a pose or offset that is not finite (which
    the pipeline's gates should have stopped) is published as ``OUT_OF_LIMITS`` without a pose
    rather than as numbers a robot might move by. The pick-list position (``pick_position``:
    a job's own result or a NEXT answer) keeps its count then, but shows no instance; a
    conveyor answer's belt result (``JobResult.belt``) is shown only with finite numbers, so
    such a result shows none either.
    """
    pick = pick_position(result)
    values: list[float] = []
    names: list[str] = []
    pose: list[float] = []
    vendor = ""
    if result.status.pose_valid and result.target is not None:
        values = [float(v) for v in result.target.values]
        names = list(result.target.fields)
        vendor = result.target.vendor
        if result.offset is not None:
            pose = [float(v) for v in result.offset.reshape(-1)]
        if not all(math.isfinite(v) for v in values + pose) or len(pose) not in (0, 16) or (
                not belt_finite(result.belt)):
            result = JobResult(job_id=result.job_id, status=Status.OUT_OF_LIMITS,
                               message="the pose is not a finite 4x4 / vendor values / belt "
                                       "position",
                               residuals=result.residuals,
                               t_done_mono_ns=result.t_done_mono_ns)
            values, names, pose, vendor = [], [], [], ""
            pick = PickPosition(pick.count, 0)
    residuals = {k: float(v) for k, v in result.residuals.items() if math.isfinite(float(v))}
    fit = residuals.get("fit_rms_mm", -1.0)
    shown = ResultValues(request_id, result.job_id & 0xFFFFFFFF, recipe, result.status,
                         result.message, vendor, names, values, pose, fit,
                         list(residuals), list(residuals.values()), timestamp, pick,
                         result.belt if belt_finite(result.belt) else None)
    return shown, result


def _arg(name: str, vtype: ua.VariantType, text: str) -> ua.Argument:
    return ua.Argument(Name=name, DataType=ua.NodeId(ua.Int32(vtype.value)), ValueRank=-1,
                       ArrayDimensions=[], Description=ua.LocalizedText(text))


# (browse name, variant type, initial value, description) of the result variables, in the
# order they are written; RequestId and Sequence come last (``publish_result``).
RESULT_DATA: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("JobId", ua.VariantType.UInt32, 0, "daemon job id (0: refused without a job)"),
    ("RecipeId", ua.VariantType.UInt16, 0, "recipe the job ran with"),
    ("Status", ua.VariantType.UInt16, int(Status.IDLE), "vgripd status code (README)"),
    ("StatusName", ua.VariantType.String, Status.IDLE.name, "name of the status code"),
    ("Message", ua.VariantType.String, "", "why, for a failed job"),
    ("Vendor", ua.VariantType.String, "", "robot convention of Values (output.vendor)"),
    ("ValueNames", ua.VariantType.String, [], "field names of Values, in the vendor's order"),
    ("Values", ua.VariantType.Double, [], "offset in the vendor's convention and units"),
    ("Pose", ua.VariantType.Double, [], "offset as a 4x4 row-major, mm (empty: no pose)"),
    ("FitRmsMm", ua.VariantType.Double, -1.0, "fit residual, mm (-1: unknown)"),
    ("ResidualNames", ua.VariantType.String, [], "names of Residuals"),
    ("Residuals", ua.VariantType.Double, [], "residual figures (px or mm by name)"),
    ("Timestamp", ua.VariantType.DateTime, ua.uatypes.FILETIME_EPOCH_AS_UTC_DATETIME,
     "when the result was produced (UTC); the null DateTime (1601-01-01, 0 on the wire) "
     "before the first result"),
    ("Count", ua.VariantType.UInt16, 0,
     "pickable objects of the job (a single object: 1 with a pose, 0 without)"),
    ("Index", ua.VariantType.UInt16, 0,
     "1-based index of the object shown; 0 none shown; Count + 1 the list is used up"),
    ("PickId", ua.VariantType.UInt16, 0,
     "pick point id of the object shown (picking.pick_points; 0 the object's own grip)"),
    ("Score", ua.VariantType.Double, UNKNOWN_SCORE,
     "detection score 0..1 of the object shown (-1: none shown or unknown)"),
    *BELT_RESULT,
)
#: The status of the result data while a job runs: the values are the previous result's.
UNCERTAIN = ua.StatusCodes.UncertainLastUsableValue

RESULT_LAST = (
    ("RequestId", ua.VariantType.UInt32, 0,
     "request (StartSingleJob's RequestId) whose result this is; 0 while a job runs"),
    ("Sequence", ua.VariantType.UInt32, 0, "+1 for every result published"),
)
EVENT_FIELDS: tuple[tuple[str, ua.VariantType], ...] = (
    ("RequestId", ua.VariantType.UInt32), ("JobId", ua.VariantType.UInt32),
    ("RecipeId", ua.VariantType.UInt16), ("ResultStatus", ua.VariantType.UInt16),
    ("StatusName", ua.VariantType.String), ("Vendor", ua.VariantType.String),
    ("ValueNames", ua.VariantType.String), ("Values", ua.VariantType.Double),
    ("Pose", ua.VariantType.Double), ("FitRmsMm", ua.VariantType.Double),
    ("Sequence", ua.VariantType.UInt32), ("Count", ua.VariantType.UInt16),
    ("Index", ua.VariantType.UInt16), ("PickId", ua.VariantType.UInt16),
    ("Score", ua.VariantType.Double),
    *((name, vtype) for name, vtype, _, _ in BELT_RESULT),
)


class Space:
    """vgripd's nodes in a started-or-not ``Server``; ``build`` adds them."""

    def __init__(self, server: Server, idx: int) -> None:
        self.server = server
        self.idx = idx
        self.nodes: dict[str, ua.NodeId] = {}
        self.types: dict[str, ua.VariantType] = {}
        self.values: dict[str, Any] = {}  # the last value written to each variable
        self.vision_system: Node | None = None
        self._state_nodes: tuple[ua.NodeId, ...] = ()
        self._states: dict[str, State] = {}
        self._result_ready: EventGenerator | None = None
        self._acquisition_done: EventGenerator | None = None
        self.state = ""
        self.sequence = 0

    async def build(self, start_job: MethodHandler, select_recipe: MethodHandler,
                    reset: MethodHandler, next_object: MethodHandler,
                    predict: MethodHandler) -> None:
        s, idx = self.server, self.idx
        vs_type = await s.create_custom_object_type(
            node_id(idx, "VisionSystemType"), ua.QualifiedName("VisionSystemType", idx))
        vs = await s.nodes.objects.add_object(node_id(idx, "VisionSystem"),
                                              ua.QualifiedName("VisionSystem", idx),
                                              objecttype=vs_type.nodeid)
        await vs.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        self.vision_system = vs

        # FiniteStateMachineType is abstract: OPC 40100's VisionStateMachineType is its subtype
        sm_type = await s.create_custom_object_type(
            node_id(idx, "VisionStateMachineType"), ua.QualifiedName("VisionStateMachineType", idx),
            ua.ObjectIds.FiniteStateMachineType)
        machine = FiniteStateMachine(s, vs, idx, "VisionStateMachine")
        machine._state_machine_type = sm_type.nodeid
        await machine.install(optionals=True)
        for name, number in STATES.items():
            state = State(name, name, number)
            await machine.add_state(state)
            self._states[name] = state
        # CurrentState and its Id / Number, written directly (the helper's change_state goes
        # through a session write per node: half the cost of a job's publish)
        sm = await vs.get_child([f"{idx}:VisionStateMachine"])
        current = await sm.get_child(["0:CurrentState"])
        number_node = await current.add_property(  # optional in StateVariableType
            node_id(idx, "VisionSystem.VisionStateMachine.CurrentState.Number"),
            ua.QualifiedName("Number", 0), ua.Variant(0, ua.VariantType.UInt32))
        self._state_nodes = (current.nodeid, (await current.get_child(["0:Id"])).nodeid,
                             number_node.nodeid)

        await vs.add_method(node_id(idx, "VisionSystem.StartSingleJob"),
                            ua.QualifiedName("StartSingleJob", idx), start_job, [],
                            [_arg("RequestId", ua.VariantType.UInt32,
                                  "id of this request; the result shows it in Result.RequestId")])
        await vs.add_method(node_id(idx, "VisionSystem.SelectRecipe"),
                            ua.QualifiedName("SelectRecipe", idx), select_recipe,
                            [_arg("RecipeId", ua.VariantType.UInt16,
                                  "job parameter of the next jobs (0 = default)")], [])
        await vs.add_method(node_id(idx, "VisionSystem.Reset"), ua.QualifiedName("Reset", idx),
                            reset, [], [])
        await vs.add_method(node_id(idx, "VisionSystem.Next"), ua.QualifiedName("Next", idx),
                            next_object, [],
                            [_arg("RequestId", ua.VariantType.UInt32,
                                  "id of this request; the result shows it in Result.RequestId")])
        await vs.add_method(node_id(idx, "VisionSystem.Predict"),
                            ua.QualifiedName("Predict", idx), predict,
                            [_arg("Count", ua.VariantType.UInt32,
                                  "conveyor: the encoder count N to predict the part at")],
                            [_arg("RequestId", ua.VariantType.UInt32,
                                  "id of this request; the result shows it in Result.RequestId")])
        for name, vtype, value, text in (
            ("SelectedRecipe", ua.VariantType.UInt16, 0, "recipe of the next StartSingleJob"),
            ("CapturedRequestId", ua.VariantType.UInt32, 0,
             "request whose image is taken: the robot may move on"),
            ("Warnings", ua.VariantType.UInt16, 0, "live warning bits: bit 0 RECALIBRATE"),
        ):
            await self._variable(vs, name, name, vtype, value, text)
        for name, vtype, value, text in LATCH_INPUTS:  # the client's to write
            await self._variable(vs, name, name, vtype, value, text, writable=True)
        result = await vs.add_object(node_id(idx, "VisionSystem.Result"),
                                     ua.QualifiedName("Result", idx))
        for name, vtype, value, text in RESULT_DATA + RESULT_LAST:
            await self._variable(result, f"Result.{name}", name, vtype, value, text)

        ready = await self._event_type("ResultReadyEventType", EVENT_FIELDS)
        done = await self._event_type("AcquisitionDoneEventType", (
            ("RequestId", ua.VariantType.UInt32), ("JobId", ua.VariantType.UInt32)))
        self._result_ready = await s.get_event_generator(ready, vs.nodeid)
        self._acquisition_done = await s.get_event_generator(done, vs.nodeid)
        await self.set_state("Ready")

    async def _event_type(self, name: str,
                          fields: Sequence[tuple[str, ua.VariantType]]) -> Node:
        """A subtype of BaseEventType with one property per field (string node ids)."""
        base = self.server.get_node(ua.ObjectIds.BaseEventType)
        etype = await base.add_object_type(node_id(self.idx, name),
                                           ua.QualifiedName(name, self.idx))
        for field, vtype in fields:
            await etype.add_property(node_id(self.idx, f"{name}.{field}"),
                                     ua.QualifiedName(field, self.idx),
                                     ua.get_default_value(vtype), varianttype=vtype)
        return etype

    async def _variable(self, parent: Node, key: str, name: str, vtype: ua.VariantType,
                        value: Any, text: str, writable: bool = False) -> None:
        """``key``: the browse path below VisionSystem (``Warnings``, ``Result.Values``);
        ``writable``: clients may write its value (of its type: asyncua refuses another)."""
        var = await parent.add_variable(node_id(self.idx, f"VisionSystem.{key}"),
                                        ua.QualifiedName(name, self.idx),
                                        ua.Variant(value, vtype), datatype=vtype.value)
        if isinstance(value, list):
            await var.write_value_rank(ua.ValueRank.OneDimension)
            await var.write_attribute(ua.AttributeIds.ArrayDimensions,
                                      ua.DataValue(ua.Variant([0], ua.VariantType.UInt32)))
        await var.write_attribute(ua.AttributeIds.Description,
                                  ua.DataValue(ua.Variant(ua.LocalizedText(text))))
        if writable:
            await var.set_writable()
        self.nodes[key] = var.nodeid
        self.types[key] = vtype
        self.values[key] = value

    async def write(self, items: Sequence[tuple[str, Any]],
                    t: datetime.datetime | None = None, status: int = 0) -> None:
        """Write ``(key, value)`` pairs in order (keys: ``CapturedRequestId``,
        ``Result.Values``, ...), with the OPC UA status code ``status`` (0: Good)."""
        now: Any = t or datetime.datetime.now(datetime.UTC)  # ua.DateTime is one
        for key, value in items:
            dv = ua.DataValue(ua.Variant(value, self.types[key]),
                              StatusCode=ua.StatusCode(ua.UInt32(status)), SourceTimestamp=now,
                              ServerTimestamp=now)
            await self.server.write_attribute_value(self.nodes[key], dv)
            self.values[key] = value

    def latch(self) -> tuple[int | None, int | None]:
        """``LatchCount`` and ``LatchFrame`` as the client left them (None: no count)."""
        return read_latch(self.server, self.nodes["LatchCount"], self.nodes["LatchFrame"])

    async def set_state(self, name: str) -> None:
        """CurrentState (LocalizedText), then its Id (the state object) and Number."""
        if name == self.state:
            return
        state = self._states[name]
        assert state.node is not None
        now: Any = datetime.datetime.now(datetime.UTC)
        for nid, variant in zip(self._state_nodes, (
                ua.Variant(ua.LocalizedText(name, "en-US"), ua.VariantType.LocalizedText),
                ua.Variant(state.node.nodeid, ua.VariantType.NodeId),
                ua.Variant(STATES[name], ua.VariantType.UInt32)), strict=True):
            await self.server.write_attribute_value(
                nid, ua.DataValue(variant, SourceTimestamp=now, ServerTimestamp=now))
        self.state = name

    async def retract(self, executing: bool = True) -> None:
        """A new request: the result area names no request until its result is in. A job
        (``executing``) also moves the state machine to SingleExecution; a NEXT takes no image
        and leaves the state as it is.

        The data variables keep their values but turn ``UncertainLastUsableValue`` first, so
        each is a data change now and Good again with the result. That fixes the order a
        subscriber receives them in: asyncua's server orders one publish response by the item
        that changed first in the publishing interval, so without this a RequestId retracted
        and set again within one interval came *before* the data of its own result, and a
        client acting on each notification in turn paired the new id with the old pose."""
        await self.write([(f"Result.{name}", self.values[f"Result.{name}"])
                          for name, *_ in RESULT_DATA], status=UNCERTAIN)
        await self.write([("Result.RequestId", 0)])
        if executing:
            await self.set_state("SingleExecution")

    async def captured(self, request_id: int, job_id: int) -> None:
        await self.write([("CapturedRequestId", request_id)])
        gen = self._acquisition_done
        assert gen is not None
        ev: Any = gen.event
        ev.RequestId = ua.Variant(request_id, ua.VariantType.UInt32)
        ev.JobId = ua.Variant(job_id & 0xFFFFFFFF, ua.VariantType.UInt32)
        ev.Message = ua.LocalizedText(f"image of request {request_id} taken (job {job_id})")
        ev.Severity = 100
        await gen.trigger()

    async def publish_result(self, shown: ResultValues) -> None:
        """The data, then RequestId, then Sequence, then the state; the event last (it carries
        the whole result in one notification)."""
        self.sequence = 1 if self.sequence >= 0xFFFFFFFF else self.sequence + 1
        r = shown
        await self.write([
            ("Result.JobId", r.job_id), ("Result.RecipeId", r.recipe),
            ("Result.Status", int(r.status)), ("Result.StatusName", r.status.name),
            ("Result.Message", r.message), ("Result.Vendor", r.vendor),
            ("Result.ValueNames", r.value_names), ("Result.Values", r.values),
            ("Result.Pose", r.pose), ("Result.FitRmsMm", r.fit_rms_mm),
            ("Result.ResidualNames", r.residual_names), ("Result.Residuals", r.residuals),
            ("Result.Timestamp", r.timestamp),
            ("Result.Count", int(r.pick.count)), ("Result.Index", int(r.pick.index)),
            ("Result.PickId", int(r.pick.pick_id)), ("Result.Score", float(r.pick.score)),
            *((f"Result.{name}", value) for name, value in belt_values(r.belt)),
            ("Result.RequestId", r.request_id), ("Result.Sequence", self.sequence),
        ], r.timestamp)
        await self.set_state("Error" if r.status in ERROR_STATUSES else "Ready")
        gen = self._result_ready
        assert gen is not None
        ev: Any = gen.event
        known = {"ResultStatus": int(r.status), "Sequence": self.sequence,
                 "Count": int(r.pick.count), "Index": int(r.pick.index),
                 "PickId": int(r.pick.pick_id), "Score": float(r.pick.score),
                 **dict(belt_values(r.belt))}
        for name, vtype in EVENT_FIELDS:
            value = known.get(name)
            if value is None:
                value = getattr(r, _EVENT_ATTR.get(name, name))
            setattr(ev, name, ua.Variant(value, vtype))
        ev.Message = ua.LocalizedText(f"request {r.request_id}: {r.status.name}")
        ev.Severity = 100 if r.status.pose_valid else 500
        ev.Time = r.timestamp
        await gen.trigger()


_EVENT_ATTR = {"RequestId": "request_id", "JobId": "job_id", "RecipeId": "recipe",
               "StatusName": "status_name", "Vendor": "vendor", "ValueNames": "value_names",
               "Values": "values", "Pose": "pose", "FitRmsMm": "fit_rms_mm"}


# -- the server certificate --------------------------------------------------------------------

CERT_NAME = "vgripd-server-cert.der"
KEY_NAME = "vgripd-server-key.pem"


def ensure_certificate(folder: Path, app_uri: str, host_names: Sequence[str],
                       days: int) -> tuple[Path, Path, bool]:
    """The server's certificate and key in ``folder``, generated (self-signed, RSA 2048,
    SHA-256, the application URI and host names as subject alternative names) when neither
    exists. Returns (certificate, key, generated). ``ValueError`` when only one of them exists
    (a half-copied folder must not be silently replaced: clients trust the old certificate)."""
    import ipaddress
    import os

    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    cert, key = folder / CERT_NAME, folder / KEY_NAME
    if cert.exists() and key.exists():
        return cert, key, False
    if cert.exists() or key.exists():
        have, missing = (cert, key) if cert.exists() else (key, cert)
        raise ValueError(f"{have} exists but {missing} does not; restore it, or remove both "
                         "to generate a new certificate (clients must then trust the new one)")
    folder.mkdir(parents=True, exist_ok=True)
    private_key = cert_gen.generate_private_key()
    alt: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri)]
    for name in dict.fromkeys(host_names):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt.append(x509.DNSName(name))
    certificate = cert_gen.generate_self_signed_app_certificate(
        private_key, "vgripd", {"organizationName": "vgripd"}, alt,
        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH], days=days)
    from cryptography.hazmat.primitives.serialization import Encoding

    fd = os.open(key, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(cert_gen.dump_private_key_as_pem(private_key))
    cert.write_bytes(certificate.public_bytes(Encoding.DER))
    return cert, key, True


@contextlib.contextmanager
def collector_paused() -> Iterator[None]:
    """No cyclic garbage collection while the server's address space is built: its tens of
    thousands of nodes are long-lived, and collecting while they are made (in asyncua's
    thread, holding the interpreter lock the event loop waits for) spent some 40 % of the
    build on passes that free nothing. Afterwards collection is on again if it was."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
