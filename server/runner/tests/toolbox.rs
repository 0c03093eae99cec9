//! Issue 32, item 1: the agent's toolbox, proved in the real sandbox. An agent's `python3` there is the project's
//! toolbox (numpy, scipy, Pillow, OpenCV), reads what the server publishes (`depth_m.npy`, `rgb.png`) and decodes
//! the demonstration MP4 of a `--demo video` episode, as the agent's unprivileged user when the runner is root and
//! inside an ordinary user's sandbox; it cannot write into the toolbox, and what it installs itself lands in its own
//! session home. `run --toolbox none` leaves the system's python3 alone, and the harness manifest names the toolbox
//! with its versions. Needs `python3 scripts/setup.py --test` (it installs the toolbox; `run` would too) and the
//! workspace's `libero-agent` built beside `libero-worker` (`cargo test --workspace` builds both).
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

use libero_episode::demo::DemoCondition;
use libero_records::batch_doc::BatchDoc;
use libero_records::batch_doc::harness_manifest::HarnessManifest;
use libero_records::typed::read_record;
use libero_runner::harness::{Harness, Launch, net_plan};
use libero_sandbox::agent_net::contain;
use libero_sandbox::sandbox::{Sandbox, SandboxSpec};
use libero_sandbox::toolbox::{self, Toolbox};
use libero_server::client::{InProcessServer, McpClient, prepare_episode};
use libero_server::episodes::PrepareRequest;
use serde_json::{Value, json};

/// What the paper's agents did first with the published files (Appendix F), and what the test reads back.
const READ_PUBLISHED: &str = r#"
import glob, json, os, sys
import numpy as np, scipy, PIL, cv2
from PIL import Image
from scipy.spatial.transform import Rotation
head = "benchmark_inputs/current_observation/head"
depth = np.load(f"{head}/depth_m.npy")
rgb = np.asarray(Image.open(f"{head}/rgb.png").convert("RGB"))
bgr = cv2.imread(f"{head}/rgb.png")
videos = {}
for path in sorted(glob.glob("benchmark_inputs/expert_demo/**/*.mp4", recursive=True)):
    cap = cv2.VideoCapture(path)
    frames, shape = 0, None
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames, shape = frames + 1, list(frame.shape)
    videos[os.path.basename(path)] = {"frames": frames, "shape": shape}
print(json.dumps({
    "executable": sys.executable, "prefix": sys.prefix, "uid": os.getuid(),
    "versions": {"numpy": np.__version__, "scipy": scipy.__version__, "pillow": PIL.__version__, "cv2": cv2.__version__},
    "depth": [list(depth.shape), str(depth.dtype), float(np.median(depth))],
    "rgb": list(rgb.shape), "same_pixels": bool((bgr[..., ::-1] == rgb).all()),
    "rotation": Rotation.from_euler("z", 90, degrees=True).as_matrix().round(6).tolist(),
    "videos": videos,
}))
"#;

/// A started episode of T14 at level 3 (its first observation published, and with `--demo video` the
/// demonstration's MP4s), shared by the tests of one process; its server lives as long as the test process.
struct Published {
    _server: InProcessServer,
    dir: PathBuf,
    workspace: PathBuf,
    mcp_url: String,
}

/// With the demonstration's MP4s (rendering them takes most of a minute in a debug build): for the tests that read them.
fn published() -> &'static Published {
    static P: OnceLock<Published> = OnceLock::new();
    P.get_or_init(|| publish(DemoCondition::Video))
}

/// Without a demonstration: for the tests that need only a workspace and an MCP endpoint.
fn published_plain() -> &'static Published {
    static P: OnceLock<Published> = OnceLock::new();
    P.get_or_init(|| publish(DemoCondition::None))
}

fn publish(demo: DemoCondition) -> Published {
    // A directory of this process's own: test runners that run each test in a process of its own (nextest)
    // run several of these at once. Kept after the process: the static is never dropped.
    let dir = tempfile::Builder::new().prefix("toolbox-tests-").tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap().keep();
    let server = InProcessServer::start(dir.join("data"), "test_finished").unwrap();
    let req = PrepareRequest {
        level: 3,
        workspace: Some(dir.join("ws")),
        wall_time_s: 1800.0,
        demo,
        ..PrepareRequest::new("T14")
    };
    let prepared = prepare_episode(&server.url, &req).unwrap();
    // The first observation is published when the agent starts the episode.
    let token = prepared.mcp_headers["Authorization"].trim_start_matches("Bearer ");
    McpClient::connect_with_token(&prepared.mcp_url, token, "toolbox-test").unwrap().call_tool("start_episode", json!({})).unwrap();
    Published { _server: server, dir, workspace: prepared.workspace, mcp_url: prepared.mcp_url }
}

fn project_toolbox() -> Toolbox {
    toolbox::ensure_project().expect("the project's toolbox (python3 scripts/setup.py --toolbox)")
}

/// The lock's pinned versions by PyPI name.
fn locked_versions() -> Vec<(String, String)> {
    let lock: Value =
        serde_json::from_str(&std::fs::read_to_string(libero_testkit::assets_dir().join("third_party.lock.json")).unwrap())
            .unwrap();
    lock["toolbox"]["wheels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| (w["pypi"].as_str().unwrap().to_owned(), w["version"].as_str().unwrap().to_owned()))
        .collect()
}

fn locked(name: &str) -> String {
    locked_versions().into_iter().find(|(n, _)| n == name).map(|(_, v)| v).unwrap()
}

/// The `libero-agent` of the same build: `sandbox-net`, the sandbox's first process, and `run`.
fn libero_agent() -> PathBuf {
    let p = Path::new(env!("CARGO_BIN_EXE_libero-worker")).with_file_name("libero-agent");
    assert!(p.is_file(), "{} missing: cargo build -p libero-agent", p.display());
    p
}

fn is_root() -> bool {
    // SAFETY: geteuid(2) has no preconditions.
    unsafe { libc::geteuid() == 0 }
}

fn text(o: &Output) -> String {
    format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// `script` run by the `python3` a shell finds on the agent's PATH, as `run` runs an agent: in the sandbox behind
/// `sandbox-net`, in the workspace, with a fresh session home of its own.
fn in_sandbox(p: &Published, sandbox: &Sandbox, name: &str, script: &str) -> Output {
    let home = p.dir.join(format!("home-{name}"));
    std::fs::create_dir(&home).unwrap();
    let env = [("PATH", "/usr/local/bin:/usr/bin:/bin"), ("LANG", "C.UTF-8"), ("TMPDIR", "/tmp")]
        .iter()
        .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
        .chain([("HOME".to_owned(), home.to_string_lossy().into_owned())])
        .collect();
    let launch = Launch {
        argv: vec!["/bin/sh".into(), "-c".into(), r#"exec python3 -c "$1""#.into(), "sh".into(), script.into()],
        env,
        files: Vec::new(),
    };
    let plan = net_plan(Harness::Command, &p.mcp_url, None, false).unwrap();
    let mut contained = contain(Some(sandbox), Some(&plan), &launch.argv, &launch.env, &p.workspace, &home, &libero_agent(), &p.dir.join(format!("private-{name}"))).unwrap();
    let mut cmd = contained.command();
    cmd.current_dir(&p.workspace).stdin(Stdio::null());
    let child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    contained.spawned();
    child.wait_with_output().unwrap()
}

fn last_json(o: &Output) -> Value {
    let out = String::from_utf8_lossy(&o.stdout);
    let line = out.lines().rev().find(|l| l.starts_with('{')).unwrap_or_else(|| panic!("no JSON line: {}", text(o)));
    serde_json::from_str(line).unwrap()
}

fn check_reads(v: &Value, o: &Output) {
    assert_eq!(v["executable"], format!("{}/bin/python3", toolbox::INSIDE), "{}", text(o));
    assert_eq!(v["prefix"], toolbox::INSIDE);
    for (key, package) in [("numpy", "numpy"), ("scipy", "scipy"), ("pillow", "pillow"), ("cv2", "opencv-python-headless")] {
        let want = locked(package);
        let got = v["versions"][key].as_str().unwrap();
        assert!(want.starts_with(got), "{key} {got}, the lock pins {package} {want}");
    }
    assert_eq!(v["depth"][0], json!([256, 256]), "{v}");
    assert_eq!(v["depth"][1], "float32");
    assert!(v["depth"][2].as_f64().unwrap() > 0.1, "metres: {v}");
    assert_eq!(v["rgb"], json!([256, 256, 3]));
    assert_eq!(v["same_pixels"], true, "Pillow and OpenCV read the same PNG");
    assert_eq!(v["rotation"][0], json!([0.0, -1.0, 0.0]));
    let videos = v["videos"].as_object().unwrap();
    assert!(!videos.is_empty(), "the demonstration's MP4s are published: {v}");
    for (name, video) in videos {
        assert!(video["frames"].as_u64().unwrap() > 1, "{name} decodes: {v}");
        assert_eq!(video["shape"][2], 3, "{name}: {v}");
    }
}

/// The sandbox as `Sandbox::detect` makes it (without a rollout's cage, whose uid `run` draws per rollout): root's
/// runner drops the agent to an unprivileged uid (nobody here), whose reads go through the toolbox's bind at /opt
/// (the cache itself lies below /root, which no other user can traverse).
#[test]
fn the_project_toolbox_reads_the_published_depth_png_and_demo_mp4_in_the_sandbox() {
    let sandbox = Sandbox::detect().unwrap().with_toolbox(Some(project_toolbox()));
    let o = in_sandbox(published(), &sandbox, "reads", READ_PUBLISHED);
    assert!(o.status.success(), "{}", text(&o));
    let v = last_json(&o);
    check_reads(&v, &o);
    if is_root() {
        assert_eq!(v["uid"], 65534, "the agent runs as nobody");
    }
}

/// The toolbox is mounted read-only: neither nobody (root's runner) nor the user-namespace root of an ordinary
/// user's sandbox can change a file of it, add one or remove one.
#[test]
fn the_agent_cannot_write_into_the_toolbox() {
    let script = r#"
import errno, json, os
import numpy
site = os.path.dirname(os.path.dirname(numpy.__file__))
attempts = {
    "append": lambda: open(numpy.__file__, "a").write("x"),
    "create": lambda: open("/opt/libero-toolbox/bin/evil", "w").write("x"),
    "mkdir": lambda: os.mkdir(os.path.join(site, "evil")),
    "chmod": lambda: os.chmod("/opt/libero-toolbox/pyvenv.cfg", 0o666),
    "unlink": lambda: os.unlink("/opt/libero-toolbox/toolbox.json"),
    "rename": lambda: os.rename(numpy.__file__, numpy.__file__ + ".x"),
}
out = {}
for name, attempt in attempts.items():
    try:
        attempt()
        out[name] = "written"
    except OSError as e:
        out[name] = errno.errorcode.get(e.errno, str(e.errno))
mounts = [l.split() for l in open("/proc/self/mountinfo")]
print(json.dumps({"attempts": out, "options": [m[5] for m in mounts if m[4] == "/opt/libero-toolbox"]}))
"#;
    let sandbox = Sandbox::detect().unwrap().with_toolbox(Some(project_toolbox()));
    let o = in_sandbox(published_plain(), &sandbox, "write", script);
    assert!(o.status.success(), "{}", text(&o));
    let v = last_json(&o);
    for (attempt, result) in v["attempts"].as_object().unwrap() {
        assert!(matches!(result.as_str(), Some("EROFS" | "EACCES" | "EPERM")), "{attempt}: {result} ({v})");
    }
    // A read-only mount, not only file modes (which would not hold the user-namespace root of an ordinary runner).
    let options = v["options"].as_array().unwrap();
    assert!(!options.is_empty() && options.iter().all(|o| o.as_str().unwrap().split(',').any(|x| x == "ro")), "{v}");
}

/// `pip install` in the sandbox goes to the rollout's own user site (PYTHONUSERBASE in the session home), which
/// Python puts before the toolbox: the toolbox stays as it was, the agent's package imports.
#[test]
fn what_the_agent_installs_lands_in_its_own_session_home() {
    let script = r#"
import base64, hashlib, json, os, subprocess, sys, zipfile
home = os.environ["HOME"]
wheel = os.path.join(home, "hello_toolbox-1.0-py3-none-any.whl")
files = {"hello_toolbox/__init__.py": b"GREETING = 'hi'\n",
         "hello_toolbox-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: hello-toolbox\nVersion: 1.0\n",
         "hello_toolbox-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
record = "".join(f"{n},sha256={base64.urlsafe_b64encode(hashlib.sha256(b).digest()).rstrip(b'=').decode()},{len(b)}\n" for n, b in files.items())
with zipfile.ZipFile(wheel, "w") as z:
    for n, b in files.items():
        z.writestr(n, b)
    z.writestr("hello_toolbox-1.0.dist-info/RECORD", record + "hello_toolbox-1.0.dist-info/RECORD,,\n")
pip = subprocess.run(["pip", "install", "--no-index", wheel], capture_output=True, text=True)
imported = subprocess.run(["python3", "-c", "import hello_toolbox, numpy; print(hello_toolbox.__file__)"], capture_output=True, text=True)
print(json.dumps({"pip": pip.returncode, "pip_out": pip.stdout + pip.stderr, "imported": imported.stdout.strip(),
                  "import_err": imported.stderr, "userbase": os.environ.get("PYTHONUSERBASE"), "home": home}))
"#;
    let sandbox = Sandbox::detect().unwrap().with_toolbox(Some(project_toolbox()));
    let o = in_sandbox(published_plain(), &sandbox, "pip", script);
    assert!(o.status.success(), "{}", text(&o));
    let v = last_json(&o);
    assert_eq!(v["pip"], 0, "{}", v["pip_out"]);
    let home = v["home"].as_str().unwrap();
    assert_eq!(v["userbase"], format!("{home}/.local"));
    let imported = v["imported"].as_str().unwrap();
    assert!(imported.starts_with(&format!("{home}/.local/lib/python3")), "{v}");
    assert!(Path::new(imported).is_file(), "the package is in the rollout's home on the host too");
    assert!(!project_toolbox().root.join("lib").read_dir().unwrap().flatten().any(|d| d.path().join("site-packages/hello_toolbox").exists()));
}

/// `--toolbox none`: no /opt/libero-toolbox, the system's python3 first on PATH, and exactly what that python3
/// imports on the host (Debian's own packages, nothing of the toolbox).
#[test]
fn without_a_toolbox_the_agent_has_the_system_python3_alone() {
    let script = r#"
import importlib.util, json, os, shutil, sys
print(json.dumps({"executable": sys.executable, "prefix": sys.prefix, "opt": os.path.exists("/opt/libero-toolbox"),
                  "which": shutil.which("python3"), "numpy": importlib.util.find_spec("numpy") is not None}))
"#;
    let o = in_sandbox(published_plain(), &Sandbox::detect().unwrap().with_toolbox(None), "none", script);
    assert!(o.status.success(), "{}", text(&o));
    let v = last_json(&o);
    assert_eq!((v["executable"].as_str(), v["prefix"].as_str(), v["opt"].as_bool()), (Some("/usr/bin/python3"), Some("/usr"), Some(false)), "{v}");
    assert_eq!(v["which"], "/usr/bin/python3");
    let host = Command::new("/usr/bin/python3").args(["-I", "-c", "import importlib.util; print(importlib.util.find_spec('numpy') is not None)"]).output().unwrap();
    assert_eq!(v["numpy"].to_string(), String::from_utf8_lossy(&host.stdout).trim().to_lowercase(), "as Debian's python3 on the host");
}

/// The runner started by an ordinary user (nobody, from root): a user namespace of that user binds a toolbox it
/// can read (a hard-linked copy of root's), and its agent reads the same files with it.
#[test]
fn an_ordinary_user_s_sandbox_reads_the_same_files_with_the_toolbox() {
    if !is_root() {
        eprintln!("not root: the_project_toolbox_reads_… ran as an ordinary user already");
        return;
    }
    let p = published();
    let (uid, gid) = (65534u32, 65534u32);
    let dir = p.dir.join("ordinary");
    std::fs::create_dir(&dir).unwrap();
    let copy = dir.join("toolbox");
    let st = Command::new("cp").arg("-al").arg(&project_toolbox().root).arg(&copy).status().unwrap();
    assert!(st.success(), "cp -al the toolbox");
    let (ws, home) = (dir.join("ws"), dir.join("home"));
    std::fs::create_dir(&ws).unwrap();
    let st = Command::new("cp").arg("-r").arg(p.workspace.join("benchmark_inputs")).arg(&ws).status().unwrap();
    assert!(st.success());
    std::fs::create_dir(&home).unwrap();
    let st = Command::new("chown").args(["-R", &format!("{uid}:{gid}")]).arg(&ws).arg(&home).status().unwrap();
    assert!(st.success());
    let detected = Sandbox::detect().unwrap();
    let sandbox = Sandbox { agent_ids: None, ..detected }.with_toolbox(Some(Toolbox::load(&copy).unwrap()));
    let spec = SandboxSpec { writable: vec![ws.clone(), home.clone()], cwd: ws.clone(), ..Default::default() };
    let argv = sandbox.command(&["/bin/sh".into(), "-c".into(), r#"exec python3 -c "$1""#.into(), "sh".into(), READ_PUBLISHED.into()], &spec);
    let mut env = vec![("PATH".to_owned(), "/usr/bin:/bin".to_owned()), ("HOME".to_owned(), home.to_string_lossy().into_owned())];
    sandbox.toolbox.as_ref().unwrap().agent_env(&mut env, &home);
    let o = Command::new("setpriv")
        .args(["--reuid", &uid.to_string(), "--regid", &gid.to_string(), "--clear-groups", "--"])
        .args(&argv)
        .env_clear()
        .envs(env)
        .current_dir("/")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let v = last_json(&o);
    check_reads(&v, &o);
}

/// A whole batch through `libero-agent run`: the command agent's `python3` is the toolbox's, and the harness
/// manifest and `batch.json` name the toolbox with every package's version; `--toolbox none` records none.
#[test]
fn run_records_the_toolbox_in_the_manifest_and_none_means_the_system_python3() {
    let dir = tempfile::tempdir().unwrap();
    let agent = "python3 -c 'import sys; print(\"PYTHON\", sys.executable)'; \
                 python3 -c 'import numpy, scipy, PIL, cv2; print(\"IMPORTS ok\")' || echo 'IMPORTS failed'; \
                 exec {libero_agent} agent --workspace {workspace}";
    for (choice, python) in [(None, format!("{}/bin/python3", toolbox::INSIDE)), (Some("none"), "/usr/bin/python3".to_owned())] {
        let batch = dir.path().join(format!("batch-{}", choice.unwrap_or("project")));
        let mut cmd = Command::new(libero_agent());
        cmd.args(["run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T14", "--reps", "1"])
            .args(["--agent-cmd", agent, "--wall-time-s", "300", "--batch"])
            .arg(&batch)
            .arg("--workspace-root")
            .arg(dir.path().join("ws"));
        if let Some(c) = choice {
            cmd.args(["--toolbox", c]);
        }
        let log = dir.path().join(format!("run-{}.log", choice.unwrap_or("project")));
        let status = run_with_timeout(cmd, &log, Duration::from_secs(600));
        assert!(status.success(), "{}", std::fs::read_to_string(&log).unwrap_or_default());
        let rollouts: Vec<PathBuf> = std::fs::read_dir(batch.join("rollouts")).unwrap().flatten().map(|e| e.path()).collect();
        assert_eq!(rollouts.len(), 1);
        let stdout = std::fs::read_to_string(rollouts[0].join("command_stdout.log")).unwrap();
        assert!(stdout.contains(&format!("PYTHON {python}")), "{stdout}");
        let manifest = HarnessManifest::read(&rollouts[0]).unwrap().expect("the rollout's harness manifest");
        let batch_json: BatchDoc = read_record(&batch.join("batch.json")).unwrap().expect("batch.json");
        if choice.is_some() {
            assert!(manifest.toolbox == Some(None) && batch_json.toolbox == Some(None), "{manifest}");
            continue;
        }
        assert!(stdout.contains("IMPORTS ok"), "{stdout}");
        let tb = manifest.toolbox.clone().flatten().expect("the manifest names the toolbox");
        assert_eq!(tb.name.as_deref(), Some("libero-sci"));
        assert_eq!(tb.inside.as_deref(), Some(toolbox::INSIDE));
        assert!(tb.python.as_deref().is_some_and(|p| p.starts_with("3.")), "{tb}");
        assert!(tb.size_bytes.is_some_and(|b| b > 100_000_000), "{tb}");
        for (name, version) in locked_versions() {
            let listed = tb.packages.iter().flatten().any(|p| p.name.as_deref() == Some(name.as_str()) && p.version.as_deref() == Some(version.as_str()));
            assert!(listed, "{name} {version} in {tb}");
        }
        assert_eq!(batch_json.toolbox().and_then(|t| t.packages.clone()), tb.packages, "batch.json names the same toolbox");
    }
}

/// `cmd` with its output in `log`, killed (and the test failed) after `limit`.
fn run_with_timeout(mut cmd: Command, log: &Path, limit: Duration) -> std::process::ExitStatus {
    let out = std::fs::File::create(log).unwrap();
    let mut child = cmd.stdin(Stdio::null()).stdout(out.try_clone().unwrap()).stderr(out).spawn().unwrap();
    let t0 = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            panic!("timed out after {limit:?}: {}", std::fs::read_to_string(log).unwrap_or_default());
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}
