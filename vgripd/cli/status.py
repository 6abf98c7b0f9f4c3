"""Show a running daemon's status: state, last job, links, counters, refusals, cycle times.

Reads the web view's ``GET /api/status`` (docs/web.md); the page itself is at ``/``. Where the
view needs the token (a non-loopback bind), it is sent as ``Authorization: Bearer``, taken from
``--token-file``, else ``$VGRIPD_TOKEN``, else the config given with ``-c``."""

from __future__ import annotations

import argparse
import json
import os
import sys
import urllib.error
import urllib.request
from typing import Any

from vgripd.config import load_config

DEFAULT_URL = "http://127.0.0.1:8730/api/status"
TOKEN_ENV = "VGRIPD_TOKEN"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--url", help=f"status endpoint (default {DEFAULT_URL})")
    where.add_argument("-c", "--config", help="take host and port from this config's [status]")
    parser.add_argument("--json", action="store_true", help="print the raw JSON")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds (default 3)")
    parser.add_argument("--token-file", metavar="FILE",
                        help=f"send the token in FILE (default: ${TOKEN_ENV}, else the -c "
                             f"config's status.token)")


def _age(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))


def format_status(s: dict[str, Any]) -> str:
    """The status JSON as a few readable lines."""
    cam = s["camera"]
    lines = [
        f"vgripd pid {s['pid']}: {s['run_state']}, job state {s['state']}, "
        f"up {_age(s['uptime_s'])}",
        f"camera {cam['type']} ({'open' if cam['open'] else 'NOT OPEN'})"
        + ("" if s["calibrated"] else ", NOT CALIBRATED"),
    ]
    rec = s.get("recipe")
    if rec:
        names = ", ".join(f"{r['number']} {r['name']}" + (" NOT CALIBRATED" if r["problem"]
                                                            else "") for r in rec["recipes"])
        active = ("none yet" if rec["active"] is None
                  else f"{rec['active']} {rec['active_name']}")
        lines.append(f"recipe {active} (configured: {names})")
    if s["job"]:
        j = s["job"]
        lines.append(f"running job {j['id']} (seq {j['seq']} from {j['link']}, "
                     f"{_age(j['age_s'])})")
    lj = s["last_job"]
    if lj:
        msg = f": {lj['message']}" if lj["message"] else ""
        published = lj.get("published", lj["status"])
        told = ("" if published == lj["status"] else
                ", NOT DELIVERED" if published is None else f", published as {published}")
        lines.append(f"last job {lj['id']}: {lj['status']} ({lj['status_code']}){msg}{told}, "
                     f"cycle {lj['cycle_ms']:.1f} ms, {_age(lj['age_s'])} ago")
    else:
        lines.append("no job yet")
    pl = s.get("pick_list")
    if pl and pl["instances"]:  # a job of several objects (a single object is a list of one)
        where = (f"used up ({pl['count']} handed out)" if pl["index"] > pl["count"]
                 else f"{pl['index']} of {pl['count']} shown")
        lines.append(f"pick list of job {pl['job_id']} ({pl['link']}): {where}, "
                     f"{pl['instances']} instances found; NEXT answers "
                     f"{_counts(s.get('next_answers') or {}) or 'none'}")
    lines.append("links:")
    for link in s["links"]:
        extra = f", last error: {link['last_error']}" if link["last_error"] else ""
        if link.get("refusals"):
            extra = f", refused {_counts(link['refusals'])}{extra}"
        lines.append(f"  {link['name']}: {link['state']}"
                     f"{', ' + link['peer'] if link['peer'] else ''}, "
                     f"{link['peers']} peers, reconnects {link['reconnects']}{extra}")
    if not s["links"]:
        lines.append("  none")
    lines.append(f"counters: {_counts(s['counters']) or 'none'}")
    if s.get("refusals"):
        lines.append(f"  of which refusals: {_counts(s['refusals'])}")
    if s.get("undelivered"):
        lines.append(f"not delivered (the link's publish failed): {_counts(s['undelivered'])}")
    cyc = s["cycle_ms"]
    if cyc.get("window"):
        lines.append(f"cycle time over the last {cyc['window']} jobs: p50 {cyc['p50']:.1f} ms, "
                     f"p95 {cyc['p95']:.1f} ms, p99 {cyc['p99']:.1f} ms, "
                     f"max {cyc['max']:.1f} ms")
    rc = s.get("recalibrate")
    if rc and rc["jobs"]:
        head = "RECALIBRATE" if rc["warning"] else "epipolar"
        since = f", for {_age(rc['since_s'])}" if rc["warning"] else ""
        lines.append(
            f"{head}: {rc['above']} of the last {rc['jobs']} stereo jobs above "
            f"{rc['threshold_px']} px (share {rc['share']:.2f}, warning above "
            f"{rc['share_limit']:.2f} once {rc['min_jobs']} jobs are in){since}"
            + ("; the stereo rig may have moved: recalibrate" if rc["warning"] else ""))
    walk = s.get("walk")
    if walk and walk["state"] != "idle":
        lines.append(f"hand-eye walk {walk['state']} on {walk['link']} ({walk.get('plan')}): "
                     f"{len(walk.get('records', []))} of {walk.get('targets')} targets, seen "
                     f"{walk.get('seen')}, not seen {walk.get('not_seen')}, unreachable "
                     f"{walk.get('unreachable')}")
    if s["record"]:
        lines.append(f"recording to {s['record']['folder']} "
                     f"({s['record']['bytes'] / 1e6:.1f} MB)")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    url = args.url or DEFAULT_URL
    token = os.environ.get(TOKEN_ENV) or None
    if getattr(args, "token_file", None):
        try:
            with open(args.token_file, encoding="utf-8") as f:
                token = f.read().strip()
        except OSError as err:
            print(f"vgripd status: --token-file {args.token_file}: {err.strerror}",
                  file=sys.stderr)
            return 1
    if args.config:
        st = load_config(args.config).status
        host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(st.host, st.host)  # bound to all
        url = f"http://{'[' + host + ']' if ':' in host else host}:{st.port}/api/status"
        token = token or st.token
    request = urllib.request.Request(url, headers={} if not token else {
        "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=args.timeout) as resp:
            data = json.loads(resp.read())
    except urllib.error.HTTPError as err:
        hint = (f" (the view needs the token: --token-file, ${TOKEN_ENV} or -c CONFIG)"
                if err.code in (401, 403) else "")
        print(f"vgripd status: {url} answered {err.code} {err.reason}{hint}", file=sys.stderr)
        return 1
    except (urllib.error.URLError, OSError, ValueError) as err:
        print(f"vgripd status: cannot read {url}: {err} (is the daemon running?)",
              file=sys.stderr)
        return 1
    print(json.dumps(data, indent=2) if args.json else format_status(data))
    return 0
