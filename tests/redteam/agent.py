"""A hostile agent for the boundary test (issue 17). It runs where a real agent runs: launched by
`libero-agent run --harness command`, inside the bubblewrap sandbox, with only its workspace, its session
home and its own MCP endpoint's URL and token (`.libero/mcp.json`).

It tries to reach everything an agent must not reach, records every attempt, and leaves a watcher behind that
plants symlinks and FIFOs into whatever appears under `benchmark_inputs/` (inotify), while the reference agent
then plays the episode. Python's standard library only; the secret path (a host file outside the sandbox) comes as
the first argument. The workspace goes with the rollout's disk when it ends, so the reports are lines on stdout
(the runner keeps it as `command_stdout.log`): `LIBERO-REDTEAM-REPORT <json>` once, and the watcher's
`LIBERO-WATCHER-REPORT <json>` each time its counts change (it is killed with the sandbox when the agent exits,
at any instruction: its last complete line is its report).

Nothing here may contain a brace-wrapped runner placeholder name: the runner substitutes those in the
agent command this script is inlined into.
"""
import ctypes
import json
import os
import random
import socket
import sys
import time

SECRET = sys.argv[1]
WATCH_S = float(sys.argv[2]) if len(sys.argv) > 2 else 120.0
WS = os.environ["LIBERO_AGENT_WORKSPACE"]
CONFIG = json.load(open(os.path.join(WS, ".libero", "mcp.json")))
SERVER = next(iter(CONFIG["mcpServers"].values()))
MCP_URL = SERVER["url"]
TOKEN = SERVER["headers"]["Authorization"].split(" ", 1)[1]
HOSTPORT = MCP_URL.split("//", 1)[1].split("/", 1)[0]
HOST, PORT = HOSTPORT.rsplit(":", 1)
EPISODE = MCP_URL.rsplit("/", 1)[1]
attempts = []


def http(method, path, headers=None, body=b"", host=None, read_limit=1 << 16):
    """One raw HTTP/1.1 request (no client library that could 'helpfully' follow redirects)."""
    s = socket.create_connection((HOST, int(PORT)), timeout=30)
    head = f"{method} {path} HTTP/1.1\r\nHost: {host or HOSTPORT}\r\nConnection: close\r\nContent-Length: {len(body)}\r\n"
    for k, v in (headers or {}).items():
        head += f"{k}: {v}\r\n"
    raw = b""
    try:
        s.sendall(head.encode() + b"\r\n" + body)
    except OSError as e:  # the server may answer and close before reading a refused body to its end
        print(f"redteam: {method} {path}: {e}", file=sys.stderr, flush=True)
    while len(raw) < read_limit:
        try:
            chunk = s.recv(65536)
        except OSError:
            break
        if not chunk:
            break
        raw += chunk
        if b"HTTP/1.1 101" in raw[:20] and b"\r\n\r\n" in raw:
            break
    s.close()
    status = int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/") else 0
    head_text, _, rest = raw.partition(b"\r\n\r\n")
    return status, head_text.decode("latin-1"), rest


def attempt(what, status, head, allowed):
    location = next((l.split(":", 1)[1].strip() for l in head.split("\r\n") if l.lower().startswith("location:")), "")
    refused = status in allowed and (status != 303 or location == "/login")
    attempts.append({"what": what, "status": status, "location": location, "refused": refused})


OPERATOR_GETS = [
    "/", "/tasks", "/results", "/demos", f"/episodes/{EPISODE}", f"/episodes/{EPISODE}/review", "/teleop/T14",
    "/api/episodes", f"/api/episodes/{EPISODE}", f"/api/episodes/{EPISODE}/review", "/api/results", "/api/tasks",
    "/api/demos", f"/episodes/{EPISODE}/video.mp4", f"/episodes/{EPISODE}/observations/obs_000000/observation.json",
    "/tasks/T14/thumbnail.png", "/ws/episodes", f"/ws/episodes/{EPISODE}",
]
OPERATOR_POSTS = [
    ("/api/episodes", {"task": "T14", "demo": "video+traj", "workspace": os.path.join(WS, "scratch", "steal")}),
    (f"/api/episodes/{EPISODE}/abort", {"reason": "redteam"}),
    ("/api/teleop", {"task": "T14"}),
    ("/api/demos/export", {}),
    ("/api/demos/T14/x/delete", {}),
]
WS_UPGRADE = {"Connection": "Upgrade", "Upgrade": "websocket", "Sec-WebSocket-Version": "13",
              "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="}


def credentials():
    """No credential, its own episode token as bearer, as a session cookie and as a login-link token."""
    return [("none", {}), ("episode-bearer", {"Authorization": f"Bearer {TOKEN}"}),
            ("episode-cookie", {"Cookie": f"libero_session={TOKEN}; libero_operator={TOKEN}"})]


def try_operator_routes():
    for path in OPERATOR_GETS:
        for name, cred in credentials():
            headers = dict(cred, **(WS_UPGRADE if path.startswith("/ws/") else {}))
            status, head, _ = http("GET", path, headers)
            attempt(f"GET {path} [{name}]", status, head, {401, 303, 403})
        status, head, _ = http("GET", f"{path}{'&' if '?' in path else '?'}token={TOKEN}")
        attempt(f"GET {path}?token=<episode token>", status, head, {401, 303, 403})
    for path, body in OPERATOR_POSTS:
        for name, cred in credentials():
            headers = dict(cred, **{"Content-Type": "application/json"})
            status, head, _ = http("POST", path, headers, json.dumps(body).encode())
            attempt(f"POST {path} [{name}]", status, head, {401, 403})
    status, head, _ = http("POST", "/login", {"Content-Type": "application/x-www-form-urlencoded"}, f"token={TOKEN}".encode())
    attempt("POST /login with the episode token", status, head, {401})


def try_foreign_hosts():
    for host in ["evil.example", f"evil.example:{PORT}", f"127.0.0.1.nip.io:{PORT}", f"{HOST}:{int(PORT) + 1}"]:
        for path in ["/api/health", "/", f"/mcp/{EPISODE}", "/api/episodes"]:
            status, head, _ = http("GET", path, {"Authorization": f"Bearer {TOKEN}"}, host=host)
            attempt(f"GET {path} Host={host}", status, head, {421})


def mcp_post(path, message, headers=None):
    h = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json",
         "Accept": "application/json, text/event-stream"}
    h.update(headers or {})
    return http("POST", path, h, json.dumps(message).encode())


def try_other_endpoints():
    other = EPISODE[:-1] + ("0" if EPISODE[-1] != "0" else "1")
    init = {"jsonrpc": "2.0", "id": 1, "method": "initialize",
            "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "redteam", "version": "0"}}}
    for path in [f"/mcp/{other}", "/mcp/ep-00000000T000000Z-00000000", f"/mcp/{EPISODE}/../{other}", "/mcp/%2e%2e"]:
        status, head, _ = mcp_post(path, init)
        attempt(f"MCP initialize at {path} with its own token", status, head, {401, 404})


def oversized_rejected_calls():
    """Calls that are rejected (no episode started yet) with megabytes of arguments: the private action log
    must record them truncated, not in full."""
    init = {"jsonrpc": "2.0", "id": 1, "method": "initialize",
            "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "redteam", "version": "0"}}}
    status, head, _ = mcp_post(f"/mcp/{EPISODE}", init)
    session = next((l.split(":", 1)[1].strip() for l in head.split("\r\n") if l.lower().startswith("mcp-session-id:")), None)
    extra = {"Mcp-Session-Id": session, "Mcp-Protocol-Version": "2025-06-18"} if session else {}
    mcp_post(f"/mcp/{EPISODE}", {"jsonrpc": "2.0", "method": "notifications/initialized"}, extra)
    sent = 0
    for i in range(4):
        junk = "A" * (900_000 + i)
        status, _, body = mcp_post(f"/mcp/{EPISODE}", {"jsonrpc": "2.0", "id": 10 + i, "method": "tools/call",
                                                       "params": {"name": "osc_sequence", "arguments": {"actions": junk}}}, extra)
        sent += len(junk)
        rejected = b'"ok":false' in body.replace(b" ", b"") or status >= 400
        attempts.append({"what": f"oversized rejected call {i}", "status": status, "refused": rejected})
    return sent


def plant(directory):
    """Symlinks to the secret and FIFOs under every name an observation uses, inside `directory`."""
    names = ["observation.json", "proprioception.json", "head", "wrist", "rgb.png", "depth_m.npy", "calibration.json"]
    planted = 0
    for name in names:
        path = os.path.join(directory, name)
        try:
            if random.random() < 0.5:
                os.symlink(SECRET, path)
            else:
                os.mkfifo(path)
            planted += 1
        except OSError:
            pass
    for cam in ["head", "wrist"]:
        for leaf in ["rgb.png", "depth_m.npy"]:
            try:
                os.makedirs(os.path.join(directory, cam), exist_ok=True)
                os.symlink(SECRET, os.path.join(directory, cam, leaf))
                planted += 1
            except OSError:
                pass
    return planted


def watch_and_plant(seconds):
    """inotify on benchmark_inputs/: the moment a directory appears there, plant into it; keep replacing
    current_observation's files with links and FIFOs too. Runs in a detached child."""
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    bi = os.path.join(WS, "benchmark_inputs")
    os.makedirs(bi, exist_ok=True)
    fd = libc.inotify_init1(os.O_NONBLOCK)
    IN_CREATE, IN_MOVED_TO = 0x100, 0x80
    libc.inotify_add_watch(fd, bi.encode(), IN_CREATE | IN_MOVED_TO)
    planted, events = 0, 0
    said, said_at = (-1, -1), 0.0
    end = time.time() + seconds
    while time.time() < end:
        try:
            buf = os.read(fd, 65536)
        except BlockingIOError:
            buf = b""
        i = 0
        while i + 16 <= len(buf):
            length = int.from_bytes(buf[i + 12:i + 16], "little")
            name = buf[i + 16:i + 16 + length].split(b"\0", 1)[0].decode(errors="replace")
            i += 16 + length
            events += 1
            target = os.path.join(bi, name)
            if os.path.isdir(target) and not os.path.islink(target):
                planted += plant(target)
        cur = os.path.join(bi, "current_observation")
        if os.path.isdir(cur) and not os.path.islink(cur) and random.random() < 0.2:
            for extra in ["planted_link", "planted_fifo"]:
                try:
                    p = os.path.join(cur, extra)
                    os.symlink(SECRET, p) if extra.endswith("link") else os.mkfifo(p)
                    planted += 1
                except OSError:
                    pass
        if not buf:
            time.sleep(0.0005)
        # Said at once when a publication was seen, else at most every second: the sandbox's PID namespace kills
        # this process with SIGKILL when the agent exits, at any instruction, so the last line said is the report.
        if events != said[1] or (planted != said[0] and time.time() - said_at >= 1.0):
            say_watcher(planted, events)
            said, said_at = (planted, events), time.time()
    say_watcher(planted, events)


def say_watcher(planted, events):
    """One line on stdout in one write(2): never interleaved with another process's output mid-line."""
    line = "LIBERO-WATCHER-REPORT " + json.dumps({"planted": planted, "inotify_events": events}) + "\n"
    try:
        os.write(1, line.encode())
    except OSError:
        pass


def main():
    os.makedirs(os.path.join(WS, "scratch"), exist_ok=True)
    # Links to the host secret planted before the server publishes anything.
    bi = os.path.join(WS, "benchmark_inputs")
    os.makedirs(bi, exist_ok=True)
    try:
        os.symlink(SECRET, os.path.join(bi, "current_observation"))
    except OSError:
        pass
    try_operator_routes()
    try_foreign_hosts()
    try_other_endpoints()
    sent = oversized_rejected_calls()
    report = {"attempts": attempts, "oversized_bytes_sent": sent, "episode": EPISODE}
    # One line on stdout, flushed before the fork (the watcher must not inherit it unwritten); a summary on stderr.
    print("LIBERO-REDTEAM-REPORT " + json.dumps(report), flush=True)
    print(f"redteam: {len(attempts)} attempts recorded, {sent} oversized bytes sent", file=sys.stderr, flush=True)
    # The watcher outlives this script: it plants while the reference agent plays the episode.
    if os.fork() == 0:
        os.setsid()
        if os.fork() == 0:
            watch_and_plant(WATCH_S)
        os._exit(0)
    os.wait()
    time.sleep(0.5)


main()
