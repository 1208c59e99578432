//! Allocator settings for the command-line tool and the benchmarks.
//!
//! The network allocates large, short-lived buffers on every call (im2col columns,
//! activations of tens of MB). With glibc's defaults, buffers above the mmap threshold are
//! mapped and unmapped each time and the heap top is trimmed back to the OS, so every
//! call pays for page faults and zeroing of fresh pages: a quarter of a pruned render's
//! time went to the kernel (`perf`). Keeping freed memory in the process removes that.

/// glibc's largest accepted mmap threshold (`DEFAULT_MMAP_THRESHOLD_MAX` on 64-bit).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: libc::c_int = 32 << 20;

/// Raises glibc's mmap threshold to its maximum and stops trimming the heap. Call once at
/// the start of `main`, before other threads start. A no-op on other platforms.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters and is called before other threads
    // exist; a failure (return 0) leaves glibc's defaults, which are correct, only slower.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
    }
}
