"""Drives one prepared episode over MCP (official Python SDK) with a scripted action sequence: start, a few
osc_sequence calls (golden.py's sinusoid, so the arm visibly moves), pauses between them so a browser watching
the live page sees each call arrive, then finish. Prints one JSON report line."""
import argparse
import asyncio
import json
import math
import sys

from mcp import Client
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client


def sinusoid(k):
    return [0.6 * math.sin(k / 5), 0.5 * math.cos(k / 7), -0.4 + 0.3 * math.sin(k / 11), 0.3 * math.sin(k / 9),
            0.2 * math.cos(k / 6), -0.25 * math.sin(k / 4), 1.0 if (k // 15) % 2 == 0 else -1.0]


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--token", required=True)
    ap.add_argument("--calls", type=int, default=4)
    ap.add_argument("--actions", type=int, default=20)
    ap.add_argument("--pause-s", type=float, default=1.0)
    args = ap.parse_args()
    server = streamable_http_client(args.url, http_client=create_mcp_http_client(
        headers={"Authorization": f"Bearer {args.token}"}))
    report = {"calls": []}
    async with Client(server) as c:
        r = (await c.call_tool("start_episode", {})).structured_content
        report["calls"].append({"tool": "start_episode", "ok": r.get("ok")})
        await asyncio.sleep(args.pause_s)
        k = 0
        for _ in range(args.calls):
            actions = [sinusoid(k + i) for i in range(args.actions)]
            k += args.actions
            r = (await c.call_tool("osc_sequence", {"actions": actions})).structured_content
            report["calls"].append({"tool": "osc_sequence", "ok": r.get("ok"), "observation_id": r.get("observation_id")})
            await asyncio.sleep(args.pause_s)
        # One rejected call, so the timeline shows an error too.
        r = (await c.call_tool("osc_sequence", {"actions": [[2, 0, 0, 0, 0, 0, 0]]})).structured_content
        report["calls"].append({"tool": "osc_sequence", "ok": r.get("ok"), "error": r.get("error")})
        r = (await c.call_tool("finish_episode", {})).structured_content
        report["calls"].append({"tool": "finish_episode", "ok": r.get("ok")})
        report["finish"] = r
    report["ok"] = all(c["ok"] for c in report["calls"] if "error" not in c)
    print(json.dumps(report))
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
