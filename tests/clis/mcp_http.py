"""The MCP client of the test agents (tests/clis/transcript_agent.py, quitting_agent.py): Python's standard library
speaking streamable HTTP to the episode's endpoint named in the workspace's `.libero/mcp.json`. The tests inline it
before the agent's own script into the `--agent-cmd` heredoc (the sandbox shows the workspace, not the repository).

Nothing here may contain a brace-wrapped runner placeholder name: the runner substitutes those in the agent command.
"""
import json
import os
import urllib.request

WS = os.environ["LIBERO_AGENT_WORKSPACE"]
SERVER = next(iter(json.load(open(os.path.join(WS, ".libero", "mcp.json")))["mcpServers"].values()))
# Loopback is reached directly: the proxy variables point at the gateway, which refuses the MCP endpoint.
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))
HEADERS = {"Content-Type": "application/json", "Accept": "application/json, text/event-stream",
           "Authorization": SERVER["headers"]["Authorization"]}
_ids = iter(range(1, 100000))


def rpc(method, params, notify=False):
    body = {"jsonrpc": "2.0", "method": method, "params": params}
    if not notify:
        body["id"] = next(_ids)
    req = urllib.request.Request(SERVER["url"], data=json.dumps(body).encode(), headers=HEADERS, method="POST")
    with OPENER.open(req, timeout=600) as r:
        session = r.headers.get("Mcp-Session-Id")
        raw = r.read().decode()
    if session:
        HEADERS["Mcp-Session-Id"] = session
    if notify:
        return None
    messages = [json.loads(raw)] if raw.lstrip().startswith("{") else [
        json.loads(line[5:]) for line in raw.splitlines() if line.startswith("data:") and line[5:].strip()]
    return next(m for m in messages if m.get("id") == body["id"])


def initialize(name):
    init = rpc("initialize", {"protocolVersion": "2025-06-18", "capabilities": {},
                              "clientInfo": {"name": name, "version": "1"}})
    HEADERS["Mcp-Protocol-Version"] = init["result"]["protocolVersion"]
    rpc("notifications/initialized", {}, notify=True)


def call(tool, arguments):
    payload = rpc("tools/call", {"name": tool, "arguments": arguments})["result"]["structuredContent"]
    assert payload["ok"], payload
    return payload
