//! The agent's toolbox: a scientific Python the sandbox shows read-only at [`INSIDE`] and puts first on `PATH`, so
//! an agent's `python3` imports numpy, scipy, Pillow and OpenCV as the paper's agents did (Appendix F) instead of
//! spending its budget re-implementing `.npy`, PNG and MP4 readers. The project's toolbox is a venv over the host's
//! Debian `/usr/bin/python3` (the interpreter the sandbox shows, since it binds the host's `/usr`), unpacked by
//! `scripts/setup.py --toolbox` from the wheels pinned with their sha256 in `assets/third_party.lock.json` into
//! `<cache>/toolbox-<name>-<hash>`. What the agent installs itself goes to its rollout's session home
//! (`PYTHONUSERBASE`), never into the toolbox. A result is only comparable with the same toolbox, so the harness
//! manifest and `batch.json` name it with its packages and versions.
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value, json};
use sha2::{Digest, Sha256};

use crate::host_paths::{SYSTEM_DIRS, cache_dir, which};

/// Where the sandbox shows the toolbox: a neutral path, since the cache lies below the runner's home (`/root`
/// when it runs as root), which the agent's user could not traverse.
pub const INSIDE: &str = "/opt/libero-toolbox";

/// The lock this runner was built with: the project's toolbox is the one it names (and the agent CLI versions,
/// the runner's `harness_versions`, the ones it lists).
pub const LOCK: &str = include_str!("../../../assets/third_party.lock.json");

/// [`LOCK`] as far as the runner reads it (the rest is `scripts/setup.py`'s).
#[derive(Debug, Deserialize)]
pub struct ThirdPartyLock {
    pub toolbox: Option<LockedToolbox>,
    /// Each agent CLI's entry beside a `why` text: read one with [`ThirdPartyLock::harness`].
    #[serde(default)]
    pub harness_versions: Map<String, Value>,
}

/// The lock's `toolbox`: the venv `scripts/setup.py --toolbox` builds.
#[derive(Debug, Default, Deserialize)]
pub struct LockedToolbox {
    pub name: Option<String>,
    pub interpreter: Option<String>,
    pub wheels: Option<Vec<LockedWheel>>,
}

/// One wheel of the lock's toolbox, as far as the toolbox's directory name hashes it.
#[derive(Debug, Deserialize)]
pub struct LockedWheel {
    pub sha256: Option<String>,
}

/// One agent CLI of the lock's `harness_versions`: its npm package and each version with why it is there.
#[derive(Debug, Deserialize)]
pub struct LockedHarness {
    pub package: Option<String>,
    /// Version → why (a text; kept as JSON so that an entry of another shape still lists its version).
    pub versions: Option<Map<String, Value>>,
}

impl ThirdPartyLock {
    /// The lock this runner was built with.
    pub fn built_in() -> Result<Self, ToolboxError> {
        serde_json::from_str(LOCK).map_err(|e| ToolboxError::Lock(e.to_string()))
    }

    /// The `harness_versions` entry of `harness` (`codex`, `claude_code`, …), if the lock lists one.
    pub fn harness(&self, harness: &str) -> Option<LockedHarness> {
        self.harness_versions.get(harness).and_then(|entry| LockedHarness::deserialize(entry).ok())
    }
}

/// The most bytes of a package's `METADATA` read for its name and version.
const MAX_METADATA_BYTES: u64 = 64 * 1024;

#[derive(Debug, thiserror::Error)]
pub enum ToolboxError {
    #[error("assets/third_party.lock.json's toolbox entry: {0}")]
    Lock(String),
    #[error("{path} is not a toolbox: {why}")]
    Invalid { path: PathBuf, why: String },
    #[error("cannot install the project's toolbox into {dir}: {why}; install it with `python3 scripts/setup.py --toolbox`, or run with --toolbox none|PATH")]
    Install { dir: PathBuf, why: String },
}

/// `run --toolbox`: none, or a toolbox directory (the project's when the flag is absent).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ToolboxChoice {
    None,
    Path(PathBuf),
}

impl std::str::FromStr for ToolboxChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim() {
            "" => Err("--toolbox takes a directory or `none`".into()),
            "none" => Ok(Self::None),
            p => Ok(Self::Path(PathBuf::from(p))),
        }
    }
}

/// One installed distribution, as its `*.dist-info/METADATA` names it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Package {
    pub name: String,
    pub version: String,
}

/// A toolbox found on disk: a venv layout (`bin/python3`, `lib/python3.X/site-packages`) over an interpreter the
/// sandbox shows.
#[derive(Debug, Clone)]
pub struct Toolbox {
    pub name: String,
    /// Its directory on the host (canonical).
    pub root: PathBuf,
    /// `bin/python3` resolved on the host.
    pub interpreter: PathBuf,
    pub python: Option<String>,
    /// Sorted by name, read from the `dist-info` directories (what is there, not what a file claims).
    pub packages: Vec<Package>,
    pub size_bytes: Option<u64>,
    /// The lock's toolbox, installed by `scripts/setup.py`.
    pub project: bool,
}

/// `toolbox-<name>-<12 hex>`, the hash over the interpreter and every wheel's sha256, as `scripts/setup.py`'s
/// `toolbox_dir_name` computes it: a changed lock is a new directory, never a half-replaced one.
pub fn project_dir_name() -> Result<String, ToolboxError> {
    let spec = ThirdPartyLock::built_in()?.toolbox.unwrap_or_default();
    let field = |v: Option<String>, k: &str| v.ok_or_else(|| ToolboxError::Lock(format!("no `{k}`")));
    let (name, interpreter) = (field(spec.name, "name")?, field(spec.interpreter, "interpreter")?);
    let wheels = spec.wheels.ok_or_else(|| ToolboxError::Lock("no `wheels`".into()))?;
    let mut lines = vec![interpreter];
    for w in wheels {
        lines.push(field(w.sha256, "sha256")?);
    }
    let digest = Sha256::digest(lines.join("\n").as_bytes());
    let hex: String = digest.iter().take(6).map(|b| format!("{b:02x}")).collect();
    Ok(format!("toolbox-{name}-{hex}"))
}

/// Where the project's toolbox lives (installed or not).
pub fn project_dir() -> Result<PathBuf, ToolboxError> {
    Ok(cache_dir().join(project_dir_name()?))
}

/// The toolbox `--toolbox` chose: the project's when absent (installed on first use), none, or a directory.
pub fn resolve(choice: Option<&ToolboxChoice>) -> Result<Option<Toolbox>, ToolboxError> {
    match choice {
        None => ensure_project().map(Some),
        Some(ToolboxChoice::None) => Ok(None),
        Some(ToolboxChoice::Path(p)) => Toolbox::load(p).map(Some),
    }
}

/// The project's toolbox, installed by `scripts/setup.py --toolbox` (its progress on this process's stderr) when
/// the cache lacks it: one installer for `make test`, `setup.py` and `run`.
pub fn ensure_project() -> Result<Toolbox, ToolboxError> {
    let dir = project_dir()?;
    if !dir.join(".complete").is_file() {
        install_project(&dir)?;
    }
    let mut toolbox = Toolbox::load(&dir)?;
    toolbox.project = true;
    Ok(toolbox)
}

fn install_project(dir: &Path) -> Result<(), ToolboxError> {
    let fail = |why: String| ToolboxError::Install { dir: dir.to_path_buf(), why };
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/setup.py");
    if !script.is_file() {
        return Err(fail(format!("the installer {} is not there", script.display())));
    }
    let python = which("python3").unwrap_or_else(|| PathBuf::from("/usr/bin/python3"));
    eprintln!("the agents' toolbox is not installed yet: installing it once into {} (about 500 MB)", dir.display());
    // Its progress goes where the runner's goes (stderr): `run --dry-run --json` keeps stdout for the schedule.
    let stdout = std::os::fd::AsFd::as_fd(&std::io::stderr()).try_clone_to_owned().map_err(|e| fail(e.to_string()))?;
    let status = Command::new(&python)
        .arg(&script)
        .arg("--toolbox")
        .stdin(Stdio::null())
        .stdout(Stdio::from(stdout))
        .status()
        .map_err(|e| fail(format!("cannot run {}: {e}", python.display())))?;
    if !status.success() {
        return Err(fail(format!("{} --toolbox failed ({status})", script.display())));
    }
    if !dir.join(".complete").is_file() {
        return Err(fail(format!(
            "{} installed another toolbox: its lock differs from the one this runner was built with (rebuild it)",
            script.display()
        )));
    }
    Ok(())
}

/// `toolbox.json`, what `scripts/setup.py --toolbox` writes beside the venv (each field read leniently: one of
/// another type is as good as absent, as the directory itself can tell).
#[derive(Debug, Default, Deserialize)]
struct RecordedToolbox {
    #[serde(default, deserialize_with = "lenient")]
    name: Option<String>,
    #[serde(default, deserialize_with = "lenient")]
    python: Option<String>,
    #[serde(default, deserialize_with = "lenient")]
    size_bytes: Option<u64>,
}

/// A field of the type asked for, else none (as `Value::as_str` and `as_u64` read it).
fn lenient<'de, D: serde::Deserializer<'de>, T: serde::de::DeserializeOwned>(d: D) -> Result<Option<T>, D::Error> {
    Ok(serde_json::from_value(Value::deserialize(d)?).ok())
}

impl Toolbox {
    /// Reads the toolbox at `root`: its interpreter must be one the sandbox shows (in the system directories or in
    /// the toolbox itself), its packages are what its `site-packages` holds. `toolbox.json` (written by
    /// `scripts/setup.py`) adds the name, Python version and size; without it the directory names the toolbox.
    pub fn load(root: &Path) -> Result<Self, ToolboxError> {
        let invalid = |why: String| ToolboxError::Invalid { path: root.to_path_buf(), why };
        let root = std::fs::canonicalize(root).map_err(|e| invalid(e.to_string()))?;
        if !root.is_dir() {
            return Err(invalid("not a directory".into()));
        }
        let interpreter = std::fs::canonicalize(root.join("bin/python3"))
            .map_err(|e| invalid(format!("bin/python3: {e} (a toolbox is laid out as a venv)")))?;
        if !interpreter.starts_with(&root) && !SYSTEM_DIRS.iter().any(|d| interpreter.starts_with(d)) {
            return Err(invalid(format!(
                "bin/python3 is {}, which the sandbox does not show (only the system directories and the toolbox)",
                interpreter.display()
            )));
        }
        let site = site_packages(&root).ok_or_else(|| invalid("no lib/python3.*/site-packages".into()))?;
        let packages = installed_packages(&site);
        let recorded: RecordedToolbox = std::fs::read_to_string(root.join("toolbox.json"))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
        let name = match recorded.name {
            Some(n) => n,
            None => root.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "toolbox".into()),
        };
        let python = recorded.python.or_else(|| pyvenv_version(&root));
        let size_bytes = recorded.size_bytes.or_else(|| Some(tree_size(&root)));
        Ok(Self { name, root, interpreter, python, packages, size_bytes, project: false })
    }

    /// For the harness manifest and `batch.json`: what the agent's `python3` was.
    pub fn describe(&self) -> Value {
        json!({
            "name": self.name,
            "source": if self.project { "the project's lock (assets/third_party.lock.json)" } else { "--toolbox PATH" },
            "python": self.python,
            "interpreter": self.interpreter,
            "packages": self.packages,
            "size_bytes": self.size_bytes,
            "host_path": self.root,
            "inside": INSIDE,
            "mount": "read-only, first on PATH as python3/python/pip",
            "agent_site": "PYTHONUSERBASE=<session home>/.local: what the agent installs itself (pip install --user, pip's default with a read-only toolbox)",
        })
    }

    /// The agent's environment with the toolbox: its `bin` first on `PATH` (then the user site's scripts), and the
    /// user site in the rollout's session home, which is the agent's to write and goes with the rollout.
    pub fn agent_env(&self, env: &mut Vec<(String, String)>, home: &Path) {
        let user_base = home.join(".local");
        let path = env.iter().find(|(k, _)| k == "PATH").map(|(_, v)| v.clone()).unwrap_or_else(|| "/usr/bin:/bin".into());
        set(env, "PATH", format!("{INSIDE}/bin:{}/bin:{path}", user_base.display()));
        set(env, "PYTHONUSERBASE", user_base.to_string_lossy().into_owned());
        set(env, "PIP_DISABLE_PIP_VERSION_CHECK", "1".into());
    }
}

fn set(env: &mut Vec<(String, String)>, key: &str, value: String) {
    env.retain(|(k, _)| k != key);
    env.push((key.to_owned(), value));
}

/// `lib/python3.X/site-packages` (the first, by name).
fn site_packages(root: &Path) -> Option<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root.join("lib"))
        .ok()?
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("python3"))
        .map(|e| e.path().join("site-packages"))
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    dirs.into_iter().next()
}

/// Every `*.dist-info` of `site`, named and versioned by its `METADATA`.
fn installed_packages(site: &Path) -> Vec<Package> {
    let mut out: Vec<Package> = std::fs::read_dir(site)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".dist-info"))
        .filter_map(|e| metadata_of(&e.path().join("METADATA")))
        .collect();
    out.sort_by_key(|p| p.name.to_lowercase());
    out
}

fn metadata_of(path: &Path) -> Option<Package> {
    let mut text = String::new();
    std::fs::File::open(path).ok()?.take(MAX_METADATA_BYTES).read_to_string(&mut text).ok()?;
    let header = |key: &str| {
        text.lines().take_while(|l| !l.is_empty()).find_map(|l| l.strip_prefix(key)).map(|v| v.trim().to_owned())
    };
    Some(Package { name: header("Name:")?, version: header("Version:")? })
}

fn pyvenv_version(root: &Path) -> Option<String> {
    let cfg = std::fs::read_to_string(root.join("pyvenv.cfg")).ok()?;
    cfg.lines().find_map(|l| {
        let (k, v) = l.split_once('=')?;
        matches!(k.trim(), "version" | "version_info").then(|| v.trim().to_owned())
    })
}

/// Bytes of the files below `root`, links not followed.
fn tree_size(root: &Path) -> u64 {
    let (mut total, mut todo) = (0, vec![root.to_path_buf()]);
    while let Some(dir) = todo.pop() {
        for e in std::fs::read_dir(&dir).into_iter().flatten().flatten() {
            match e.metadata() {
                Ok(m) if m.is_dir() => todo.push(e.path()),
                Ok(m) => total += m.len(),
                Err(_) => {}
            }
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_runner_names_the_project_toolbox_as_setup_py_does() {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/setup.py");
        let out = Command::new("python3").arg(script).arg("--print-toolbox-dir").output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let printed = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
        assert_eq!(printed.file_name().unwrap().to_string_lossy(), project_dir_name().unwrap());
        assert!(project_dir_name().unwrap().starts_with("toolbox-libero-sci-"));
    }

    #[test]
    fn toolbox_choice_is_none_or_a_directory() {
        assert_eq!("none".parse::<ToolboxChoice>(), Ok(ToolboxChoice::None));
        assert_eq!("/opt/tb".parse::<ToolboxChoice>(), Ok(ToolboxChoice::Path("/opt/tb".into())));
        assert!("".parse::<ToolboxChoice>().is_err());
    }

    fn fake_toolbox(python: &Path) -> tempfile::TempDir {
        let t = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(t.path().join("bin")).unwrap();
        std::os::unix::fs::symlink(python, t.path().join("bin/python3")).unwrap();
        let info = t.path().join("lib/python3.11/site-packages/opencv_python_headless-4.10.0.84.dist-info");
        std::fs::create_dir_all(&info).unwrap();
        std::fs::write(info.join("METADATA"), "Metadata-Version: 2.1\nName: opencv-python-headless\nVersion: 4.10.0.84\n\nName: body\n").unwrap();
        let info = t.path().join("lib/python3.11/site-packages/numpy-1.26.4.dist-info");
        std::fs::create_dir_all(&info).unwrap();
        std::fs::write(info.join("METADATA"), "Name: numpy\nVersion: 1.26.4\n").unwrap();
        std::fs::write(t.path().join("pyvenv.cfg"), "home = /usr/bin\nversion = 3.11.2\n").unwrap();
        t
    }

    /// A directory of one's own is described by what it holds; one whose python the sandbox cannot show is refused
    /// before any agent starts with a `python3` that does not run.
    #[test]
    fn a_toolbox_lists_what_its_site_packages_hold_and_needs_an_interpreter_the_sandbox_shows() {
        let t = fake_toolbox(Path::new("/usr/bin/python3"));
        let tb = Toolbox::load(t.path()).unwrap();
        let listed: Vec<(&str, &str)> = tb.packages.iter().map(|p| (p.name.as_str(), p.version.as_str())).collect();
        assert_eq!(listed, [("numpy", "1.26.4"), ("opencv-python-headless", "4.10.0.84")]);
        assert_eq!(tb.python.as_deref(), Some("3.11.2"));
        assert_eq!(tb.name, t.path().file_name().unwrap().to_string_lossy());
        assert!(tb.describe()["packages"][1]["version"] == "4.10.0.84" && tb.describe()["inside"] == INSIDE);
        let elsewhere = tempfile::tempdir().unwrap();
        std::fs::write(elsewhere.path().join("python3"), "").unwrap();
        let t = fake_toolbox(&elsewhere.path().join("python3"));
        let err = Toolbox::load(t.path()).unwrap_err().to_string();
        assert!(err.contains("which the sandbox does not show"), "{err}");
        assert!(Toolbox::load(elsewhere.path()).unwrap_err().to_string().contains("bin/python3"));
    }

    #[test]
    fn the_agent_env_puts_the_toolbox_first_and_the_user_site_in_the_session_home() {
        let t = fake_toolbox(Path::new("/usr/bin/python3"));
        let tb = Toolbox::load(t.path()).unwrap();
        let mut env = vec![("PATH".to_owned(), "/usr/bin:/bin".to_owned()), ("HOME".to_owned(), "/b/home".to_owned())];
        tb.agent_env(&mut env, Path::new("/b/home"));
        let get = |k: &str| env.iter().find(|(x, _)| x == k).map(|(_, v)| v.as_str());
        assert_eq!(get("PATH"), Some("/opt/libero-toolbox/bin:/b/home/.local/bin:/usr/bin:/bin"));
        assert_eq!(get("PYTHONUSERBASE"), Some("/b/home/.local"));
        assert_eq!(env.iter().filter(|(k, _)| k == "PATH").count(), 1);
    }
}
