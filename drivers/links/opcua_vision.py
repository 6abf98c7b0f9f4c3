"""The OPC 40100 (OPC UA for Machine Vision) side of the ``opcua`` link, on the official NodeSet.

``VisionSpace.build`` loads ``nodesets/Opc.Ua.MachineVision.NodeSet2.xml`` (namespace
``http://opcfoundation.org/UA/MachineVision``, model 1.0.0) with asyncua's XML importer,
builds its data types, and adds one ``VisionSystemType`` instance, ``Objects/VisionSystem`` in
the namespace ``urn:vgripd:vision-system`` (string node ids by browse path, e.g.
``VisionSystem.VisionStateMachine.AutomaticModeStateMachine.StartSingleJob``). Its methods are
answered here by the rules of ``vgripd.peer.visionsm.VisionMachine`` (the link's one state
machine and handshake); the optional nodes vgripd does not implement (file transfer, products,
adding or removing recipes and configurations, step models) are removed from the instance so
that a client never calls a method without an implementation.

What each method maps to (docs/opcua.md, "OPC 40100" has the table):

- recipes: ``PrepareRecipe``'s ExternalId names a configured recipe by number or name; the
  InternalId is the number (``Id``) with the name as ``Description``;
- configuration: the one loaded config, its ``Hash`` the SHA-256 of the config as the daemon
  judged it (``set_configuration``); ``ActivateConfiguration`` confirms it (a config is changed
  through the judged transaction, not through OPC UA);
- results: every published result becomes a ``ResultDataType`` (``ResultContent``: key/value
  pairs with the vgripd status, the pose and vendor values, the pick-list position), raised as
  a ``ResultReadyEventType`` event on the VisionSystem object and kept, the last
  ``RECENT_RESULTS``, for ``GetResultById`` / ``GetResultComponentsById`` /
  ``GetResultListFiltered``;
- ``Plc``: plain variables for clients that cannot take events or structures (an S7-1500's
  OPC UA client blocks): the state, the last result's fields, the pick list and a conveyor's
  belt result, the latch the PLC writes (``opcua_belt``), and the methods ``PrepareRecipe``,
  ``StartJob``, ``Next`` and ``Predict`` with plain arguments;
- ``StartContinuous``: a chain of jobs, each a request of the link's handshake, the next one
  started after each published result (``continue_later``) until Stop, Abort, Halt or Reset.
"""

from __future__ import annotations

import asyncio
import datetime
import hashlib
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.server.event_generator import EventGenerator

from drivers.links.opcua_belt import (
    BELT_RESULT,
    LATCH_INPUTS,
    belt_values,
    belt_variants,
    count_argument,
    read_latch,
)
from drivers.links.opcua_nodeset import prune
from drivers.links.opcua_space import ResultValues
from vgripd.peer.jobcore import Command
from vgripd.peer.visionsm import (
    BAD_ARGUMENT,
    Auto,
    Top,
    Verdict,
    VisionMachine,
    result_state,
)
from vgripd.types import Status

NODESET = Path(__file__).with_name("nodesets") / "Opc.Ua.MachineVision.NodeSet2.xml"
MV_URI = "http://opcfoundation.org/UA/MachineVision"
INSTANCE_URI = "urn:vgripd:vision-system"
#: results kept for ResultManagement (GetResultById and the lists)
RECENT_RESULTS = 64
#: node ids in the NodeSet (namespace MV_URI)
VISION_SYSTEM_TYPE = 1003
STATE_IDS = {Top.PREOPERATIONAL: 5028, Top.HALTED: 5029, Top.ERROR: 5030,
             Top.OPERATIONAL: 5031, Auto.INITIALIZED: 5056, Auto.READY: 5057,
             Auto.SINGLE_EXECUTION: 5058, Auto.CONTINUOUS_EXECUTION: 5059}
EVENT_TYPES = {"ResultReady": 1024, "AcquisitionDone": 1025, "RecipePrepared": 1022,
               "JobStarted": 1013}
#: optional nodes of the instance vgripd does not implement (browse paths below VisionSystem)
NOT_IMPLEMENTED = (
    "RecipeManagement.AddRecipe", "RecipeManagement.RemoveRecipe",
    "RecipeManagement.PrepareProduct", "RecipeManagement.UnprepareProduct",
    "RecipeManagement.UnlinkProduct", "RecipeManagement.ReleaseRecipeHandle",
    "RecipeManagement.Products", "RecipeManagement.Recipes", "RecipeManagement.RecipeTransfer",
    "ConfigurationManagement.AddConfiguration", "ConfigurationManagement.RemoveConfiguration",
    "ConfigurationManagement.ReleaseConfigurationHandle",
    "ConfigurationManagement.Configurations", "ConfigurationManagement.ConfigurationTransfer",
    "ResultManagement.ReleaseResultHandle", "ResultManagement.Results",
    "ResultManagement.ResultTransfer",
    "VisionStateMachine.PreoperationalStepModel", "VisionStateMachine.HaltedStepModel",
    "VisionStateMachine.ErrorStepModel",
    "VisionStateMachine.AutomaticModeStateMachine.InitializedStepModel",
    "VisionStateMachine.AutomaticModeStateMachine.ReadyStepModel",
    "VisionStateMachine.AutomaticModeStateMachine.SingleExecutionStepModel",
    "VisionStateMachine.AutomaticModeStateMachine.ContinuousExecutionStepModel",
)
#: the plain variables (``Plc``): name, type, first value, description; written in this order,
#: ``ResultId`` and ``Sequence`` last (a result's data is complete when its id shows)
PLAIN_STATE: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("State", ua.VariantType.String, "Preoperational",
     "the state: Preoperational, Halted, Error, or Operational.<automatic-mode state>"),
    ("StateNumber", ua.VariantType.UInt32, 1, "VisionStateMachine StateNumber (1..4)"),
    ("AutoStateNumber", ua.VariantType.UInt32, 0,
     "automatic-mode StateNumber (5 Initialized, 6 Ready, 7 SingleExecution, "
     "8 ContinuousExecution; 0 not Operational)"),
    ("PreparedRecipe", ua.VariantType.String, "", "InternalId of the prepared recipe"),
    ("JobId", ua.VariantType.String, "", "JobId of the request running or last started"),
)
PLAIN_RESULT: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("ResultJobId", ua.VariantType.String, "", "JobId of the last result"),
    ("ResultState", ua.VariantType.Int32, 0, "1 Completed, 3 Aborted, 4 Failed (0 none yet)"),
    ("Status", ua.VariantType.UInt16, int(Status.IDLE), "vgripd status code (README)"),
    ("StatusName", ua.VariantType.String, Status.IDLE.name, "name of the status code"),
    ("Vendor", ua.VariantType.String, "", "robot convention of Values"),
    ("ValueNames", ua.VariantType.String, [], "field names of Values"),
    ("Values", ua.VariantType.Double, [], "offset in the vendor's convention and units"),
    ("Pose", ua.VariantType.Double, [], "offset as a 4x4 row-major, mm (empty: no pose)"),
    ("Count", ua.VariantType.UInt16, 0, "pickable objects of the job"),
    ("Index", ua.VariantType.UInt16, 0, "1-based index of the object shown (0 none)"),
    ("PickId", ua.VariantType.UInt16, 0, "pick point id of the object shown"),
    ("Score", ua.VariantType.Double, -1.0, "detection score 0..1 (-1 unknown)"),
    *BELT_RESULT,
)
PLAIN_LAST: tuple[tuple[str, ua.VariantType, Any, str], ...] = (
    ("ResultId", ua.VariantType.String, "", "ResultId of the last result; \"\" while a job runs"),
    ("Sequence", ua.VariantType.UInt32, 0, "+1 for every result published"),
)
UNCERTAIN = ua.StatusCodes.UncertainLastUsableValue
#: The NodeSet's structures (``mv.ResultDataType`` ...): asyncua makes them classes of ``ua``
#: when it builds the data types (``load_data_type_definitions``), so they exist only then.
mv: Any = ua

#: (status, code name, why) -> the StatusCode answered (the link counts and logs it)
Refuse = Callable[[Status, str, str], ua.StatusCode]
#: (command, verdict for seq, the request's 40100 metadata) -> the verdict, the request started
#: when it is ok
Request = Callable[[int, Callable[[int], Verdict], "JobInfo"], Awaitable[tuple[Verdict, int]]]


@dataclass
class JobInfo:
    """A request's OPC 40100 metadata, kept until its result."""

    meas_id: Any = None
    part_id: Any = None
    recipe_external: Any = None
    product_id: Any = None
    started: datetime.datetime | None = None
    t_start_ns: int = 0
    t_captured_ns: int = 0
    simulated: bool = False
    #: OPC 40100's JobId: the request's own sequence, or the first one of a continuous chain
    job_id: str = ""
    #: A conveyor's latch (``Trigger.latch_count`` / ``latch_frame``): the latch variables as
    #: the request found them, Predict's count N; None: none
    count: int | None = None
    frame: int | None = None


#: Subtypes of BinaryIdBaseDataType whose Definition in the NodeSet is empty (the fields are the
#: base type's): NodeSet data type id by name
BINARY_IDS = {"RecipeIdExternalDataType": 3002, "RecipeIdInternalDataType": 3013,
              "ConfigurationIdDataType": 3008}


async def register_binary_ids(get_node: Callable[[ua.NodeId], Node], mv_index: int) -> None:
    """Give each of ``BINARY_IDS`` a class and binary encoding of its own, after asyncua's
    ``load_data_type_definitions`` (server or client).

    asyncua (2.1) builds these three from the abstract base's definition and registers all of
    them as the base's class, so it encodes a RecipeIdExternalDataType with the encoding id of
    BinaryIdBaseDataType, which another stack cannot decode, and cannot decode the right id
    another stack sends. Each class here is a subclass of the base (same fields), registered
    under its own Default Binary encoding node.
    """
    import dataclasses

    base = ua.BinaryIdBaseDataType  # type: ignore[attr-defined]
    for name, number in BINARY_IDS.items():
        type_id = ua.NodeId(ua.Int32(number), ua.Int16(mv_index))
        encoding = None
        for node in await get_node(type_id).get_referenced_nodes(ua.ObjectIds.HasEncoding):
            if (await node.read_browse_name()).Name == "Default Binary":
                encoding = node.nodeid
        if encoding is None:
            raise ValueError(f"{name}: no Default Binary encoding in the NodeSet")
        cls: type = dataclasses.dataclass(type(name, (base,), {"__module__": __name__}))
        # asyncua's lookup tables only: ``ua.<name>`` stays asyncua's (binding it again logs
        # a name collision); vgripd builds these ids with ``binary_id``
        ua.extension_objects_by_typeid[encoding] = cls
        ua.typeid_by_extension_objects[cls] = encoding
        ua.extension_objects_by_datatype[type_id] = cls
        ua.datatype_by_extension_object[cls] = type_id
        BINARY_ID_CLASSES[name] = cls


#: the classes ``register_binary_ids`` made, by name
BINARY_ID_CLASSES: dict[str, type] = {}


def binary_id(name: str, **fields: Any) -> Any:
    """A RecipeIdExternal/RecipeIdInternal/ConfigurationId value that encodes with its own
    type's encoding id (``register_binary_ids``)."""
    return BINARY_ID_CLASSES[name](**fields)


def _code(name: str) -> int:
    return int(getattr(ua.StatusCodes, name))


def _ext(value: Any) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.ExtensionObject)


def _i32(value: int) -> ua.Variant:
    return ua.Variant(value, ua.VariantType.Int32)


class VisionMethods:
    """The answers to the VisionSystem's methods (``VisionSpace`` adds the nodes they act on)."""

    machine: VisionMachine
    recipes: dict[int, str]
    results: deque[Any]
    configuration_id: str
    configuration_hash: bytes
    configuration_time: datetime.datetime
    idx: int
    chain: JobInfo | None
    _chain_task: asyncio.Task[None] | None
    _request: Request
    _refuse: Refuse

    async def show_state(self) -> None:
        raise NotImplementedError

    async def _event(self, name: str, message: str, **fields: ua.Variant) -> None:
        raise NotImplementedError

    async def _write_safety(self, triggered: bool, text: str) -> None:
        raise NotImplementedError

    def _recipe_id(self, number: int) -> Any:
        return binary_id("RecipeIdInternalDataType", Id=str(number),
                         Description=ua.LocalizedText(self.recipes.get(number, "")))

    def _configuration(self) -> Any:
        cid = binary_id("ConfigurationIdDataType", Id=self.configuration_id,
                        Hash=self.configuration_hash or None,
                        HashAlgorithm="SHA-256" if self.configuration_hash else None)
        return mv.ConfigurationDataType(InternalId=cid, LastModified=self.configuration_time)

    def recipe_number(self, ident: Any, field: str) -> int | str | None:
        """The configured recipe an id names (its ``Id``: the number or the name); None for
        an empty id; a message (str) when it names none."""
        text = str(getattr(ident, "Id", "") or "").strip() if ident is not None else ""
        if not text:
            return None
        for number, name in self.recipes.items():
            if text in (str(number), name):
                return number
        known = ", ".join(f"{n} {name}" for n, name in sorted(self.recipes.items()))
        return f"{field}: recipe {text!r} is not configured (configured: {known})"

    def _args(self, method: str, args: Sequence[ua.Variant],
              kinds: Sequence[type | tuple[type, ...]]) -> list[Any] | ua.StatusCode:
        """The values of ``args`` when they are as many as ``kinds`` and of those types (a
        null structure passes as None); the refusal otherwise."""
        if len(args) < len(kinds):
            return self._refuse(Status.BAD_REQUEST, "BadArgumentsMissing",
                                f"{method} takes {len(kinds)} arguments, {len(args)} given")
        if len(args) > len(kinds):
            return self._refuse(Status.BAD_REQUEST, "BadTooManyArguments",
                                f"{method} takes {len(kinds)} arguments, {len(args)} given")
        values = [a.Value for a in args]
        for i, (value, kind) in enumerate(zip(values, kinds, strict=True)):
            if value is not None and not isinstance(value, kind):
                return self._refuse(Status.BAD_REQUEST, "BadInvalidArgument",
                                    f"{method}: argument {i + 1} is a {type(value).__name__}")
        return values

    def _verdict(self, verdict: Verdict, method: str) -> list[ua.Variant] | ua.StatusCode:
        if verdict.refused:
            return self._refuse(Status.BAD_REQUEST, verdict.refused, f"{method}: {verdict.why}")
        return [_i32(0)]

    async def _moved(self, verdict: Verdict, method: str) -> list[ua.Variant] | ua.StatusCode:
        answer = self._verdict(verdict, method)
        if verdict.ok:
            await self.show_state()
        return answer

    async def _select_mode_automatic(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("SelectModeAutomatic", args, [])
        if isinstance(checked, ua.StatusCode):
            return checked
        return await self._moved(self.machine.select_mode_automatic(), "SelectModeAutomatic")

    async def _halt(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Halt", args, [int, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        return await self._moved(self.machine.halt(), "Halt")

    async def _reset(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Reset", args, [int, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        return await self._moved(self.machine.reset(), "Reset")

    async def _confirm_all(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """No condition of vgripd waits for a confirmation: nothing to confirm."""
        checked = self._args("ConfirmAll", args, [ua.LocalizedText])
        return checked if isinstance(checked, ua.StatusCode) else []

    async def _start_single_job(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        return await self._start("StartSingleJob", args)

    async def _start(self, method: str, args: Sequence[ua.Variant]) -> Any:
        """StartSingleJob or StartContinuous: the same arguments and answers."""
        checked = self._args(method, args, [
            mv.MeasIdDataType, mv.PartIdDataType, mv.BinaryIdBaseDataType,
            mv.ProductIdDataType, list])
        if isinstance(checked, ua.StatusCode):
            return checked
        meas, part, recipe, product, _parameters = checked
        number = self.recipe_number(recipe, f"{method} RecipeId")
        if isinstance(number, str):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT, number)
        info = JobInfo(meas, part, recipe, product, simulated=self.machine.simulation)
        if method == "StartContinuous":
            self.chain = info  # each next job of the chain carries its ids (continue_chain)
            return await self._job(Command.TRIGGER, lambda seq: self.machine.start_continuous(
                seq, number), info, method)
        return await self._job(Command.TRIGGER, lambda seq: self.machine.start_single_job(
            seq, number), info, method)

    def continue_later(self) -> None:
        """After a result is published: in ContinuousExecution, start the chain's next job in
        a task of its own, so that the daemon is done with this job when it asks for one."""
        if self.machine.wants_next:
            self._chain_task = asyncio.create_task(self.continue_chain())

    async def close(self) -> None:
        task, self._chain_task = self._chain_task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def continue_chain(self) -> None:
        """ContinuousExecution after a published result: the chain's next job (nothing when
        the chain ended, or a request of the older namespace runs: its result comes back
        here)."""
        if self.chain is None or not self.machine.wants_next:
            return
        info = JobInfo(self.chain.meas_id, self.chain.part_id, self.chain.recipe_external,
                       self.chain.product_id, simulated=self.machine.simulation,
                       job_id=self.chain.job_id)
        await self._job(Command.TRIGGER, self.machine.continue_job, info, "StartContinuous")

    async def _job(self, command: int, verdict_for: Callable[[int], Verdict], info: JobInfo,
                   method: str) -> Any:
        info.started = datetime.datetime.now(datetime.UTC)
        info.t_start_ns = time.monotonic_ns()
        if command != Command.PREDICT:  # a job or Next takes the latch in place now
            info.count, info.frame = self.latch()
        verdict, seq = await self._request(command, verdict_for, info)
        if verdict.refused:
            status = (verdict.decision.code if verdict.decision is not None
                      else Status.BAD_REQUEST)
            return self._refuse(status, verdict.refused, f"{method}: {verdict.why}")
        if command == Command.TRIGGER:
            await self._event("JobStarted", f"job {info.job_id} started (request {seq})",
                              JobId=_ext(mv.JobIdDataType(Id=info.job_id)))
        return [_ext(mv.JobIdDataType(Id=info.job_id)), _i32(0)]

    async def _start_continuous(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        return await self._start("StartContinuous", args)

    async def _stop(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Stop", args, [int, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        return await self._moved(self.machine.stop(), "Stop")

    async def _abort(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Abort", args, [int, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        return await self._moved(self.machine.abort(), "Abort")

    async def _simulation_mode(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("SimulationMode", args, [bool, int, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        return self._verdict(self.machine.set_simulation(bool(checked[0])), "SimulationMode")

    async def _prepare_recipe(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("PrepareRecipe", args, [mv.BinaryIdBaseDataType,
                                                     mv.BinaryIdBaseDataType])
        if isinstance(checked, ua.StatusCode):
            return checked
        number = self.recipe_number(checked[0], "PrepareRecipe ExternalId")
        if number is None:
            number = self.recipe_number(checked[1], "PrepareRecipe InternalIdIn")
        if number is None:
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT,
                                "PrepareRecipe: give ExternalId.Id (a recipe number or name)")
        refused = await self._prepare(number, "PrepareRecipe")
        if refused is not None or isinstance(number, str):
            return refused
        return [_ext(self._recipe_id(number)), ua.Variant(True, ua.VariantType.Boolean),
                _i32(0)]

    async def _prepare(self, number: int | str, method: str) -> ua.StatusCode | None:
        """Prepare the recipe ``number`` (a message: no such recipe); the refusal or None."""
        if isinstance(number, str):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT, number)
        verdict = self.machine.prepare_recipe(number)
        if verdict.refused:
            answer = self._verdict(verdict, method)
            assert isinstance(answer, ua.StatusCode)
            return answer
        await self.show_state()
        await self._event("RecipePrepared", f"recipe {number} prepared")
        return None

    async def _plain_prepare(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Plc.PrepareRecipe", args, [str])
        if isinstance(checked, ua.StatusCode):
            return checked
        ident = mv.RecipeIdExternalDataType(Id=checked[0] or "")
        number = self.recipe_number(ident, "Plc.PrepareRecipe RecipeId")
        if number is None:
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT,
                                "Plc.PrepareRecipe: give a recipe number or name")
        refused = await self._prepare(number, "Plc.PrepareRecipe")
        if refused is not None:
            return refused
        return [ua.Variant(str(number), ua.VariantType.String), _i32(0)]

    async def _unprepare_recipe(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("UnprepareRecipe", args, [mv.BinaryIdBaseDataType,
                                                       mv.BinaryIdBaseDataType])
        if isinstance(checked, ua.StatusCode):
            return checked
        number = self.recipe_number(checked[0], "UnprepareRecipe ExternalId")
        if number is None:
            number = self.recipe_number(checked[1], "UnprepareRecipe InternalIdIn")
        if not isinstance(number, int):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT,
                                number or "UnprepareRecipe: give ExternalId or InternalIdIn")
        verdict = self.machine.unprepare_recipe(number)
        if verdict.refused:
            return self._verdict(verdict, "UnprepareRecipe")
        await self.show_state()
        return [_ext(self._recipe_id(number)), _i32(0)]

    async def _recipe_list(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("GetRecipeListFiltered", args, [
            mv.BinaryIdBaseDataType, mv.ProductIdDataType, int, int, int, (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        external, _product, prepared, max_results, start, _timeout = checked
        numbers = sorted(self.recipes)
        wanted = self.recipe_number(external, "GetRecipeListFiltered ExternalId")
        if wanted is not None:
            numbers = [n for n in numbers if n == wanted]
        if prepared in (0, 1):  # TriStateBoolean: 0 false, 1 true, 2 don't care
            numbers = [n for n in numbers if (n == self.machine.recipe) == bool(prepared)]
        page, complete = _page(numbers, start or 0, max_results or 0)
        return [ua.Variant(complete, ua.VariantType.Boolean),
                ua.Variant(len(numbers), ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant([self._recipe_id(n) for n in page], ua.VariantType.ExtensionObject),
                _i32(0)]

    def set_configuration(self, name: str, digest: bytes) -> None:
        self.configuration_id = name
        self.configuration_hash = digest
        self.configuration_time = datetime.datetime.now(datetime.UTC)

    async def _activate_configuration(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("ActivateConfiguration", args, [mv.BinaryIdBaseDataType])
        if isinstance(checked, ua.StatusCode):
            return checked
        if not self._is_ours(checked[0]):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT,
                                "ActivateConfiguration: only the loaded configuration "
                                f"{self.configuration_id!r} exists (change the config through "
                                "vgripd, not OPC UA)")
        return [_i32(0)]

    def _is_ours(self, ident: Any) -> bool:
        return ident is not None and getattr(ident, "Id", None) == self.configuration_id

    async def _configuration_by_id(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("GetConfigurationById", args, [mv.BinaryIdBaseDataType,
                                                            (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        if not self._is_ours(checked[0]):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT,
                                f"GetConfigurationById: no configuration {checked[0]!r}")
        return [ua.Variant(0, ua.VariantType.UInt32), _ext(self._configuration()), _i32(0)]

    async def _configuration_list(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("GetConfigurationList", args, [int, int, (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        page, complete = _page([self._configuration()], checked[1] or 0, checked[0] or 0)
        return [ua.Variant(complete, ua.VariantType.Boolean), ua.Variant(1, ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(page, ua.VariantType.ExtensionObject), _i32(0)]

    def _find(self, ident: Any) -> Any:
        wanted = getattr(ident, "Id", None)
        return next((r for r in reversed(self.results) if r.ResultId.Id == wanted), None)

    async def _result_by_id(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("GetResultById", args, [mv.ResultIdDataType, (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        found = self._find(checked[0])
        if found is None:
            return self._refuse(Status.BAD_REQUEST, "BadNoMatch",
                                f"GetResultById: no result {checked[0]!r} among the last "
                                f"{RECENT_RESULTS}")
        return [ua.Variant(0, ua.VariantType.UInt32), _ext(found), _i32(0)]

    async def _result_components_by_id(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("GetResultComponentsById", args, [mv.ResultIdDataType,
                                                               (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        r = self._find(checked[0])
        if r is None:
            return self._refuse(Status.BAD_REQUEST, "BadNoMatch",
                                f"GetResultComponentsById: no result {checked[0]!r}")
        b = ua.VariantType.Boolean
        return [ua.Variant(False, b), ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(r.IsPartial, b), ua.Variant(r.IsSimulated, b),
                _i32(r.ResultState), _ext(r.MeasId), _ext(r.PartId), _ext(r.ExternalRecipeId),
                _ext(r.InternalRecipeId), _ext(r.ProductId), _ext(r.ExternalConfigurationId),
                _ext(r.InternalConfigurationId), _ext(r.JobId),
                ua.Variant(r.CreationTime, ua.VariantType.DateTime), _ext(r.ProcessingTimes),
                ua.Variant(r.ResultContent, ua.VariantType.Variant), _i32(0)]

    async def _result_list(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        structures = (mv.MeasIdDataType, mv.PartIdDataType, mv.BinaryIdBaseDataType,
                      mv.BinaryIdBaseDataType, mv.BinaryIdBaseDataType,
                      mv.BinaryIdBaseDataType, mv.ProductIdDataType, mv.JobIdDataType)
        checked = self._args("GetResultListFiltered", args,
                             [int, *structures, int, int, (int, float)])
        if isinstance(checked, ua.StatusCode):
            return checked
        state, *ids = checked[:9]
        max_results, start = checked[9], checked[10]
        fields = ("MeasId", "PartId", "ExternalRecipeId", "InternalRecipeId",
                  "ExternalConfigurationId", "InternalConfigurationId", "ProductId", "JobId")
        found = [r for r in self.results if not state or r.ResultState == state]
        for name, ident in zip(fields, ids, strict=True):
            wanted = getattr(ident, "Id", "") if ident is not None else ""
            if wanted:
                found = [r for r in found if getattr(getattr(r, name), "Id", None) == wanted]
        page, complete = _page(found, start or 0, max_results or 0)
        return [ua.Variant(complete, ua.VariantType.Boolean),
                ua.Variant(len(found), ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(page, ua.VariantType.ExtensionObject), _i32(0)]

    async def _report_safety_state(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        """Shown, never acted on: OPC 40100's safety state is information, not a safety
        function."""
        checked = self._args("ReportSafetyState", args, [bool, str])
        if isinstance(checked, ua.StatusCode):
            return checked
        await self._write_safety(bool(checked[0]), checked[1] or "")
        return [_i32(0)]

    async def _plain_start(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Plc.StartJob", args, [str])
        if isinstance(checked, ua.StatusCode):
            return checked
        ident = mv.RecipeIdExternalDataType(Id=checked[0] or "")
        number = self.recipe_number(ident, "Plc.StartJob RecipeId")
        if isinstance(number, str):
            return self._refuse(Status.BAD_REQUEST, BAD_ARGUMENT, number)
        answer = await self._job(Command.TRIGGER, lambda seq: self.machine.start_single_job(
            seq, number), JobInfo(simulated=self.machine.simulation), "Plc.StartJob")
        return _plain_answer(answer)

    async def _plain_next(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        checked = self._args("Plc.Next", args, [])
        if isinstance(checked, ua.StatusCode):
            return checked
        answer = await self._job(Command.NEXT, self.machine.next_object, JobInfo(), "Plc.Next")
        return _plain_answer(answer)

    async def _plain_predict(self, parent: ua.NodeId, *args: ua.Variant) -> Any:
        count = count_argument("Plc.Predict", args)
        if isinstance(count, tuple):
            return self._refuse(Status.BAD_REQUEST, *count)
        answer = await self._job(Command.PREDICT, self.machine.predict, JobInfo(count=count),
                                 "Plc.Predict")
        return _plain_answer(answer)

    def latch(self) -> tuple[int | None, int | None]:
        raise NotImplementedError


class VisionSpace(VisionMethods):
    """The VisionSystem instance and the answers to its methods (one per open link)."""

    def __init__(self, server: Server, machine: VisionMachine, request: Request,
                 refuse: Refuse) -> None:
        self.server = server
        self.machine = machine
        self._request = request
        self._refuse = refuse
        self.idx = 0  # the instance namespace
        self.mv = 0  # the MachineVision namespace
        self.recipes: dict[int, str] = {0: "default"}
        self.configuration_id = "vgripd"
        self.configuration_hash = b""
        self.configuration_time = datetime.datetime.now(datetime.UTC)
        self.results: deque[Any] = deque(maxlen=RECENT_RESULTS)
        self.pending: dict[int, JobInfo] = {}
        #: the ids StartContinuous was called with, for each job of its chain
        self.chain: JobInfo | None = None
        self._chain_task: asyncio.Task[None] | None = None
        self.sequence = 0
        self.vision_system: Node | None = None
        self._state_nodes: dict[str, ua.NodeId] = {}
        self._plain: dict[str, tuple[ua.NodeId, ua.VariantType]] = {}
        self._values: dict[str, Any] = {}
        self._events: dict[str, EventGenerator] = {}
        self._config_node: ua.NodeId | None = None

    async def build(self) -> None:
        s = self.server
        await s.import_xml(str(NODESET))
        await s.load_data_type_definitions()
        self.mv = await s.get_namespace_index(MV_URI)
        await register_binary_ids(s.get_node, self.mv)
        self.idx = idx = await s.register_namespace(INSTANCE_URI)
        vs = await s.nodes.objects.add_object(
            self._nid(""), ua.QualifiedName("VisionSystem", idx),
            objecttype=self._mv_id(VISION_SYSTEM_TYPE))
        await vs.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        self.vision_system = vs
        await prune(s, [s.get_node(self._nid(path)) for path in NOT_IMPLEMENTED])
        auto = "VisionStateMachine.AutomaticModeStateMachine"
        handlers: dict[str, Callable[..., Awaitable[Any]]] = {
            "VisionStateMachine.SelectModeAutomatic": self._select_mode_automatic,
            "VisionStateMachine.Halt": self._halt,
            "VisionStateMachine.Reset": self._reset,
            "VisionStateMachine.ConfirmAll": self._confirm_all,
            f"{auto}.StartSingleJob": self._start_single_job,
            f"{auto}.StartContinuous": self._start_continuous,
            f"{auto}.Stop": self._stop,
            f"{auto}.Abort": self._abort,
            f"{auto}.SimulationMode": self._simulation_mode,
            "RecipeManagement.PrepareRecipe": self._prepare_recipe,
            "RecipeManagement.UnprepareRecipe": self._unprepare_recipe,
            "RecipeManagement.GetRecipeListFiltered": self._recipe_list,
            "ConfigurationManagement.ActivateConfiguration": self._activate_configuration,
            "ConfigurationManagement.GetConfigurationById": self._configuration_by_id,
            "ConfigurationManagement.GetConfigurationList": self._configuration_list,
            "ResultManagement.GetResultById": self._result_by_id,
            "ResultManagement.GetResultComponentsById": self._result_components_by_id,
            "ResultManagement.GetResultListFiltered": self._result_list,
            "SafetyStateManagement.ReportSafetyState": self._report_safety_state,
        }
        for path, handler in handlers.items():
            s.link_method(s.get_node(self._nid(path)), handler)
        for key, path in (("top", "VisionStateMachine.CurrentState"),
                          ("top.id", "VisionStateMachine.CurrentState.Id"),
                          ("auto", f"{auto}.CurrentState"),
                          ("auto.id", f"{auto}.CurrentState.Id")):
            self._state_nodes[key] = self._nid(path)
        self._config_node = self._nid("ConfigurationManagement.ActiveConfiguration")
        for name, type_id in EVENT_TYPES.items():
            self._events[name] = await s.get_event_generator(self._mv_id(type_id),
                                                             vs.nodeid)
        plc = await vs.add_object(self._nid("Plc"), ua.QualifiedName("Plc", idx))
        for name, vtype, value, text in PLAIN_STATE + PLAIN_RESULT + PLAIN_LAST:
            await self._variable(plc, name, vtype, value, text)
        for name, vtype, value, text in LATCH_INPUTS:  # the PLC's to write
            await self._variable(plc, name, vtype, value, text, writable=True)
        string = ua.VariantType.String
        await plc.add_method(self._nid("Plc.StartJob"), ua.QualifiedName("StartJob", idx),
                             self._plain_start,
                             [_arg("RecipeId", string, "recipe number or name (\"\": prepared)")],
                             [_arg("JobId", string, "the job's id (Plc.ResultJobId shows it)"),
                              _arg("Error", ua.VariantType.Int32, "0: started")])
        await plc.add_method(self._nid("Plc.PrepareRecipe"),
                             ua.QualifiedName("PrepareRecipe", idx), self._plain_prepare,
                             [_arg("RecipeId", string, "recipe number or name")],
                             [_arg("RecipeId", string, "the prepared recipe's number (its "
                                   "InternalId, Plc.PreparedRecipe shows it)"),
                              _arg("Error", ua.VariantType.Int32, "0: prepared")])
        await plc.add_method(self._nid("Plc.Next"), ua.QualifiedName("Next", idx),
                             self._plain_next, [],
                             [_arg("JobId", string, "the request's id"),
                              _arg("Error", ua.VariantType.Int32, "0: started")])
        await plc.add_method(self._nid("Plc.Predict"), ua.QualifiedName("Predict", idx),
                             self._plain_predict,
                             [_arg("Count", ua.VariantType.UInt32,
                                   "conveyor: the encoder count N to predict the part at")],
                             [_arg("JobId", string, "the request's id"),
                              _arg("Error", ua.VariantType.Int32, "0: started")])
        await self._write_safety(False, "")
        await self.show_configuration()
        await self.show_state()

    def _nid(self, path: str) -> ua.NodeId:
        return ua.NodeId(ua.String("VisionSystem" + (f".{path}" if path else "")),
                         ua.Int16(self.idx))

    def _mv_id(self, number: int) -> ua.NodeId:
        return ua.NodeId(ua.Int32(number), ua.Int16(self.mv))

    async def _variable(self, parent: Node, name: str, vtype: ua.VariantType, value: Any,
                        text: str, writable: bool = False) -> None:
        var = await parent.add_variable(self._nid(f"Plc.{name}"), ua.QualifiedName(name, self.idx),
                                        ua.Variant(value, vtype), datatype=vtype.value)
        if isinstance(value, list):
            await var.write_value_rank(ua.ValueRank.OneDimension)
        if writable:  # of its type: asyncua refuses another
            await var.set_writable()
        await var.write_attribute(ua.AttributeIds.Description,
                                  ua.DataValue(ua.Variant(ua.LocalizedText(text))))
        self._plain[name] = (var.nodeid, vtype)
        self._values[name] = value

    async def write(self, items: Sequence[tuple[str, Any]], status: int = 0) -> None:
        """Write plain variables in the order given (``status``: the OPC UA status code)."""
        now: Any = datetime.datetime.now(datetime.UTC)
        for name, value in items:
            nid, vtype = self._plain[name]
            await self.server.write_attribute_value(nid, ua.DataValue(
                ua.Variant(value, vtype), StatusCode=ua.StatusCode(ua.UInt32(status)),
                SourceTimestamp=now, ServerTimestamp=now))
            self._values[name] = value

    async def _set(self, nid: ua.NodeId, variant: ua.Variant) -> None:
        now: Any = datetime.datetime.now(datetime.UTC)
        await self.server.write_attribute_value(nid, ua.DataValue(
            variant, SourceTimestamp=now, ServerTimestamp=now))

    def set_recipes(self, recipes: Mapping[int, str]) -> None:
        self.recipes = dict(recipes) or {0: "default"}

    def latch(self) -> tuple[int | None, int | None]:
        """``Plc.LatchCount`` and ``Plc.LatchFrame`` as the PLC left them (None: no count)."""
        return read_latch(self.server, self._plain["LatchCount"][0],
                          self._plain["LatchFrame"][0])

    async def show_configuration(self) -> None:
        assert self._config_node is not None
        await self._set(self._config_node, _ext(self._configuration()))

    async def show_state(self) -> None:
        """CurrentState and Id of both state machines and the plain state, as the machine is."""
        m = self.machine
        for key, state in (("top", m.top), ("auto", m.auto)):
            await self._set(self._state_nodes[key], ua.Variant(
                ua.LocalizedText(state.label if state else "", "en-US"),
                ua.VariantType.LocalizedText))
            await self._set(self._state_nodes[f"{key}.id"], ua.Variant(
                self._mv_id(STATE_IDS[state]) if state else ua.NodeId(),
                ua.VariantType.NodeId))
        prepared = "" if m.recipe is None else str(m.recipe)
        await self.write([("State", m.state_path), ("StateNumber", m.top.number),
                          ("AutoStateNumber", m.auto.number if m.auto else 0),
                          ("PreparedRecipe", prepared)])

    async def retract(self, seq: int) -> None:
        """A request started: the result's plain data turns uncertain, then ResultId is
        cleared (the data keeps its values until the result; see ``Space.retract``)."""
        await self.write([(name, self._values[name]) for name, *_ in PLAIN_RESULT],
                         status=UNCERTAIN)
        info = self.pending.get(seq)
        await self.write([("ResultId", ""), ("JobId", info.job_id if info else str(seq))])
        await self.show_state()

    async def captured(self, seq: int, job_id: int) -> None:
        info = self.pending.get(seq)
        if info is not None:
            info.t_captured_ns = time.monotonic_ns()
        job = info.job_id if info is not None else str(seq)
        await self._event("AcquisitionDone", f"image of request {seq} taken (daemon job "
                          f"{job_id})", JobId=_ext(mv.JobIdDataType(Id=job)))

    async def publish(self, seq: int, shown: ResultValues, t_done_ns: int,
                      moves: tuple[str, ...]) -> None:
        """A result: the plain data, then ResultId and Sequence, the state, the stored
        ResultDataType and the ResultReady event."""
        info = self.pending.pop(seq, JobInfo(job_id=str(seq)))
        self.sequence = 1 if self.sequence >= 0xFFFFFFFF else self.sequence + 1
        result_id = str(self.sequence)
        state = result_state(shown.status)
        r = shown
        await self.write([
            ("ResultJobId", info.job_id), ("ResultState", state), ("Status", int(r.status)),
            ("StatusName", r.status.name), ("Vendor", r.vendor), ("ValueNames", r.value_names),
            ("Values", r.values), ("Pose", r.pose), ("Count", int(r.pick.count)),
            ("Index", int(r.pick.index)), ("PickId", int(r.pick.pick_id)),
            ("Score", float(r.pick.score)), *belt_values(r.belt), ("ResultId", result_id),
            ("Sequence", self.sequence)])
        await self.show_state()
        data = self._result_data(result_id, seq, shown, info, t_done_ns)
        self.results.append(data)
        gen = self._events["ResultReady"]
        ev: Any = gen.event
        for field in ("ResultId", "IsPartial", "IsSimulated", "ResultState", "MeasId", "PartId",
                      "ExternalRecipeId", "InternalRecipeId", "ProductId",
                      "ExternalConfigurationId", "InternalConfigurationId", "JobId",
                      "CreationTime", "ProcessingTimes"):
            value = getattr(data, field)
            setattr(ev, field, ua.Variant(value, _FIELD_TYPES.get(field,
                                                                  ua.VariantType.ExtensionObject)))
        ev.ResultContent = ua.Variant(data.ResultContent, ua.VariantType.Variant)
        ev.Message = ua.LocalizedText(f"result {result_id} of job {seq}: {r.status.name}")
        ev.Severity = 100 if r.status.pose_valid else 500
        ev.Time = r.timestamp
        await gen.trigger()

    def _result_data(self, result_id: str, seq: int, shown: ResultValues, info: JobInfo,
                     t_done_ns: int) -> Any:
        r = shown
        end = r.timestamp
        start = info.started or end
        times = mv.ProcessingTimesDataType(StartTime=start, EndTime=end)
        if info.t_start_ns and info.t_captured_ns:
            times.AcquisitionDuration = (info.t_captured_ns - info.t_start_ns) / 1e6
            times.ProcessingDuration = max(0, t_done_ns - info.t_captured_ns) / 1e6
        content = [("Status", ua.Variant(int(r.status), ua.VariantType.UInt16)),
                   ("StatusName", ua.Variant(r.status.name, ua.VariantType.String)),
                   ("Message", ua.Variant(r.message, ua.VariantType.String)),
                   ("DaemonJobId", ua.Variant(r.job_id, ua.VariantType.UInt32)),
                   ("Vendor", ua.Variant(r.vendor, ua.VariantType.String)),
                   ("ValueNames", ua.Variant(r.value_names, ua.VariantType.String)),
                   ("Values", ua.Variant(r.values, ua.VariantType.Double)),
                   ("Pose", ua.Variant(r.pose, ua.VariantType.Double)),
                   ("FitRmsMm", ua.Variant(r.fit_rms_mm, ua.VariantType.Double)),
                   ("Count", ua.Variant(int(r.pick.count), ua.VariantType.UInt16)),
                   ("Index", ua.Variant(int(r.pick.index), ua.VariantType.UInt16)),
                   ("PickId", ua.Variant(int(r.pick.pick_id), ua.VariantType.UInt16)),
                   ("Score", ua.Variant(float(r.pick.score), ua.VariantType.Double)),
                   *belt_variants(r.belt)]
        return mv.ResultDataType(
            ResultId=mv.ResultIdDataType(Id=result_id), IsPartial=False,
            IsSimulated=info.simulated, ResultState=result_state(r.status),
            MeasId=info.meas_id, PartId=info.part_id, ExternalRecipeId=info.recipe_external,
            InternalRecipeId=self._recipe_id(r.recipe), ProductId=info.product_id,
            InternalConfigurationId=self._configuration().InternalId,
            JobId=mv.JobIdDataType(Id=info.job_id), CreationTime=end, ProcessingTimes=times,
            ResultContent=[_ext(ua.KeyValuePair(Key=ua.QualifiedName(k, self.idx), Value=v))
                           for k, v in content])

    async def _event(self, name: str, message: str, **fields: ua.Variant) -> None:
        gen = self._events[name]
        ev: Any = gen.event
        for key, value in fields.items():
            if hasattr(ev, key):  # a field of this event type
                setattr(ev, key, value)
        ev.Message = ua.LocalizedText(message)
        ev.Severity = 100
        ev.Time = datetime.datetime.now(datetime.UTC)
        await gen.trigger()

    def begin(self, seq: int, info: JobInfo) -> None:
        """Request ``seq`` started (of either namespace): its metadata waits for its result."""
        info.job_id = info.job_id or str(seq)
        self.pending[seq] = info

    async def _write_safety(self, triggered: bool, text: str) -> None:
        await self._set(self._nid("SafetyStateManagement.VisionSafetyTriggered"),
                        ua.Variant(triggered, ua.VariantType.Boolean))
        await self._set(self._nid("SafetyStateManagement.VisionSafetyInformation"),
                        ua.Variant(text, ua.VariantType.String))


_FIELD_TYPES = {"IsPartial": ua.VariantType.Boolean, "IsSimulated": ua.VariantType.Boolean,
                "ResultState": ua.VariantType.Int32, "CreationTime": ua.VariantType.DateTime}


def _plain_answer(answer: Any) -> Any:
    """A JobIdDataType answer as its plain string."""
    if isinstance(answer, ua.StatusCode):
        return answer
    return [ua.Variant(answer[0].Value.Id, ua.VariantType.String), answer[1]]


def _page(items: Sequence[Any], start: int, max_results: int) -> tuple[list[Any], bool]:
    """Items ``start`` .. ``start + max_results`` (0: all), and whether that is the rest."""
    end = len(items) if max_results <= 0 else start + max_results
    return list(items[start:end]), end >= len(items)


def _arg(name: str, vtype: ua.VariantType, text: str) -> ua.Argument:
    return ua.Argument(Name=name, DataType=ua.NodeId(ua.Int32(vtype.value)), ValueRank=-1,
                       ArrayDimensions=[], Description=ua.LocalizedText(text))


def config_digest(text: str) -> bytes:
    """The SHA-256 of a config as the daemon judged it (its canonical JSON)."""
    return hashlib.sha256(text.encode()).digest()




#: The plain methods (``Plc``): name, inputs, outputs (name: type), what it does.
PLAIN_METHODS = (
    ("PrepareRecipe", "RecipeId: String", "RecipeId: String, Error: Int32",
     "prepare a recipe by number or name (RecipeManagement.PrepareRecipe)"),
    ("StartJob", "RecipeId: String", "JobId: String, Error: Int32",
     "start one job, \"\" the prepared recipe (StartSingleJob)"),
    ("Next", "", "JobId: String, Error: Int32",
     "the next object of the last job's pick list (a conveyor: the queue's next part)"),
    ("Predict", "Count: UInt32", "JobId: String, Error: Int32",
     "a conveyor: where the part last served will be at the encoder count Count"),
)
#: The standard's nodes a PLC with structure support calls, in the order it calls them.
STANDARD_SEQUENCE = (
    "VisionStateMachine.SelectModeAutomatic",
    "RecipeManagement.PrepareRecipe",
    "VisionStateMachine.AutomaticModeStateMachine.StartSingleJob",
    "ResultReadyEventType (event on VisionSystem)",
    "ResultManagement.GetResultById",
)


def plc_contract() -> dict[str, Any]:
    """What a PLC reads and calls (docs/opcua.md, "OPC 40100"): the instance's namespace, the
    plain ``Plc`` variables (first the two the PLC writes, a conveyor's latch, then those
    vgripd writes, in the order it writes them) and its methods, and the standard's sequence;
    the setup page's link step shows it."""
    return {
        "namespace": INSTANCE_URI, "machine_vision": MV_URI,
        "node_id": "ns=<index of the namespace>;s=VisionSystem.<browse path>",
        "variables": [{"node": f"VisionSystem.Plc.{name}", "type": vtype.name, "text": text}
                      for name, vtype, _, text in LATCH_INPUTS + PLAIN_STATE + PLAIN_RESULT
                      + PLAIN_LAST],
        "methods": [{"node": f"VisionSystem.Plc.{name}", "in": args, "out": out, "text": text}
                    for name, args, out, text in PLAIN_METHODS],
        "standard": [f"VisionSystem.{path}" for path in STANDARD_SEQUENCE],
    }
