//! `run --harness-version`: which installed copy of a harness's CLI a batch runs, and the version each rollout ran.
//!
//! The lock's `harness_versions` lists the versions of each CLI that stand side by side (the paper's Codex 0.154.0 and
//! Claude Code 2.1.139, App. A, beside the tests' 0.169.0 and 2.1.330). `scripts/setup.py --harnesses` installs every
//! one that `node_test` does not into a prefix of its own, `<cache>/harnesses/<harness>-<version>`. A version asked for
//! resolves to the executable of the first copy that prints exactly it on `--version`: its own prefix, the tests'
//! install (`<cache>/node`), the command on PATH. Without `--harness-version` nothing of this runs: the command on PATH
//! is launched as before. Every rollout probes `--version` of the executable it launches ([`probe`]) and keeps what it
//! printed in its record.
use std::ffi::OsStr;
use std::io::Read;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::bail;
use libero_records::batch_doc::HarnessVersion;

use super::harness::Harness;
use libero_sandbox::host_paths::{cache_dir, which_in};

/// The command that installs the lock's versions.
pub const SETUP_COMMAND: &str = "python3 scripts/setup.py --harnesses";

/// How long a `--version` probe may take (an `npx` probe downloads its package first).
const PROBE_TIMEOUT: Duration = Duration::from_secs(90);

/// The most characters of a probe's output kept in a record.
const PROBE_OUTPUT_CHARS: usize = 500;

/// Where a version of `harness` installed apart lives: `<cache>/harnesses/<harness>-<version>`, as
/// `scripts/setup.py`'s `harness_dir_name` names it.
pub fn install_dir(cache: &Path, harness: Harness, version: &str) -> PathBuf {
    cache.join("harnesses").join(format!("{}-{version}", harness.as_str()))
}

/// The lock's entry of a harness: its npm package and each version it lists with why (`the paper's (App. A)`).
#[derive(Debug, Clone, PartialEq)]
pub struct LockEntry {
    pub package: String,
    pub versions: Vec<(String, String)>,
}

/// The lock's `harness_versions` entry of `harness`, if it lists one.
pub fn lock_entry(harness: Harness) -> Option<LockEntry> {
    let entry = libero_sandbox::toolbox::ThirdPartyLock::built_in().ok()?.harness(harness.as_str())?;
    let versions = entry.versions?.into_iter().map(|(v, why)| (v, why.as_str().unwrap_or_default().to_owned()));
    Some(LockEntry { package: entry.package?, versions: versions.collect() })
}

/// Where an installed copy was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// `<cache>/harnesses/<harness>-<version>`.
    Apart,
    /// `<cache>/node`, what `scripts/setup.py --test` installs (the lock's `node_test`).
    Tests,
    /// The command on the runner's PATH.
    Path,
}

impl Place {
    fn describe(self) -> &'static str {
        match self {
            Place::Apart => "installed apart",
            Place::Tests => "the tests' install",
            Place::Path => "on PATH",
        }
    }
}

/// One installed copy of a harness's CLI and the version its `--version` printed.
#[derive(Debug, Clone, PartialEq)]
pub struct Installed {
    pub executable: PathBuf,
    pub place: Place,
    pub version: Option<String>,
}

/// Every copy of `harness`'s CLI on this machine, in the order `--harness-version` looks: each version installed
/// apart under `cache` (by name), the tests' install, the command on the search path `path`; each with the version it
/// prints. A file found twice is listed once.
pub fn installed(harness: Harness, cache: &Path, path: &OsStr) -> Vec<Installed> {
    let Some(command) = harness.command() else { return Vec::new() };
    let prefix = format!("{}-", harness.as_str());
    let mut apart: Vec<PathBuf> = std::fs::read_dir(cache.join("harnesses"))
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| e.path().join("node_modules/.bin").join(command))
        .collect();
    apart.sort();
    let candidates = apart
        .into_iter()
        .map(|p| (p, Place::Apart))
        .chain([(cache.join("node/node_modules/.bin").join(command), Place::Tests)])
        .chain(which_in(command, path).map(|p| (p, Place::Path)));
    let mut out: Vec<Installed> = Vec::new();
    for (executable, place) in candidates.filter(|(p, _)| p.is_file()) {
        let real = std::fs::canonicalize(&executable).ok();
        if out.iter().any(|i| std::fs::canonicalize(&i.executable).ok() == real) {
            continue;
        }
        let version = probe(&[executable.to_string_lossy().into_owned(), "--version".into()], path).observed;
        out.push(Installed { executable, place, version });
    }
    out
}

/// A version as `--harness-version` takes it: digits, letters and `.-+_` (it names a directory).
fn check_version(version: &str) -> anyhow::Result<()> {
    let ok = !version.is_empty()
        && version.len() <= 64
        && version.chars().all(|c| c.is_ascii_alphanumeric() || ".-+_".contains(c))
        && version.chars().next().is_some_and(|c| c.is_ascii_alphanumeric());
    if !ok {
        bail!("--harness-version {version:?} is not a version (digits, letters and .-+_, e.g. 0.154.0)");
    }
    Ok(())
}

/// The executable of `harness` at exactly `version` ([`installed`] in `cache` and on `path`), or an error that says
/// which versions are installed and how to install the one asked for.
pub fn resolve(harness: Harness, version: &str, cache: &Path, path: &OsStr) -> anyhow::Result<PathBuf> {
    if harness.command().is_none() {
        bail!("--harness-version picks a version of an agent CLI; --harness {} runs --agent-cmd, which has none", harness.as_str());
    }
    check_version(version)?;
    let found = installed(harness, cache, path);
    if let Some(i) = found.iter().find(|i| i.version.as_deref() == Some(version)) {
        return Ok(i.executable.clone());
    }
    let name = harness.as_str();
    let listed: Vec<String> = found
        .iter()
        .map(|i| format!("{} ({}, {})", i.version.as_deref().unwrap_or("no version printed"), i.place.describe(), i.executable.display()))
        .collect();
    let mut msg = format!(
        "{name} {version} is not installed on this machine; installed: {}.",
        if listed.is_empty() { "none".to_owned() } else { listed.join(", ") }
    );
    let entry = lock_entry(harness);
    let pinned: Vec<(String, String)> = entry.as_ref().map(|e| e.versions.clone()).unwrap_or_default();
    let dir = install_dir(cache, harness, version);
    if pinned.iter().any(|(v, _)| v == version) {
        let pinned: Vec<String> = pinned.iter().map(|(v, why)| format!("{v} ({why})")).collect();
        msg.push_str(&format!(" The lock pins {name} {}: `{SETUP_COMMAND}` installs them (this one into {}).", pinned.join(", "), dir.display()));
        bail!("{msg}");
    }
    if !pinned.is_empty() {
        let pinned: Vec<&str> = pinned.iter().map(|(v, _)| v.as_str()).collect();
        msg.push_str(&format!(" The lock pins {name} {} (`{SETUP_COMMAND}` installs them), not {version}.", pinned.join(", ")));
    }
    let package = entry.map(|e| e.package).or_else(|| harness.npm_cli().map(|(p, _)| p.rsplit_once('@').map_or(p, |(p, _)| p).to_owned()));
    if let Some(package) = package {
        msg.push_str(&format!(" To run {version} anyway, install it apart: `npm install --prefix {} --save-exact {package}@{version}`.", dir.display()));
    }
    bail!("{msg}")
}

/// [`resolve`] in this machine's cache (`$LIBERO_AGENT_CACHE`, else `~/.cache/libero-agent`) and on the runner's PATH.
pub fn resolve_here(harness: Harness, version: &str) -> anyhow::Result<PathBuf> {
    resolve(harness, version, &cache_dir(), &std::env::var_os("PATH").unwrap_or_default())
}

/// `--version` of the CLI a rollout of `harness` launches ([`crate::harness::cli_command`]); `None` for `command`.
pub fn probe_cli(harness: Harness, npm_cli_installed: bool, cli_path: Option<&Path>) -> Option<HarnessVersion> {
    let argv = harness.version_probe(npm_cli_installed, cli_path)?;
    Some(probe(&argv, &std::env::var_os("PATH").unwrap_or_default()))
}

/// Runs `argv` (a `--version` command; at most 90 s) and reads what it printed: the command, the first
/// version-looking word of its output, the output, and the file the command is on the search path `path`.
pub fn probe(argv: &[String], path: &OsStr) -> HarnessVersion {
    probe_within(argv, path, PROBE_TIMEOUT)
}

fn probe_within(argv: &[String], path: &OsStr, timeout: Duration) -> HarnessVersion {
    let text = output_within(argv, timeout);
    let observed = text
        .split(|c: char| c.is_whitespace() || c == '@' || c == 'v')
        .find(|w| w.split('.').count() >= 3 && w.split('.').next().is_some_and(|x| x.parse::<u32>().is_ok()))
        .map(str::to_owned);
    let command = cli_command_of(argv);
    HarnessVersion {
        requested: Some(command.join(" ")),
        observed,
        probe_output: Some(text.trim().chars().take(PROBE_OUTPUT_CHARS).collect()),
        executable: command.first().and_then(|c| which_in(c, path)).map(|p| p.to_string_lossy().into_owned()),
        ..Default::default()
    }
}

/// A `--version` argv without its `--version`.
fn cli_command_of(argv: &[String]) -> &[String] {
    argv.strip_suffix(&["--version".to_owned()]).unwrap_or(argv)
}

/// Stdout and stderr of `argv`, stopped (its whole process group) after `timeout`.
fn output_within(argv: &[String], timeout: Duration) -> String {
    let Some(program) = argv.first() else { return String::new() };
    let spawned = Command::new(program)
        .args(&argv[1..])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn();
    let mut child = match spawned {
        Ok(c) => c,
        Err(e) => return format!("cannot run {program}: {e}"),
    };
    let drain = |pipe: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut bytes = Vec::new();
            if let Some(p) = pipe {
                let _ = p.take(1 << 20).read_to_end(&mut bytes);
            }
            bytes
        })
    };
    let out = drain(child.stdout.take().map(|p| Box::new(p) as Box<dyn Read + Send>));
    let err = drain(child.stderr.take().map(|p| Box::new(p) as Box<dyn Read + Send>));
    let t0 = Instant::now();
    let mut timed_out = false;
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if t0.elapsed() < timeout => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                timed_out = true;
                // SAFETY: signals the probe's own process group, which `process_group(0)` made.
                unsafe { libc::kill(-(child.id() as libc::pid_t), libc::SIGKILL) };
                let _ = child.wait();
                break;
            }
        }
    }
    let mut text = String::from_utf8_lossy(&out.join().unwrap_or_default()).into_owned();
    text.push_str(&String::from_utf8_lossy(&err.join().unwrap_or_default()));
    if timed_out {
        text.push_str(&format!("\n(stopped: no answer within {} s)", timeout.as_secs_f64()));
    }
    text
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::PermissionsExt;

    use super::*;

    /// An executable at `path` that prints `line` on `--version`.
    fn fake_cli(path: &Path, line: &str) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, format!("#!/bin/sh\necho '{line}'\n")).unwrap();
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
    }

    /// A cache with Codex 0.154.0 installed apart and 0.169.0 as the tests' install, and a PATH whose `codex` is
    /// 0.170.1.
    fn machine() -> (tempfile::TempDir, PathBuf, std::ffi::OsString) {
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("cache");
        fake_cli(&install_dir(&cache, Harness::Codex, "0.154.0").join("node_modules/.bin/codex"), "codex-cli 0.154.0");
        fake_cli(&cache.join("node/node_modules/.bin/codex"), "codex-cli 0.169.0");
        fake_cli(&dir.path().join("bin/codex"), "codex-cli 0.170.1");
        let path = std::env::join_paths([dir.path().join("bin"), PathBuf::from("/usr/bin"), PathBuf::from("/bin")]).unwrap();
        (dir, cache, path)
    }

    #[test]
    fn a_version_asked_for_resolves_to_the_copy_that_prints_it() {
        let (dir, cache, path) = machine();
        let apart = resolve(Harness::Codex, "0.154.0", &cache, &path).unwrap();
        assert_eq!(apart, cache.join("harnesses/codex-0.154.0/node_modules/.bin/codex"));
        assert_eq!(resolve(Harness::Codex, "0.169.0", &cache, &path).unwrap(), cache.join("node/node_modules/.bin/codex"));
        assert_eq!(resolve(Harness::Codex, "0.170.1", &cache, &path).unwrap(), dir.path().join("bin/codex"));
        let found = installed(Harness::Codex, &cache, &path);
        let seen: Vec<(Place, Option<&str>)> = found.iter().map(|i| (i.place, i.version.as_deref())).collect();
        assert_eq!(seen, [(Place::Apart, Some("0.154.0")), (Place::Tests, Some("0.169.0")), (Place::Path, Some("0.170.1"))]);
        // The probe of what a rollout launches names the file and the version.
        let v = probe_cli(Harness::Codex, false, Some(&apart)).unwrap();
        assert_eq!((v.observed.as_deref(), v.executable.as_deref()), (Some("0.154.0"), Some(apart.to_str().unwrap())));
        assert_eq!(v.requested.as_deref(), apart.to_str());
    }

    #[test]
    fn a_version_not_installed_is_an_error_naming_the_installed_ones_and_the_setup_command() {
        let (_dir, cache, path) = machine();
        // A version the lock pins, not installed here.
        let e = format!("{:#}", resolve(Harness::ClaudeCode, "2.1.139", &cache, &path).unwrap_err());
        assert!(e.starts_with("claude_code 2.1.139 is not installed on this machine; installed: none."), "{e}");
        assert!(e.contains("The lock pins claude_code 2.1.139 (the paper's (App. A)), 2.1.330"), "{e}");
        assert!(e.contains(&format!("`{SETUP_COMMAND}` installs them (this one into {})", cache.join("harnesses/claude_code-2.1.139").display())), "{e}");
        // A version the lock does not pin: what is installed, and how to install it apart.
        let e = format!("{:#}", resolve(Harness::Codex, "0.160.0", &cache, &path).unwrap_err());
        assert!(e.contains("codex 0.160.0 is not installed on this machine; installed: 0.154.0 (installed apart, "), "{e}");
        assert!(e.contains("0.169.0 (the tests' install, ") && e.contains("0.170.1 (on PATH, "), "{e}");
        assert!(e.contains("The lock pins codex 0.154.0, 0.169.0"), "{e}");
        let npm = format!("npm install --prefix {} --save-exact @openai/codex@0.160.0", cache.join("harnesses/codex-0.160.0").display());
        assert!(e.contains(&npm), "{e}");
        // No CLI, or no version.
        assert!(format!("{:#}", resolve(Harness::Command, "1.0.0", &cache, &path).unwrap_err()).contains("--agent-cmd"));
        for bad in ["../0.154.0", "", "0.1/2", "-1"] {
            assert!(format!("{:#}", resolve(Harness::Codex, bad, &cache, &path).unwrap_err()).contains("is not a version"), "{bad}");
        }
    }

    #[test]
    fn the_lock_lists_the_papers_versions_beside_the_tests() {
        let codex = lock_entry(Harness::Codex).unwrap();
        assert_eq!(codex.package, "@openai/codex");
        let versions: Vec<&str> = codex.versions.iter().map(|(v, _)| v.as_str()).collect();
        assert_eq!(versions, ["0.154.0", "0.169.0"]);
        let claude = lock_entry(Harness::ClaudeCode).unwrap();
        assert_eq!((claude.package.as_str(), claude.versions[0].0.as_str()), ("@anthropic-ai/claude-code", "2.1.139"));
        assert_eq!(lock_entry(Harness::QwenCode), None);
    }

    #[test]
    fn a_probe_that_hangs_is_stopped() {
        let dir = tempfile::tempdir().unwrap();
        let cli = dir.path().join("slow");
        std::fs::write(&cli, "#!/bin/sh\necho starting\nsleep 30\n").unwrap();
        std::fs::set_permissions(&cli, std::fs::Permissions::from_mode(0o755)).unwrap();
        let t0 = Instant::now();
        let v = probe_within(&[cli.to_string_lossy().into_owned(), "--version".into()], OsStr::new(""), Duration::from_millis(300));
        assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
        assert_eq!(v.observed, None);
        assert!(v.probe_output.as_deref().is_some_and(|o| o.starts_with("starting") && o.contains("stopped")), "{v:?}");
        let missing = probe(&["/nonexistent/codex".into(), "--version".into()], OsStr::new(""));
        assert!(missing.probe_output.unwrap().starts_with("cannot run /nonexistent/codex"));
    }
}
