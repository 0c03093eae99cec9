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
