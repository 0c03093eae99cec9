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

/// Directories whose removal goes deeper than this are left in place: observation directories are two
/// levels deep, and only an agent makes deeper ones (each level costs a descriptor).
pub const MAX_REMOVE_DEPTH: usize = 32;
/// Entries one removal deletes at most, so an agent adding entries as fast as we delete cannot hold a
/// publication forever.
pub const MAX_REMOVE_ENTRIES: usize = 100_000;

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
pub fn rename_noreplace_at(from_dir: BorrowedFd<'_>, from: &str, to_dir: BorrowedFd<'_>, to: &str) -> std::io::Result<()> {
    match rustix::fs::renameat_with(from_dir, from, to_dir, to, RenameFlags::NOREPLACE) {
        Err(Errno::INVAL) => Ok(rustix::fs::renameat(from_dir, from, to_dir, to)?),
        other => Ok(other?),
    }
}

/// Unlinks the entry `name` of `dir` whatever it is (a symlink itself, never its target; a FIFO without
/// opening it), a directory with its contents. Subdirectories are opened with `O_NOFOLLOW|O_DIRECTORY`
/// relative to their parent, never by path. A missing entry is not an error.
pub fn remove_at(dir: BorrowedFd<'_>, name: &str) -> std::io::Result<()> {
    let name = std::ffi::CString::new(name).map_err(std::io::Error::other)?;
    let mut budget = MAX_REMOVE_ENTRIES;
    remove_entry(dir, &name, 0, &mut budget)
}

fn remove_entry(dir: BorrowedFd<'_>, name: &std::ffi::CStr, depth: usize, budget: &mut usize) -> std::io::Result<()> {
    if *budget == 0 {
        return Err(std::io::Error::other(format!("more than {MAX_REMOVE_ENTRIES} entries to remove")));
    }
    *budget -= 1;
    match rustix::fs::unlinkat(dir, name, AtFlags::empty()) {
        Ok(()) | Err(Errno::NOENT) => return Ok(()),
        Err(Errno::ISDIR | Errno::PERM) => {} // a directory: empty it first
        Err(e) => return Err(e.into()),
    }
    if depth >= MAX_REMOVE_DEPTH {
        return Err(std::io::Error::other(format!("directory tree deeper than {MAX_REMOVE_DEPTH} levels")));
    }
    let sub = match rustix::fs::openat(dir, name, DIR_FLAGS, Mode::empty()) {
        Ok(fd) => fd,
        Err(Errno::NOENT) => return Ok(()),
        // Replaced by a non-directory since the unlink: unlink that instead.
        Err(Errno::NOTDIR | Errno::LOOP) => return remove_entry(dir, name, depth, budget),
        Err(e) => return Err(e.into()),
    };
    empty_dir(sub.as_fd(), depth + 1, budget)?;
    match rustix::fs::unlinkat(dir, name, AtFlags::REMOVEDIR) {
        Ok(()) | Err(Errno::NOENT) => Ok(()),
        Err(e) => Err(e.into()),
    }
}

/// Removes every entry of the open directory `dir`, in batches (names are collected before deleting, as
/// deleting while reading may skip entries).
fn empty_dir(dir: BorrowedFd<'_>, depth: usize, budget: &mut usize) -> std::io::Result<()> {
    const BATCH: usize = 256;
    loop {
        let mut names = Vec::new();
        let mut entries = Dir::read_from(dir)?;
        while let Some(entry) = entries.read() {
            let entry = entry?;
            let name = entry.file_name();
            if name.to_bytes() != b"." && name.to_bytes() != b".." {
                names.push(name.to_owned());
            }
            if names.len() == BATCH {
                break;
            }
        }
        if names.is_empty() {
            return Ok(());
        }
        for name in &names {
            remove_entry(dir, name, depth, budget)?;
        }
    }
}

/// `prefix` + 128 random bits in hex: a name nobody can have created in advance except by watching.
pub use crate::json::random_name;

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

    #[test]
    fn removal_gives_up_on_a_tree_deeper_than_the_limit() {
        let dir = tempfile::tempdir().unwrap();
        let mut deep = dir.path().join("deep");
        for _ in 0..=MAX_REMOVE_DEPTH {
            deep.push("d");
        }
        fs::create_dir_all(&deep).unwrap();
        let root = open_dir_path(dir.path()).unwrap();
        assert!(remove_at(root.as_fd(), "deep").is_err());
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
