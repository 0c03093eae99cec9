"""A red-team agent that tries to leave its sandbox (issue 30): run as `--harness command` by
server/app/tests/sandbox_escape.rs, inside the bubblewrap sandbox, before the reference agent plays the episode.

Every attempt is recorded with whether the boundary refused it; the report is printed as one line on stdout,
`LIBERO-ESCAPE-REPORT <json>` (the workspace goes with the rollout's disk when it ends; the runner keeps stdout as
`command_stdout.log`). Arguments: the path of the libero-agent binary, then a JSON object with the host's loopback
port of a decoy service (`decoy_port`), the pid of a host process (`host_pid`), the runner's uid (`runner_uid`), a
marker file name (`marker`) that must not appear in the host's /tmp, the model API's `host:port` (`model_api`), and
the rollout's caps (`caps`: `max_processes`, `memory_bytes`, `disk_bytes`; null where the runner runs agents
unconfined, and the attacks on the caps are skipped).

Nothing here may contain a brace-wrapped runner placeholder name: the runner substitutes those in the agent command
this script is inlined into.
"""
import ctypes
import errno
import json
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request

ARGS = json.loads(sys.argv[2])
ARGS["agent_exe"] = sys.argv[1]
libc = ctypes.CDLL(None, use_errno=True)
attempts = []


def record(name, refused, detail=""):
    attempts.append({"attack": name, "refused": bool(refused), "detail": str(detail)[:400]})


def syscall_refused(name, fn):
    """`fn` returns a libc result; refused when it is -1 (errno kept)."""
    ctypes.set_errno(0)
    rc = fn()
    err = ctypes.get_errno()
    record(name, rc == -1, f"rc={rc} errno={errno.errorcode.get(err, err)}")


def raises(name, fn):
    try:
        out = fn()
        record(name, False, f"succeeded: {out!r}")
    except Exception as e:  # noqa: BLE001 - any refusal counts
        record(name, True, repr(e))


# Who the agent is.
status = open("/proc/self/status").read()
fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
caps = {k: fields[k].strip() for k in ("CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb")}
record("holds a capability", all(int(v, 16) == 0 for v in caps.values()), caps)
record("may gain privileges by exec", fields["NoNewPrivs"].strip() == "1", fields["NoNewPrivs"])
record("is uid 0 outside the sandbox", os.getuid() != 0 or ARGS["runner_uid"] != 0, f"uid={os.getuid()}")

# Mounts: remount the read-only system and binaries, mount anything.
MS_RDONLY, MS_REMOUNT, MS_BIND = 1, 32, 4096
for target in ("/usr", "/etc", os.path.dirname(ARGS["agent_exe"])):
    syscall_refused(f"remount {target} read-write",
                    lambda t=target: libc.mount(None, t.encode(), None, MS_REMOUNT | MS_BIND, None))
os.makedirs("/tmp/m", exist_ok=True)
syscall_refused("mount a tmpfs", lambda: libc.mount(b"none", b"/tmp/m", b"tmpfs", 0, None))
raises("mount(8) -o remount,rw /usr", lambda: subprocess.run(["mount", "-o", "remount,rw", "/usr"], check=True, capture_output=True))

# Files that are not the agent's.
raises("write the libero-agent binary", lambda: open(ARGS["agent_exe"], "ab").write(b"x"))
raises("chmod the libero-agent binary", lambda: os.chmod(ARGS["agent_exe"], 0o777))
raises("chmod a system file", lambda: os.chmod("/etc/hostname" if os.path.exists("/etc/hostname") else "/etc/passwd", 0o666))
raises("write /usr", lambda: open("/usr/lib/libero-escape", "w").write("x"))
raises("read /etc/shadow", lambda: open("/etc/shadow").read())

# New namespaces (a way to regain capabilities).
CLONE_NEWUSER, CLONE_NEWNS, CLONE_NEWNET = 0x10000000, 0x20000, 0x40000000
syscall_refused("unshare a user namespace", lambda: libc.unshare(CLONE_NEWUSER))
syscall_refused("unshare a mount namespace", lambda: libc.unshare(CLONE_NEWNS))
syscall_refused("unshare a network namespace", lambda: libc.unshare(CLONE_NEWNET))
raises("unshare(1) -Ur", lambda: subprocess.run(["unshare", "-Ur", "true"], check=True, capture_output=True))

# Other processes: the host's are not there; signals and ptrace reach nothing.
PTRACE_ATTACH = 16
syscall_refused("ptrace a host process", lambda: libc.ptrace(PTRACE_ATTACH, ARGS["host_pid"], None, None))
raises("signal a host process", lambda: os.kill(ARGS["host_pid"], 0))
pids = [p for p in os.listdir("/proc") if p.isdigit()]
record("sees host processes", len(pids) < 20, f"{len(pids)} processes")

# Raw sockets.
raises("raw ICMP socket", lambda: socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP))
raises("packet socket", lambda: socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0))

# The network: the host's loopback services and every other host are not there.
def connect(host, port, family=socket.AF_INET):
    s = socket.socket(family, socket.SOCK_STREAM)
    s.settimeout(3)
    try:
        s.connect((host, port))
        return "connected"
    finally:
        s.close()

raises("connect to a host loopback service", lambda: connect("127.0.0.1", ARGS["decoy_port"]))
raises("connect to a host loopback service on ::1", lambda: connect("::1", ARGS["decoy_port"], socket.AF_INET6))
raises("connect to PostgreSQL on loopback", lambda: connect("127.0.0.1", 5432))
raises("connect to another host", lambda: connect("192.0.2.1", 80))
raises("connect to a public address", lambda: connect("1.1.1.1", 443))
ifaces = [l.split(":")[0].strip() for l in open("/proc/net/dev").read().splitlines()[2:]]
record("has an interface besides lo", ifaces == ["lo"], ifaces)

# The runner's proxy: only the allow-list.
proxy = os.environ.get("HTTPS_PROXY", "")
record("has the runner's proxy", proxy.startswith("http://127.0.0.1:"), proxy)


def connect_through_proxy(target):
    host, port = proxy[len("http://"):].rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=5)
    try:
        s.sendall(f"CONNECT {target} HTTP/1.1\r\nHost: {target}\r\n\r\n".encode())
        line = s.recv(200).split(b"\r\n", 1)[0].decode(errors="replace")
    finally:
        s.close()
    if " 200" in line:
        return line
    raise PermissionError(line)

def forward_through_proxy(url):
    """An absolute-form request sent to the proxy itself (no client's no_proxy rule in the way)."""
    host, port = proxy[len("http://"):].rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=5)
    try:
        authority = url.split("/")[2]
        s.sendall(f"GET {url} HTTP/1.1\r\nHost: {authority}\r\nConnection: close\r\n\r\n".encode())
        line = s.recv(200).split(b"\r\n", 1)[0].decode(errors="replace")
    finally:
        s.close()
    if " 403" in line or not line:
        raise PermissionError(line)
    return line

if proxy:
    raises("CONNECT to a host loopback service", lambda: connect_through_proxy(f"127.0.0.1:{ARGS['decoy_port']}"))
    raises("CONNECT to a host not on the allow-list", lambda: connect_through_proxy("example.com:443"))
    raises("forward-proxy GET to a host loopback service", lambda: forward_through_proxy(f"http://127.0.0.1:{ARGS['decoy_port']}/"))
    # The model API itself only through the gateway's base URL (its routes, metered): a tunnel would pass anything.
    if ARGS.get("model_api"):
        raises("CONNECT to the model API's own host", lambda: connect_through_proxy(ARGS["model_api"]))

# The kernel's less-guarded interfaces: refused by the seccomp allow-list whatever the kernel's own settings
# (raw syscall numbers of x86_64; skipped on other architectures).
if platform.machine() == "x86_64":
    SYS_ADD_KEY, SYS_KEYCTL, SYS_PERF_EVENT_OPEN, SYS_BPF, SYS_USERFAULTFD, SYS_IO_URING_SETUP = 248, 250, 298, 321, 323, 425
    KEY_SPEC_SESSION_KEYRING, KEY_SPEC_USER_KEYRING, KEYCTL_READ = -3, -4, 11
    for ring, spec in (("user", KEY_SPEC_USER_KEYRING), ("session", KEY_SPEC_SESSION_KEYRING)):
        syscall_refused(f"add_key into the {ring} keyring",
                        lambda s=spec: libc.syscall(SYS_ADD_KEY, b"user", b"libero-escape", b"x", ctypes.c_size_t(1), ctypes.c_long(s)))
        keybuf = ctypes.create_string_buffer(4096)
        syscall_refused(f"keyctl read of the {ring} keyring",
                        lambda s=spec: libc.syscall(SYS_KEYCTL, ctypes.c_long(KEYCTL_READ), ctypes.c_long(s), keybuf, ctypes.c_size_t(4096)))
    uring_params = ctypes.create_string_buffer(120)  # struct io_uring_params, zeroed
    syscall_refused("io_uring_setup", lambda: libc.syscall(SYS_IO_URING_SETUP, ctypes.c_uint(8), uring_params))
    # struct perf_event_attr (128 bytes): type PERF_TYPE_SOFTWARE, size, config PERF_COUNT_SW_CPU_CLOCK; this process.
    perf_attr = ctypes.create_string_buffer(128)
    ctypes.memmove(perf_attr, (1).to_bytes(4, "little") + (128).to_bytes(4, "little"), 8)
    syscall_refused("perf_event_open on itself",
                    lambda: libc.syscall(SYS_PERF_EVENT_OPEN, perf_attr, ctypes.c_long(0), ctypes.c_long(-1), ctypes.c_long(-1), ctypes.c_ulong(0)))
    # union bpf_attr for BPF_MAP_CREATE: an array map of one 4-byte entry.
    bpf_attr = ctypes.create_string_buffer(128)
    ctypes.memmove(bpf_attr, b"".join(v.to_bytes(4, "little") for v in (2, 4, 4, 1)), 16)
    syscall_refused("bpf(BPF_MAP_CREATE)", lambda: libc.syscall(SYS_BPF, ctypes.c_long(0), bpf_attr, ctypes.c_uint(128)))
    UFFD_USER_MODE_ONLY = 1
    syscall_refused("userfaultfd", lambda: libc.syscall(SYS_USERFAULTFD, ctypes.c_long(os.O_CLOEXEC | os.O_NONBLOCK | UFFD_USER_MODE_ONLY)))
else:
    print(f"escape: {platform.machine()}: the raw-syscall attacks are x86_64's, skipped", file=sys.stderr)

# The rollout's caps on processes, memory and disk (only where the runner enforces them: a root runner).
LIMITS = ARGS.get("caps")


def fork_flood(cap):
    """Up to 2 x cap children that sleep; refused when the cap stopped them at cap or fewer."""
    sleep = shutil.which("sleep") or "/bin/sleep"
    children, failure = [], None
    for _ in range(2 * cap):
        try:
            pid = os.fork()
        except OSError as e:
            failure = e
            break
        if pid == 0:
            try:
                os.execv(sleep, ["sleep", "120"])
            finally:
                os._exit(0)
        children.append(pid)
    for pid in children:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    for pid in children:
        try:
            os.waitpid(pid, 0)
        except OSError:
            pass
    record(f"fork more than the cap of {cap} processes", len(children) <= cap,
           f"{len(children)} children forked, then {failure!r}")


def allocate(cap):
    """A child allocating (and touching) twice the memory cap; refused when it was killed or failed."""
    n = 2 * cap
    try:
        p = subprocess.run([sys.executable, "-c", f"b = b'x' * {n}; print(len(b))"], capture_output=True, timeout=300)
        record(f"allocate {n} bytes over the memory cap of {cap}", p.returncode != 0,
               f"exit {p.returncode}: {p.stdout[-100:]!r} {p.stderr[-200:]!r}")
    except subprocess.TimeoutExpired as e:
        record(f"allocate {n} bytes over the memory cap of {cap}", False, f"still running: {e}")


def fill_disk(cap):
    """1 MiB writes in turn into the workspace, /tmp and $HOME until the disk is full; refused when no more than the
    cap went in. The files are deleted after, so the episode can still publish its observations."""
    dirs = [os.environ.get("LIBERO_AGENT_WORKSPACE") or os.getcwd(), "/tmp", os.environ.get("HOME") or "/tmp"]
    paths = [os.path.join(d, f".libero-escape-fill-{i}") for i, d in enumerate(dirs)]
    fds = [os.open(p, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600) for p in paths]
    chunk = b"\xa5" * (1 << 20)
    total, refusal, i = 0, None, 0
    try:
        while total <= cap + (64 << 20):
            try:
                total += os.write(fds[i % len(fds)], chunk)
            except OSError as e:
                if e.errno in (errno.ENOSPC, errno.EDQUOT):
                    refusal = e
                    break
                raise
            i += 1
    finally:
        for fd in fds:
            os.close(fd)
        for p in paths:
            try:
                os.unlink(p)
            except OSError:
                pass
    record(f"fill the workspace, /tmp and $HOME past the disk cap of {cap}", refusal is not None and total <= cap,
           f"{total} bytes written, then {refusal!r}")


if LIMITS:
    fork_flood(int(LIMITS["max_processes"]))
    allocate(int(LIMITS["memory_bytes"]))
    fill_disk(int(LIMITS["disk_bytes"]))
else:
    print("escape: the runner caps no resources here: the fork, memory and disk attacks are skipped", file=sys.stderr)

# The model API the harness is configured with is reachable (through the gateway).
base = os.environ.get("LIBERO_MODEL_API_BASE")
model_reply = None
if base:
    req = urllib.request.Request(base + "/models", headers={"Authorization": "Bearer " + os.environ.get("LIBERO_MODEL_API_KEY", "")})
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    model_reply = opener.open(req, timeout=10).read().decode()

# A file in the sandbox's /tmp does not reach the host's.
open(f"/tmp/{ARGS['marker']}", "w").write("escape")

# The report: one line on stdout (kept as command_stdout.log; the workspace does not outlive the rollout).
report = {"attempts": attempts, "uid": os.getuid(), "gid": os.getgid(), "model_reply": model_reply, "capabilities": caps}
print("LIBERO-ESCAPE-REPORT " + json.dumps(report), flush=True)
print(f"escape: {len(attempts)} attempts, {sum(not a['refused'] for a in attempts)} let through", file=sys.stderr)
