//! Issue 30's proof that the sandbox holds against the runner being root and against the network: a red-team agent
//! (`tests/redteam/escape.py`) runs where a real agent runs — `libero-agent run --harness command`, inside the
//! bubblewrap sandbox, against the runner's in-process server — and tries what an attacker would: remount the
//! read-only system, the binary and the grader's code read-write, mount, chmod, write the `libero-agent` binary,
//! read `/etc/shadow`, make new namespaces to regain capabilities, ptrace and signal a host process, open raw
//! sockets, reach a decoy service on the host's loopback (IPv4 and IPv6), PostgreSQL's port and other hosts, and
//! tunnel through the runner's proxy to anything off its allow-list; use the kernel's keyrings, io_uring, perf
//! events, bpf and userfaultfd (issue 47: the seccomp allow-list refuses them); and, where the runner is root and
//! caps each rollout, fork past the process cap, allocate past the memory cap and fill the workspace, /tmp and
//! $HOME past the disk cap. Every attempt must be refused, the decoy must see no connection, and the agent must
//! still reach exactly its two addresses: its episode's MCP endpoint (the reference agent then plays the episode to
//! a valid outcome) and its model API (a scripted endpoint on the host's loopback, reached only through the
//! runner's gateway, which records the request). The harness manifest records the sandbox's ids, capability sets
//! and mounts as the agent's first process saw them, the caps and what the agent used of them. The workspace goes
//! with the rollout's disk, so the red team's report is the line it printed on stdout (`command_stdout.log`).
use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use libero_records::batch_doc::harness_manifest::HarnessManifest;
use libero_testkit::{cache_dir, repo_root};
use serde_json::Value;

mod common;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-agent")
}

/// A host loopback service the agent must not reach: counts every connection it accepts.
fn decoy(listener: TcpListener) -> Arc<AtomicUsize> {
    let hits = Arc::new(AtomicUsize::new(0));
    let h = hits.clone();
    std::thread::spawn(move || {
        for c in listener.incoming().flatten() {
            h.fetch_add(1, Ordering::SeqCst);
            drop(c);
        }
    });
    hits
}

/// A scripted model API on the host's loopback: answers every request with a model list and counts them.
fn model_api() -> (u16, Arc<AtomicUsize>) {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    let hits = Arc::new(AtomicUsize::new(0));
    let h = hits.clone();
    std::thread::spawn(move || {
        for mut c in l.incoming().flatten() {
            h.fetch_add(1, Ordering::SeqCst);
            let mut buf = [0u8; 8192];
            let _ = c.set_read_timeout(Some(Duration::from_secs(5)));
            let _ = c.read(&mut buf);
            let body = r#"{"object":"list","data":[{"id":"scripted-model"}]}"#;
            let _ = write!(c, "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len());
        }
    });
    (port, hits)
}

/// How the runner is started: as this test's user, or as an ordinary user (from root: `setpriv` to nobody, with a
/// hard-linked copy of the asset cache that user can read and the test's directory given to it).
struct Runner {
    as_user: Option<(u32, u32)>,
    cache: Option<PathBuf>,
    home: Option<PathBuf>,
}

impl Runner {
    /// Whether this runner caps each rollout (root: a cgroup, a uid and a size-capped disk per rollout).
    fn caps(&self) -> bool {
        // SAFETY: getuid(2) has no preconditions.
        self.as_user.is_none() && unsafe { libc::getuid() } == 0
    }

    fn command(&self) -> Command {
        let Some((uid, gid)) = self.as_user else { return Command::new(bin()) };
        let mut c = Command::new("setpriv");
        c.args(["--reuid", &uid.to_string(), "--regid", &gid.to_string(), "--clear-groups", "--"]).arg(bin());
        let cache = self.cache.as_ref().unwrap();
        c.env("LIBERO_AGENT_CACHE", cache).env("LD_LIBRARY_PATH", cache.join("mujoco-3.17.0/lib")).env("HOME", self.home.as_ref().unwrap());
        c
    }
}

/// The caps a root runner gives the red team's rollout: small, so the fork, memory and disk attacks run fast.
const MAX_PROCESSES: u64 = 256;
const MEMORY_BYTES: u64 = 512 << 20;
const DISK_BYTES: u64 = 256 << 20;
/// `--agent-uids`' default: the host uids a root runner's agents run as, one per rollout.
const AGENT_UIDS: std::ops::RangeInclusive<u64> = 3_000_000..=3_065_535;

fn run_batch(runner: &Runner, batch: &Path, workspaces: &Path, credentials: &Path, agent_cmd: &str) {
    let mut cmd = runner.command();
    cmd.args(["run", "--experiment", "main_table", "--harness", "command", "--model", "escape", "--tasks", "T14", "--reps", "1"])
        .args(["--agent-cmd", agent_cmd, "--wall-time-s", "300", "--batch"])
        .arg(batch)
        .arg("--workspace-root")
        .arg(workspaces)
        .arg("--credentials-file")
        .arg(credentials);
    if runner.caps() {
        cmd.args(["--agent-max-processes", &MAX_PROCESSES.to_string(), "--agent-memory", "512MiB", "--agent-disk", "256MiB"]);
    } else {
        // An ordinary user's runner cannot mount each rollout's disk nor switch the agent to a uid of its own.
        cmd.arg("--unconfined-resources");
    }
    let mut child = cmd.stdout(Stdio::null()).stderr(Stdio::inherit()).spawn().expect("run libero-agent run");
    common::wait_success(&mut child, Duration::from_secs(600), "the batch");
}

/// Root's asset cache is private to root: a copy of hard links (no data copied) in directories nobody can read.
fn cache_for(dir: &Path, uid: u32, gid: u32) -> PathBuf {
    let copy = dir.join("cache");
    std::fs::create_dir(&copy).unwrap();
    let toolbox = libero_sandbox::toolbox::project_dir_name().expect("toolbox name");
    for part in ["mujoco-3.17.0", "robosuite-1.4.0", "hf-libero-0.1.4", "libero-assets-0.1.0", toolbox.as_str()] {
        let st = Command::new("cp").arg("-al").arg(cache_dir().join(part)).arg(&copy).status().unwrap();
        assert!(st.success(), "cp -al {part}");
    }
    let st = Command::new("find").arg(&copy).args(["-type", "d", "-exec", "chmod", "0755", "{}", "+"]).status().unwrap();
    assert!(st.success());
    std::os::unix::fs::chown(dir, Some(uid), Some(gid)).unwrap();
    copy
}

#[test]
fn an_agent_in_the_sandbox_holds_no_capability_and_reaches_only_its_endpoint_and_model_api() {
    let dir = tempfile::tempdir().unwrap();
    escape_attempt(dir.path(), &Runner { as_user: None, cache: None, home: None });
}

/// The same attacks with the runner started by an ordinary user (nobody, switched to from root; when this test
/// itself runs as an ordinary user, the test above is that case already).
#[test]
fn an_agent_of_an_ordinary_user_s_runner_is_held_the_same_way() {
    // SAFETY: getuid(2) has no preconditions.
    if unsafe { libc::getuid() } != 0 {
        eprintln!("not root: an_agent_in_the_sandbox_holds_no_capability_… ran as an ordinary user");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (uid, gid) = (65534, 65534);
    let cache = cache_for(dir.path(), uid, gid);
    let home = dir.path().join("home");
    std::fs::create_dir(&home).unwrap();
    std::os::unix::fs::chown(&home, Some(uid), Some(gid)).unwrap();
    escape_attempt(dir.path(), &Runner { as_user: Some((uid, gid)), cache: Some(cache), home: Some(home) });
}

fn escape_attempt(dir: &Path, runner: &Runner) {
    let decoy_v4 = TcpListener::bind("127.0.0.1:0").unwrap();
    let decoy_port = decoy_v4.local_addr().unwrap().port();
    let mut hits = vec![decoy(decoy_v4)];
    if let Ok(v6) = TcpListener::bind(("::1", decoy_port)) {
        hits.push(decoy(v6));
    }
    let (model_port, model_hits) = model_api();
    let credentials = dir.join("credentials");
    std::fs::write(&credentials, format!("APIURL=http://127.0.0.1:{model_port}/v1\nAPIKEY=sk-escape-test-key-0123\n")).unwrap();
    let marker = format!("libero-escape-{}", std::process::id());
    // SAFETY: getuid(2) has no preconditions.
    let runner_uid = runner.as_user.map(|(u, _)| u).unwrap_or_else(|| unsafe { libc::getuid() });
    let caps = runner.caps().then(|| serde_json::json!({"max_processes": MAX_PROCESSES, "memory_bytes": MEMORY_BYTES, "disk_bytes": DISK_BYTES}));
    let args = serde_json::json!({"decoy_port": decoy_port, "host_pid": std::process::id(), "runner_uid": runner_uid, "marker": marker,
        "model_api": format!("127.0.0.1:{model_port}"), "caps": caps});
    let script = std::fs::read_to_string(repo_root().join("tests/redteam/escape.py")).unwrap();
    let agent_cmd = format!(
        "python3 - {{libero_agent}} '{args}' <<'PY'\n{script}\nPY\nexec {{libero_agent}} agent --workspace {{workspace}}"
    );
    let batch = dir.join("batch");
    let workspaces = dir.join("ws");
    run_batch(runner, &batch, &workspaces, &credentials, &agent_cmd);

    let rec: Value = serde_json::from_str(std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap().lines().next().unwrap()).unwrap();
    let rollout = batch.join("rollouts/w1_t14_level3");
    let stderr = String::from_utf8_lossy(&std::fs::read(rollout.join("command_stderr.log")).unwrap_or_default()).into_owned();
    let ws = PathBuf::from(rec["workspace"].as_str().unwrap());
    let report = common::marked_line(&rollout.join("command_stdout.log"), "LIBERO-ESCAPE-REPORT ")
        .unwrap_or_else(|| panic!("no escape report on the agent's stdout; its stderr:\n{stderr}"));
    let attempts = report["attempts"].as_array().unwrap();
    // 32 attacks everywhere, 8 raw syscalls on x86_64, 3 on the caps where the runner enforces them.
    let expected = 32 + if std::env::consts::ARCH == "x86_64" { 8 } else { 0 } + if runner.caps() { 3 } else { 0 };
    assert!(attempts.len() >= expected, "{} attempts, {expected} expected: {attempts:#?}", attempts.len());
    let let_through: Vec<&Value> = attempts.iter().filter(|a| a["refused"] != true).collect();
    assert!(let_through.is_empty(), "the sandbox let these through: {let_through:#?}");
    let tried = |prefix: &str| attempts.iter().any(|a| a["attack"].as_str().is_some_and(|n| n.starts_with(prefix)));
    if std::env::consts::ARCH == "x86_64" {
        for attack in ["add_key into the user keyring", "add_key into the session keyring", "keyctl read of the user keyring",
            "keyctl read of the session keyring", "io_uring_setup", "perf_event_open", "bpf(BPF_MAP_CREATE)", "userfaultfd"]
        {
            assert!(tried(attack), "{attack} was not tried: {attempts:#?}");
        }
    }
    assert!(tried("CONNECT to the model API's own host"), "{attempts:#?}");
    for attack in ["fork more than the cap", "allocate", "fill the workspace, /tmp and $HOME"] {
        assert_eq!(tried(attack), runner.caps(), "{attack}: tried exactly where the runner caps the rollout: {attempts:#?}");
    }
    for (i, h) in hits.iter().enumerate() {
        assert_eq!(h.load(Ordering::SeqCst), 0, "the host's decoy {i} was reached");
    }
    assert!(!Path::new("/tmp").join(&marker).exists(), "the sandbox's /tmp is the host's");

    // Its two addresses work: the model API through the gateway, the episode to a valid outcome.
    assert!(report["model_reply"].as_str().is_some_and(|r| r.contains("scripted-model")), "{report}");
    assert_eq!(model_hits.load(Ordering::SeqCst), 1, "exactly the agent's one model request reached the model API");
    assert!(rec["outcome"] == "SUCCESS" || rec["outcome"] == "FAIL", "{rec}\n{stderr}");
    assert_eq!(rec["result_status"], "finished", "{rec}");
    let records = std::fs::read_to_string(rollout.join("sandbox/model_api.jsonl")).unwrap();
    let records: Vec<Value> = records.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(records.iter().any(|r| r["status"] == 200 && r["path"].as_str().is_some_and(|p| p.ends_with("/models"))), "{records:#?}");
    assert!(records.iter().filter(|r| r["status"] == 403).count() >= 4, "the refused tunnels are recorded: {records:#?}");
    assert!(!std::fs::read_to_string(rollout.join("sandbox/model_api.jsonl")).unwrap().contains("sk-escape-test-key"), "no key in the records");

    // The manifest: the sandbox as the agent's first process saw it.
    let manifest = HarnessManifest::read(&rollout).unwrap().expect("the rollout's harness manifest");
    let relay_dir = manifest.relay_dir().expect("the relay sockets' directory");
    assert!(relay_dir.as_os_str().len() < 90 && !relay_dir.exists(), "the relay sockets are removed after the rollout: {}", relay_dir.display());
    let sr = manifest.sandbox_report().expect("the sandbox's report");
    let caps = sr.capabilities.clone().unwrap_or_default();
    for (set, mask) in [("inheritable", &caps.inheritable), ("permitted", &caps.permitted), ("effective", &caps.effective), ("bounding", &caps.bounding), ("ambient", &caps.ambient)] {
        assert_eq!(mask.clone().flatten().as_deref(), Some("0000000000000000"), "{set}: {sr}");
    }
    assert_eq!(sr.no_new_privs, Some(Some(true)), "{sr}");
    assert_eq!(sr.seccomp.clone().flatten().as_deref(), Some("2"), "a seccomp filter: {sr}");
    assert_eq!(sr.network_interfaces.clone(), Some(vec!["lo".to_owned()]), "{sr}");
    assert!(sr.mounts.iter().flatten().any(|x| x.mountpoint.as_deref() == Some("/usr") && x.options.as_deref().is_some_and(|o| o.starts_with("ro"))), "{sr}");
    // The model API is reached through the gateway's base URL alone (metered, its routes only), never a tunnel.
    let network = manifest.network().expect("the network plan");
    assert!(network.proxy_allow_list.as_ref().is_some_and(Vec::is_empty), "{manifest}");
    let model_api = network.model_api.clone().unwrap_or_default();
    assert_eq!(model_api.upstream.flatten(), Some(format!("http://127.0.0.1:{model_port}/v1")), "{manifest}");
    assert!(model_api.routes.iter().flatten().any(|x| x == "GET /v1/models"), "{manifest}");
    let sandbox = manifest.sandbox().expect("the sandbox's description");
    assert!(sandbox.seccomp.as_ref().is_some_and(Value::is_object), "the seccomp policy is described: {manifest}");
    let uid = report["uid"].as_u64().expect("the agent's uid");
    if runner_uid == 0 {
        // As root: the agent is a host uid of the rollout's own, one no host process runs as.
        assert!(AGENT_UIDS.contains(&uid), "the agent's uid {uid} is not one of --agent-uids' {AGENT_UIDS:?}: {report}");
        assert_eq!(sr.uid.clone().flatten().and_then(|u| u.first().cloned()), Some(uid.to_string()), "{sr}");
        let identity = sandbox.identity.clone().unwrap_or_default();
        assert_eq!(identity.agent_uid, Some(uid), "{manifest}");
        assert_eq!(identity.agent_gid, report["gid"].as_u64(), "{manifest}");
    } else {
        assert_eq!(uid, u64::from(runner_uid), "{report}");
    }

    // The caps: in the manifest and batch.json where the runner enforces them, and what the agent met of them.
    let batch_doc: Value = serde_json::from_slice(&std::fs::read(batch.join("batch.json")).unwrap()).unwrap();
    if runner.caps() {
        let caps = sandbox.resources.clone().flatten().expect("the caps in force");
        assert_eq!((caps.max_processes, caps.memory_bytes, caps.disk_bytes), (Some(MAX_PROCESSES), Some(MEMORY_BYTES), Some(DISK_BYTES)), "{manifest}");
        let in_batch = &batch_doc["sandbox"]["resources"];
        assert_eq!((in_batch["max_processes"].as_u64(), in_batch["memory_bytes"].as_u64(), in_batch["disk_bytes"].as_u64()), (caps.max_processes, caps.memory_bytes, caps.disk_bytes), "batch.json names the same caps: {batch_doc}");
        let used = manifest.resources_used().expect("what the agent used of its caps");
        assert!(used.forks_refused.flatten().is_some_and(|n| n >= 1), "the fork flood met the cap: {used}");
        assert!(
            used.oom_kills.flatten().is_some_and(|n| n >= 1) || used.memory_limit_hits.flatten().is_some_and(|n| n >= 1),
            "the allocation met the cap: {used}"
        );
        assert!(used.memory_peak_bytes.flatten().is_some_and(|b| b <= MEMORY_BYTES), "{used}");
        assert!(used.processes_peak.flatten().is_some_and(|n| n <= MAX_PROCESSES), "{used}");
        // The rollout's disk is gone with its workspace, session home and /tmp; its logs were kept.
        assert!(!ws.exists() && !ws.parent().unwrap().exists(), "the rollout's disk outlived it: {}", ws.display());
        assert!(!std::fs::read_to_string("/proc/self/mounts").unwrap().contains(&ws.parent().unwrap().display().to_string()), "still mounted");
    } else {
        assert!(sandbox.resources == Some(None) && batch_doc["sandbox"]["resources"].is_null(), "unconfined: no caps claimed: {manifest}");
    }
}
