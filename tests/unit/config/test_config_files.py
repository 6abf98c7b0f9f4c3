"""Every file in config/ loads, and config/example.toml names every field of the model."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import BaseModel

from tests.conftest import REPO
from vgripd.config import Config, load_config

CONFIG_DIR = REPO / "config"
EXAMPLE = CONFIG_DIR / "example.toml"


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.rglob("*.toml")), ids=lambda p: p.name)
def test_every_config_file_loads(path: Path) -> None:
    load_config(path)


def _section_models() -> dict[str, type[BaseModel]]:
    out = {}
    for name, field in Config.model_fields.items():
        ann = field.annotation
        for candidate in (ann, *getattr(ann, "__args__", ())):
            if isinstance(candidate, type) and issubclass(candidate, BaseModel):
                out[name] = candidate
    return out


def test_example_documents_every_section_and_field() -> None:
    """The README says config/example.toml documents every field: each section of the model
    appears as a table and each of its fields as a key (set, or shown commented out)."""
    text = EXAMPLE.read_text()
    keys = set(re.findall(r"^#?\s*([A-Za-z_]\w*)\s*=", text, re.M))
    keys |= {part for header in re.findall(r"^#?\s*\[+([\w.]+)\]+", text, re.M)
             for part in header.split(".")}
    missing = []
    for section, model in _section_models().items():
        if section == "about":
            continue
        if section not in keys:
            missing.append(f"[{section}]")
        missing += [f"{section}.{f}" for f in model.model_fields if f not in keys]
    assert not missing, f"config/example.toml does not mention: {missing}"
