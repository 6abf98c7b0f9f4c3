"""The pure parts of the reload (``vgripd.service.ops.reload``): the diff, the keys only a restart
can change, and the config a reload applies."""

from __future__ import annotations

from vgripd.config import Config, config_from_dict
from vgripd.service.ops.reload import applicable, config_diff, restart_keys

TOKEN = "a-test-token-of-32-characters-xx"


def make(**sections: object) -> Config:
    return config_from_dict({"camera": {"type": "synthetic", "seed": 1},
                             "links": [{"type": "modbus_server", "port": 5020}],
                             "status": {"token": TOKEN}, **sections})


def test_the_diff_names_each_changed_leaf_with_secrets_redacted() -> None:
    old = make()
    new = config_from_dict({**old.model_dump(mode="json", exclude_none=True),
                            "vision": {"min_contrast": 20.0},
                            "status": {"token": "another-token-of-32-characters-x"}})
    diff = config_diff(old, new)
    assert "vision.min_contrast: 25.0 -> 20.0" in diff
    assert not any(TOKEN in line or "another-token" in line for line in diff)
    assert config_diff(old, old) == []


def test_restart_keys_are_named_and_kept_as_they_run() -> None:
    old = make()
    data = old.model_dump(mode="json", exclude_none=True)
    data["links"][0]["port"] = 5021
    data["vision"]["min_features"] = 5
    new = config_from_dict(data)
    assert restart_keys(old, new) == ["links.0.port"]
    applied = applicable(old, new)
    assert applied.links == old.links  # the running link stays until a restart
    assert applied.vision.min_features == 5  # the rest applies
    assert applicable(old, make()) == make()
