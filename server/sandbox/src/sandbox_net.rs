//! `libero-agent sandbox-net`: the first process inside the agent's sandbox. The sandbox has a network namespace of
//! its own (only `lo`), so nothing of the host is reachable; this process listens on the loopback addresses the
//! agent is told about (its episode's MCP endpoint, its model API) and relays each connection to a Unix socket that
//! the runner owns outside the sandbox (bound in at `/run/libero/`). Then it reports what the sandbox is (uid, gid,
//! capability sets, no_new_privs, mounts, interfaces) on a pipe only the runner reads, closes it, and starts the
//! agent. The agent may kill this process: it then loses its own endpoints, nothing else.
use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::PathBuf;
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{Context, bail};
use serde::Deserialize;
use serde_json::{Value, json};

/// Connections relayed at once per listener; more wait in the listen backlog.
const MAX_CONNECTIONS: usize = 256;

/// One loopback address inside the sandbox and the runner's Unix socket it leads to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ListenSpec {
    pub addr: SocketAddr,
    pub socket: PathBuf,
}

impl std::str::FromStr for ListenSpec {
    type Err = String;
    /// `127.0.0.1:8080=/run/libero/mcp.sock`, `[::1]:8080=/run/libero/mcp.sock`.
    fn from_str(s: &str) -> Result<Self, String> {
        let (addr, socket) = s.split_once('=').ok_or_else(|| format!("{s}: expected ADDR:PORT=/path/to/socket"))?;
        let addr: SocketAddr = addr.parse().map_err(|e| format!("{addr}: {e}"))?;
        if !addr.ip().is_loopback() {
            return Err(format!("{addr}: only loopback addresses are relayed"));
        }
        Ok(Self { addr, socket: PathBuf::from(socket) })
    }
}

impl std::fmt::Display for ListenSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}={}", self.addr, self.socket.display())
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct SandboxNetArgs {
    /// `ADDR:PORT=/unix/socket`: listen on the loopback address, relay each connection to the socket.
    #[arg(long = "listen")]
    pub listens: Vec<ListenSpec>,
    /// A pipe the runner reads: the sandbox's report (one JSON object), written before the agent starts.
    #[arg(long)]
    pub report_fd: Option<i32>,
    /// `UID:GID`: as root, become this unprivileged user (every capability set emptied) before the agent starts.
    /// Required when this process runs as root: an agent never runs as root.
    #[arg(long, value_parser = parse_ids)]
    pub drop_to: Option<(u32, u32)>,
    /// The agent's command.
    #[arg(last = true, required = true)]
    pub argv: Vec<String>,
}

fn parse_ids(s: &str) -> Result<(u32, u32), String> {
    let (u, g) = s.split_once(':').ok_or_else(|| format!("{s}: expected UID:GID"))?;
    let u: u32 = u.parse().map_err(|e| format!("{u}: {e}"))?;
    let g: u32 = g.parse().map_err(|e| format!("{g}: {e}"))?;
    if u == 0 || g == 0 {
        return Err("the agent's ids must not be root's".into());
    }
    Ok((u, g))
}

/// Binds every listener, reports, starts the agent and relays until the agent exits; returns its exit code.
pub fn run(args: &SandboxNetArgs) -> anyhow::Result<i32> {
    // Descriptors inherited through bubblewrap (other than the report pipe) never reach the agent.
    close_on_exec_inherited(args.report_fd);
    let mut bound = Vec::new();
    for spec in &args.listens {
        let l = TcpListener::bind(spec.addr).with_context(|| format!("sandbox-net: cannot listen on {}", spec.addr))?;
        bound.push((l, spec.socket.clone()));
    }
    // SAFETY: geteuid(2) has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    match args.drop_to {
        Some((uid, gid)) => become_unprivileged(uid, gid).context("sandbox-net: cannot drop to the agent's user")?,
        None if root => bail!("sandbox-net: refusing to start an agent as root (pass --drop-to UID:GID)"),
        None => {}
    }
    confine().context("sandbox-net: cannot confine the agent (session keyring, no_new_privs, seccomp)")?;
    if let Some(fd) = args.report_fd {
        // SAFETY: the runner passed this descriptor (the write end of its pipe) for us alone; it is closed here.
        let mut f = unsafe { <std::fs::File as std::os::fd::FromRawFd>::from_raw_fd(fd) };
        let report = serde_json::to_vec(&sandbox_report(&args.listens))?;
        let _ = f.write_all(&report);
    }
    for (listener, socket) in bound {
        std::thread::Builder::new().name("sandbox-net".into()).spawn(move || accept_loop(listener, socket))?;
    }
    let Some((program, rest)) = args.argv.split_first() else { bail!("sandbox-net: no command") };
    let status = Command::new(program).args(rest).status().with_context(|| format!("sandbox-net: cannot start {program}"))?;
    use std::os::unix::process::ExitStatusExt;
    Ok(status.code().unwrap_or_else(|| 128 + status.signal().unwrap_or(0)))
}

/// Marks every inherited descriptor above stderr close-on-exec, except `keep`.
fn close_on_exec_inherited(keep: Option<i32>) {
    let Ok(dir) = std::fs::read_dir("/proc/self/fd") else { return };
    let fds: Vec<i32> = dir.flatten().filter_map(|e| e.file_name().to_str()?.parse().ok()).collect();
    for fd in fds.into_iter().filter(|fd| *fd > 2 && Some(*fd) != keep) {
        // SAFETY: fcntl(2) on a descriptor number; an already-closed one (the directory's own) just fails.
        unsafe { libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC) };
    }
}

fn check(rc: libc::c_int) -> std::io::Result<()> {
    if rc < 0 { Err(std::io::Error::last_os_error()) } else { Ok(()) }
}

/// Root → `uid:gid` with no supplementary groups and every capability set empty (bounding and ambient included).
fn become_unprivileged(uid: u32, gid: u32) -> std::io::Result<()> {
    // SAFETY: plain system calls on this process's credentials; no memory is shared with them.
    unsafe {
        for cap in 0..=63 {
            // EINVAL past the kernel's last capability: nothing to drop there.
            libc::prctl(libc::PR_CAPBSET_DROP, cap, 0, 0, 0);
        }
        check(libc::prctl(libc::PR_CAP_AMBIENT, libc::PR_CAP_AMBIENT_CLEAR_ALL, 0, 0, 0))?;
        check(libc::setgroups(0, std::ptr::null()))?;
        check(libc::setresgid(gid, gid, gid))?;
        check(libc::setresuid(uid, uid, uid))?;
        // setresuid away from 0 empties the permitted and effective sets; the inheritable one is emptied here.
        #[repr(C)]
        struct Header {
            version: u32,
            pid: i32,
        }
        #[repr(C)]
        #[derive(Clone, Copy)]
        struct Data {
            effective: u32,
            permitted: u32,
            inheritable: u32,
        }
        let mut header = Header { version: 0x2008_0522, pid: 0 }; // _LINUX_CAPABILITY_VERSION_3
        let data = [Data { effective: 0, permitted: 0, inheritable: 0 }; 2];
        check(libc::syscall(libc::SYS_capset, &mut header as *mut Header, data.as_ptr()) as libc::c_int)?;
        if libc::geteuid() == 0 || libc::getuid() == 0 {
            return Err(std::io::Error::other("still root after setresuid"));
        }
    }
    Ok(())
}

/// A fresh anonymous session keyring (whatever session keyring the runner had — a systemd service's, a PAM
/// login's — is left behind), then no_new_privs and the seccomp allow-list ([`crate::seccomp`]), under which no
/// keyring call is possible at all: no key of this rollout reaches another, and none of the runner's reaches it.
fn confine() -> anyhow::Result<()> {
    // SAFETY: keyctl(2) KEYCTL_JOIN_SESSION_KEYRING with a null name makes and joins a new anonymous keyring.
    let rc = unsafe { libc::syscall(libc::SYS_keyctl, KEYCTL_JOIN_SESSION_KEYRING, std::ptr::null::<libc::c_char>()) };
    if rc < 0 {
        let e = std::io::Error::last_os_error();
        // A kernel built without keys (ENOSYS), or a container policy that already refuses keyctl: no keyring
        // can be reached from here either way.
        if !matches!(e.raw_os_error(), Some(libc::ENOSYS) | Some(libc::EPERM)) {
            return Err(anyhow::anyhow!("cannot join a fresh session keyring: {e}"));
        }
    }
    crate::seccomp::install()?;
    Ok(())
}

const KEYCTL_JOIN_SESSION_KEYRING: libc::c_long = 1;

fn accept_loop(listener: TcpListener, socket: PathBuf) {
    let live = Arc::new(AtomicUsize::new(0));
    for conn in listener.incoming() {
        let Ok(tcp) = conn else { continue };
        if live.load(Ordering::SeqCst) >= MAX_CONNECTIONS {
            drop(tcp);
            continue;
        }
        live.fetch_add(1, Ordering::SeqCst);
        let (held, socket) = (live.clone(), socket.clone());
        // Each connection on a thread of its own from its first step: connecting to the runner's socket can wait
        // (its backlog full of this agent's slow connections) without holding up the connections after it.
        let spawned = std::thread::Builder::new().name("sandbox-net-conn".into()).spawn(move || {
            if let Ok(unix) = UnixStream::connect(&socket) {
                relay(tcp, unix);
            }
            held.fetch_sub(1, Ordering::SeqCst);
        });
        if spawned.is_err() {
            // No thread for it (the agent's process cap): the connection is dropped with the closure.
            live.fetch_sub(1, Ordering::SeqCst);
        }
    }
}

/// Copies both ways until both directions are done, passing half-closes on.
fn relay(tcp: TcpStream, unix: UnixStream) {
    let (Ok(tcp2), Ok(unix2)) = (tcp.try_clone(), unix.try_clone()) else { return };
    let up = std::thread::spawn(move || {
        let (mut from, to) = (tcp2, unix2);
        copy(&mut from, &mut &to);
        let _ = to.shutdown(Shutdown::Write);
    });
    let (mut from, to) = (unix, tcp);
    copy(&mut from, &mut &to);
    let _ = to.shutdown(Shutdown::Write);
    let _ = up.join();
}

fn copy(from: &mut impl Read, to: &mut impl Write) {
    let mut buf = [0u8; 16 * 1024];
    loop {
        match from.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => {
                if to.write_all(&buf[..n]).is_err() {
                    return;
                }
            }
        }
    }
}

/// What the sandbox is, as the kernel tells this process: ids, capability sets, no_new_privs, seccomp, mounts and
/// network interfaces. Recorded in the rollout's harness manifest.
pub fn sandbox_report(listens: &[ListenSpec]) -> Value {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| status.lines().find_map(|l| l.strip_prefix(name).map(|v| v.trim().to_owned()));
    let words = |name: &str| field(name).map(|v| v.split_whitespace().map(str::to_owned).collect::<Vec<_>>());
    let mounts: Vec<Value> = std::fs::read_to_string("/proc/self/mountinfo")
        .unwrap_or_default()
        .lines()
        .filter_map(|l| {
            // `id parent major:minor root mountpoint options … - fstype source super-options`
            let (left, right) = l.split_once(" - ")?;
            let f: Vec<&str> = left.split_whitespace().collect();
            let r: Vec<&str> = right.split_whitespace().collect();
            Some(json!({"mountpoint": f.get(4)?, "root": f.get(3)?, "options": f.get(5)?, "fstype": r.first()?}))
        })
        .collect();
    let interfaces: Vec<String> = std::fs::read_to_string("/proc/self/net/dev")
        .unwrap_or_default()
        .lines()
        .skip(2)
        .filter_map(|l| l.split(':').next().map(|n| n.trim().to_owned()))
        .collect();
    let ns = |name: &str| std::fs::read_link(format!("/proc/self/ns/{name}")).ok().map(|p| p.to_string_lossy().into_owned());
    json!({
        "schema_version": "libero.sandbox_report.v1",
        "uid": words("Uid:"), "gid": words("Gid:"), "groups": words("Groups:"),
        "uid_map": std::fs::read_to_string("/proc/self/uid_map").ok().map(|s| s.split_whitespace().collect::<Vec<_>>().join(" ")),
        "gid_map": std::fs::read_to_string("/proc/self/gid_map").ok().map(|s| s.split_whitespace().collect::<Vec<_>>().join(" ")),
        "capabilities": {
            "inheritable": field("CapInh:"), "permitted": field("CapPrm:"), "effective": field("CapEff:"),
            "bounding": field("CapBnd:"), "ambient": field("CapAmb:"),
        },
        "no_new_privs": field("NoNewPrivs:").map(|v| v == "1"),
        "seccomp": field("Seccomp:"),
        "namespaces": {"user": ns("user"), "net": ns("net"), "pid": ns("pid"), "mnt": ns("mnt")},
        "network_interfaces": interfaces,
        "relays": listens.iter().map(|l| json!({"listen": l.addr.to_string(), "to": l.socket})).collect::<Vec<_>>(),
        "mounts": mounts,
    })
}

/// Whether a report says the agent holds no capability and cannot gain one.
pub fn report_holds_no_capability(report: &Value) -> bool {
    let view = PrivilegeView::deserialize(report).unwrap_or_default();
    let c = &view.capabilities;
    [&c.inheritable, &c.permitted, &c.effective, &c.bounding, &c.ambient]
        .iter()
        .all(|set| set.as_str().is_some_and(|v| v.trim_start_matches('0').is_empty()))
        && view.no_new_privs == true
}

/// The part of a [`sandbox_report`] that tells whether the agent holds or can gain a capability (values kept as
/// JSON: a report of another shape holds no proof, read as "it may").
#[derive(Deserialize, Default)]
struct PrivilegeView {
    #[serde(default)]
    capabilities: CapabilitySets,
    #[serde(default)]
    no_new_privs: Value,
}

/// The report's `capabilities`: each set as `/proc/self/status` prints it (hex).
#[derive(Deserialize, Default)]
struct CapabilitySets {
    #[serde(default)]
    inheritable: Value,
    #[serde(default)]
    permitted: Value,
    #[serde(default)]
    effective: Value,
    #[serde(default)]
    bounding: Value,
    #[serde(default)]
    ambient: Value,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listen_specs_parse_loopback_only() {
        let s: ListenSpec = "127.0.0.1:8080=/run/libero/mcp.sock".parse().unwrap();
        assert_eq!((s.addr.port(), s.socket.to_str()), (8080, Some("/run/libero/mcp.sock")));
        assert_eq!(s.to_string(), "127.0.0.1:8080=/run/libero/mcp.sock");
        assert!("[::1]:9=/x".parse::<ListenSpec>().is_ok());
        assert!("0.0.0.0:80=/x".parse::<ListenSpec>().is_err());
        assert!("10.0.0.1:80=/x".parse::<ListenSpec>().is_err());
        assert!("127.0.0.1:80".parse::<ListenSpec>().is_err());
    }

    #[test]
    fn a_connection_is_relayed_both_ways_with_half_close() {
        let dir = tempfile::tempdir().unwrap();
        let sock = dir.path().join("s.sock");
        let server = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        let echo = std::thread::spawn(move || {
            let (mut c, _) = server.accept().unwrap();
            let mut got = Vec::new();
            c.read_to_end(&mut got).unwrap();
            c.write_all(&[b"echo:".as_slice(), &got].concat()).unwrap();
        });
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        std::thread::spawn(move || accept_loop(listener, sock));
        let mut c = TcpStream::connect(addr).unwrap();
        c.write_all(b"hello").unwrap();
        c.shutdown(Shutdown::Write).unwrap();
        let mut back = String::new();
        c.read_to_string(&mut back).unwrap();
        assert_eq!(back, "echo:hello");
        echo.join().unwrap();
    }

    /// Installed on one thread of this test process (seccomp and the session keyring are per thread here): the
    /// thread's session keyring is a new one, and no keyring call gets through afterwards.
    #[test]
    fn confining_leaves_the_runner_s_session_keyring_and_closes_every_keyring_call() {
        std::thread::spawn(|| {
            // SAFETY: KEYCTL_GET_KEYRING_ID (0) of the session keyring (-3), not creating one.
            let before = unsafe { libc::syscall(libc::SYS_keyctl, 0, -3, 0) };
            confine().unwrap();
            let status = std::fs::read_to_string("/proc/thread-self/status").unwrap();
            assert!(status.lines().any(|l| l.starts_with("Seccomp:") && l.ends_with('2')), "{status}");
            assert!(status.lines().any(|l| l.starts_with("NoNewPrivs:") && l.ends_with('1')), "{status}");
            // SAFETY: as above; the filter answers before the kernel looks.
            let after = unsafe { libc::syscall(libc::SYS_keyctl, 0, -3, 0) };
            assert_eq!((after, std::io::Error::last_os_error().raw_os_error()), (-1, Some(libc::EPERM)), "before: {before}");
            // SAFETY: setns(2) on an invalid descriptor; the filter answers before the kernel looks at it.
            let rc = unsafe { libc::setns(-1, 0) };
            assert_eq!((rc, std::io::Error::last_os_error().raw_os_error()), (-1, Some(libc::EPERM)));
            assert_eq!(std::thread::spawn(|| 7).join().unwrap(), 7, "threads start");
        })
        .join()
        .unwrap();
    }

    #[test]
    fn ids_of_root_are_refused() {
        assert_eq!(parse_ids("65534:65534"), Ok((65534, 65534)));
        assert!(parse_ids("0:65534").is_err() && parse_ids("65534:0").is_err() && parse_ids("65534").is_err());
    }

    #[test]
    fn this_process_report_has_ids_capabilities_and_mounts() {
        let r = sandbox_report(&[]);
        assert!(r["uid"].as_array().is_some_and(|a| a.len() == 4), "{r}");
        assert!(r["capabilities"]["effective"].is_string());
        assert!(r["mounts"].as_array().is_some_and(|m| !m.is_empty()));
        assert!(r["network_interfaces"].as_array().is_some_and(|i| i.iter().any(|n| n == "lo")));
    }
}
