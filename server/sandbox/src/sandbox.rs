//! The agent's sandbox: bubblewrap with fresh mount, PID, IPC, UTS and network namespaces. The agent sees the
//! system directories read-only (`/usr`, `/lib*`, `/bin`, `/sbin`, `/etc`), its own CLI's install, the files it is
//! given to read, and writes only its workspace and its session home. Everything else — `tasks/`, `assets/`, the
//! asset cache, the server's data directory and store, other episodes' workspaces and run directories, the batch
//! directory — does not exist inside. Its network namespace holds only `lo`: the first process inside
//! (`libero-agent sandbox-net`, [`crate::sandbox_net`]) relays the loopback addresses of its MCP endpoint and its
//! model API to Unix sockets the runner owns (bound at [`RELAY_DIR`]), and nothing else of any host is reachable.
//!
//! The agent holds no capability and cannot gain one. As an ordinary user the sandbox is a user namespace of that
//! user with every capability dropped and further user namespaces disabled. As root, bubblewrap builds the
//! namespaces with root's rights (so it can bind what only root can read, such as CLIs installed under `/root`),
//! keeps only CAP_SETUID/CAP_SETGID/CAP_SETPCAP for `sandbox-net`, which empties the bounding set, switches to the
//! unprivileged [`AGENT_UID`]/[`AGENT_GID`], clears every capability set, sets no_new_privs and installs a seccomp
//! filter that refuses new namespaces before it starts the agent. Read-only mounts then stay read-only: remounting
//! needs CAP_SYS_ADMIN, which no process of the agent has in any namespace.
//!
//! The agent's toolbox ([`crate::toolbox`]), when the run has one, is shown read-only at [`toolbox::INSIDE`].
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, bail};

use crate::host_paths::SYSTEM_DIRS;
pub use crate::host_paths::{which, which_in};
use crate::resources::{Resources, RolloutCage};
use crate::toolbox::{self, Toolbox};


/// The host uid and gid a sandboxed agent runs as when the runner is root (`nobody`/`nogroup` on Debian).
pub const AGENT_UID: u32 = 65534;
pub const AGENT_GID: u32 = 65534;

/// The size of the sandbox's in-memory `/tmp` (2 GiB).
const TMP_BYTES: &str = "2147483648";

/// Where the runner's relay sockets appear inside the sandbox.
pub const RELAY_DIR: &str = "/run/libero";

/// A working bubblewrap.
#[derive(Debug, Clone)]
pub struct Sandbox {
    pub bwrap: PathBuf,
    pub version: String,
    /// The unprivileged host ids the agent is switched to (`Some` when the runner is root; an ordinary user's
    /// agent keeps that user's ids inside a user namespace of its own).
    pub agent_ids: Option<(u32, u32)>,
    /// The agent's Python toolbox, bound read-only at [`toolbox::INSIDE`] (`None`: the system's python3 alone).
    pub toolbox: Option<Toolbox>,
    /// Per-rollout caps on processes, memory, CPU and disk, and the agents' uid range ([`crate::resources`]);
    /// `None`: unconfined (`--unconfined-resources` where they cannot be enforced).
    pub resources: Option<Resources>,
    /// A host directory shown as the sandbox's `/tmp` (and `/dev/shm`): the rollout's capped disk. `None`: an
    /// in-memory tmpfs of [`TMP_BYTES`].
    pub tmp: Option<PathBuf>,
}

/// What one agent may see.
#[derive(Debug, Clone, Default)]
pub struct SandboxSpec {
    /// Read-write (the workspace, the session home).
    pub writable: Vec<PathBuf>,
    /// Read-only extras outside the system directories (the CLI's install, this binary and its libraries).
    pub readable: Vec<PathBuf>,
    /// Host files shown read-only at another path inside (`/etc/hosts`).
    pub files: Vec<(PathBuf, PathBuf)>,
    /// A host directory shown at [`RELAY_DIR`] (the runner's relay sockets).
    pub relay_dir: Option<PathBuf>,
    pub cwd: PathBuf,
}

impl Sandbox {
    /// Checks that bubblewrap exists and can build a sandbox here (user namespaces may be disabled, e.g. in
    /// some containers); the error says what failed and that `--no-sandbox` is the explicit way out.
    pub fn detect() -> anyhow::Result<Self> {
        let bwrap = which("bwrap").context(
            "bubblewrap (`bwrap`) is not installed (Debian: apt-get install bubblewrap); pass --no-sandbox to run \
             agents without isolation",
        )?;
        let version = Command::new(&bwrap)
            .arg("--version")
            .output()
            .ok()
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
            .unwrap_or_default();
        // SAFETY: geteuid(2) has no preconditions.
        let agent_ids = (unsafe { libc::geteuid() } == 0).then_some((AGENT_UID, AGENT_GID));
        let s = Self { bwrap, version, agent_ids, toolbox: None, resources: None, tmp: None };
        let probe = s.command(&["/bin/true".to_owned()], &SandboxSpec { cwd: "/".into(), ..Default::default() });
        let out = Command::new(&probe[0]).args(&probe[1..]).output().context("cannot run bwrap")?;
        if !out.status.success() {
            bail!(
                "bubblewrap cannot create a sandbox on this machine ({}): {}; user namespaces may be disabled \
                 (kernel.unprivileged_userns_clone / user.max_user_namespaces, or the container's seccomp policy). \
                 Pass --no-sandbox to run agents without isolation",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            );
        }
        Ok(s)
    }

    /// The same sandbox with `toolbox` as the agent's Python.
    pub fn with_toolbox(self, toolbox: Option<Toolbox>) -> Self {
        Self { toolbox, ..self }
    }

    /// The same sandbox with per-rollout caps (`None`: unconfined).
    pub fn with_resources(self, resources: Option<Resources>) -> Self {
        Self { resources, ..self }
    }

    /// This sandbox for one rollout: the agent runs as the cage's own uid, with the cage's disk as `/tmp`.
    pub fn for_cage(&self, cage: Option<&RolloutCage>) -> Self {
        let mut s = self.clone();
        if let Some(c) = cage {
            s.agent_ids = c.ids.or(s.agent_ids);
            s.tmp = c.tmp();
        }
        s
    }

    /// How the sandbox isolates, for the harness manifest (what the agent itself reports comes beside it).
    pub fn describe(&self) -> serde_json::Value {
        serde_json::json!({
            "bubblewrap": self.version,
            "namespaces": ["mount", "pid", "ipc", "uts", "net", "cgroup"],
            "identity": match self.agent_ids {
                Some((u, g)) => serde_json::json!({"runner": "root", "agent_uid": u, "agent_gid": g,
                    "uid_per_rollout": self.resources.as_ref().is_some_and(|r| r.agent_uids.is_some()),
                    "how": "bubblewrap as root keeps CAP_SETUID/SETGID/SETPCAP for sandbox-net, which drops the bounding set, switches to the rollout's own ids, clears every capability set, joins a fresh session keyring, sets no_new_privs and the seccomp allow-list"}),
                None => serde_json::json!({"runner": "unprivileged", "how": "a user namespace of the runner's user, every capability dropped, further user namespaces disabled, a fresh session keyring, no_new_privs and the seccomp allow-list"}),
            },
            "seccomp": crate::seccomp::describe(),
            "resources": self.resources.as_ref().map(Resources::describe),
            "network": "own namespace with only lo; sandbox-net relays the MCP endpoint and the model API to the runner's Unix sockets",
        })
    }

    /// The argv running `argv` inside the sandbox.
    pub fn command(&self, argv: &[String], spec: &SandboxSpec) -> Vec<String> {
        let mut a: Vec<String> = vec![self.bwrap.to_string_lossy().into_owned()];
        let mut push = |xs: &[&str]| a.extend(xs.iter().map(|s| (*s).to_owned()));
        push(&["--unshare-pid", "--unshare-ipc", "--unshare-uts", "--unshare-net", "--unshare-cgroup-try"]);
        push(&["--die-with-parent", "--new-session", "--hostname", "libero-agent"]);
        if self.agent_ids.is_some() {
            // Root builds the namespaces; sandbox-net keeps only what it needs to become the agent's user.
            push(&["--cap-drop", "ALL", "--cap-add", "CAP_SETUID", "--cap-add", "CAP_SETGID", "--cap-add", "CAP_SETPCAP"]);
        } else {
            push(&["--unshare-user", "--disable-userns", "--cap-drop", "ALL"]);
        }
        for dir in SYSTEM_DIRS {
            let p = Path::new(dir);
            match std::fs::symlink_metadata(p) {
                Ok(m) if m.file_type().is_symlink() => {
                    if let Ok(target) = std::fs::read_link(p) {
                        push(&["--symlink", &target.to_string_lossy(), dir]);
                    }
                }
                Ok(_) => push(&["--ro-bind", dir, dir]),
                Err(_) => {}
            }
        }
        push(&["--dev", "/dev", "--proc", "/proc"]);
        match &self.tmp {
            // The rollout's capped disk: what the agent writes to /tmp and /dev/shm counts against the same cap.
            Some(tmp) => {
                let t = tmp.to_string_lossy();
                push(&["--bind", &t, "/tmp", "--bind", &t, "/dev/shm"]);
            }
            // The sandbox's /tmp lives in memory: bounded, so an agent filling it cannot take the host's memory.
            None => push(&["--perms", "1777", "--size", TMP_BYTES, "--tmpfs", "/tmp"]),
        }
        push(&["--tmpfs", "/run"]);
        // bubblewrap makes missing parents of a mount point private (0700) when it runs as root: the agent's user
        // could not reach its own workspace or CLI below them. Every parent is made first, world-searchable.
        let relay = spec.relay_dir.as_ref().map(|_| PathBuf::from(RELAY_DIR));
        let toolbox_inside = self.toolbox.as_ref().map(|_| PathBuf::from(toolbox::INSIDE));
        let dests = spec
            .readable
            .iter()
            .chain(&spec.writable)
            .chain(spec.files.iter().map(|(_, inside)| inside))
            .chain(relay.iter())
            .chain(toolbox_inside.iter());
        let mut parents: Vec<&Path> = dests
            .flat_map(|p| p.ancestors().skip(1))
            .filter(|d| *d != Path::new("/") && !d.as_os_str().is_empty() && !SYSTEM_DIRS.iter().any(|s| d.starts_with(s)))
            .collect();
        parents.sort();
        parents.dedup();
        for d in parents {
            if d != Path::new("/tmp") && d != Path::new("/run") {
                push(&["--perms", "0755", "--dir", &d.to_string_lossy()]);
            }
        }
        if let Some(tb) = &self.toolbox {
            push(&["--ro-bind", &tb.root.to_string_lossy(), toolbox::INSIDE]);
        }
        // Later mounts win: system first, then the extras, then the writable directories. A link stays a link
        // (npm's `node_modules/.bin/x -> ../pkg/cli.js`): a script finds its modules relative to its real path.
        for p in &spec.readable {
            let s = p.to_string_lossy();
            if SYSTEM_DIRS.iter().any(|d| p.starts_with(d)) {
                continue;
            }
            match std::fs::read_link(p) {
                Ok(target) => push(&["--symlink", &target.to_string_lossy(), &s]),
                Err(_) => push(&["--ro-bind-try", &s, &s]),
            }
        }
        for p in &spec.writable {
            let s = p.to_string_lossy();
            push(&["--bind", &s, &s]);
        }
        for (host, inside) in &spec.files {
            push(&["--ro-bind", &host.to_string_lossy(), &inside.to_string_lossy()]);
        }
        if let Some(dir) = &spec.relay_dir {
            push(&["--ro-bind", &dir.to_string_lossy(), RELAY_DIR]);
        }
        push(&["--chdir", &spec.cwd.to_string_lossy(), "--"]);
        a.extend(argv.iter().cloned());
        a
    }
}

/// The `libero-agent` binary `agent_exe` (the runner's `agent_exe`) and the shared libraries this process loaded from
/// outside the system directories (libmujoco from the asset cache, which every binary of the project links): what
/// a sandboxed `libero-agent agent`/`mcp-stdio` needs to start. Only these files, not their folders, so the
/// cache's assets stay invisible.
pub fn own_binary_files(agent_exe: &Path) -> Vec<PathBuf> {
    let mut out = vec![agent_exe.to_path_buf()];
    if let Ok(maps) = std::fs::read_to_string("/proc/self/maps") {
        for line in maps.lines() {
            let Some(path) = line.split_whitespace().nth(5) else { continue };
            let p = PathBuf::from(path);
            if path.starts_with('/') && path.contains(".so") && !SYSTEM_DIRS.iter().any(|d| p.starts_with(d)) && !out.contains(&p) {
                out.push(p);
            }
        }
    }
    out
}

/// The install of a CLI named `program`: the path found on the search path `path`, the links to the executable, the
/// executable and, for npm-installed CLIs, its package directory and its dependencies'; for a script, the same for the
/// interpreter its `#!` line names (`#!/usr/bin/env node` → the `node` on `path`, e.g. a Node 22 installed next to
/// the CLI). Paths inside the system directories are visible anyway.
pub fn cli_install_paths(program: &str, path: &std::ffi::OsStr) -> Vec<PathBuf> {
    let Some(found) = which_in(program, path) else { return Vec::new() };
    let mut out = install_of(&found);
    let resolved = std::fs::canonicalize(&found).unwrap_or(found);
    if let Some(interpreter) = script_interpreter(&resolved).and_then(|i| which_in(&i, path)) {
        out.extend(install_of(&interpreter).into_iter().filter(|p| !out.contains(p)).collect::<Vec<_>>());
    }
    out
}

/// `path`, every link on the way to the executable, the executable, and for an npm package its directory and
/// those of its dependencies.
fn install_of(path: &Path) -> Vec<PathBuf> {
    let mut out = vec![path.to_path_buf()];
    let mut at = path.to_path_buf();
    while let Ok(target) = std::fs::read_link(&at) {
        at = at.parent().map(|d| d.join(&target)).unwrap_or(target);
        out.push(at.clone());
    }
    let resolved = std::fs::canonicalize(path).unwrap_or(at);
    if let Some(pkg) = npm_package_dir(&resolved) {
        out.push(pkg.to_path_buf());
        out.extend(npm_dependency_dirs(pkg));
    }
    out.push(resolved);
    out.dedup();
    out
}

/// The npm package a file belongs to: `…/node_modules/<name>` or `…/node_modules/@scope/<name>`.
fn npm_package_dir(file: &Path) -> Option<&Path> {
    file.ancestors().find(|a| match a.parent() {
        Some(p) if p.ends_with("node_modules") => true,
        Some(p) => p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('@')) && p.parent().is_some_and(|g| g.ends_with("node_modules")),
        None => false,
    })
}

/// The directories of a package's dependencies and optional dependencies, transitively, found as Node finds them:
/// the package's own `node_modules` first, then each ancestor's (npm hoists most of them to the top).
fn npm_dependency_dirs(pkg: &Path) -> Vec<PathBuf> {
    let (mut out, mut todo) = (Vec::<PathBuf>::new(), vec![pkg.to_path_buf()]);
    while let Some(dir) = todo.pop() {
        let Ok(text) = std::fs::read_to_string(dir.join("package.json")) else { continue };
        let Ok(manifest) = serde_json::from_str::<serde_json::Value>(&text) else { continue };
        for key in ["dependencies", "optionalDependencies"] {
            for name in manifest[key].as_object().into_iter().flat_map(|m| m.keys()) {
                let found = dir.ancestors().map(|a| a.join("node_modules").join(name)).find(|p| p.is_dir());
                if let Some(found) = found.filter(|f| !out.contains(f)) {
                    out.push(found.clone());
                    todo.push(found);
                }
            }
        }
    }
    out
}

/// The program a script's `#!` line runs: `#!/usr/bin/env node` → `node`, `#!/opt/x/bin/node` → that path.
fn script_interpreter(script: &Path) -> Option<String> {
    use std::io::Read;
    let mut head = [0u8; 256];
    let n = std::fs::File::open(script).ok()?.read(&mut head).ok()?;
    let line = std::str::from_utf8(&head[..n]).ok()?.strip_prefix("#!")?.lines().next()?.to_owned();
    let mut words = line.split_whitespace().filter(|w| !w.starts_with('-'));
    let first = words.next()?;
    if first.ends_with("/env") { words.next().map(str::to_owned) } else { Some(first.to_owned()) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_binds_only_what_the_spec_names() {
        let s = Sandbox { bwrap: "/usr/bin/bwrap".into(), version: String::new(), agent_ids: None, toolbox: None, resources: None, tmp: None };
        let spec = SandboxSpec {
            writable: vec!["/tmp/ws/w1".into()],
            readable: vec!["/usr/bin/codex".into(), "/opt/tool".into()],
            cwd: "/tmp/ws/w1".into(),
            ..Default::default()
        };
        let a = s.command(&["sh".into(), "-c".into(), "true".into()], &spec);
        let joined = a.join(" ");
        assert!(joined.contains("--bind /tmp/ws/w1 /tmp/ws/w1"));
        assert!(joined.contains("--ro-bind-try /opt/tool /opt/tool"));
        assert!(!joined.contains("/usr/bin/codex"), "inside /usr already");
        assert!(joined.contains("--ro-bind /usr /usr") && joined.contains("--unshare-user --disable-userns --cap-drop ALL"));
        assert!(joined.contains("--unshare-net") && joined.contains("--perms 0755 --dir /opt") && joined.contains("--perms 0755 --dir /tmp/ws"));
        assert!(joined.ends_with("--chdir /tmp/ws/w1 -- sh -c true"));
        // The workspace's bind comes after the /tmp tmpfs, so it is not hidden by it.
        let tmpfs = a.iter().position(|x| x == "/tmp").unwrap();
        let bind = a.iter().position(|x| x == "/tmp/ws/w1").unwrap();
        assert!(tmpfs < bind);
    }

    /// As root, bubblewrap builds the namespaces and keeps only what `sandbox-net` needs to become the agent's
    /// unprivileged user; as an ordinary user, a user namespace with everything dropped and no nested ones.
    #[test]
    fn a_root_runner_s_sandbox_keeps_only_the_capabilities_to_drop_to_the_agent_s_user() {
        let spec = SandboxSpec { writable: vec!["/root/b/home".into()], cwd: "/".into(), relay_dir: Some("/root/b/net".into()), ..Default::default() };
        let root = Sandbox { bwrap: "/usr/bin/bwrap".into(), version: String::new(), agent_ids: Some((AGENT_UID, AGENT_GID)), toolbox: None, resources: None, tmp: None };
        let joined = root.command(&["x".into()], &spec).join(" ");
        assert!(joined.contains("--cap-drop ALL --cap-add CAP_SETUID --cap-add CAP_SETGID --cap-add CAP_SETPCAP"), "{joined}");
        assert!(!joined.contains("--unshare-user") && joined.contains("--unshare-net"), "{joined}");
        assert!(joined.contains("--perms 0755 --dir /root ") && joined.contains("--perms 1777 --size 2147483648 --tmpfs /tmp"), "{joined}");
        assert!(joined.contains(&format!("--ro-bind /root/b/net {RELAY_DIR}")), "{joined}");
        let user = Sandbox { agent_ids: None, ..root };
        let joined = user.command(&["x".into()], &spec).join(" ");
        assert!(joined.contains("--unshare-user --disable-userns --cap-drop ALL") && !joined.contains("--cap-add"), "{joined}");
    }

    /// The cache lies below the runner's home (`/root`, 0700): the agent's user reaches the toolbox at a neutral
    /// path of its own, read-only, with world-searchable parents.
    #[test]
    fn the_toolbox_is_bound_read_only_at_a_neutral_path() {
        let tb = Toolbox {
            name: "t".into(),
            root: "/root/.cache/libero-agent/toolbox-t-0".into(),
            interpreter: "/usr/bin/python3.11".into(),
            python: None,
            packages: Vec::new(),
            size_bytes: None,
            project: true,
        };
        let s = Sandbox { bwrap: "/usr/bin/bwrap".into(), version: String::new(), agent_ids: Some((AGENT_UID, AGENT_GID)), toolbox: None, resources: None, tmp: None };
        let spec = SandboxSpec { cwd: "/".into(), ..Default::default() };
        assert!(!s.command(&["x".into()], &spec).join(" ").contains(toolbox::INSIDE));
        let joined = s.with_toolbox(Some(tb)).command(&["x".into()], &spec).join(" ");
        assert!(joined.contains("--perms 0755 --dir /opt --ro-bind /root/.cache/libero-agent/toolbox-t-0 /opt/libero-toolbox"), "{joined}");
        assert!(!joined.contains("--dir /root"), "nothing of the runner's home is made: {joined}");
    }

    /// An npm install as the runner sees it: `.bin/tool -> ../@scope/tool/cli.js`, a script run by `node`.
    #[test]
    fn an_npm_cli_is_exposed_as_its_links_package_and_interpreter() {
        let dir = tempfile::tempdir().unwrap();
        let nm = dir.path().join("node_modules");
        std::fs::create_dir_all(nm.join("@scope/tool/bin")).unwrap();
        std::fs::create_dir_all(nm.join(".bin")).unwrap();
        std::fs::write(nm.join("@scope/tool/bin/cli.js"), "#!/usr/bin/env -S node --no-warnings\nimport './x.js'\n").unwrap();
        std::fs::write(nm.join("@scope/tool/package.json"), r#"{"dependencies": {"ws": "^8"}, "optionalDependencies": {"pty": "1"}}"#).unwrap();
        std::fs::create_dir_all(nm.join("ws/lib")).unwrap();
        std::fs::write(nm.join("ws/package.json"), r#"{"dependencies": {"nested": "1"}}"#).unwrap();
        std::fs::create_dir_all(nm.join("ws/node_modules/nested")).unwrap();
        std::fs::create_dir_all(nm.join("unrelated")).unwrap();
        std::os::unix::fs::symlink("../@scope/tool/bin/cli.js", nm.join(".bin/tool")).unwrap();
        let paths = install_of(&nm.join(".bin/tool"));
        assert_eq!(paths[0], nm.join(".bin/tool"));
        // The package and its dependency closure (hoisted, nested; a missing optional one skipped), nothing else.
        for dir in ["@scope/tool", "ws", "ws/node_modules/nested"] {
            assert!(paths.contains(&nm.join(dir)), "{dir}: {paths:?}");
        }
        assert!(!paths.iter().any(|p| p.ends_with("unrelated") || p.ends_with("pty") || *p == nm.join("@scope")), "{paths:?}");
        assert_eq!(script_interpreter(&nm.join("@scope/tool/bin/cli.js")).as_deref(), Some("node"));
        std::fs::write(dir.path().join("native"), b"\x7fELF\x02\x01").unwrap();
        assert_eq!(script_interpreter(&dir.path().join("native")), None);
        // Inside the sandbox the link is recreated as a link, so the script resolves its modules where it lives.
        let s = Sandbox { bwrap: "/usr/bin/bwrap".into(), version: String::new(), agent_ids: None, toolbox: None, resources: None, tmp: None };
        let spec = SandboxSpec { readable: paths, cwd: "/".into(), ..Default::default() };
        let joined = s.command(&["tool".into()], &spec).join(" ");
        assert!(joined.contains(&format!("--symlink ../@scope/tool/bin/cli.js {}", nm.join(".bin/tool").display())), "{joined}");
        assert!(joined.contains(&format!("--ro-bind-try {0} {0}", nm.join("@scope/tool").display())), "{joined}");
    }
}
