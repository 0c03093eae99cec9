//! The operator credential as files: where `serve` keeps its token and how a client command of the same user
//! finds it without extra typing.
//!
//! `serve` writes its token to `<data>/operator_token` (0600) and registers it for its bound address in the
//! user's registry, `$LIBERO_AGENT_STATE/servers/<ip>_<port>.token` (default `~/.local/state/libero-agent/`,
//! directory 0700, file 0600), removed again when it stops. A client given a server URL takes the token from,
//! in order: `--operator-token-file` (or `$LIBERO_AGENT_OPERATOR_TOKEN_FILE`), the registry entry of the URL's
//! address, the default data directory's `operator_token`. A sandboxed agent sees none of these files: its
//! sandbox holds only its workspace and session home.
use std::fs;
use std::io::Write;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use anyhow::{Context, bail};

/// Name of the token file in the data directory.
pub const TOKEN_FILE: &str = "operator_token";
/// Environment variable naming a token file (what `--operator-token-file` sets for the whole process).
pub const TOKEN_FILE_ENV: &str = "LIBERO_AGENT_OPERATOR_TOKEN_FILE";

/// A token file named on the command line, for every client call of this process.
static EXPLICIT_FILE: OnceLock<PathBuf> = OnceLock::new();
/// Servers running inside this process (`run`, the benches): base URL and token, known without any file.
static IN_PROCESS: Mutex<Vec<(String, String)>> = Mutex::new(Vec::new());

/// Makes an in-process server's token known to this process's client calls (until [`forget_in_process`]).
pub fn remember_in_process(base_url: &str, token: &str) {
    if let Ok(mut m) = IN_PROCESS.lock() {
        m.push((base_url.trim_end_matches('/').to_owned(), token.to_owned()));
    }
}

pub fn forget_in_process(base_url: &str) {
    if let Ok(mut m) = IN_PROCESS.lock() {
        m.retain(|(u, _)| u != base_url.trim_end_matches('/'));
    }
}

/// Makes `file` the operator token of every later client call of this process (`--operator-token-file`).
pub fn use_token_file(file: &Path) {
    let _ = EXPLICIT_FILE.set(file.to_path_buf());
}

/// Reads and checks a token file: at least 16 characters, none of them whitespace, `;` or `,`.
pub fn read_token_file(file: &Path) -> anyhow::Result<String> {
    let text = fs::read_to_string(file).with_context(|| format!("cannot read the operator token file {}", file.display()))?;
    let token = text.lines().next().unwrap_or("").trim().to_owned();
    if token.len() < 16 || token.len() > 512 || token.chars().any(|c| c.is_whitespace() || c.is_control() || c == ';' || c == ',') {
        bail!("{}: the operator token must be 16 to 512 characters without spaces, ';' or ','", file.display());
    }
    Ok(token)
}

/// The user's registry of running servers' tokens.
pub fn registry_dir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("LIBERO_AGENT_STATE") {
        return Some(PathBuf::from(d).join("servers"));
    }
    let state = std::env::var_os("XDG_STATE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/state")))?;
    Some(state.join("libero-agent/servers"))
}

/// The registry file of a server bound to `addr`.
fn registry_file(dir: &Path, addr: SocketAddr) -> PathBuf {
    let ip = addr.ip().to_string().replace(':', "-");
    dir.join(format!("{ip}_{}.token", addr.port()))
}

/// Writes `token` to `path` with mode 0600 (replacing the file atomically, never through a link).
pub fn write_private(path: &Path, token: &str) -> anyhow::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let tmp = dir.join(format!(".{}.{}.tmp", path.file_name().and_then(|n| n.to_str()).unwrap_or("token"), std::process::id()));
    let _ = fs::remove_file(&tmp);
    let mut f = fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .custom_flags(libc::O_NOFOLLOW)
        .open(&tmp)
        .with_context(|| format!("cannot create {}", tmp.display()))?;
    f.write_all(token.as_bytes())?;
    f.write_all(b"\n")?;
    f.sync_all()?;
    fs::rename(&tmp, path).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}

/// A server's registration: written at start, removed at stop (only if it still holds this server's token).
pub struct Registration {
    path: PathBuf,
    token: String,
}

impl Registration {
    /// Registers `token` for `addr` in the user's registry; `None` (with a warning) where there is no home.
    pub fn register(addr: SocketAddr, token: &str) -> Option<Self> {
        let dir = registry_dir()?;
        let made = fs::DirBuilder::new().recursive(true).mode(0o700).create(&dir);
        let path = registry_file(&dir, addr);
        let written = made.map_err(anyhow::Error::from).and_then(|()| {
            fs::set_permissions(&dir, fs::Permissions::from_mode(0o700))?;
            write_private(&path, &format!("{token}\n{}", std::process::id()))
        });
        match written {
            Ok(()) => Some(Self { path, token: token.to_owned() }),
            Err(e) => {
                eprintln!("warning: cannot register the operator token in {}: {e:#}", dir.display());
                None
            }
        }
    }
}

impl Drop for Registration {
    fn drop(&mut self) {
        if read_token_file(&self.path).is_ok_and(|t| t == self.token) {
            let _ = fs::remove_file(&self.path);
        }
    }
}

/// The socket addresses a server reachable at `host:port` may have registered under.
fn candidate_addrs(host: &str, port: u16) -> Vec<SocketAddr> {
    let host = host.trim_start_matches('[').trim_end_matches(']');
    let mut ips: Vec<IpAddr> = match host.parse::<IpAddr>() {
        Ok(ip) => vec![ip],
        Err(_) if host.eq_ignore_ascii_case("localhost") => vec![Ipv4Addr::LOCALHOST.into(), Ipv6Addr::LOCALHOST.into()],
        Err(_) => vec![],
    };
    // A server bound to every address registers as 0.0.0.0 or [::].
    ips.extend([IpAddr::from(Ipv4Addr::UNSPECIFIED), IpAddr::from(Ipv6Addr::UNSPECIFIED)]);
    ips.into_iter().map(|ip| SocketAddr::new(ip, port)).collect()
}

/// Whether the server that wrote registry entry `file` still runs (a killed server cannot remove its entry).
fn registrant_alive(file: &Path) -> bool {
    let pid = fs::read_to_string(file).ok().and_then(|t| t.lines().nth(1).and_then(|p| p.trim().parse::<u32>().ok()));
    pid.is_some_and(|p| Path::new(&format!("/proc/{p}")).exists())
}

/// `host` and `port` of an `http://host:port/...` URL.
fn host_port(base_url: &str) -> Option<(String, u16)> {
    let rest = base_url.strip_prefix("http://")?;
    let authority = rest.split('/').next()?;
    let (host, port) = authority.rsplit_once(':').filter(|(h, _)| !h.ends_with(':'))?;
    Some((host.to_owned(), port.parse().ok()?))
}

/// The operator token for the server at `base_url`, if this user can find one (see the module doc).
pub fn token_for(base_url: &str) -> anyhow::Result<Option<String>> {
    let base = base_url.trim_end_matches('/');
    if let Some((_, token)) = IN_PROCESS.lock().ok().and_then(|m| m.iter().find(|(u, _)| base.starts_with(u.as_str())).cloned()) {
        return Ok(Some(token));
    }
    if let Some(file) = EXPLICIT_FILE.get() {
        return read_token_file(file).map(Some);
    }
    if let Some(file) = std::env::var_os(TOKEN_FILE_ENV) {
        return read_token_file(Path::new(&file)).map(Some);
    }
    if let (Some(dir), Some((host, port))) = (registry_dir(), host_port(base_url)) {
        for addr in candidate_addrs(&host, port) {
            let file = registry_file(&dir, addr);
            if registrant_alive(&file)
                && let Ok(token) = read_token_file(&file)
            {
                return Ok(Some(token));
            }
        }
    }
    Ok(read_token_file(&crate::default_data_dir().join(TOKEN_FILE)).ok())
}

/// `Authorization: Bearer …` for the server at `base_url` (empty when no token is found: the server then
/// answers 401, and the caller's error says how to pass one).
pub fn operator_headers(base_url: &str) -> anyhow::Result<Vec<(String, String)>> {
    Ok(token_for(base_url)?.map(|t| vec![("Authorization".to_owned(), format!("Bearer {t}"))]).unwrap_or_default())
}

/// What to tell a user whose request was refused for want of the operator token.
pub fn missing_token_hint(base_url: &str) -> String {
    format!(
        "the server at {base_url} needs its operator token: run this command as the user who started `libero-agent serve` \
         (it registers the token in {}), or pass --operator-token-file <data>/{TOKEN_FILE}",
        registry_dir().map(|d| d.display().to_string()).unwrap_or_else(|| "~/.local/state/libero-agent/servers".into())
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_map_to_the_addresses_a_server_registers_under() {
        assert_eq!(host_port("http://127.0.0.1:8080/api"), Some(("127.0.0.1".into(), 8080)));
        assert_eq!(host_port("http://[::1]:9/"), Some(("[::1]".into(), 9)));
        assert_eq!(host_port("http://localhost"), None);
        let c = candidate_addrs("localhost", 80);
        assert!(c.contains(&"127.0.0.1:80".parse().unwrap()) && c.contains(&"[::1]:80".parse().unwrap()));
        assert!(c.contains(&"0.0.0.0:80".parse().unwrap()));
    }

    #[test]
    fn token_files_are_private_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("t");
        write_private(&f, "0123456789abcdef0123").unwrap();
        assert_eq!(fs::metadata(&f).unwrap().permissions().mode() & 0o777, 0o600);
        assert_eq!(read_token_file(&f).unwrap(), "0123456789abcdef0123");
        fs::write(&f, "short").unwrap();
        assert!(read_token_file(&f).is_err());
    }

    #[test]
    fn writing_a_token_never_follows_a_planted_link() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        fs::write(&victim, "keep").unwrap();
        let f = dir.path().join("t");
        std::os::unix::fs::symlink(&victim, &f).unwrap();
        write_private(&f, "0123456789abcdef0123").unwrap();
        assert_eq!(fs::read_to_string(&victim).unwrap(), "keep");
        assert!(!fs::symlink_metadata(&f).unwrap().file_type().is_symlink());
    }
}
