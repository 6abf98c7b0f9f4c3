"""``vgripd calibrate handeye walk --running [URL]``: the running daemon walks the plan; this
command starts it over the web API (``POST /api/handeye/walk/start``, with the token) and prints
each target as the daemon records it (``GET /api/handeye``), until the walk ends. Ctrl-C stops
the walk (``POST /api/handeye/walk/stop?by=command``; the record stays, run again to resume)
and prints the targets recorded since the last poll from the stop's answer."""

from __future__ import annotations

import argparse
import json
import os
import time
import urllib.error
import urllib.request
from typing import Any

from vgripd.cli.status import TOKEN_ENV
from vgripd.config import load_config
from vgripd.errors import CalibrationError

DEFAULT_BASE = "http://127.0.0.1:8730"
POLL_S = 0.5
TIMEOUT_S = 10.0


def _call(base: str, path: str, token: str | None, body: Any = None) -> tuple[int, Any]:
    data = None if body is None else json.dumps(body).encode()
    headers = {"Content-Type": "application/json"} if data is not None else {}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    request = urllib.request.Request(base + path, data=data, headers=headers,
                                     method="GET" if data is None else "POST")
    try:
        with urllib.request.urlopen(request, timeout=TIMEOUT_S) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        text = err.read().decode(errors="replace")
        try:
            return err.code, json.loads(text)
        except ValueError:
            return err.code, {"refused": text.strip()}
    except OSError as err:
        raise CalibrationError(f"{base}: the running daemon does not answer: {err}") from None


def _where(args: argparse.Namespace) -> tuple[str, str | None]:
    token = os.environ.get(TOKEN_ENV) or None
    base = args.running or DEFAULT_BASE
    if args.config:
        st = load_config(args.config).status
        if not args.running:
            host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(st.host, st.host)
            base = f"http://{'[' + host + ']' if ':' in host else host}:{st.port}"
        token = token or st.token
    return base.rstrip("/"), token


def _print_new(walk: dict[str, Any], shown: set[int]) -> None:
    """Print the targets of ``walk`` (the daemon's snapshot) not in ``shown``, and add them."""
    for r in walk.get("records", []):
        if r["target"] not in shown:
            shown.add(r["target"])
            extra = (f", {r['corners']} corners" if r["status"] == "seen"
                     else f": {r['reason']}" if r["reason"] else "")
            print(f"  target {r['target']}: {r['status']}{extra}", flush=True)


def run_running(args: argparse.Namespace) -> int:
    if args.plan is None:
        raise CalibrationError("calibrate handeye walk --running: give --plan PLAN (a file in "
                               "the daemon's config folder)")
    base, token = _where(args)
    code, out = _call(base, "/api/handeye/walk/start", token,
                      {"plan": args.plan, "link": args.link})
    if code != 200:
        raise CalibrationError(f"the daemon refused the walk ({code}): "
                               f"{out.get('refused') or out}")
    print(f"walk {out.get('record')}: {out.get('targets')} targets, from target "
          f"{out.get('index')}, served by the daemon on link {out.get('link')}")
    shown = {r["target"] for r in out.get("records", [])}
    try:
        while True:
            _, data = _call(base, "/api/handeye", token)
            walk = data["walk"]
            _print_new(walk, shown)
            if walk["state"] != "walking":
                break
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        _, walk = _call(base, "/api/handeye/walk/stop?by=command", token, {})
        _print_new(walk, shown)  # those recorded since the last poll
    print(f"walk {walk['state']}: seen {walk.get('seen')}, not seen {walk.get('not_seen')}, "
          f"unreachable {walk.get('unreachable')}"
          + (f" ({walk['message']})" if walk.get("message") else ""))
    if walk["state"] == "complete":
        print(f"solve and accept on {base}/handeye/walk, or: vgripd calibrate handeye "
              f"--samples {walk.get('record')} --intrinsics CONFIG -o handeye.toml")
    return 0 if walk["state"] == "complete" else 1
