"""Files that travel with the package: the robot program templates, the example configs, the
documentation pages and the systemd unit.

They live in the checkout as ``robots/``, ``config/examples/``, ``docs/`` and ``systemd/``;
``vgripd/share/`` links to them, so a wheel carries them as package data under
``vgripd/share/`` and an editable install reads them through the same links. Code finds them
here, through :mod:`importlib.resources`, never by a path relative to the checkout.
"""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

#: The folders of ``vgripd/share/``.
ROBOTS = "robots"
EXAMPLES = "examples"
DOCS = "docs"
SYSTEMD = "systemd"


def shared(*parts: str) -> Traversable:
    """``vgripd/share/<parts...>`` of the installed package (a folder or a file)."""
    node = files("vgripd").joinpath("share")
    for part in parts:
        node = node.joinpath(part)
    return node
