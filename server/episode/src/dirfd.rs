//! File operations relative to directory file descriptors, for directories the agent can write too (same
//! Unix user): any entry there may be replaced by a symlink, a file or a FIFO at any moment. So nothing
//! here follows a symlink (`O_NOFOLLOW`, `*at` calls), nothing opens an entry it did not just create
//! (`O_EXCL`) except directories (`O_DIRECTORY`, which refuses a FIFO before opening it), and no
//! descriptor leaks into child processes (`O_CLOEXEC`).
use std::io::Write;
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::path::Path;

use rustix::fs::{AtFlags, Dir, Mode, OFlags, RenameFlags};
use rustix::io::Errno;

/// Steps (an unlink, an open, a read of a directory) one removal takes at most, so an agent adding entries as
/// fast as we delete cannot hold a publication forever (an observation takes a few dozen; only an agent makes
/// trees that need more).
pub const MAX_REMOVE_ENTRIES: usize = 1_000_000;
/// Directory levels one removal holds open at once (each costs a descriptor). A directory found deeper is first
/// moved up, under a fresh name, into the directory being removed, and removed from there: any depth is
/// removed with at most this many descriptors, and without recursion.
pub const MAX_OPEN_LEVELS: usize = 32;

const DIR_FLAGS: OFlags = OFlags::RDONLY
    .union(OFlags::DIRECTORY)
    .union(OFlags::NOFOLLOW)
    .union(OFlags::CLOEXEC)
    .union(OFlags::NONBLOCK);

/// Whether an error means "someone else's entry was in the way" (planted, replaced or removed by the
/// agent) rather than a failure of the filesystem itself.
pub fn is_interference(e: &std::io::Error) -> bool {
    matches!(
        Errno::from_io_error(e),
        Some(Errno::EXIST | Errno::LOOP | Errno::NOTDIR | Errno::NOENT | Errno::ISDIR | Errno::NOTEMPTY)
    )
}

/// Opens the directory at `path`, refusing a symlink as its last component (the workspace root, which the
/// server created).
pub fn open_dir_path(path: &Path) -> std::io::Result<OwnedFd> {
    Ok(rustix::fs::open(path, DIR_FLAGS, Mode::empty())?)
}

/// Opens the existing directory `name` in `dir`; a symlink, file or FIFO there fails (`ELOOP`/`ENOTDIR`)
/// without being opened.
pub fn open_dir_at(dir: BorrowedFd<'_>, name: &str) -> std::io::Result<OwnedFd> {
    Ok(rustix::fs::openat(dir, name, DIR_FLAGS, Mode::empty())?)
}

/// Creates the directory `name` in `dir` (failing with `EEXIST` if any entry has that name) and opens it.
pub fn make_dir_at(dir: BorrowedFd<'_>, name: &str, mode: u32) -> std::io::Result<OwnedFd> {
    rustix::fs::mkdirat(dir, name, Mode::from_raw_mode(mode))?;
    open_dir_at(dir, name)
}

/// Creates the directory `name` in `dir` unless an entry of that name exists (whatever it is: opening it
/// with [`open_dir_at`] tells).
pub fn ensure_dir_at(dir: BorrowedFd<'_>, name: &str, mode: u32) -> std::io::Result<()> {
    match rustix::fs::mkdirat(dir, name, Mode::from_raw_mode(mode)) {
        Ok(()) | Err(Errno::EXIST) => Ok(()),
        Err(e) => Err(e.into()),
    }
}

/// Creates the file `name` in `dir` (failing with `EEXIST` if any entry has that name, a symlink
/// included), writes `bytes` and fsyncs it.
pub fn write_new_file_at(dir: BorrowedFd<'_>, name: &str, bytes: &[u8]) -> std::io::Result<()> {
    write_new_file_mode_at(dir, name, bytes, 0o666)
}

/// [`write_new_file_at`] with the file's permission bits (before the umask): 0600 for what holds a secret.
pub fn write_new_file_mode_at(dir: BorrowedFd<'_>, name: &str, bytes: &[u8], mode: u32) -> std::io::Result<()> {
    let flags = OFlags::WRONLY | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC;
    let fd = rustix::fs::openat(dir, name, flags, Mode::from_raw_mode(mode))?;
    let mut file = std::fs::File::from(fd);
    file.write_all(bytes)?;
    file.sync_all()
}

/// fsync of an open directory, so entries created or renamed in it survive a crash.
pub fn sync_dir_fd(dir: BorrowedFd<'_>) -> std::io::Result<()> {
    Ok(rustix::fs::fsync(dir)?)
}

/// Swaps two existing entries atomically (`renameat2(RENAME_EXCHANGE)`); `EINVAL` where the filesystem
/// cannot, `EXDEV` across filesystems, `ENOENT` if either is missing.
pub fn exchange_at(a_dir: BorrowedFd<'_>, a: &str, b_dir: BorrowedFd<'_>, b: &str) -> std::io::Result<()> {
    Ok(rustix::fs::renameat_with(a_dir, a, b_dir, b, RenameFlags::EXCHANGE)?)
}

/// Renames `from` to `to`, failing if `to` exists (`RENAME_NOREPLACE`, or a plain rename where the
/// filesystem lacks it: then an existing empty directory at `to` would be replaced).
pub fn rename_noreplace_at<P: rustix::path::Arg + Copy, Q: rustix::path::Arg + Copy>(
    from_dir: BorrowedFd<'_>,
    from: P,
    to_dir: BorrowedFd<'_>,
    to: Q,
) -> std::io::Result<()> {
    match rustix::fs::renameat_with(from_dir, from, to_dir, to, RenameFlags::NOREPLACE) {
        Err(Errno::INVAL) => Ok(rustix::fs::renameat(from_dir, from, to_dir, to)?),
        other => Ok(other?),
    }
}

/// Makes the open directory `dir` usable by its owner again (`u+rwx`), as an agent may `chmod 000` what the
/// server made in its workspace (same user). Other mode bits are kept.
/// Whether it had to.
pub fn ensure_owner_rwx(dir: BorrowedFd<'_>) -> std::io::Result<bool> {
    let mode = rustix::fs::fstat(dir)?.st_mode;
    if mode & 0o700 == 0o700 {
        return Ok(false);
    }
    rustix::fs::fchmod(dir, Mode::from_raw_mode((mode & 0o7777) | 0o700))?;
    Ok(true)
}

/// [`ensure_owner_rwx`] for the directory `name` in `dir`, which its mode may keep us from opening
/// (`EACCES`): it is pinned with `O_PATH|O_NOFOLLOW|O_DIRECTORY` (no permission needed, never a symlink's
/// target, never a FIFO) and changed through `/proc/self/fd`, which names exactly that inode. A symlink,
/// file or FIFO there fails with `ENOTDIR`/`ELOOP`.
pub fn repair_dir_mode_at(dir: BorrowedFd<'_>, name: &str) -> std::io::Result<()> {
    let flags = OFlags::PATH | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC;
    let pinned = rustix::fs::openat(dir, name, flags, Mode::empty())?;
    repair_pinned(&pinned)
}

fn repair_pinned(pinned: &OwnedFd) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let mode = rustix::fs::fstat(pinned)?.st_mode;
    if mode & 0o700 != 0o700 {
        let path = format!("/proc/self/fd/{}", pinned.as_raw_fd());
        rustix::fs::chmod(path.as_str(), Mode::from_raw_mode((mode & 0o7777) | 0o700))?;
    }
    Ok(())
}

/// Unlinks the entry `name` of `dir` whatever it is (a symlink itself, never its target; a FIFO or socket
/// without opening it), a directory with its contents however deep or wide, whatever their modes (a directory
/// the agent made unreadable is made `u+rwx` first). Subdirectories are opened with `O_NOFOLLOW|O_DIRECTORY`
/// relative to their parent, never by path; the walk is iterative and holds at most [`MAX_OPEN_LEVELS`]
/// descriptors. A missing entry is not an error; a tree needing more than [`MAX_REMOVE_ENTRIES`] steps is.
pub fn remove_at(dir: BorrowedFd<'_>, name: &str) -> std::io::Result<()> {
    let name = std::ffi::CString::new(name).map_err(std::io::Error::other)?;
    remove_tree(dir, name, MAX_REMOVE_ENTRIES)
}

/// One open directory of a removal: its descriptor, its name in its parent and names read but not yet removed.
struct Level {
    fd: OwnedFd,
    name: std::ffi::CString,
    pending: Vec<std::ffi::CString>,
}

/// What [`open_for_removal`] found.
enum Found {
    Dir(OwnedFd),
    Gone,
    NotDir,
}

/// Opens the directory `name` of `dir` to empty it, making it `u+rwx` first if it is not.
fn open_for_removal(dir: BorrowedFd<'_>, name: &std::ffi::CStr) -> std::io::Result<Found> {
    for _ in 0..3 {
        match rustix::fs::openat(dir, name, DIR_FLAGS, Mode::empty()) {
            Ok(fd) => {
                ensure_owner_rwx(fd.as_fd())?;
                return Ok(Found::Dir(fd));
            }
            Err(Errno::NOENT) => return Ok(Found::Gone),
            Err(Errno::NOTDIR | Errno::LOOP) => return Ok(Found::NotDir),
            Err(Errno::ACCESS | Errno::PERM) => {
                let flags = OFlags::PATH | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC;
                match rustix::fs::openat(dir, name, flags, Mode::empty()) {
                    Ok(pinned) => repair_pinned(&pinned)?,
                    Err(Errno::NOENT) => return Ok(Found::Gone),
                    Err(Errno::NOTDIR | Errno::LOOP) => return Ok(Found::NotDir),
                    Err(e) => return Err(e.into()),
                }
            }
            Err(e) => return Err(e.into()),
        }
    }
    Err(Errno::ACCESS.into())
}

/// Up to `n` names of the open directory `dir` (a fresh read from its start: removed entries are gone).
fn read_names(dir: BorrowedFd<'_>, n: usize) -> std::io::Result<Vec<std::ffi::CString>> {
    let mut names = Vec::new();
    let mut entries = Dir::read_from(dir)?;
    while let Some(entry) = entries.read() {
        let entry = entry?;
        let name = entry.file_name();
        if name.to_bytes() != b"." && name.to_bytes() != b".." {
            names.push(name.to_owned());
            if names.len() == n {
                break;
            }
        }
    }
    Ok(names)
}

fn remove_tree(parent: BorrowedFd<'_>, name: std::ffi::CString, mut budget: usize) -> std::io::Result<()> {
    /// Names read from a directory at once (names are collected before deleting: deleting while reading may
    /// skip entries).
    const BATCH: usize = 256;
    let mut stack: Vec<Level> = Vec::new();
    // The entry of the innermost open directory (or of `parent`) to remove next.
    let mut next = Some(name);
    loop {
        if budget == 0 {
            return Err(std::io::Error::other(format!("gave up removing after {MAX_REMOVE_ENTRIES} steps")));
        }
        budget -= 1;
        let here = stack.last().map_or(parent, |l| l.fd.as_fd());
        if let Some(child) = next.take() {
            let unlinked = rustix::fs::unlinkat(here, &child, AtFlags::empty());
            let refused = match unlinked {
                Ok(()) | Err(Errno::NOENT) => continue,
                Err(e @ (Errno::ISDIR | Errno::PERM)) => e, // a directory (Linux says EISDIR, POSIX EPERM)
                // The directory holding it was made read-only since we opened it: repair, then once more.
                Err(Errno::ACCESS) if ensure_owner_rwx(here)? => {
                    next = Some(child);
                    continue;
                }
                Err(e) => return Err(e.into()),
            };
            match open_for_removal(here, &child)? {
                Found::Gone => {}
                // Replaced by a non-directory since the unlink: unlink that. A non-directory that refused the
                // unlink outright cannot be removed.
                Found::NotDir if refused == Errno::PERM => return Err(refused.into()),
                Found::NotDir => next = Some(child),
                Found::Dir(fd) if stack.len() < MAX_OPEN_LEVELS => stack.push(Level { fd, name: child, pending: Vec::new() }),
                Found::Dir(fd) => {
                    // Too deep to hold open: move it up into the directory being removed, under a fresh name.
                    // Its mode is fixed (moving a directory to another parent needs write access to it).
                    drop(fd);
                    let fresh = random_name(".libero-removing-")?;
                    match rename_noreplace_at(here, child.as_c_str(), stack[0].fd.as_fd(), fresh.as_str()) {
                        Ok(()) => {}
                        Err(e) if Errno::from_io_error(&e) == Some(Errno::NOENT) => {}
                        Err(e) => return Err(e),
                    }
                }
            }
            continue;
        }
        let Some(top) = stack.last_mut() else { return Ok(()) };
        if top.pending.is_empty() {
            top.pending = read_names(top.fd.as_fd(), BATCH)?;
            top.pending.reverse();
        }
        if let Some(child) = top.pending.pop() {
            next = Some(child);
            continue;
        }
        // Empty: remove it from its parent.
        let Some(done) = stack.pop() else { return Ok(()) };
        drop(done.fd);
        let up = stack.last().map_or(parent, |l| l.fd.as_fd());
        match rustix::fs::unlinkat(up, &done.name, AtFlags::REMOVEDIR) {
            Ok(()) | Err(Errno::NOENT) => {}
            // Refilled, or replaced by something else, since it was read empty: once more.
            Err(Errno::NOTEMPTY | Errno::EXIST | Errno::NOTDIR) => next = Some(done.name),
            Err(Errno::ACCESS) if ensure_owner_rwx(up)? => next = Some(done.name),
            Err(e) => return Err(e.into()),
        }
    }
}

/// `prefix` + 128 random bits in hex: a name nobody can have created in advance except by watching.
pub use libero_records::json::random_name;

#[cfg(test)]
pub(crate) mod test_support {
    /// Runs `f` on a thread of its own without `CAP_DAC_OVERRIDE` and `CAP_DAC_READ_SEARCH` in its effective
    /// set (capabilities belong to a thread), so that when the tests run as root, mode bits restrict it as they
    /// restrict a server running as an ordinary user: what an agent's `chmod 000` does to the real server.
    pub fn unprivileged<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
        let thread = std::thread::spawn(move || {
            use rustix::thread::{CapabilitySet, capabilities, set_capabilities};
            let mut caps = capabilities(None).expect("capget");
            caps.effective.remove(CapabilitySet::DAC_OVERRIDE | CapabilitySet::DAC_READ_SEARCH);
            set_capabilities(None, caps).expect("capset");
            f()
        });
        thread.join().unwrap_or_else(|p| std::panic::resume_unwind(p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs;
    use std::os::unix::fs::symlink;

    fn fifo(path: &Path) {
        rustix::fs::mknodat(rustix::fs::CWD, path, rustix::fs::FileType::Fifo, Mode::from_raw_mode(0o600), 0).unwrap();
    }

    #[test]
    fn removal_unlinks_symlinks_and_fifos_without_touching_their_targets() {
        let dir = tempfile::tempdir().unwrap();
        let outside = dir.path().join("outside");
        fs::create_dir(&outside).unwrap();
        fs::write(outside.join("keep.txt"), b"host file").unwrap();
        let tree = dir.path().join("tree");
        fs::create_dir_all(tree.join("head/deeper")).unwrap();
        symlink(&outside, tree.join("head/link_to_dir")).unwrap();
        symlink(outside.join("keep.txt"), tree.join("link_to_file")).unwrap();
        fifo(&tree.join("head/deeper/pipe"));
        fs::write(tree.join("observation.json"), b"{}").unwrap();
        let root = open_dir_path(dir.path()).unwrap();
        remove_at(root.as_fd(), "tree").unwrap();
        assert!(!tree.exists());
        assert_eq!(fs::read(outside.join("keep.txt")).unwrap(), b"host file");
        remove_at(root.as_fd(), "tree").expect("a missing entry is already removed");
    }

    fn chmod(path: &Path, mode: u32) {
        use std::os::unix::fs::PermissionsExt;
        fs::set_permissions(path, fs::Permissions::from_mode(mode)).unwrap();
    }

    #[test]
    fn removal_goes_any_depth_without_following_a_link_out() {
        let dir = tempfile::tempdir().unwrap();
        let outside = dir.path().join("outside");
        fs::create_dir_all(outside.join("sub")).unwrap();
        fs::write(outside.join("keep.txt"), b"host file").unwrap();
        let mut deep = dir.path().join("deep");
        for level in 0..200 {
            deep.push("d");
            if level % 40 == 0 {
                fs::create_dir_all(&deep).unwrap();
                fs::write(deep.join("junk.bin"), b"junk").unwrap();
                symlink(&outside, deep.join("link_out")).unwrap();
            }
        }
        fs::create_dir_all(&deep).unwrap();
        symlink(&outside, deep.join("link_out")).unwrap();
        symlink(outside.join("keep.txt"), deep.join("file_link")).unwrap();
        fifo(&deep.join("pipe"));
        let root = open_dir_path(dir.path()).unwrap();
        remove_at(root.as_fd(), "deep").expect("a 200-level tree is removed");
        assert!(!dir.path().join("deep").exists());
        assert_eq!(fs::read(outside.join("keep.txt")).unwrap(), b"host file");
        assert!(outside.join("sub").is_dir(), "the directory a link pointed to is untouched");
        assert_eq!(names(dir.path()), ["outside"], "nothing was moved out of the tree");
    }

    #[test]
    fn removal_of_a_wide_tree_finishes() {
        let dir = tempfile::tempdir().unwrap();
        let wide = dir.path().join("wide");
        fs::create_dir(&wide).unwrap();
        for i in 0..3000 {
            fs::write(wide.join(format!("f{i}")), b"x").unwrap();
        }
        for i in 0..300 {
            fs::create_dir(wide.join(format!("d{i}"))).unwrap();
            fs::write(wide.join(format!("d{i}/x")), b"x").unwrap();
        }
        let root = open_dir_path(dir.path()).unwrap();
        remove_at(root.as_fd(), "wide").unwrap();
        assert!(!wide.exists());
    }

    #[test]
    fn removal_repairs_directories_made_unreadable_or_read_only() {
        let dir = tempfile::tempdir().unwrap();
        let tree = dir.path().join("tree");
        fs::create_dir_all(tree.join("locked/inner/deeper")).unwrap();
        fs::write(tree.join("locked/inner/deeper/f"), b"x").unwrap();
        fs::create_dir_all(tree.join("readonly/sub")).unwrap();
        fs::write(tree.join("readonly/f"), b"x").unwrap();
        chmod(&tree.join("locked/inner/deeper"), 0o000);
        chmod(&tree.join("locked/inner"), 0o000);
        chmod(&tree.join("locked"), 0o000);
        chmod(&tree.join("readonly/sub"), 0o500);
        chmod(&tree.join("readonly"), 0o500);
        chmod(&tree, 0o000);
        let path = dir.path().to_path_buf();
        test_support::unprivileged(move || {
            assert!(fs::read_dir(path.join("tree")).is_err(), "mode bits bind this thread");
            let root = open_dir_path(&path).unwrap();
            remove_at(root.as_fd(), "tree").expect("unreadable directories are made usable and removed");
            assert!(!path.join("tree").exists());
        });
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        v.sort();
        v
    }

    #[test]
    fn directory_opens_refuse_symlinks_and_never_open_a_fifo() {
        let dir = tempfile::tempdir().unwrap();
        fs::create_dir(dir.path().join("real")).unwrap();
        symlink(dir.path().join("real"), dir.path().join("link")).unwrap();
        fifo(&dir.path().join("pipe"));
        let root = open_dir_path(dir.path()).unwrap();
        assert!(open_dir_at(root.as_fd(), "real").is_ok());
        let link = Errno::from_io_error(&open_dir_at(root.as_fd(), "link").unwrap_err());
        assert!(matches!(link, Some(Errno::LOOP | Errno::NOTDIR)), "{link:?}"); // Linux says ENOTDIR with O_DIRECTORY
        assert_eq!(Errno::from_io_error(&open_dir_at(root.as_fd(), "pipe").unwrap_err()), Some(Errno::NOTDIR));
        assert!(open_dir_path(&dir.path().join("link")).is_err(), "the last component is not followed");
    }

    #[test]
    fn new_files_never_write_through_a_planted_symlink() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("host_file");
        fs::write(&target, b"original").unwrap();
        symlink(&target, dir.path().join("rgb.png")).unwrap();
        let root = open_dir_path(dir.path()).unwrap();
        let err = write_new_file_at(root.as_fd(), "rgb.png", b"overwritten").unwrap_err();
        assert!(is_interference(&err), "{err}");
        assert_eq!(fs::read(&target).unwrap(), b"original");
    }

    #[test]
    fn random_names_differ() {
        let (a, b) = (random_name(".x-").unwrap(), random_name(".x-").unwrap());
        assert!(a.starts_with(".x-") && a.len() == 3 + 32);
        assert_ne!(a, b);
    }
}
