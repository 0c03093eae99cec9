//! Removing what an agent may have left: its workspace and its session home, where it could write anything,
//! as deep and as wide as it liked, with links to host files and directories among it. [`remove_tree`] walks
//! without recursion and without following a link: every directory is opened relative to its parent with
//! `O_NOFOLLOW | O_DIRECTORY` (a link, a FIFO or a device there is unlinked, never opened), every entry removed
//! with `unlinkat`, so a link to a host directory goes and the directory it named stays as it was. At most
//! [`MAX_OPEN_DIRS`] directories are open at once: a directory found deeper than that is first moved up to the
//! top of the tree (`renameat`, which never follows a link either) and emptied from there, so a tree of any depth
//! costs a bounded number of descriptors. A directory the agent made unreadable or unwritable is given back its
//! owner's permissions first (through a descriptor that refuses links).
use std::ffi::{CStr, CString};
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, OwnedFd};
use std::path::Path;

use rustix::fs::{AtFlags, Dir, Mode, OFlags, RenameFlags};
use rustix::io::Errno;

/// Directories open at once at most (the walk's depth before it moves a subtree up).
pub const MAX_OPEN_DIRS: usize = 48;
/// Entries removed at most, so that a process still adding entries cannot keep the removal going forever.
pub const MAX_ENTRIES: u64 = 20_000_000;

const DIR_FLAGS: OFlags = OFlags::RDONLY
    .union(OFlags::DIRECTORY)
    .union(OFlags::NOFOLLOW)
    .union(OFlags::CLOEXEC)
    .union(OFlags::NONBLOCK);

/// What a removal did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Removed {
    /// Entries unlinked (files, links, directories).
    pub entries: u64,
    /// Subtrees moved up to keep the walk shallow.
    pub moved_up: u64,
}

/// Removes `path` and everything below it; its last component may be anything (a link is unlinked, not
/// followed), its parent is opened by path (it is the caller's own directory). A missing `path` is not an error.
pub fn remove_tree(path: &Path) -> std::io::Result<Removed> {
    let bad = || std::io::Error::other(format!("{} has no parent directory and name", path.display()));
    let name = path.file_name().ok_or_else(bad)?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => return Err(bad()),
    };
    let name = CString::new(name.as_encoded_bytes()).map_err(|_| bad())?;
    let dir = match rustix::fs::open(parent, DIR_FLAGS.difference(OFlags::NOFOLLOW), Mode::empty()) {
        Ok(d) => d,
        Err(Errno::NOENT) => return Ok(Removed::default()),
        Err(e) => return Err(e.into()),
    };
    remove_tree_at(dir.as_fd(), &name)
}

/// One open directory of the walk.
struct Frame {
    dir: Dir,
    /// Its name in the directory below it on the stack (or in the removal's parent).
    name: CString,
}

fn open_dir_at(dir: BorrowedFd<'_>, name: &CStr) -> Result<OwnedFd, Errno> {
    match rustix::fs::openat(dir, name, DIR_FLAGS, Mode::empty()) {
        Err(Errno::ACCESS) => {
            // Unreadable (mode 0): the owner's permissions back, through a descriptor that is this very directory.
            let path = rustix::fs::openat(dir, name, OFlags::PATH | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC, Mode::empty())?;
            rustix::fs::chmod(format!("/proc/self/fd/{}", path.as_raw_fd()).as_str(), Mode::from_raw_mode(0o700))?;
            rustix::fs::openat(dir, name, DIR_FLAGS, Mode::empty())
        }
        other => other,
    }
}

/// Removes the entry `name` of `dir` and everything below it (see the module's documentation).
pub fn remove_tree_at(parent: BorrowedFd<'_>, name: &CStr) -> std::io::Result<Removed> {
    let mut done = Removed::default();
    match rustix::fs::unlinkat(parent, name, AtFlags::empty()) {
        Ok(()) => {
            done.entries = 1;
            return Ok(done);
        }
        Err(Errno::NOENT) => return Ok(done),
        Err(Errno::ISDIR | Errno::PERM) => {}
        Err(e) => return Err(e.into()),
    }
    let root = match open_dir_at(parent, name) {
        Ok(fd) => fd,
        Err(Errno::NOENT) => return Ok(done),
        // Replaced by something that is not a directory since: unlink that.
        Err(Errno::NOTDIR | Errno::LOOP) => {
            return match rustix::fs::unlinkat(parent, name, AtFlags::empty()) {
                Ok(()) | Err(Errno::NOENT) => Ok(done),
                Err(e) => Err(e.into()),
            };
        }
        Err(e) => return Err(e.into()),
    };
    let mut stack = vec![Frame { dir: Dir::new(root)?, name: name.to_owned() }];
    let mut spill = 0u64;
    loop {
        if done.entries >= MAX_ENTRIES {
            return Err(std::io::Error::other(format!("more than {MAX_ENTRIES} entries to remove")));
        }
        let Some(top) = stack.last_mut() else { break };
        let Some(entry) = top.dir.read() else {
            // Empty as far as this pass saw: remove it from its parent, or read it again if something arrived.
            let Some(mut frame) = stack.pop() else { break };
            let parent_fd = match stack.last() {
                Some(below) => below.dir.fd()?,
                None => parent,
            };
            match rustix::fs::unlinkat(parent_fd, frame.name.as_c_str(), AtFlags::REMOVEDIR) {
                Ok(()) => done.entries += 1,
                Err(Errno::NOENT) => {}
                Err(Errno::NOTEMPTY | Errno::EXIST) => {
                    // Entries came in after this pass read past them (subtrees moved up to the top among them).
                    // Counted towards the bound, so that a busy writer cannot keep this going forever.
                    done.entries += 1;
                    frame.dir.rewind();
                    stack.push(frame);
                }
                Err(e) => return Err(e.into()),
            }
            continue;
        };
        let child = entry?.file_name().to_owned();
        if child.as_c_str() == c"." || child.as_c_str() == c".." {
            continue;
        }
        let depth = stack.len();
        let (Some(top), Some(root)) = (stack.last(), stack.first()) else { break };
        let (here, root_fd) = (top.dir.fd()?, root.dir.fd()?);
        let unlinked = match rustix::fs::unlinkat(here, &child, AtFlags::empty()) {
            Err(Errno::ACCESS) => {
                // The agent took write permission away from this directory: give it back, then try again.
                rustix::fs::fchmod(here, Mode::from_raw_mode(0o700))?;
                rustix::fs::unlinkat(here, &child, AtFlags::empty())
            }
            other => other,
        };
        match unlinked {
            Ok(()) => {
                done.entries += 1;
                continue;
            }
            Err(Errno::NOENT) => continue,
            Err(Errno::ISDIR | Errno::PERM) => {}
            Err(e) => return Err(e.into()),
        }
        if depth >= MAX_OPEN_DIRS {
            // Too deep to open one more: move the subtree up to the top, to be emptied from there.
            if move_up(here, &child, root_fd, &mut spill)? {
                done.moved_up += 1;
            }
            continue;
        }
        let opened = match open_dir_at(here, &child) {
            Ok(fd) => fd,
            Err(Errno::NOENT) => continue,
            // Replaced by a non-directory since the unlink: unlink that.
            Err(Errno::NOTDIR | Errno::LOOP) => {
                match rustix::fs::unlinkat(here, &child, AtFlags::empty()) {
                    Ok(()) => done.entries += 1,
                    Err(Errno::NOENT) => {}
                    Err(e) => return Err(e.into()),
                }
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        stack.push(Frame { dir: Dir::new(opened)?, name: child });
    }
    Ok(done)
}

/// Renames `name` of `dir` to a fresh name in `root`; false if it was gone.
fn move_up(dir: BorrowedFd<'_>, name: &CStr, root: BorrowedFd<'_>, spill: &mut u64) -> std::io::Result<bool> {
    loop {
        *spill += 1;
        let to = CString::new(format!(".libero-cleanup-{spill}")).map_err(std::io::Error::other)?;
        match rustix::fs::renameat_with(dir, name, root, &to, RenameFlags::NOREPLACE) {
            Ok(()) => return Ok(true),
            Err(Errno::NOENT) => return Ok(false),
            Err(Errno::EXIST | Errno::NOTEMPTY) => continue,
            // No RENAME_NOREPLACE on this filesystem: a plain rename onto a name no entry has.
            Err(Errno::INVAL) => match rustix::fs::statat(root, &to, AtFlags::SYMLINK_NOFOLLOW) {
                Err(Errno::NOENT) => match rustix::fs::renameat(dir, name, root, &to) {
                    Ok(()) => return Ok(true),
                    Err(Errno::NOENT) => return Ok(false),
                    Err(e) => return Err(e.into()),
                },
                _ => continue,
            },
            Err(e) => return Err(e.into()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    #[test]
    fn a_deep_wide_tree_goes_and_links_out_of_it_leave_their_targets() {
        let t = tempfile::tempdir().unwrap();
        let host = t.path().join("host");
        std::fs::create_dir_all(host.join("sub")).unwrap();
        std::fs::write(host.join("sub/keep.txt"), "host data").unwrap();
        std::fs::write(t.path().join("host-file"), "host file").unwrap();
        let ws = t.path().join("ws");
        std::fs::create_dir(&ws).unwrap();
        // 2500 levels (a path of 5000 bytes, past PATH_MAX, and far past MAX_OPEN_DIRS), made through directory
        // descriptors; at every level a file, a link to the host directory and one to a host file.
        let mut dir = rustix::fs::open(&ws, DIR_FLAGS, Mode::empty()).unwrap();
        for level in 0..2500 {
            let f = rustix::fs::openat(&dir, "f", OFlags::WRONLY | OFlags::CREATE, Mode::from_raw_mode(0o644)).unwrap();
            rustix::io::write(&f, format!("{level}").as_bytes()).unwrap();
            rustix::fs::symlinkat(&host, &dir, "host-link").unwrap();
            rustix::fs::symlinkat(t.path().join("host-file"), &dir, "file-link").unwrap();
            rustix::fs::mkdirat(&dir, "d", Mode::from_raw_mode(0o755)).unwrap();
            dir = rustix::fs::openat(&dir, "d", DIR_FLAGS, Mode::empty()).unwrap();
        }
        drop(dir);
        // Wide: 5000 files and 300 directories with a file each in one directory.
        let wide = ws.join("wide");
        std::fs::create_dir(&wide).unwrap();
        for i in 0..5000 {
            std::fs::write(wide.join(format!("file{i}")), "").unwrap();
        }
        for i in 0..300 {
            std::fs::create_dir(wide.join(format!("dir{i}"))).unwrap();
            std::fs::write(wide.join(format!("dir{i}/x")), "").unwrap();
        }
        // A FIFO, and directories without permissions.
        assert!(std::process::Command::new("mkfifo").arg(ws.join("fifo")).status().unwrap().success());
        std::fs::create_dir_all(ws.join("locked/inner")).unwrap();
        std::fs::write(ws.join("locked/inner/f"), "").unwrap();
        std::fs::set_permissions(ws.join("locked/inner"), std::fs::Permissions::from_mode(0o000)).unwrap();
        std::fs::set_permissions(ws.join("locked"), std::fs::Permissions::from_mode(0o500)).unwrap();

        let removed = remove_tree(&ws).unwrap();
        assert!(std::fs::symlink_metadata(&ws).is_err(), "the workspace is gone");
        assert!(removed.moved_up > 0, "the deep part was moved up: {removed:?}");
        assert!(removed.entries >= 2500 * 4 + 5000 + 600, "{removed:?}");
        assert_eq!(std::fs::read_to_string(host.join("sub/keep.txt")).unwrap(), "host data", "the linked directory is untouched");
        assert_eq!(std::fs::read_to_string(t.path().join("host-file")).unwrap(), "host file");
        let left: Vec<_> = std::fs::read_dir(t.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left.len(), 2, "only the host's entries are left: {left:?}");
        // Missing: nothing to do. A link in its place: the link goes, its target stays.
        assert_eq!(remove_tree(&ws).unwrap(), Removed::default());
        std::os::unix::fs::symlink(&host, &ws).unwrap();
        assert_eq!(remove_tree(&ws).unwrap().entries, 1);
        assert!(host.join("sub/keep.txt").is_file());
    }
}
