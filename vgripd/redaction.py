"""The one redaction of secrets for everything that shows or writes the configuration or what
the daemon saw: the web page and ``/api/config``, the status and job JSON, each recorded job's
``config.toml`` and ``pair.json``, and the support bundle (config, status, log lines).

Two kinds of secret are hidden:

- the value of a key that names one (``token``, ``password``/``passwd``, ``passphrase``,
  ``secret``, ``credential``, ``api_key``/``apikey``, ``private_key``, ``access_key``), at any
  depth, whatever its type. A key named plain ``key`` is no secret: it names a config key (a
  job diagnosis' ``causes[].key``, ``vision.working_distance_mm``), and hiding it would hide
  the diagnosis;
- credentials inside a string, wherever the string is: the user information of a URL
  (``rtsp://admin:pw@cam/stream`` -> ``rtsp://<redacted>@cam/stream``) and a query parameter
  that names a secret (``?token=...``, ``&password=...``).

``REDACTED`` replaces the secret. A redacted ``status.token`` keeps a recorded config loadable
(``vgripd replay -c JOB/config.toml``), but a daemon refuses to serve with it (docs/web.md).
"""

from __future__ import annotations

import re
from typing import Any

REDACTED = "<redacted>"

_SECRET_KEY = re.compile(
    r"token|passw(or)?d|passphrase|secret|credential|(api|private|access)[_\-.]?key",
    re.IGNORECASE)
# scheme://user[:password]@ : from "//" to the last "@" before the path (a password may hold "@").
_URL_USERINFO = re.compile(r"(?P<scheme>\b[a-z][a-z0-9+.\-]*://)(?P<userinfo>[^/?#\s]+)@",
                           re.IGNORECASE)
_QUERY_SECRET = re.compile(
    r"(?P<name>[?&;](?:[a-z0-9_\-.]*(?:token|passw(?:or)?d|secret|credential|api_?key)"
    r"[a-z0-9_\-.]*|key|[a-z0-9\-.]*_key)=)(?P<value>[^&;#\s]*)", re.IGNORECASE)


def is_secret_key(key: object) -> bool:
    """Whether a mapping key names a secret (its value is then never shown)."""
    return bool(_SECRET_KEY.search(str(key)))


def redact_text(text: str) -> str:
    """``text`` with URL credentials and secret query parameters replaced by ``REDACTED``."""
    if "@" in text:
        text = _URL_USERINFO.sub(lambda m: f"{m['scheme']}{REDACTED}@", text)
    if "=" in text:
        text = _QUERY_SECRET.sub(lambda m: f"{m['name']}{REDACTED}", text)
    return text


def redact(data: Any) -> Any:
    """JSON-like ``data`` (dicts, lists, tuples, strings, numbers) with every secret replaced by
    ``REDACTED``: values of keys that name a secret, and credentials in any string."""
    if isinstance(data, dict):
        return {k: (REDACTED if v is not None and is_secret_key(k) else redact(v))
                for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [redact(v) for v in data]
    if isinstance(data, str):
        return redact_text(data)
    return data
