//! What a sandboxed agent can reach, and the runner's side of it. The agent's network namespace holds only `lo`;
//! inside it `sandbox-net` ([`crate::sandbox_net`]) listens on
//! - the MCP endpoint's own address (`127.0.0.1:<server port>`, and `[::1]` on the same port), relayed to the
//!   episode's server, so the URL in the agent's configuration is unchanged (a server named by host name is mapped
//!   to loopback in the sandbox's `/etc/hosts`);
//! - the model API at `127.0.0.1:`[`MODEL_API_PORT`], relayed to the runner's gateway ([`crate::netgate`]), which
//!   reverse-proxies the harness's own model-API endpoints ([`NetPlan::routes`]) below its API base to the real
//!   upstream and, as an HTTP(S) proxy, tunnels only to the hosts of an allow-list taken from the harness's
//!   launch (the npm registry for `npx` launches; never the model API itself, whose traffic goes through the base
//!   URL, metered). It records every request (time, bytes, the model's reported token usage) in the rollout's
//!   private directory.
//!
//! Every other address, on loopback or anywhere, does not exist for the agent.
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr, ToSocketAddrs};
use std::os::fd::{AsRawFd, OwnedFd};
use std::os::unix::net::UnixListener;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use serde_json::Value;

use crate::netgate;
use crate::sandbox::{RELAY_DIR, Sandbox, SandboxSpec, cli_install_paths, own_binary_files};
use crate::sandbox_net::ListenSpec;

/// The model API's port on the sandbox's loopback (another one when the MCP endpoint has this port).
pub const MODEL_API_PORT: u16 = 18790;
/// The npm registry, reached by harnesses the paper launched through `npx` when their pinned CLI is not installed.
pub const NPM_REGISTRY: (&str, u16) = ("registry.npmjs.org", 443);
/// The most bytes of the sandbox's report read.
const MAX_REPORT_BYTES: u64 = 1 << 20;

/// The addresses of one agent's namespace and where they lead.
#[derive(Debug, Clone)]
pub struct NetPlan {
    /// The MCP endpoint's port, listened on inside at 127.0.0.1 and ::1.
    pub mcp_port: u16,
    /// The server's address as the runner reaches it.
    pub mcp_target: SocketAddr,
    /// The server's host name, mapped to 127.0.0.1 inside, when the URL names one.
    pub mcp_host_name: Option<String>,
    /// The model API's port inside.
    pub model_port: u16,
    /// The real API base the gateway forwards to (the credentials', else the harness's default).
    pub upstream: Option<url::Url>,
    /// The harness's model-API endpoints, the only origin-form requests the gateway passes on upstream (the
    /// runner's `Harness::model_api_endpoints` below the upstream's path); empty without an upstream.
    pub routes: Vec<netgate::Route>,
    /// host:port pairs the gateway's proxy tunnels to. Never the upstream: every harness reaches its model API
    /// through the gateway's base URL, and a tunnel there would pass any endpoint on, unmetered.
    pub allowed: Vec<(String, u16)>,
}

impl NetPlan {
    /// The plan for an agent on the episode at `mcp_url` whose model API lies at `api_base` (the credentials' base
    /// URL, else its harness's default), where only `endpoints(<api_base's path>)` (method, path) are passed on;
    /// `via_npx` when the harness's CLI is fetched by `npx` at launch. The harness itself is the runner's business:
    /// the boundary only needs where the traffic may go.
    pub fn new(
        mcp_url: &str,
        api_base: Option<&str>,
        endpoints: impl FnOnce(&str) -> Vec<(&'static str, String)>,
        via_npx: bool,
    ) -> anyhow::Result<Self> {
        let url = url::Url::parse(mcp_url).with_context(|| format!("the episode's MCP URL {mcp_url}"))?;
        let mcp_port = url.port_or_known_default().with_context(|| format!("{mcp_url} has no port"))?;
        let (mcp_target, mcp_host_name) = match url.host() {
            Some(url::Host::Ipv4(ip)) if ip.is_loopback() => (SocketAddr::new(IpAddr::V4(ip), mcp_port), None),
            Some(url::Host::Ipv6(ip)) if ip.is_loopback() => (SocketAddr::new(IpAddr::V6(ip), mcp_port), None),
            Some(url::Host::Domain(name)) => {
                let target = (name, mcp_port)
                    .to_socket_addrs()
                    .with_context(|| format!("cannot resolve the episode server {name}"))?
                    .next()
                    .with_context(|| format!("the episode server {name} has no address"))?;
                let mapped = (name != "localhost").then(|| name.to_owned());
                (target, mapped)
            }
            _ => bail!(
                "the agent's network namespace reaches its episode server by loopback or by host name; {mcp_url} names a \
                 non-loopback address: give the server as http://<host name>:<port>"
            ),
        };
        let model_port = if mcp_port == MODEL_API_PORT { MODEL_API_PORT + 1 } else { MODEL_API_PORT };
        let upstream = match api_base {
            Some(b) => Some(url::Url::parse(b).with_context(|| format!("the API base URL {b}"))?),
            None => None,
        };
        let routes = match &upstream {
            Some(u) => endpoints(u.path())
                .into_iter()
                .filter_map(|(method, path)| Some(netgate::Route::new(http::Method::from_bytes(method.as_bytes()).ok()?, path)))
                .collect(),
            None => Vec::new(),
        };
        let mut allowed = Vec::new();
        if via_npx {
            allowed.push((NPM_REGISTRY.0.to_owned(), NPM_REGISTRY.1));
        }
        Ok(Self { mcp_port, mcp_target, mcp_host_name, model_port, upstream, routes, allowed })
    }

    /// The model API base as the agent sees it: the gateway's loopback address with the upstream's path.
    pub fn agent_api_base(&self) -> Option<String> {
        let u = self.upstream.as_ref()?;
        Some(format!("http://127.0.0.1:{}{}", self.model_port, u.path().trim_end_matches('/')))
    }

    /// The proxy environment: every HTTP(S) client that honours it goes through the gateway's allow-list; loopback
    /// (the MCP endpoint, the gateway's own base) is reached directly.
    pub fn proxy_env(&self) -> Vec<(String, String)> {
        let proxy = format!("http://127.0.0.1:{}", self.model_port);
        let mut env: Vec<(String, String)> = ["HTTPS_PROXY", "https_proxy", "HTTP_PROXY", "http_proxy", "ALL_PROXY", "all_proxy"]
            .iter()
            .map(|k| ((*k).to_owned(), proxy.clone()))
            .collect();
        let mut no_proxy = "localhost,127.0.0.1,::1".to_owned();
        if let Some(name) = &self.mcp_host_name {
            no_proxy.push(',');
            no_proxy.push_str(name);
        }
        env.push(("NO_PROXY".into(), no_proxy.clone()));
        env.push(("no_proxy".into(), no_proxy));
        // Node's own fetch honours the variables only when asked (Node 22.21+ / 24).
        env.push(("NODE_USE_ENV_PROXY".into(), "1".into()));
        if let Some(base) = self.agent_api_base() {
            env.push(("LIBERO_MODEL_API_BASE".into(), base));
        }
        env
    }

    /// The loopback addresses `sandbox-net` listens on, with the sockets (inside) they lead to.
    fn listens(&self) -> Vec<ListenSpec> {
        let mcp = PathBuf::from(RELAY_DIR).join("mcp.sock");
        let model = PathBuf::from(RELAY_DIR).join("model.sock");
        vec![
            ListenSpec { addr: SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), self.mcp_port), socket: mcp.clone() },
            ListenSpec { addr: SocketAddr::new(IpAddr::V6(Ipv6Addr::LOCALHOST), self.mcp_port), socket: mcp },
            ListenSpec { addr: SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), self.model_port), socket: model.clone() },
            ListenSpec { addr: SocketAddr::new(IpAddr::V6(Ipv6Addr::LOCALHOST), self.model_port), socket: model },
        ]
    }

    /// The sandbox's `/etc/hosts`: loopback names, and the server's host name on loopback.
    fn hosts_file(&self) -> String {
        let mut s = "127.0.0.1\tlocalhost\n::1\tlocalhost ip6-localhost ip6-loopback\n127.0.1.1\tlibero-agent\n".to_owned();
        if let Some(name) = &self.mcp_host_name {
            s.push_str(&format!("127.0.0.1\t{name}\n"));
        }
        s
    }

    /// For the harness manifest.
    pub fn describe(&self) -> Value {
        serde_json::json!({
            "mcp": {"inside": [format!("127.0.0.1:{}", self.mcp_port), format!("[::1]:{}", self.mcp_port)], "to": self.mcp_target.to_string(),
                "host_name_on_loopback": self.mcp_host_name},
            "model_api": {"inside": format!("127.0.0.1:{}", self.model_port), "upstream": self.upstream.as_ref().map(|u| u.as_str()),
                "agent_base": self.agent_api_base(), "routes": self.routes.iter().map(ToString::to_string).collect::<Vec<_>>()},
            "proxy_allow_list": self.allowed.iter().map(|(h, p)| format!("{h}:{p}")).collect::<Vec<_>>(),
            "everything_else": "unreachable (the namespace has only lo)",
        })
    }
}

/// A sandboxed launch ready to start, and the runner's relays it needs while it runs.
pub struct Contained {
    pub argv: Vec<String>,
    pub env: Vec<(String, String)>,
    /// The gateway's records (`model_api.jsonl`) when the agent has a namespace of its own.
    pub model_api_records: Option<PathBuf>,
    report_read: Option<OwnedFd>,
    report_write: Option<OwnedFd>,
    _relay: Option<netgate::Relay>,
    _gateway: Option<netgate::Gateway>,
    /// Dropped last: the sockets' directory.
    relay_dir: Option<RelayDir>,
}

/// Prepares the launch `argv`, with its whole environment `env`, to run sandboxed (or plainly, without a sandbox):
/// the relays and the gateway started with their sockets in a fresh short-named directory, the sandbox's files
/// (`hosts`, the gateway's records) in `private/`, the workspace and session home handed to the agent's user when
/// the runner is root, the sandbox's toolbox first on the agent's `PATH`, and the argv wrapped in bubblewrap and
/// `sandbox-net`.
#[allow(clippy::too_many_arguments)] // the launch (argv, env), where it runs (workspace, home, private) and with what
pub fn contain(
    sandbox: Option<&Sandbox>,
    plan: Option<&NetPlan>,
    argv: &[String],
    env: &[(String, String)],
    workspace: &Path,
    home: &Path,
    agent_exe: &Path,
    private: &Path,
) -> anyhow::Result<Contained> {
    let (Some(sb), Some(plan)) = (sandbox, plan) else {
        return Ok(Contained {
            argv: argv.to_vec(),
            env: env.to_vec(),
            model_api_records: None,
            report_read: None,
            report_write: None,
            _relay: None,
            _gateway: None,
            relay_dir: None,
        });
    };
    // The relay sockets live in a fresh directory with a short path (a Unix socket's path has at most 107 bytes,
    // and batch directories can be deep), the agent's user's alone; it goes when the rollout ends.
    std::fs::create_dir_all(private).with_context(|| format!("cannot create {}", private.display()))?;
    let net = RelayDir::create()?;
    if let Some((uid, gid)) = sb.agent_ids {
        std::os::unix::fs::chown(&net.0, Some(uid), Some(gid)).with_context(|| format!("cannot give {} to the agent", net.0.display()))?;
    }
    let net_path = net.0.clone();
    let bind = |name: &str| -> anyhow::Result<UnixListener> {
        let p = net_path.join(name);
        let _ = std::fs::remove_file(&p);
        let l = UnixListener::bind(&p).with_context(|| format!("cannot listen on {}", p.display()))?;
        // Only the agent's user connects (the directory is the runner's; the socket is the agent's or 0600).
        if let Some((uid, gid)) = sb.agent_ids {
            std::os::unix::fs::chown(&p, Some(uid), Some(gid)).with_context(|| format!("cannot give {} to the agent", p.display()))?;
        }
        set_mode(&p, 0o600)?;
        Ok(l)
    };
    // A loopback server sees this agent's connections come from an address of its own (127.0.0.0/8 is all
    // loopback), so its per-address caps bound each agent alone.
    let source = plan.mcp_target.ip().is_loopback().then(|| plan.mcp_target.is_ipv4()).filter(|v4| *v4).map(|_| own_loopback_address());
    let relay =
        netgate::relay_unix_to_tcp_from(bind("mcp.sock")?, plan.mcp_target, source).context("cannot start the MCP relay")?;
    let records = private.join("model_api.jsonl");
    let gateway = netgate::start(
        bind("model.sock")?,
        netgate::GatewayConfig {
            upstream: plan.upstream.clone(),
            routes: plan.routes.clone(),
            allowed: plan.allowed.clone(),
            records: records.clone(),
            max_records: netgate::MAX_RECORDS,
        },
    )
    .context("cannot start the model API gateway")?;
    let hosts = private.join("hosts");
    std::fs::write(&hosts, plan.hosts_file())?;
    set_mode(&hosts, 0o644)?;
    let launch_env = env;
    let mut env = launch_env.to_vec();
    env.extend(plan.proxy_env());
    // The agent's own `python3` is the toolbox's.
    if let Some(tb) = &sb.toolbox {
        tb.agent_env(&mut env, home);
    }
    write_login_profile(home, &env)?;
    if let Some(ids) = sb.agent_ids {
        give_to_agent(workspace, ids, &["benchmark_inputs"])?;
        give_to_agent(home, ids, &[])?;
    }
    // The report pipe: close-on-exec here, opened for the sandbox's first process only (see `command`).
    let (read, write) = rustix::pipe::pipe_with(rustix::pipe::PipeFlags::CLOEXEC).context("cannot create the report pipe")?;
    let mut inner = vec![agent_exe.to_string_lossy().into_owned(), "sandbox-net".into()];
    for l in plan.listens() {
        inner.extend(["--listen".into(), l.to_string()]);
    }
    inner.extend(["--report-fd".into(), write.as_raw_fd().to_string()]);
    if let Some((uid, gid)) = sb.agent_ids {
        inner.extend(["--drop-to".into(), format!("{uid}:{gid}")]);
    }
    inner.push("--".into());
    inner.extend(argv.iter().cloned());
    // The CLI is found on the runner's PATH (the launch's, before the toolbox went first).
    let path = launch_env.iter().find(|(k, _)| k == "PATH").map(|(_, v)| v.as_str()).unwrap_or_default();
    let mut readable = own_binary_files(agent_exe);
    readable.extend(argv.first().map(|p| cli_install_paths(p, path.as_ref())).unwrap_or_default());
    let spec = SandboxSpec {
        writable: vec![workspace.to_path_buf(), home.to_path_buf()],
        readable,
        files: vec![(hosts, PathBuf::from("/etc/hosts"))],
        relay_dir: Some(net_path),
        cwd: workspace.to_path_buf(),
    };
    Ok(Contained {
        argv: sb.command(&inner, &spec),
        env,
        model_api_records: Some(records),
        report_read: Some(read),
        report_write: Some(write),
        _relay: Some(relay),
        _gateway: Some(gateway),
        relay_dir: Some(net),
    })
}

/// `<home>/.profile`, which restores the agent's `PATH`: the CLIs run their shell commands in login shells
/// (Codex's `exec_command` does by default), and a login shell's `/etc/profile` sets `PATH` anew (Debian's does),
/// which would hide the toolbox's `python3` behind the system's. The file is the agent's own to change.
fn write_login_profile(home: &Path, env: &[(String, String)]) -> anyhow::Result<()> {
    let Some((_, path)) = env.iter().find(|(k, _)| k == "PATH") else { return Ok(()) };
    let quoted = format!("'{}'", path.replace('\'', "'\\''"));
    let text = format!(
        "# Written by libero-agent's runner: a login shell's /etc/profile sets PATH anew, which would hide the\n\
         # toolbox's python3 (/opt/libero-toolbox/bin) behind the system's; this restores the PATH the agent was given.\n\
         PATH={quoted}\nexport PATH\n"
    );
    let p = home.join(".profile");
    std::fs::write(&p, text).with_context(|| format!("cannot write {}", p.display()))?;
    set_mode(&p, 0o644)
}

/// A random address of 127.0.0.0/8 other than 127.0.0.1 and 127.0.1.1 (names of this host).
fn own_loopback_address() -> IpAddr {
    let mut b = [0u8; 3];
    // SAFETY: getrandom(2) fills the buffer it is given, of the length it is given.
    unsafe { libc::getrandom(b.as_mut_ptr().cast(), b.len(), 0) };
    IpAddr::V4(Ipv4Addr::new(127, b[0].max(2), b[1], b[2].clamp(2, 254)))
}

/// A directory `<tmp>/libero-net-<random>` (0700) removed on drop.
struct RelayDir(PathBuf);

impl RelayDir {
    fn create() -> anyhow::Result<Self> {
        use std::os::unix::fs::DirBuilderExt;
        let mut bytes = [0u8; 8];
        // SAFETY: getrandom(2) fills the buffer it is given, of the length it is given.
        let n = unsafe { libc::getrandom(bytes.as_mut_ptr().cast(), bytes.len(), 0) };
        if n != bytes.len() as isize {
            bail!("getrandom failed: {}", std::io::Error::last_os_error());
        }
        let name = format!("libero-net-{}", bytes.iter().map(|b| format!("{b:02x}")).collect::<String>());
        let tmp = std::env::temp_dir();
        // Leave room for `/mcp.sock` under the 107-byte limit.
        let base = if tmp.as_os_str().len() + name.len() + 10 < 100 { tmp } else { PathBuf::from("/tmp") };
        let dir = base.join(name);
        std::fs::DirBuilder::new().mode(0o700).create(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
        Ok(Self(dir))
    }
}

impl Drop for RelayDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

impl Contained {
    /// The command to start (environment replaced by the launch's; the report pipe's write end inherited).
    pub fn command(&self) -> Command {
        let mut cmd = Command::new(&self.argv[0]);
        cmd.args(&self.argv[1..]).env_clear().envs(self.env.iter().map(|(k, v)| (k, v)));
        if let Some(w) = &self.report_write {
            let fd = w.as_raw_fd();
            // SAFETY: runs in the child between fork and exec; fcntl(2) is async-signal-safe.
            unsafe {
                cmd.pre_exec(move || {
                    if libc::fcntl(fd, libc::F_SETFD, 0) < 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                    Ok(())
                });
            }
        }
        cmd
    }

    /// After the spawn: the runner's copy of the pipe's write end is closed, so the report ends when the
    /// sandbox's first process closes its copy.
    /// The directory of the relay sockets (gone once this is dropped).
    pub fn relay_dir(&self) -> Option<&Path> {
        self.relay_dir.as_ref().map(|d| d.0.as_path())
    }

    pub fn spawned(&mut self) {
        self.report_write = None;
    }

    /// The sandbox's report, as its first process wrote it (bounded; `None` without a sandbox, or when nothing
    /// came within `wait`).
    pub fn report(&mut self, wait: Duration) -> Option<Value> {
        self.report_write = None;
        let fd = self.report_read.take()?;
        rustix::fs::fcntl_setfl(&fd, rustix::fs::OFlags::NONBLOCK).ok()?;
        let mut file = std::fs::File::from(fd);
        let (mut buf, t0) = (Vec::new(), Instant::now());
        loop {
            use std::io::Read;
            let mut chunk = [0u8; 8192];
            match file.read(&mut chunk) {
                Ok(0) => break,
                Ok(n) => {
                    buf.extend_from_slice(&chunk[..n]);
                    if buf.len() as u64 > MAX_REPORT_BYTES {
                        return None;
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock && t0.elapsed() < wait => {
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(_) => break,
            }
        }
        serde_json::from_slice(&buf).ok()
    }
}

fn set_mode(p: &Path, mode: u32) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(p, std::fs::Permissions::from_mode(mode)).with_context(|| format!("cannot chmod {}", p.display()))
}

/// Hands a freshly prepared tree to the agent's user (no agent has run in it yet; links are changed, never
/// followed), leaving the entries named in `keep` (and what is below them) to the server.
fn give_to_agent(root: &Path, (uid, gid): (u32, u32), keep: &[&str]) -> anyhow::Result<()> {
    let mut todo = vec![root.to_path_buf()];
    while let Some(p) = todo.pop() {
        std::os::unix::fs::lchown(&p, Some(uid), Some(gid)).with_context(|| format!("cannot give {} to the agent", p.display()))?;
        let meta = std::fs::symlink_metadata(&p)?;
        if meta.is_dir() {
            for e in std::fs::read_dir(&p)? {
                let e = e?;
                if p == root && keep.iter().any(|k| e.file_name() == *k) {
                    continue;
                }
                todo.push(e.path());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Endpoints as a harness names them below the API base's path (the runner's `Harness::model_api_endpoints`).
    fn endpoints(base: &str) -> Vec<(&'static str, String)> {
        let base = base.trim_end_matches('/');
        vec![("POST", format!("{base}/responses")), ("GET", format!("{base}/models"))]
    }

    #[test]
    fn the_agent_sees_its_server_s_port_and_the_gateway_s_base_with_the_upstream_path() {
        let p = NetPlan::new("http://127.0.0.1:41234/mcp/ep-1", Some("https://api.example.com/v1/"), endpoints, false).unwrap();
        assert_eq!((p.mcp_port, p.mcp_target.to_string().as_str(), p.mcp_host_name.as_deref()), (41234, "127.0.0.1:41234", None));
        assert_eq!(p.agent_api_base().as_deref(), Some("http://127.0.0.1:18790/v1"));
        assert!(p.allowed.is_empty(), "the model API is reached through the base URL, never a tunnel: {:?}", p.allowed);
        let routes: Vec<String> = p.routes.iter().map(ToString::to_string).collect();
        assert_eq!(routes, ["POST /v1/responses", "GET /v1/models"], "the endpoints below the upstream's path only");
        assert_eq!(p.describe()["model_api"]["routes"], serde_json::json!(routes));
        let env = p.proxy_env();
        assert!(env.contains(&("HTTPS_PROXY".into(), "http://127.0.0.1:18790".into())));
        assert!(env.iter().any(|(k, v)| k == "NO_PROXY" && v.contains("127.0.0.1")));
        assert!(env.contains(&("LIBERO_MODEL_API_BASE".into(), "http://127.0.0.1:18790/v1".into())));
        // On the gateway's default port, the MCP endpoint keeps it; through npx: the registry too.
        let q = NetPlan::new("http://localhost:18790/mcp/x", Some("https://api.anthropic.com"), endpoints, true).unwrap();
        assert_eq!(q.model_port, 18791, "never the MCP endpoint's port");
        assert_eq!(q.agent_api_base().as_deref(), Some("http://127.0.0.1:18791"));
        assert_eq!(q.allowed, vec![("registry.npmjs.org".to_owned(), 443)], "the npm registry for npx, not the model API");
        assert!(q.mcp_host_name.is_none(), "localhost is loopback already");
        assert!(NetPlan::new("http://10.1.2.3:8080/mcp/x", None, endpoints, false).is_err(), "a remote IP cannot be mapped");
        let none = NetPlan::new("http://127.0.0.1:8080/mcp/x", None, endpoints, false).unwrap();
        assert!(none.upstream.is_none() && none.allowed.is_empty() && none.routes.is_empty() && none.agent_api_base().is_none());
    }

    #[test]
    fn a_server_named_by_host_name_is_loopback_inside() {
        let p = NetPlan::new("http://localhost:8080/mcp/x", None, endpoints, false).unwrap();
        assert!(p.mcp_target.ip().is_loopback());
        let mut named = p.clone();
        named.mcp_host_name = Some("gpu-7.lab".into());
        assert!(named.hosts_file().contains("127.0.0.1\tgpu-7.lab\n"));
        assert!(named.proxy_env().iter().any(|(k, v)| k == "NO_PROXY" && v.ends_with(",gpu-7.lab")));
    }
}
