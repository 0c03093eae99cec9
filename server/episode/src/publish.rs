//! Publication of `benchmark_inputs/current_observation/` (§3.4) into a workspace the agent shares with
//! the server (same Unix user, and it can watch with inotify). The frame is encoded once in memory; the
//! private archive is written from those bytes, never read back from the workspace. The public copy is
//! built in a staging directory the agent cannot see (a server-owned sibling of the workspace; inside
//! `benchmark_inputs` only as a fallback), written through directory descriptors with `O_EXCL` and
//! `O_NOFOLLOW` under a fresh random name, fsync'd, then swapped in with one
//! `renameat2(RENAME_EXCHANGE)` so that a reader always finds a complete directory; the previous frame is
//! removed without following or opening anything the agent may have put in it. Nothing the agent plants
//! (symlink, file, FIFO, socket) is ever followed or opened: it makes an exclusive creation fail, and the
//! publication discards that staging and retries under another name.
//!
//! The agent may also wreck the workspace itself, at any moment, in a loop: delete, rename away or replace
//! `benchmark_inputs` or `current_observation` (by a file, a symlink, a FIFO, a socket, a tree of any depth),
//! or `chmod 000` them. Every attempt therefore starts again from the workspace root the server holds open:
//! `benchmark_inputs` is reopened (recreated, or its mode repaired, when it is not a usable directory) and,
//! after the swap, checked to be still linked and still the workspace's `benchmark_inputs`; if not, the
//! frame is staged and swapped again. A publication gives up only after [`ATTEMPTS`] attempts the agent
//! spoiled, or at once on a failure no retry can mend (a full disk, the workspace root itself removed); the
//! episode then goes on (the actor tells the agent; see [`crate::error::PublishError`]).
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::path::{Path, PathBuf};

use rustix::fs::{Mode, OFlags};
use rustix::io::Errno;
use serde_json::Value;

use crate::dirfd::{
    ensure_dir_at, ensure_owner_rwx, exchange_at, make_dir_at, open_dir_at, open_dir_path, random_name, remove_at,
    rename_noreplace_at, repair_dir_mode_at, sync_dir_fd, write_new_file_at,
};
pub use crate::error::PublishError;
use crate::observation::{EncodedObservation, Frame, Level, encode_observation, write_encoded_dir};

const BENCHMARK_INPUTS: &str = "benchmark_inputs";
const CURRENT: &str = "current_observation";
/// Suffix of the staging sibling `<workspace parent>/.<workspace name>.libero-staging/`.
pub const STAGING_SUFFIX: &str = ".libero-staging";
/// Attempts of one publication: each failed one means the agent changed the workspace under it (took a
/// staging name, removed, moved or replaced `benchmark_inputs` or `current_observation`).
pub const ATTEMPTS: usize = 8;

fn errno(e: &std::io::Error) -> Option<Errno> {
    Errno::from_io_error(e)
}

/// Failures that another attempt cannot mend.
fn is_hopeless(e: &std::io::Error) -> bool {
    matches!(
        errno(e),
        Some(Errno::NOSPC | Errno::DQUOT | Errno::ROFS | Errno::IO | Errno::NOMEM | Errno::MFILE | Errno::NFILE)
    )
}

/// How one attempt ended, short of success.
enum Spoiled {
    /// The agent was in the way: try again from the workspace root.
    Retry(std::io::Error),
    /// No attempt can succeed.
    Hopeless(std::io::Error),
}

impl From<std::io::Error> for Spoiled {
    fn from(e: std::io::Error) -> Self {
        if is_hopeless(&e) { Spoiled::Hopeless(e) } else { Spoiled::Retry(e) }
    }
}

impl From<Errno> for Spoiled {
    fn from(e: Errno) -> Self {
        std::io::Error::from(e).into()
    }
}

/// The server-owned staging directory beside the workspace, outside what a sandboxed agent can see.
struct SiblingStaging {
    parent: OwnedFd,
    name: String,
    dir: OwnedFd,
}

impl SiblingStaging {
    /// Creates (0700) or reopens `<parent>/.<name>.libero-staging` on the workspace's filesystem.
    fn create(workspace_path: &Path, workspace: BorrowedFd<'_>) -> std::io::Result<Self> {
        let ws_name = workspace_path.file_name().and_then(|n| n.to_str()).ok_or_else(|| {
            std::io::Error::other(format!("{}: no UTF-8 final component to name a staging sibling", workspace_path.display()))
        })?;
        let parent_path = workspace_path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        // The parent is the operator's (the server made the workspace in it): following a link there is fine.
        let parent = rustix::fs::open(parent_path, OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC, Mode::empty())?;
        let name = format!(".{ws_name}{STAGING_SUFFIX}");
        ensure_dir_at(parent.as_fd(), &name, 0o700)?;
        let dir = open_dir_at(parent.as_fd(), &name)?;
        rustix::fs::fchmod(&dir, Mode::from_raw_mode(0o700))?; // one left by a crash is made private again
        if rustix::fs::fstat(&dir)?.st_dev != rustix::fs::fstat(workspace)?.st_dev {
            return Err(Errno::XDEV.into()); // the exchange would fail: stage in the workspace instead
        }
        Ok(Self { parent, name, dir })
    }

    /// Whether the sibling is still there and private (it is out of a sandboxed agent's reach; an agent
    /// without the sandbox may remove it or change its mode).
    fn still_usable(&self) -> bool {
        match rustix::fs::fstat(&self.dir) {
            Ok(st) if st.st_nlink > 0 => {
                st.st_mode & 0o777 == 0o700 || rustix::fs::fchmod(&self.dir, Mode::from_raw_mode(0o700)).is_ok()
            }
            _ => false,
        }
    }
}

/// Where staging directories are made.
enum StagingArea {
    /// The sibling is created at the first publication.
    Untried,
    Sibling(SiblingStaging),
    /// No sibling (it could not be created, or the exchange crossed filesystems): inside `benchmark_inputs`.
    InWorkspace,
}

/// Moments of a publication attempt at which tests act as the agent.
#[cfg(test)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Moment {
    /// Before `benchmark_inputs` is opened.
    Begin,
    /// The frame is staged; `benchmark_inputs` is open.
    Staged,
    /// The frame was swapped into the open `benchmark_inputs`, not yet checked.
    Swapped,
}

/// What a test's agent does at each moment of each attempt of a publisher.
#[cfg(test)]
pub(crate) type Hook = Box<dyn FnMut(Moment, usize) + Send>;

/// Hooks for the publishers that tests of other modules open (the actor opens its own): by workspace path.
#[cfg(test)]
static INSTALLED_HOOKS: std::sync::Mutex<Vec<(PathBuf, Hook)>> = std::sync::Mutex::new(Vec::new());

/// Makes the next publisher opened on `workspace` run `hook` (see [`ObservationPublisher::with_hook`]).
#[cfg(test)]
pub(crate) fn install_hook(workspace: &Path, hook: impl FnMut(Moment, usize) + Send + 'static) {
    INSTALLED_HOOKS.lock().unwrap_or_else(|p| p.into_inner()).push((workspace.to_path_buf(), Box::new(hook)));
}

#[cfg(test)]
fn installed_hook(workspace: &Path) -> Option<Hook> {
    let mut hooks = INSTALLED_HOOKS.lock().unwrap_or_else(|p| p.into_inner());
    let i = hooks.iter().position(|(p, _)| p == workspace)?;
    Some(hooks.swap_remove(i).1)
}

/// Publishes an episode's observations into its workspace. Holds the workspace root open for the episode's
/// life, so that the agent renaming things inside it never redirects the server's writes.
pub struct ObservationPublisher {
    workspace: OwnedFd,
    workspace_path: PathBuf,
    staging: StagingArea,
    /// Staging names (random; tests inject planted ones).
    names: Box<dyn FnMut() -> std::io::Result<String> + Send>,
    /// What a test's agent does at each moment of each attempt (attempt index from 0).
    #[cfg(test)]
    hook: Option<Hook>,
}

impl ObservationPublisher {
    /// Opens the existing workspace root (its last component must not be a symlink).
    pub fn open(workspace: &Path) -> std::io::Result<Self> {
        let fd = open_dir_path(workspace)
            .map_err(|e| std::io::Error::new(e.kind(), format!("workspace {}: {e}", workspace.display())))?;
        Ok(Self {
            workspace: fd,
            workspace_path: workspace.to_path_buf(),
            staging: StagingArea::Untried,
            names: Box::new(|| random_name(".current_observation.next-")),
            #[cfg(test)]
            hook: installed_hook(workspace),
        })
    }

    /// Stages under the names `names` gives instead of random ones (tests plant entries under them).
    #[cfg(test)]
    fn with_names(mut self, names: impl FnMut() -> std::io::Result<String> + Send + 'static) -> Self {
        self.names = Box::new(names);
        self
    }

    /// Runs `hook` at every [`Moment`] of every attempt (tests sabotage the workspace there).
    #[cfg(test)]
    fn with_hook(mut self, hook: impl FnMut(Moment, usize) + Send + 'static) -> Self {
        self.hook = Some(Box::new(hook));
        self
    }

    #[cfg(test)]
    fn at(&mut self, moment: Moment, attempt: usize) {
        if let Some(hook) = self.hook.as_mut() {
            hook(moment, attempt);
        }
    }

    /// Publishes `frame` as the workspace's current observation; returns the observation document.
    /// `private_copy_root`, when given, first receives an evaluator-private copy at `<root>/<observation_id>/`,
    /// written from the same in-memory bytes.
    pub fn publish(&mut self, frame: &Frame, level: Level, private_copy_root: Option<&Path>) -> Result<Value, PublishError> {
        let encoded = encode_observation(frame, level).map_err(PublishError::Private)?;
        if let Some(root) = private_copy_root {
            write_private_copy(root, &encoded).map_err(PublishError::Private)?;
        }
        self.publish_encoded(&encoded).map_err(PublishError::Workspace)?;
        Ok(encoded.document)
    }

    /// Stages `encoded` and swaps it in as `current_observation`, attempt after attempt while the agent is
    /// in the way (see the module's documentation).
    pub fn publish_encoded(&mut self, encoded: &EncodedObservation) -> std::io::Result<()> {
        let mut last = None;
        for attempt in 0..ATTEMPTS {
            match self.attempt(encoded, attempt) {
                Ok(()) => return Ok(()),
                Err(Spoiled::Hopeless(e)) => return Err(e),
                Err(Spoiled::Retry(e)) => {
                    log::debug!("{}: publication attempt {attempt} spoiled: {e}", self.workspace_path.display());
                    last = Some(e);
                }
            }
        }
        let why = last.map(|e| e.to_string()).unwrap_or_default();
        Err(std::io::Error::other(format!("gave up after {ATTEMPTS} attempts, each spoiled by a change to the workspace (last: {why})")))
    }

    /// One attempt, from the workspace root.
    #[cfg_attr(not(test), allow(unused_variables))]
    fn attempt(&mut self, encoded: &EncodedObservation, attempt: usize) -> Result<(), Spoiled> {
        #[cfg(test)]
        self.at(Moment::Begin, attempt);
        let ws = self.workspace.as_fd();
        if rustix::fs::fstat(ws)?.st_nlink == 0 {
            return Err(Spoiled::Hopeless(std::io::Error::other("the workspace directory itself was removed")));
        }
        ensure_owner_rwx(ws)?;
        let bi = self.benchmark_inputs()?;
        self.prepare_staging();
        let name = (self.names)()?;
        let in_sibling = matches!(self.staging, StagingArea::Sibling(_));
        let area = match &self.staging {
            StagingArea::Sibling(s) => s.dir.as_fd(),
            _ => bi.as_fd(),
        };
        let staged = match stage(area, &name, encoded) {
            Ok(staged) => staged,
            Err(e) => {
                discard(area, &name);
                return Err(e.into());
            }
        };
        #[cfg(test)]
        self.at(Moment::Staged, attempt);
        let area = match &self.staging {
            StagingArea::Sibling(s) => s.dir.as_fd(),
            _ => bi.as_fd(),
        };
        if let Err(e) = swap_in(area, &name, bi.as_fd()) {
            discard(area, &name);
            if in_sibling && errno(&e) == Some(Errno::XDEV) {
                log::warn!("{}: staging sibling on another filesystem; staging in the workspace", self.workspace_path.display());
                self.staging = StagingArea::InWorkspace;
            }
            return Err(e.into());
        }
        #[cfg(test)]
        self.at(Moment::Swapped, attempt);
        // The frame is in the directory opened above; is that still the workspace's `benchmark_inputs`, and the
        // frame still its `current_observation`?
        let spoiled = |what: &str| Spoiled::Retry(std::io::Error::other(format!("{what} during the publication")));
        let published = rustix::fs::fstat(&bi)?;
        if published.st_nlink == 0 {
            return Err(spoiled("benchmark_inputs was removed"));
        }
        let now = open_dir_at(self.workspace.as_fd(), BENCHMARK_INPUTS).and_then(|fd| Ok(rustix::fs::fstat(&fd)?));
        if !now.is_ok_and(|st| (st.st_dev, st.st_ino) == (published.st_dev, published.st_ino)) {
            return Err(spoiled("benchmark_inputs was moved or replaced"));
        }
        // `staged` is still open, so its inode cannot have been freed and reused by whatever replaced it.
        let staged = rustix::fs::fstat(&staged)?;
        let current = rustix::fs::statat(&bi, CURRENT, rustix::fs::AtFlags::SYMLINK_NOFOLLOW);
        if !current.is_ok_and(|st| (st.st_dev, st.st_ino) == (staged.st_dev, staged.st_ino)) {
            return Err(spoiled("current_observation was removed or replaced"));
        }
        Ok(())
    }

    /// Creates the sibling staging directory at the first publication (or again if it went), or settles for
    /// the workspace.
    fn prepare_staging(&mut self) {
        if let StagingArea::Sibling(s) = &self.staging {
            if s.still_usable() {
                return;
            }
            log::warn!("{}: staging sibling removed or changed; making it again", self.workspace_path.display());
            self.staging = StagingArea::Untried;
        }
        if !matches!(self.staging, StagingArea::Untried) {
            return;
        }
        self.staging = match SiblingStaging::create(&self.workspace_path, self.workspace.as_fd()) {
            Ok(s) => StagingArea::Sibling(s),
            Err(e) => {
                log::warn!("{}: no staging sibling ({e}); staging in the workspace", self.workspace_path.display());
                StagingArea::InWorkspace
            }
        };
    }

    /// `benchmark_inputs`, opened without following and made usable (`u+rwx`). Whatever else the agent put
    /// under that name (a symlink, a file, a FIFO, a socket) is unlinked and the directory recreated; one it
    /// made unreadable gets its mode back.
    fn benchmark_inputs(&self) -> std::io::Result<OwnedFd> {
        let ws = self.workspace.as_fd();
        for _ in 0..ATTEMPTS {
            match open_dir_at(ws, BENCHMARK_INPUTS) {
                Ok(fd) => {
                    ensure_owner_rwx(fd.as_fd())?;
                    return Ok(fd);
                }
                Err(e) => match errno(&e) {
                    Some(Errno::NOENT) => {}
                    // Only a non-directory is unlinked here (EISDIR: it became a directory again; reopen it).
                    Some(Errno::LOOP | Errno::NOTDIR) => match rustix::fs::unlinkat(ws, BENCHMARK_INPUTS, rustix::fs::AtFlags::empty()) {
                        Ok(()) | Err(Errno::NOENT | Errno::ISDIR | Errno::PERM) => {}
                        Err(e) => return Err(e.into()),
                    },
                    Some(Errno::ACCESS | Errno::PERM) => match repair_dir_mode_at(ws, BENCHMARK_INPUTS) {
                        Ok(()) => continue,
                        Err(r) if matches!(errno(&r), Some(Errno::NOENT | Errno::NOTDIR | Errno::LOOP)) => continue,
                        Err(r) => return Err(r),
                    },
                    _ => return Err(e),
                },
            }
            ensure_dir_at(ws, BENCHMARK_INPUTS, 0o777)?;
        }
        Err(std::io::Error::other(format!("{BENCHMARK_INPUTS} kept being replaced")))
    }

    /// Removes the sibling staging directory once the episode has ended (a later publication would make a
    /// new one).
    pub fn release_staging(&mut self) {
        if let StagingArea::Sibling(s) = std::mem::replace(&mut self.staging, StagingArea::Untried) {
            if let Err(e) = remove_at(s.parent.as_fd(), &s.name) {
                log::warn!("{}: staging sibling {} left behind: {e}", self.workspace_path.display(), s.name);
            }
        }
    }
}

impl Drop for ObservationPublisher {
    fn drop(&mut self) {
        self.release_staging();
    }
}

/// Writes the private archive's copy at `<root>/<observation_id>/` from memory (the run directory is private).
pub fn write_private_copy(root: &Path, encoded: &EncodedObservation) -> std::io::Result<()> {
    std::fs::create_dir_all(root)?;
    let dest = root.join(&encoded.observation_id);
    match std::fs::create_dir(&dest) {
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(std::io::Error::other(format!(
            "duplicate observation id {} in the private archive",
            encoded.observation_id
        ))),
        other => other,
    }?;
    write_encoded_dir(&dest, encoded)
}

/// Creates the staging directory `name` in `area` and writes `encoded` into it, every entry created new;
/// the directory, open (held, its identity stays its own: the inode cannot be reused while it is open).
fn stage(area: BorrowedFd<'_>, name: &str, encoded: &EncodedObservation) -> std::io::Result<OwnedFd> {
    let root = make_dir_at(area, name, 0o777)?;
    let mut dirs: Vec<(&str, OwnedFd)> = Vec::new();
    for sub in encoded.dirs() {
        dirs.push((sub, make_dir_at(root.as_fd(), sub, 0o777)?));
    }
    for file in &encoded.files {
        let (dir, file_name) = file.split();
        let fd = match dir {
            None => root.as_fd(),
            Some(d) => dirs.iter().find(|(n, _)| *n == d).map(|(_, fd)| fd.as_fd()).ok_or_else(|| {
                std::io::Error::other(format!("{}: directory not staged", file.rel_path))
            })?,
        };
        write_new_file_at(fd, file_name, &file.bytes)?;
    }
    for (_, fd) in &dirs {
        sync_dir_fd(fd.as_fd())?;
    }
    sync_dir_fd(root.as_fd())?;
    Ok(root)
}

/// Makes the staged `area/name` the current observation. The first publication (or one after the agent
/// removed the current one) renames; later ones exchange, then remove the previous frame. A
/// `current_observation` the agent made read-only (moving a directory to another parent writes its `..`)
/// gets its mode back first.
fn swap_in(area: BorrowedFd<'_>, name: &str, bi: BorrowedFd<'_>) -> std::io::Result<()> {
    let exchanged = match exchange_at(area, name, bi, CURRENT) {
        Err(e) if matches!(errno(&e), Some(Errno::ACCESS | Errno::PERM)) => {
            repair_dir_mode_at(bi, CURRENT)?;
            exchange_at(area, name, bi, CURRENT)
        }
        other => other,
    };
    match exchanged {
        Ok(()) => {
            sync_dir_fd(bi)?;
            discard(area, name); // now the previous frame
        }
        Err(e) if errno(&e) == Some(Errno::NOENT) => rename_noreplace_at(area, name, bi, CURRENT)?,
        Err(e) if errno(&e) == Some(Errno::INVAL) => {
            // Filesystems without RENAME_EXCHANGE: the original rename-aside sequence.
            let previous = random_name(".current_observation.previous-")?;
            rename_noreplace_at(bi, CURRENT, bi, previous.as_str())?;
            rename_noreplace_at(area, name, bi, CURRENT)?;
            sync_dir_fd(bi)?;
            discard(bi, &previous);
        }
        Err(e) => return Err(e),
    }
    sync_dir_fd(bi)?;
    sync_dir_fd(area)
}

/// Removes a staging directory or a previous frame. A failure (only an agent builds trees too large to
/// remove, or keeps adding to one) leaves it in place and is logged: the publication itself is complete.
fn discard(dir: BorrowedFd<'_>, name: &str) {
    if let Err(e) = remove_at(dir, name) {
        log::warn!("cannot remove {name}: {e}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observation::{CameraFrame, RgbImage, RobotReadout};
    use std::fs;
    use std::os::unix::fs::{FileTypeExt, symlink};
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::time::Duration;

    /// A synthetic frame (writer test only; episodes publish rendered frames).
    fn frame(index: u64, w: u32, h: u32) -> Frame {
        let n = (w * h) as usize;
        let cam = |shade: u8| CameraFrame {
            image: RgbImage { width: w, height: h, rgb: vec![shade; n * 3] },
            depth_m: (0..n).map(|i| 0.5 + i as f32 * 0.01).collect(),
            depth_valid: (0..n).map(|i| i % 7 != 0).collect(),
            intrinsic_matrix_3x3: [[1.0, 0.0, w as f64 / 2.0], [0.0, 1.0, h as f64 / 2.0], [0.0, 0.0, 1.0]],
            t_robot_base_from_camera: [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        };
        Frame {
            frame_index: index,
            robot: RobotReadout { sim_time_s: index as f64 * 0.05, ..Default::default() },
            head: cam(10),
            wrist: cam(200),
            // The task's reference image, published in every frame (§3.9): one more server-written subdirectory.
            task_reference: Some(RgbImage { width: 2, height: 2, rgb: vec![77; 12] }),
        }
    }

    /// A workspace `<tmp>/ws` with its publisher; the sibling staging directory is `<tmp>/.ws.libero-staging`.
    struct Fixture {
        dir: tempfile::TempDir,
        publisher: ObservationPublisher,
        /// Whether a file planted at the sibling's path makes staging fall back into `benchmark_inputs`.
        in_workspace: bool,
    }

    impl Fixture {
        fn new() -> Self {
            let dir = tempfile::tempdir().unwrap();
            fs::create_dir(dir.path().join("ws")).unwrap();
            let publisher = ObservationPublisher::open(&dir.path().join("ws")).unwrap();
            Self { dir, publisher, in_workspace: false }
        }
        /// Without a staging sibling: a file planted where it would go.
        fn in_workspace() -> Self {
            let f = Self::new();
            fs::write(f.sibling(), b"not a directory").unwrap();
            Self { in_workspace: true, ..f }
        }
        fn ws(&self) -> PathBuf {
            self.dir.path().join("ws")
        }
        fn bi(&self) -> PathBuf {
            self.ws().join(BENCHMARK_INPUTS)
        }
        fn sibling(&self) -> PathBuf {
            self.dir.path().join(format!(".ws{STAGING_SUFFIX}"))
        }
        fn staging_dir(&self) -> PathBuf {
            if self.in_workspace { self.bi() } else { self.sibling() }
        }
        fn publish(&mut self, index: u64) -> Result<Value, PublishError> {
            let private = self.dir.path().join("private");
            self.publisher.publish(&frame(index, 4, 3), Level::L3, Some(&private))
        }
        fn current_id(&self) -> Value {
            let path = self.bi().join("current_observation/observation.json");
            let text = fs::read(&path).unwrap_or_else(|e| {
                let kinds: Vec<String> = [self.ws(), self.bi(), self.bi().join("current_observation"), path.clone()]
                    .iter()
                    .map(|p| format!("{}: {:?}", p.display(), fs::symlink_metadata(p).map(|m| m.file_type())))
                    .collect();
                panic!("{}: {e}; {kinds:#?}", path.display())
            });
            serde_json::from_slice::<Value>(&text).unwrap()["observation_id"].clone()
        }
        /// A host directory outside the workspace with one file the agent must never get at.
        fn host_dir(&self) -> PathBuf {
            let host = self.dir.path().join("host");
            if !host.exists() {
                fs::create_dir(&host).unwrap();
                fs::write(host.join("secret.txt"), b"host secret").unwrap();
            }
            host
        }
        fn assert_host_untouched(&self) {
            let names: Vec<_> = fs::read_dir(self.host_dir()).unwrap().map(|e| e.unwrap().file_name()).collect();
            assert_eq!(names, ["secret.txt"], "nothing written into the host directory");
            assert_eq!(fs::read(self.host_dir().join("secret.txt")).unwrap(), b"host secret");
        }
    }

    fn names_of(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> =
            fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        names
    }

    fn fifo(path: &Path) {
        rustix::fs::mknodat(rustix::fs::CWD, path, rustix::fs::FileType::Fifo, Mode::from_raw_mode(0o600), 0).unwrap();
    }

    /// Every file of a private archive entry, by relative path.
    fn archive_files(root: &Path) -> Vec<(String, Vec<u8>)> {
        let mut out = Vec::new();
        for dir in ["", "head", "wrist", "task_reference"] {
            for name in names_of(&root.join(dir)) {
                let path = root.join(dir).join(&name);
                let meta = fs::symlink_metadata(&path).unwrap();
                assert!(!meta.file_type().is_symlink(), "{} is a symlink", path.display());
                if meta.is_file() {
                    let rel = if dir.is_empty() { name } else { format!("{dir}/{name}") };
                    out.push((rel, fs::read(&path).unwrap()));
                }
            }
        }
        out.sort();
        out
    }

    /// Runs `f` on another thread and fails the test if it has not returned within a few seconds.
    fn within_seconds<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        within(Duration::from_secs(10), f)
    }

    fn within<T: Send + 'static>(limit: Duration, f: impl FnOnce() -> T + Send + 'static) -> T {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(limit).expect("publication blocked on something the agent made")
    }

    #[test]
    fn levels_publish_exactly_the_level_matrix_files() {
        for level in [Level::L1, Level::L2, Level::L3] {
            let mut f = Fixture::new();
            let doc = f.publisher.publish(&frame(0, 4, 3), level, None).unwrap();
            let cur = f.bi().join("current_observation");
            let depth_files = ["depth_m.npy", "depth_valid_mask.png", "depth_visualization.png"];
            for cam in ["head", "wrist"] {
                assert!(cur.join(cam).join("rgb.png").is_file());
                for file in depth_files {
                    assert_eq!(cur.join(cam).join(file).is_file(), level == Level::L3, "{level:?} {cam}/{file}");
                }
                let keys: Vec<&String> = doc["cameras"][cam].as_object().unwrap().keys().collect();
                let expected: &[&str] = if level == Level::L3 {
                    &["depth", "intrinsic_matrix_3x3", "matrix_T_robot_base_from_camera_opencv_4x4", "rgb"]
                } else {
                    &["rgb"]
                };
                assert_eq!(keys, expected);
            }
            assert_eq!(doc.get("proprioception").is_some(), level >= Level::L2);
            assert_eq!(doc["capabilities"]["metric_depth"], level == Level::L3);
            let on_disk: Value = serde_json::from_slice(&fs::read(cur.join("observation.json")).unwrap()).unwrap();
            assert_eq!(on_disk, doc);
        }
    }

    #[test]
    fn no_staging_is_left_behind_and_the_sibling_goes_with_the_publisher() {
        let mut f = Fixture::new();
        for i in 0..3 {
            f.publish(i).unwrap();
            assert_eq!(names_of(&f.bi()), ["current_observation"], "no staging in the workspace");
            assert!(names_of(&f.sibling()).is_empty(), "no staging in the sibling");
        }
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(fs::metadata(f.sibling()).unwrap().permissions().mode() & 0o777, 0o700);
        let sibling = f.sibling();
        drop(f.publisher);
        assert!(!sibling.exists(), "the staging sibling is removed with the publisher");
        let mut g = Fixture::in_workspace();
        g.publish(0).unwrap();
        g.publish(1).unwrap();
        assert_eq!(names_of(&g.bi()), ["current_observation"], "fallback staging leaves nothing behind");
    }

    #[test]
    fn a_reader_never_sees_a_partial_or_missing_observation() {
        for mut f in [Fixture::new(), Fixture::in_workspace()] {
            f.publisher.publish(&frame(0, 32, 32), Level::L3, None).unwrap();
            let stop = Arc::new(AtomicBool::new(false));
            let reader = {
                let (cur, stop) = (f.bi().join("current_observation"), stop.clone());
                std::thread::spawn(move || {
                    let mut reads = 0u32;
                    while !stop.load(Ordering::Relaxed) {
                        let text = fs::read(cur.join("observation.json")).expect("observation.json always present");
                        let doc: Value = serde_json::from_slice(&text).expect("always complete JSON");
                        assert!(doc["observation_id"].as_str().unwrap().starts_with("obs_"));
                        reads += 1;
                    }
                    reads
                })
            };
            for i in 1..=30 {
                f.publisher.publish(&frame(i, 32, 32), Level::L3, None).unwrap();
            }
            stop.store(true, Ordering::Relaxed);
            assert!(reader.join().unwrap() > 0);
            assert_eq!(f.current_id(), "obs_000030");
        }
    }

    #[test]
    fn private_copy_refuses_a_duplicate_id() {
        let mut f = Fixture::new();
        f.publish(0).unwrap();
        assert!(f.dir.path().join("private/obs_000000/observation.json").is_file());
        assert!(f.publish(0).is_err());
    }

    #[test]
    fn private_archive_is_written_from_memory() {
        // Every staging name is taken by a symlink to a host directory, so no staging directory is ever
        // made: the archive can only come from the encoded bytes.
        let mut f = Fixture::new();
        let host = f.host_dir();
        let staging = f.staging_dir();
        f.publisher = ObservationPublisher::open(&f.ws()).unwrap().with_names(move || {
            let name = random_name(".planted-")?;
            fs::create_dir_all(&staging)?;
            symlink(&host, staging.join(&name))?;
            Ok(name)
        });
        assert!(f.publish(7).is_err(), "no staging name was free");
        let archived = archive_files(&f.dir.path().join("private/obs_000007"));
        let encoded = encode_observation(&frame(7, 4, 3), Level::L3).unwrap();
        let mut expected: Vec<(String, Vec<u8>)> = encoded.files.into_iter().map(|e| (e.rel_path, e.bytes)).collect();
        expected.sort();
        assert_eq!(archived, expected, "the archive holds exactly the encoded bytes");
        f.assert_host_untouched();
        // And a normal publication puts the same bytes in both places.
        let mut g = Fixture::new();
        g.publish(1).unwrap();
        assert_eq!(archive_files(&g.bi().join("current_observation")), archive_files(&g.dir.path().join("private/obs_000001")));
    }

    #[test]
    fn a_symlink_planted_in_staging_is_never_followed() {
        for mut f in [Fixture::new(), Fixture::in_workspace()] {
            let (host, staging) = (f.host_dir(), f.staging_dir());
            fs::create_dir_all(&staging).unwrap();
            // The first name is a symlink to the host directory, the second a directory whose `head` is one.
            symlink(&host, staging.join("planted-1")).unwrap();
            fs::create_dir(staging.join("planted-2")).unwrap();
            symlink(&host, staging.join("planted-2/head")).unwrap();
            let mut names = vec!["fresh".to_owned(), "planted-2".to_owned(), "planted-1".to_owned()];
            f.publisher = ObservationPublisher::open(&f.ws()).unwrap().with_names(move || Ok(names.pop().unwrap()));
            f.publish(3).unwrap();
            assert_eq!(f.current_id(), "obs_000003");
            f.assert_host_untouched();
            assert!(archive_files(&f.dir.path().join("private/obs_000003")).iter().all(|(_, b)| b != b"host secret"));
            assert!(!staging.join("planted-1").exists() && !staging.join("planted-2").exists(), "planted entries discarded");
        }
    }

    #[test]
    fn publication_fails_cleanly_when_every_staging_name_is_taken() {
        let mut f = Fixture::in_workspace();
        let bi = f.bi();
        f.publisher = ObservationPublisher::open(&f.ws()).unwrap().with_names(move || {
            fs::create_dir_all(&bi)?;
            fs::write(bi.join("taken"), b"agent file")?;
            Ok("taken".to_owned())
        });
        let err = f.publish(0).unwrap_err();
        assert!(err.to_string().contains("gave up"), "{err}");
    }

    #[test]
    fn symlinked_workspace_entries_are_replaced_never_followed() {
        // `benchmark_inputs` itself a symlink to a host directory.
        let mut f = Fixture::new();
        symlink(f.host_dir(), f.bi()).unwrap();
        f.publish(0).unwrap();
        assert!(!fs::symlink_metadata(f.bi()).unwrap().file_type().is_symlink(), "recreated as a directory");
        assert_eq!(f.current_id(), "obs_000000");
        f.assert_host_untouched();
        // `current_observation` a symlink to the host directory: exchanged out and unlinked, target intact.
        let cur = f.bi().join("current_observation");
        fs::rename(&cur, f.dir.path().join("moved_away")).unwrap();
        symlink(f.host_dir(), &cur).unwrap();
        f.publish(1).unwrap();
        assert_eq!(f.current_id(), "obs_000001");
        f.assert_host_untouched();
        // The previous frame's files replaced by links to a host file: removed, never written through.
        symlink(f.host_dir().join("secret.txt"), cur.join("head/stolen.png")).unwrap();
        fs::remove_dir_all(cur.join("wrist")).unwrap();
        symlink(f.host_dir(), cur.join("wrist")).unwrap();
        f.publish(2).unwrap();
        f.assert_host_untouched();
    }

    #[test]
    fn a_fifo_in_the_workspace_never_blocks_publication() {
        let plants: [(&str, fn(&Fixture)); 5] = [
            ("benchmark_inputs", |f| fifo(&f.bi())),
            ("current_observation", |f| {
                fs::remove_dir_all(f.bi().join("current_observation")).unwrap();
                fifo(&f.bi().join("current_observation"));
            }),
            ("a previous frame's file", |f| {
                let png = f.bi().join("current_observation/head/rgb.png");
                fs::remove_file(&png).unwrap();
                fifo(&png);
            }),
            ("the staging sibling", |f| fifo(&f.sibling())),
            ("a staging name in the workspace", |f| fifo(&f.bi().join(".current_observation.next-planted"))),
        ];
        for (what, plant) in plants {
            let mut f = Fixture::new();
            if what != "benchmark_inputs" && what != "the staging sibling" {
                f.publish(0).unwrap();
            }
            if what == "a staging name in the workspace" {
                let mut names = vec![".current_observation.next-fresh".to_owned(), ".current_observation.next-planted".to_owned()];
                // The old publisher's drop removes its sibling; a file there keeps the new one in the workspace.
                f.publisher = ObservationPublisher::open(&f.ws()).unwrap().with_names(move || Ok(names.pop().unwrap()));
                fs::write(f.sibling(), b"no sibling").unwrap();
            }
            plant(&f);
            let f = within_seconds(move || {
                f.publish(1).unwrap_or_else(|e| panic!("with a FIFO as {what}: {e}"));
                f
            });
            assert_eq!(f.current_id(), "obs_000001", "{what}");
            let leftovers = names_of(&f.bi());
            assert_eq!(leftovers, ["current_observation"], "{what}");
            assert!(fs::symlink_metadata(f.bi()).unwrap().is_dir());
            if what == "the staging sibling" {
                assert!(fs::symlink_metadata(f.sibling()).unwrap().file_type().is_fifo(), "left alone, never opened");
            }
        }
    }

    #[test]
    fn a_racing_agent_never_gets_a_host_file_into_the_archive() {
        // Without the sandbox the agent sees both staging areas; it swaps every staged file it can find for a
        // symlink to a host file, as fast as it can.
        for mut f in [Fixture::new(), Fixture::in_workspace()] {
            let secret = f.host_dir().join("secret.txt");
            let areas = [f.sibling(), f.bi()];
            let stop = Arc::new(AtomicBool::new(false));
            let agent = {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    while !stop.load(Ordering::Relaxed) {
                        for area in &areas {
                            let Ok(entries) = fs::read_dir(area) else { continue };
                            for staging in entries.flatten().filter(|e| e.file_name() != "current_observation") {
                                for rel in ["observation.json", "head/rgb.png", "wrist/depth_m.npy"] {
                                    let p = staging.path().join(rel);
                                    let _ = fs::remove_file(&p);
                                    let _ = symlink(&secret, &p);
                                }
                            }
                        }
                    }
                })
            };
            for i in 0..20 {
                let _ = f.publish(i); // the agent may win every name of one publication: that fails, cleanly
            }
            stop.store(true, Ordering::Relaxed);
            agent.join().unwrap();
            f.assert_host_untouched();
            for entry in fs::read_dir(f.dir.path().join("private")).unwrap() {
                for (rel, bytes) in archive_files(&entry.unwrap().path()) {
                    assert_ne!(bytes, b"host secret", "{rel}");
                }
            }
        }
    }

    // ---- An agent wrecking its own workspace (issue 30): publication recovers, or fails as the agent's error.

    /// `chmod` of a directory, never through a link (the agent's own links must not make the test blame the
    /// server for a host directory's mode).
    fn set_mode(path: &Path, mode: u32) {
        use std::os::unix::fs::PermissionsExt;
        if fs::symlink_metadata(path).is_ok_and(|m| m.is_dir()) {
            let _ = fs::set_permissions(path, fs::Permissions::from_mode(mode));
        }
    }

    /// What an agent does to remove whatever is at `path`: it gives itself access to its own directories first.
    fn remove_any(path: &Path) {
        fn open_up(path: &Path) {
            let Ok(meta) = fs::symlink_metadata(path) else { return };
            if meta.is_dir() {
                set_mode(path, 0o700);
                for e in fs::read_dir(path).into_iter().flatten().flatten() {
                    open_up(&e.path());
                }
            }
        }
        let Ok(meta) = fs::symlink_metadata(path) else { return };
        if meta.is_dir() {
            open_up(path);
            let _ = fs::remove_dir_all(path);
        } else {
            let _ = fs::remove_file(path);
        }
    }

    fn unique() -> usize {
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        NEXT.fetch_add(1, Ordering::Relaxed)
    }

    /// A directory `levels` deep with junk at every level.
    fn deep_tree(root: &Path, levels: usize) {
        let mut p = root.to_path_buf();
        for i in 0..levels {
            p.push(format!("level{i}"));
        }
        let _ = fs::create_dir_all(&p);
        let _ = fs::write(p.join("junk"), b"junk");
    }

    /// Everything an agent may do to its workspace; each takes the workspace and a host directory outside it.
    const SABOTAGES: [(&str, fn(&Path, &Path)); 17] = [
        ("delete benchmark_inputs", |ws, _| remove_any(&ws.join(BENCHMARK_INPUTS))),
        ("rename benchmark_inputs away", |ws, _| {
            let _ = fs::rename(ws.join(BENCHMARK_INPUTS), ws.join(format!("moved-{}", unique())));
        }),
        ("replace benchmark_inputs by a file", |ws, _| {
            remove_any(&ws.join(BENCHMARK_INPUTS));
            let _ = fs::write(ws.join(BENCHMARK_INPUTS), b"not a directory");
        }),
        ("replace benchmark_inputs by a symlink to a host directory", |ws, host| {
            remove_any(&ws.join(BENCHMARK_INPUTS));
            let _ = symlink(host, ws.join(BENCHMARK_INPUTS));
        }),
        ("replace benchmark_inputs by a FIFO", |ws, _| {
            remove_any(&ws.join(BENCHMARK_INPUTS));
            let _ = rustix::fs::mknodat(rustix::fs::CWD, &ws.join(BENCHMARK_INPUTS), rustix::fs::FileType::Fifo, Mode::from_raw_mode(0o600), 0);
        }),
        ("replace benchmark_inputs by a socket", |ws, _| {
            remove_any(&ws.join(BENCHMARK_INPUTS));
            let _ = std::os::unix::net::UnixListener::bind(ws.join(BENCHMARK_INPUTS));
        }),
        ("replace benchmark_inputs by a deep tree", |ws, _| {
            remove_any(&ws.join(BENCHMARK_INPUTS));
            deep_tree(&ws.join(BENCHMARK_INPUTS), 60);
        }),
        ("chmod 000 benchmark_inputs", |ws, _| set_mode(&ws.join(BENCHMARK_INPUTS), 0o000)),
        ("chmod 500 benchmark_inputs", |ws, _| set_mode(&ws.join(BENCHMARK_INPUTS), 0o500)),
        ("chmod 000 the workspace root", |ws, _| set_mode(ws, 0o000)),
        ("chmod 000 current_observation", |ws, _| {
            let cur = ws.join(BENCHMARK_INPUTS).join(CURRENT);
            set_mode(&cur.join("head"), 0o000);
            set_mode(&cur, 0o000);
        }),
        ("replace current_observation by a symlink to a host directory", |ws, host| {
            remove_any(&ws.join(BENCHMARK_INPUTS).join(CURRENT));
            let _ = symlink(host, ws.join(BENCHMARK_INPUTS).join(CURRENT));
        }),
        ("replace current_observation by a FIFO", |ws, _| {
            let cur = ws.join(BENCHMARK_INPUTS).join(CURRENT);
            remove_any(&cur);
            let _ = rustix::fs::mknodat(rustix::fs::CWD, &cur, rustix::fs::FileType::Fifo, Mode::from_raw_mode(0o600), 0);
        }),
        ("plant a deep tree and links in current_observation", |ws, host| {
            let cur = ws.join(BENCHMARK_INPUTS).join(CURRENT);
            deep_tree(&cur.join("deep"), 80);
            let _ = symlink(host, cur.join("head/link_out"));
        }),
        ("wreck the task reference", |ws, host| {
            let reference = ws.join(BENCHMARK_INPUTS).join(CURRENT).join("task_reference");
            let _ = fs::remove_file(reference.join("rgb.png"));
            let _ = symlink(host.join("secret.txt"), reference.join("rgb.png"));
            set_mode(&reference, 0o000);
        }),
        ("fill benchmark_inputs with junk", |ws, host| {
            let bi = ws.join(BENCHMARK_INPUTS);
            for i in 0..50 {
                let _ = fs::write(bi.join(format!("junk{i}")), b"junk");
            }
            let _ = symlink(host, bi.join(".current_observation.next-link"));
            let _ = fs::create_dir_all(bi.join("task_reference/rgb.png"));
        }),
        ("wreck the demonstration bundle", |ws, host| {
            let demo = ws.join(BENCHMARK_INPUTS).join("expert_demo");
            let _ = fs::create_dir_all(demo.join("video"));
            let _ = symlink(host, demo.join("video/head_rgb.mp4"));
            set_mode(&demo.join("video"), 0o000);
            set_mode(&demo, 0o000);
        }),
    ];

    /// Publishes frame `index` with `sabotage` done at `moment` of the first `times` attempts, on a thread whose
    /// mode bits bind (as the server's do when it is not root), and checks the outcome.
    fn sabotaged(mut f: Fixture, what: &'static str, sabotage: fn(&Path, &Path), moment: Moment, times: usize, index: u64) -> Fixture {
        let (ws, host) = (f.ws(), f.host_dir());
        let placeholder = ObservationPublisher::open(&ws).unwrap();
        f.publisher = std::mem::replace(&mut f.publisher, placeholder).with_hook(move |m, attempt| {
            if m == moment && attempt < times {
                sabotage(&ws, &host);
            }
        });
        let f = crate::dirfd::test_support::unprivileged(move || {
            let mut f = f;
            f.publish(index).unwrap_or_else(|e| panic!("{what} at {moment:?} ({times}×): {e}"));
            f.publisher.hook = None;
            f
        });
        let context = format!("{what} at {moment:?} ({times}×)");
        eprintln!("checking {context}");
        let bi = fs::symlink_metadata(f.bi()).unwrap_or_else(|e| panic!("{context}: {e}"));
        assert!(bi.is_dir() && !bi.file_type().is_symlink(), "{context}: benchmark_inputs is a real directory");
        assert_eq!(f.current_id(), format!("obs_{index:06}").as_str(), "{context}");
        f.assert_host_untouched();
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(fs::metadata(f.host_dir()).unwrap().permissions().mode() & 0o777, 0o750, "{context}: host mode");
        let mut outside = names_of(f.dir.path());
        outside.retain(|n| !["ws", "host", "private", ".ws.libero-staging"].contains(&n.as_str()));
        assert!(outside.is_empty(), "{context}: the server wrote beside the workspace: {outside:?}");
        if !f.in_workspace {
            assert!(names_of(&f.sibling()).is_empty(), "{context}: staging left behind in the sibling");
        }
        let stale: Vec<String> = names_of(&f.bi()).into_iter().filter(|n| n.starts_with(".current_observation.")).collect();
        assert!(stale.iter().all(|n| n == ".current_observation.next-link"), "{context}: staging left in the workspace: {stale:?}");
        f
    }

    fn fixture_with_host(in_workspace: bool) -> Fixture {
        let f = if in_workspace { Fixture::in_workspace() } else { Fixture::new() };
        set_mode(&f.host_dir(), 0o750);
        f
    }

    #[test]
    fn every_sabotage_before_a_publication_is_repaired() {
        for (what, sabotage) in SABOTAGES {
            for in_workspace in [false, true] {
                let mut f = fixture_with_host(in_workspace);
                f.publish(0).unwrap();
                sabotage(&f.ws(), &f.host_dir());
                // The start of an episode: the agent wrecked the workspace before the first publication.
                let g = fixture_with_host(in_workspace);
                sabotage(&g.ws(), &g.host_dir());
                sabotaged(f, what, |_, _| {}, Moment::Begin, 0, 1);
                sabotaged(g, what, |_, _| {}, Moment::Begin, 0, 0);
            }
        }
    }

    #[test]
    fn every_sabotage_during_a_publication_is_survived() {
        for (what, sabotage) in SABOTAGES {
            for moment in [Moment::Begin, Moment::Staged, Moment::Swapped] {
                for in_workspace in [false, true] {
                    let mut f = fixture_with_host(in_workspace);
                    f.publish(0).unwrap();
                    let f = sabotaged(f, what, sabotage, moment, 1, 1);
                    // Again at once, three attempts in a row, on the repaired workspace.
                    sabotaged(f, what, sabotage, moment, 3, 2);
                }
            }
        }
    }

    #[test]
    fn an_agent_that_spoils_every_attempt_gets_an_error_and_the_next_publication_succeeds() {
        let mut f = fixture_with_host(false);
        f.publish(0).unwrap();
        let (ws, bi) = (f.ws(), f.bi());
        f.publisher = ObservationPublisher::open(&ws).unwrap().with_hook(move |m, _| {
            if m == Moment::Staged {
                remove_any(&bi);
            }
        });
        let err = f.publish(1).unwrap_err();
        assert!(matches!(err, PublishError::Workspace(_)), "{err}");
        assert!(err.to_string().contains(&format!("gave up after {ATTEMPTS} attempts")), "{err}");
        assert!(f.dir.path().join("private/obs_000001/observation.json").is_file(), "archived all the same");
        f.publisher.hook = None;
        f.publish(2).unwrap();
        assert_eq!(f.current_id(), "obs_000002");
        f.assert_host_untouched();
    }

    #[test]
    fn a_removed_workspace_root_fails_at_once_and_a_full_disk_is_not_retried() {
        let mut f = fixture_with_host(false);
        f.publish(0).unwrap();
        let ws = f.ws();
        remove_any(&ws);
        let t = std::time::Instant::now();
        let err = f.publish(1).unwrap_err();
        assert!(matches!(&err, PublishError::Workspace(e) if e.to_string().contains("workspace directory itself was removed")), "{err}");
        assert!(t.elapsed() < Duration::from_secs(5));
        assert!(is_hopeless(&Errno::NOSPC.into()) && !is_hopeless(&Errno::NOENT.into()) && !is_hopeless(&Errno::ACCESS.into()));
    }

    #[test]
    fn a_saboteur_in_a_tight_loop_never_blocks_never_escapes_and_never_wins_for_good() {
        for in_workspace in [false, true] {
            let f = fixture_with_host(in_workspace);
            let (ws, host) = (f.ws(), f.host_dir());
            let stop = Arc::new(AtomicBool::new(false));
            // The agent: every sabotage, in turn, as fast as it can (with the capabilities of the test, so a
            // `chmod 000` cannot stop it; the publisher's thread is bound by mode bits).
            let agent = {
                let (stop, ws, host) = (stop.clone(), ws.clone(), host.clone());
                std::thread::spawn(move || {
                    let mut rounds = 0usize;
                    while !stop.load(Ordering::Relaxed) {
                        let (_, sabotage) = SABOTAGES[rounds % SABOTAGES.len()];
                        sabotage(&ws, &host);
                        rounds += 1;
                    }
                    rounds
                })
            };
            let (f, outcomes) = within(Duration::from_secs(60), move || {
                crate::dirfd::test_support::unprivileged(move || {
                    let mut f = f;
                    let mut outcomes = (0, 0);
                    for i in 0..24 {
                        match f.publish(i) {
                            Ok(_) => outcomes.0 += 1,
                            Err(PublishError::Workspace(_)) => outcomes.1 += 1,
                            Err(e) => panic!("not the workspace's failure: {e}"),
                        }
                    }
                    (f, outcomes)
                })
            });
            stop.store(true, Ordering::Relaxed);
            assert!(agent.join().unwrap() > 0);
            assert_eq!(outcomes.0 + outcomes.1, 24);
            // The agent stops: the next publication repairs everything.
            let f = sabotaged(f, "after the loop", |_, _| {}, Moment::Begin, 0, 24);
            drop(f);
        }
    }
}
