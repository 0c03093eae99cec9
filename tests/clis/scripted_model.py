"""A scripted model endpoint for the real agent CLIs: no model, a fixed script of tool calls.

It speaks the wire APIs the CLIs use, streaming as they ask:
  POST .../v1/messages          Anthropic Messages (SSE when "stream": true)   — Claude Code
  POST .../v1/responses         OpenAI Responses (SSE when "stream": true)    — Codex
  POST .../v1/chat/completions  OpenAI Chat Completions (SSE when streaming)  — OpenAI-compatible harnesses
Every answer depends only on the request: the number of script tool calls already in the conversation picks
the next step of the script (`--script robot`, the default: start_episode, two osc_sequence calls, finish_episode,
then a final text answer; `--script perception`: start_episode, then the CLI's own shell tool running
tests/clis/perception_program.py — Appendix F's back-projection with numpy, scipy, Pillow and OpenCV —, then an
osc_sequence whose action is read from that command's output as the model saw it, finish_episode, a text), and
the tool is called by whatever name the CLI offered for it (e.g. `mcp__libero__start_episode`, or `start_episode`
in Codex's `mcp__libero` namespace). A CLI that keeps MCP tools behind a search tool first gets the search. A
request that offers none of the episode's tools (a CLI's side request) gets a short text answer. Each reply reports fixed
token usage, and one JSON line per request is appended to --log (path, whether the API key matched, the tool
names offered, the step, what was answered, the usage reported), never the key itself.

Usage: SCRIPTED_MODEL_API_KEY=KEY scripted_model.py --log FILE [--script robot|perception]   (prints {"port": N} on stdout, serves until
killed; the key comes from the environment so that it is on no command line)
"""
import argparse
import json
import os
import re
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

SCRIPT = [
    ("start_episode", {}),
    ("osc_sequence", {"actions": [[0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0], [0.0, 0.0, -0.5, 0.0, 0.0, 0.0, -1.0]]}),
    ("osc_sequence", {"actions": [[0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]]}),
    ("finish_episode", {}),
]
SCRIPT_TOOLS = ["start_episode", "osc_sequence", "finish_episode"]
# The shell tools of the CLIs: Codex's unified exec, Claude Code's Bash, Qwen Code's, Kimi Code's.
SHELL_TOOLS = ["exec_command", "Bash", "run_shell_command", "Shell", "shell"]
SHELL = "<shell>"
PROGRAM = open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "perception_program.py")).read()
PERCEPTION_COMMAND = "python3 - <<'PY'\n" + PROGRAM + "PY"
MARKER = re.compile(r"LIBERO_PERCEPTION action=([-0-9.,e]+)")
PERCEPTION = [
    ("start_episode", {}),
    (SHELL, PERCEPTION_COMMAND),
    ("osc_sequence", "from the command's output"),
    ("finish_episode", {}),
]
SCRIPTS = {"robot": SCRIPT, "perception": PERCEPTION}
FINAL_TEXT = "The episode is finished."
# Usage reported by every reply (per request): input, of which cached, and output tokens.
INPUT_TOKENS, CACHED_TOKENS, OUTPUT_TOKENS = 1200, 400, 30

LOCK = threading.Lock()


def tools_offered(body: dict) -> list:
    """(namespace, name) of every tool the request offers; Codex groups an MCP server's tools in a namespace."""
    out = []
    for t in body.get("tools") or []:
        if not isinstance(t, dict):
            continue
        if t.get("type") == "namespace":
            out += [(t.get("name"), f.get("name")) for f in t.get("tools") or [] if isinstance(f, dict)]
            continue
        name = t.get("name") or (t.get("function") or {}).get("name")
        if name:
            out.append((None, name))
    return out


def display(tool) -> str:
    namespace, name = tool
    return f"{namespace}__{name}" if namespace else name


def offered(tools: list, wanted: str):
    """The CLI's (namespace, name) for one of the episode's tools: exact, or prefixed like mcp__libero__<tool>."""
    for tool in tools:
        if tool[1] == wanted or tool[1].endswith("__" + wanted):
            return tool
    return None


def shell_offered(tools: list):
    """The CLI's shell tool, if it offers one."""
    for wanted in SHELL_TOOLS:
        for tool in tools:
            if tool[1] == wanted:
                return tool
    return None


def shell_arguments(body: dict, tool, command: str) -> dict:
    """The shell call's arguments under the CLI's own parameter names (`cmd` for Codex, `command` for the rest;
    an array-typed command is an argv)."""
    for t in body.get("tools") or []:
        if not isinstance(t, dict) or (t.get("name") or (t.get("function") or {}).get("name")) != tool[1]:
            continue
        schema = t.get("parameters") or t.get("input_schema") or (t.get("function") or {}).get("parameters") or {}
        props = schema.get("properties") or {}
        if "cmd" in props:
            return {"cmd": command}
        if (props.get("command") or {}).get("type") == "array":
            return {"command": ["bash", "-c", command]}
    return {"command": command, "description": "Back-project the head depth into the robot base frame"}


def strings_in(v):
    """Every string inside a JSON value, and inside strings that are themselves JSON."""
    if isinstance(v, str):
        yield v
        if v[:1] in "{[":
            try:
                yield from strings_in(json.loads(v))
            except ValueError:
                pass
    elif isinstance(v, dict):
        for x in v.values():
            yield from strings_in(x)
    elif isinstance(v, list):
        for x in v:
            yield from strings_in(x)


def perceived_action(body: dict):
    """The action the perception program printed, as the conversation the CLI sent carries it (the last one)."""
    found = [m for s in strings_in(body.get("messages") or body.get("input") or []) for m in MARKER.findall(s)]
    if not found:
        return None
    values = [float(x) for x in found[-1].split(",") if x]
    return values if len(values) == 7 else None


def calls_made(body: dict) -> list:
    """The names of the tool calls already in the conversation (Anthropic, Responses or Chat Completions)."""
    names = []
    for m in body.get("messages") or []:
        for call in m.get("tool_calls") or []:
            names.append((call.get("function") or {}).get("name", ""))
        content = m.get("content")
        if isinstance(content, list):
            names += [b.get("name", "") for b in content if isinstance(b, dict) and b.get("type") == "tool_use"]
    items = body.get("input")
    for item in items if isinstance(items, list) else []:
        if isinstance(item, dict) and item.get("type") == "function_call":
            names.append(item.get("name", ""))
    return names


def next_step(body: dict, script: list):
    """((namespace, name) as offered, arguments, step) or (None, text, step). A CLI that keeps MCP tools behind a
    search tool (Qwen Code's `tool_search`) gets that search first, as a model would do."""
    tools = tools_offered(body)
    made = calls_made(body)
    step = sum(1 for name in made if any(name == t or name.endswith("__" + t) for t in SCRIPT_TOOLS)
               or name in SHELL_TOOLS)
    if not any(offered(tools, t) for t in SCRIPT_TOOLS):
        search = offered(tools, "tool_search")
        if search and step == 0 and not any(n.endswith("tool_search") for n in made):
            return search, {"query": "select:" + ",".join(f"mcp__libero__{t}" for t in SCRIPT_TOOLS)}, "search"
        return None, "ok", None
    if step < len(script):
        wanted, args = script[step]
        if wanted == SHELL:
            shell = shell_offered(tools)
            if shell is None:
                return None, "this CLI offers no shell tool", step
            return shell, shell_arguments(body, shell, args), step
        if isinstance(args, str):
            action = perceived_action(body)
            if action is None:
                return None, "the perception program's output did not reach me", step
            return offered(tools, wanted), {"actions": [action, action]}, step
        return offered(tools, wanted), args, step
    return None, FINAL_TEXT, step


def sse(events: list) -> bytes:
    out = []
    for name, data in events:
        if name:
            out.append(f"event: {name}\n")
        out.append(f"data: {data if isinstance(data, str) else json.dumps(data)}\n\n")
    return "".join(out).encode()


def anthropic(body: dict, tool, payload, n: int):
    usage = {"input_tokens": INPUT_TOKENS - CACHED_TOKENS, "cache_creation_input_tokens": 0,
             "cache_read_input_tokens": CACHED_TOKENS, "output_tokens": OUTPUT_TOKENS}
    if tool:
        block = {"type": "tool_use", "id": f"toolu_{n:04d}", "name": display(tool), "input": payload}
        stop = "tool_use"
    else:
        block = {"type": "text", "text": payload}
        stop = "end_turn"
    message = {"id": f"msg_{n:04d}", "type": "message", "role": "assistant", "model": body.get("model", "scripted"),
               "content": [block], "stop_reason": stop, "stop_sequence": None, "usage": usage}
    if not body.get("stream"):
        return "application/json", json.dumps(message).encode(), usage
    start = dict(message, content=[], stop_reason=None, usage=dict(usage, output_tokens=1))
    if tool:
        events = [("content_block_start", {"type": "content_block_start", "index": 0,
                                           "content_block": dict(block, input={})}),
                  ("content_block_delta", {"type": "content_block_delta", "index": 0,
                                           "delta": {"type": "input_json_delta", "partial_json": json.dumps(payload)}})]
    else:
        events = [("content_block_start", {"type": "content_block_start", "index": 0,
                                           "content_block": {"type": "text", "text": ""}}),
                  ("content_block_delta", {"type": "content_block_delta", "index": 0,
                                           "delta": {"type": "text_delta", "text": payload}})]
    events = [("message_start", {"type": "message_start", "message": start})] + events + [
        ("content_block_stop", {"type": "content_block_stop", "index": 0}),
        ("message_delta", {"type": "message_delta", "delta": {"stop_reason": stop, "stop_sequence": None},
                           "usage": {"output_tokens": OUTPUT_TOKENS}}),
        ("message_stop", {"type": "message_stop"}),
    ]
    return "text/event-stream", sse(events), usage


def responses(body: dict, tool, payload, n: int):
    usage = {"input_tokens": INPUT_TOKENS, "input_tokens_details": {"cached_tokens": CACHED_TOKENS},
             "output_tokens": OUTPUT_TOKENS, "output_tokens_details": {"reasoning_tokens": 0},
             "total_tokens": INPUT_TOKENS + OUTPUT_TOKENS}
    if tool:
        item = {"type": "function_call", "id": f"fc_{n:04d}", "call_id": f"call_{n:04d}", "name": tool[1],
                "arguments": json.dumps(payload), "status": "completed"}
        if tool[0]:
            item["namespace"] = tool[0]
    else:
        item = {"type": "message", "id": f"msg_{n:04d}", "role": "assistant", "status": "completed",
                "content": [{"type": "output_text", "text": payload, "annotations": []}]}
    response = {"id": f"resp_{n:04d}", "object": "response", "status": "completed", "model": body.get("model"),
                "output": [item], "usage": usage}
    if not body.get("stream"):
        return "application/json", json.dumps(response).encode(), usage
    events = [("response.created", {"type": "response.created", "response": dict(response, status="in_progress",
                                                                                 output=[], usage=None)}),
              ("response.output_item.added", {"type": "response.output_item.added", "output_index": 0,
                                               "item": dict(item, status="in_progress")})]
    if not tool:
        events.append(("response.output_text.delta", {"type": "response.output_text.delta", "item_id": item["id"],
                                                      "output_index": 0, "content_index": 0, "delta": payload}))
    events += [("response.output_item.done", {"type": "response.output_item.done", "output_index": 0, "item": item}),
               ("response.completed", {"type": "response.completed", "response": response})]
    return "text/event-stream", sse(events), usage


def chat(body: dict, tool, payload, n: int):
    usage = {"prompt_tokens": INPUT_TOKENS, "completion_tokens": OUTPUT_TOKENS,
             "total_tokens": INPUT_TOKENS + OUTPUT_TOKENS, "prompt_tokens_details": {"cached_tokens": CACHED_TOKENS}}
    if tool:
        message = {"role": "assistant", "content": None, "tool_calls": [
            {"index": 0, "id": f"call_{n:04d}", "type": "function",
             "function": {"name": display(tool), "arguments": json.dumps(payload)}}]}
        finish = "tool_calls"
    else:
        message = {"role": "assistant", "content": payload}
        finish = "stop"
    base = {"id": f"chatcmpl-{n:04d}", "created": 0, "model": body.get("model")}
    if not body.get("stream"):
        reply = dict(base, object="chat.completion", usage=usage,
                     choices=[{"index": 0, "message": message, "finish_reason": finish}])
        return "application/json", json.dumps(reply).encode(), usage
    chunk = dict(base, object="chat.completion.chunk")
    events = [(None, dict(chunk, choices=[{"index": 0, "delta": message, "finish_reason": None}])),
              (None, dict(chunk, choices=[{"index": 0, "delta": {}, "finish_reason": finish}])),
              (None, dict(chunk, choices=[], usage=usage)),
              (None, "[DONE]")]
    return "text/event-stream", sse(events), usage


class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    counter = 0
    dumped = 0

    def log_message(self, *args):
        pass

    def reply(self, status: int, ctype: str, data: bytes):
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-cache")
        self.end_headers()
        self.wfile.write(data)

    def record(self, entry: dict):
        with LOCK:
            with open(self.server.log_path, "a") as f:
                f.write(json.dumps(entry) + "\n")

    def do_GET(self):
        # Codex first tries the Responses API over a WebSocket: 426 tells it to use plain HTTPS streaming at once.
        upgrade = self.headers.get("Upgrade", "").lower() == "websocket"
        self.record({"method": "GET", "path": self.path, "websocket": upgrade})
        if upgrade:
            self.reply(426, "application/json", b'{"error": {"message": "use HTTP streaming"}}')
        else:
            self.reply(404, "application/json", b'{"error": {"type": "not_found", "message": "scripted endpoint"}}')

    def do_POST(self):
        length = int(self.headers.get("Content-Length") or 0)
        raw = self.rfile.read(length)
        key = self.server.api_key
        auth_ok = self.headers.get("x-api-key") == key or self.headers.get("Authorization") == f"Bearer {key}"
        try:
            body = json.loads(raw or b"{}")
        except ValueError:
            self.record({"method": "POST", "path": self.path, "error": "body is not JSON",
                         "content_encoding": self.headers.get("Content-Encoding")})
            self.reply(400, "application/json", b'{"error": {"message": "body is not JSON"}}')
            return
        if self.server.dump:
            with LOCK:
                Handler.dumped += 1
                with open(os.path.join(self.server.dump, f"request_{Handler.dumped:03d}.json"), "wb") as f:
                    f.write(raw)
        path = self.path.split("?")[0]
        api = next((f for suffix, f in (("/messages", anthropic), ("/responses", responses),
                                        ("/chat/completions", chat)) if path.endswith(suffix)), None)
        if api is None or not auth_ok:
            self.record({"method": "POST", "path": self.path, "auth_ok": auth_ok, "refused": True})
            self.reply(404 if api is None else 401, "application/json", b'{"error": {"message": "refused"}}')
            return
        with LOCK:
            Handler.counter += 1
            n = Handler.counter
        tool, payload, step = next_step(body, SCRIPTS[self.server.script])
        ctype, data, usage = api(body, tool, payload, n)
        self.record({"method": "POST", "path": self.path, "auth_ok": auth_ok, "stream": bool(body.get("stream")),
                     "model": body.get("model"), "tools": [display(t) for t in tools_offered(body)],
                     "step": step, "answer": display(tool) if tool else "text", "usage": usage,
                     "arguments": payload if tool else None, "text": None if tool else payload})
        self.reply(200, ctype, data)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--log", required=True)
    ap.add_argument("--script", choices=sorted(SCRIPTS), default="robot")
    ap.add_argument("--dump", help="also write every request body into this directory (for debugging)")
    args = ap.parse_args()
    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.log_path = args.log
    server.dump = args.dump
    server.script = args.script
    server.api_key = os.environ["SCRIPTED_MODEL_API_KEY"]
    print(json.dumps({"port": server.server_address[1]}), flush=True)
    server.serve_forever()


if __name__ == "__main__":
    sys.exit(main())
