"""Every camera the service can hold meets ``Camera``: each registered driver class and the
worker process's ``WorkerCamera`` have every member, with the protocol's parameters."""

from __future__ import annotations

import inspect

import pytest

from vgripd.errors import DriverError
from vgripd.registry import CAMERAS, load_class
from vgripd.service.worker.camera import Camera
from vgripd.service.worker.process import WorkerCamera

MEMBERS = [name for name in vars(Camera) if not name.startswith("_")]


def _classes() -> list[tuple[str, type]]:
    out: list[tuple[str, type]] = [("worker", WorkerCamera)]
    for name in CAMERAS:
        try:
            out.append((name, load_class(CAMERAS, "camera", name)))
        except DriverError:  # an optional SDK missing: that driver is tested where it is
            continue
    return out


def test_the_protocol_names_what_the_service_uses() -> None:
    assert {"type_name", "describe", "open", "close", "grab", "set_settings", "focus",
            "stuck_s"} <= set(MEMBERS)


@pytest.mark.parametrize(("name", "cls"), _classes(), ids=lambda v: v if isinstance(v, str)
                         else "")
def test_camera_classes_meet_the_protocol(name: str, cls: type) -> None:
    missing = [m for m in MEMBERS if not hasattr(cls, m) and m != "type_name"]
    assert not missing, f"{name}: {cls.__name__} lacks {missing}"
    if name != "worker":  # a driver class names its type; the worker's handle, per instance
        assert cls.type_name == name
    for member in MEMBERS:
        wanted = getattr(Camera, member)
        if isinstance(wanted, property):
            continue
        have = inspect.signature(getattr(cls, member))
        for param in inspect.signature(wanted).parameters.values():
            assert param.name in have.parameters, f"{name}: {member} lacks {param.name}"
            if param.default is not inspect.Parameter.empty:
                assert have.parameters[param.name].default == param.default, (
                    f"{name}: {member}'s {param.name}")
        assert inspect.iscoroutinefunction(getattr(cls, member)) == \
            inspect.iscoroutinefunction(wanted), f"{name}: {member} async or not"
