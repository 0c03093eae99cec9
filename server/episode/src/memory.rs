//! The allocator policy of a server that runs for weeks, set by the episode lifecycle (which builds and frees the
//! worlds). An episode's world peaks at about a gigabyte (MuJoCo's compile, the renderer's upload), allocated and
//! freed on the episode's own threads. With glibc's defaults that freed memory stays in the allocator's per-thread
//! arenas: resident size grew by about 240 MB per episode although nothing was still in use (`bench soak` reads
//! both figures).

/// Blocks of this size and more get a mapping of their own, returned to the OS when freed. glibc starts at
/// 128 KiB but raises the threshold itself, up to 32 MiB, each time a big block is freed, after which a world's
/// big arrays come from (and stay in) the arenas; a fixed threshold also turns that adjustment off.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD_BYTES: libc::c_int = 1 << 20;

/// Free memory at the top of an arena up to this size stays there until [`return_freed_memory`]; beyond it,
/// `free` hands it back at once. glibc's 128 KiB made the renderer's every frame a cycle of give back and fault
/// in again: lavapipe's per-frame buffers (a few MB in blocks under the mmap threshold) were returned with
/// `madvise` on each free and zeroed by the kernel on the next frame's first touch, about 14,000 page faults (54 MB
/// cleared) per live frame, on the thread that shades the vertices of both cameras before any pixel. 16 MiB
/// already stops that; 32 leaves a margin. What a released world frees is trimmed explicitly whatever this is.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const TRIM_THRESHOLD_BYTES: libc::c_int = 32 << 20;

/// Sets the policy above for the whole process (idempotent).
pub fn tune_for_long_runs() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes glibc's allocation parameters.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES);
    }
}

/// Gives the pages the allocator holds free back to the OS (call after episodes released their worlds).
pub fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages of the allocator's own arenas to the OS.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(all(test, feature = "world", target_os = "linux", target_env = "gnu"))]
mod tests {
    use crate::observation::Level;
    use crate::task::resolve_task;
    use crate::world::{LiberoWorld, WorldSpec};
    use crate::World;

    /// Minor page faults of this process so far.
    fn minor_faults() -> u64 {
        // SAFETY: getrusage writes only into the struct it is given.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        assert_eq!(unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) }, 0);
        usage.ru_minflt as u64
    }

    /// Frames rendered one after another (a watched or teleoperated episode) fault in no fresh pages: the
    /// renderer's per-frame buffers stay with the allocator between frames. With glibc's default trim threshold
    /// every frame gave them back and faulted them in again, about 14,000 pages a frame.
    #[test]
    fn frames_rendered_one_after_another_do_not_fault_their_buffers_in_again() {
        super::tune_for_long_runs();
        let paths = libero_sim::AssetPaths::discover().expect("assets: run scripts/setup.py");
        let spec = WorldSpec { task: resolve_task("T14", &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
        let mut world = LiberoWorld::new(&spec, libero_render::Renderer::new().unwrap()).unwrap();
        world.start().unwrap();
        for i in 0..5 {
            world.frame(i).unwrap();
        }
        const FRAMES: u64 = 20;
        let before = minor_faults();
        for i in 0..FRAMES {
            world.frame(5 + i).unwrap();
        }
        let per_frame = (minor_faults() - before) / FRAMES;
        assert!(per_frame < 1_000, "{per_frame} minor page faults per rendered frame");
    }
}
