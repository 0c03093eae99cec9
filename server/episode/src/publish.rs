//! Publication of `benchmark_inputs/current_observation/` (§3.4) into a workspace the agent shares with
//! the server (same Unix user, and it can watch with inotify). The frame is encoded once in memory; the
//! private archive is written from those bytes, never read back from the workspace. The public copy is
//! built in a staging directory the agent cannot see (a server-owned sibling of the workspace; inside
//! `benchmark_inputs` only as a fallback), written through directory descriptors with `O_EXCL` and
//! `O_NOFOLLOW` under a fresh random name, fsync'd, then swapped in with one
//! `renameat2(RENAME_EXCHANGE)` so that a reader always finds a complete directory; the previous frame is
//! removed without following or opening anything the agent may have put in it. Nothing the agent plants
//! (symlink, file, FIFO) is ever followed or opened: it makes an exclusive creation fail, and the
//! publication discards that staging and retries under another name.
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::path::{Path, PathBuf};

use rustix::fs::{Mode, OFlags};
use rustix::io::Errno;
use serde_json::Value;

use crate::dirfd::{
    ensure_dir_at, exchange_at, is_interference, make_dir_at, open_dir_at, open_dir_path, random_name, remove_at,
    rename_noreplace_at, sync_dir_fd, write_new_file_at,
};
use crate::observation::{EncodedObservation, Frame, Level, encode_observation, write_encoded_dir};

const BENCHMARK_INPUTS: &str = "benchmark_inputs";
const CURRENT: &str = "current_observation";
/// Suffix of the staging sibling `<workspace parent>/.<workspace name>.libero-staging/`.
pub const STAGING_SUFFIX: &str = ".libero-staging";
/// Fresh names a publication tries before failing: each failure means the agent took the name first.
const ATTEMPTS: usize = 4;

fn errno(e: &std::io::Error) -> Option<Errno> {
    Errno::from_io_error(e)
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
}

/// Where staging directories are made.
enum StagingArea {
    /// The sibling is created at the first publication.
    Untried,
    Sibling(SiblingStaging),
    /// No sibling (it could not be created, or the exchange crossed filesystems): inside `benchmark_inputs`.
    InWorkspace,
}

/// Publishes an episode's observations into its workspace. Holds the workspace root open for the episode's
/// life, so that the agent renaming things inside it never redirects the server's writes.
pub struct ObservationPublisher {
    workspace: OwnedFd,
    workspace_path: PathBuf,
    staging: StagingArea,
    /// Staging names (random; tests inject planted ones).
    names: Box<dyn FnMut() -> std::io::Result<String> + Send>,
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
        })
    }

    /// Stages under the names `names` gives instead of random ones (tests plant entries under them).
    #[cfg(test)]
    fn with_names(mut self, names: impl FnMut() -> std::io::Result<String> + Send + 'static) -> Self {
        self.names = Box::new(names);
        self
    }

    /// Publishes `frame` as the workspace's current observation; returns the observation document.
    /// `private_copy_root`, when given, first receives an evaluator-private copy at `<root>/<observation_id>/`,
    /// written from the same in-memory bytes.
    pub fn publish(&mut self, frame: &Frame, level: Level, private_copy_root: Option<&Path>) -> std::io::Result<Value> {
        let encoded = encode_observation(frame, level)?;
        if let Some(root) = private_copy_root {
            write_private_copy(root, &encoded)?;
        }
        self.publish_encoded(&encoded)?;
        Ok(encoded.document)
    }

    /// Stages `encoded` and swaps it in as `current_observation`, retrying under fresh names while the agent
    /// is in the way.
    pub fn publish_encoded(&mut self, encoded: &EncodedObservation) -> std::io::Result<()> {
        let bi = self.benchmark_inputs()?;
        let mut last = None;
        for _ in 0..ATTEMPTS {
            let name = (self.names)()?;
            self.prepare_staging();
            let in_sibling = matches!(self.staging, StagingArea::Sibling(_));
            let area = match &self.staging {
                StagingArea::Sibling(s) => s.dir.as_fd(),
                _ => bi.as_fd(),
            };
            let result = stage(area, &name, encoded).and_then(|()| swap_in(area, &name, bi.as_fd()));
            let Err(e) = result else { return Ok(()) };
            discard(area, &name);
            if in_sibling && errno(&e) == Some(Errno::XDEV) {
                log::warn!("{}: staging sibling on another filesystem; staging in the workspace", self.workspace_path.display());
                self.staging = StagingArea::InWorkspace;
            } else if !is_interference(&e) {
                return Err(e);
            }
            last = Some(e);
        }
        let why = last.map(|e| e.to_string()).unwrap_or_default();
        Err(std::io::Error::other(format!("publication gave up after {ATTEMPTS} staging names were taken ({why})")))
    }

    /// Creates the sibling staging directory at the first publication, or settles for the workspace.
    fn prepare_staging(&mut self) {
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

    /// `benchmark_inputs`, opened without following. Whatever else the agent put under that name (a
    /// symlink, a file, a FIFO) is unlinked and the directory recreated.
    fn benchmark_inputs(&self) -> std::io::Result<OwnedFd> {
        let ws = self.workspace.as_fd();
        for _ in 0..ATTEMPTS {
            match open_dir_at(ws, BENCHMARK_INPUTS) {
                Ok(fd) => return Ok(fd),
                Err(e) if errno(&e) == Some(Errno::NOENT) => {}
                Err(e) if matches!(errno(&e), Some(Errno::LOOP | Errno::NOTDIR)) => remove_at(ws, BENCHMARK_INPUTS)?,
                Err(e) => return Err(e),
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
fn write_private_copy(root: &Path, encoded: &EncodedObservation) -> std::io::Result<()> {
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

/// Creates the staging directory `name` in `area` and writes `encoded` into it, every entry created new.
fn stage(area: BorrowedFd<'_>, name: &str, encoded: &EncodedObservation) -> std::io::Result<()> {
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
    sync_dir_fd(root.as_fd())
}

/// Makes the staged `area/name` the current observation. The first publication (or one after the agent
/// removed the current one) renames; later ones exchange, then remove the previous frame.
fn swap_in(area: BorrowedFd<'_>, name: &str, bi: BorrowedFd<'_>) -> std::io::Result<()> {
    match exchange_at(area, name, bi, CURRENT) {
        Ok(()) => {
            sync_dir_fd(bi)?;
            discard(area, name); // now the previous frame
        }
        Err(e) if errno(&e) == Some(Errno::NOENT) => rename_noreplace_at(area, name, bi, CURRENT)?,
        Err(e) if errno(&e) == Some(Errno::INVAL) => {
            // Filesystems without RENAME_EXCHANGE: the original rename-aside sequence.
            let previous = random_name(".current_observation.previous-")?;
            rename_noreplace_at(bi, CURRENT, bi, &previous)?;
            rename_noreplace_at(area, name, bi, CURRENT)?;
            sync_dir_fd(bi)?;
            discard(bi, &previous);
        }
        Err(e) => return Err(e),
    }
    sync_dir_fd(bi)?;
    sync_dir_fd(area)
}

/// Removes a staging directory or a previous frame. A failure (only an agent builds trees too deep or too
/// large to remove) leaves it in place and is logged: the publication itself is complete.
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
            task_reference: None,
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
        fn publish(&mut self, index: u64) -> std::io::Result<Value> {
            let private = self.dir.path().join("private");
            self.publisher.publish(&frame(index, 4, 3), Level::L3, Some(&private))
        }
        fn current_id(&self) -> Value {
            let text = fs::read(self.bi().join("current_observation/observation.json")).unwrap();
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
        for dir in ["", "head", "wrist"] {
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
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(Duration::from_secs(10)).expect("publication blocked on something the agent made")
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
}
