//! Allocator settings for the command-line tool (deepstereo-train) and the benchmarks.
//!
//! The network allocates large, short-lived buffers on every call (im2col columns,
//! activations of tens of MB). With glibc's defaults, buffers above the mmap threshold are
//! mapped and unmapped each time and the heap top is trimmed back to the OS, so every
//! call pays for page faults and zeroing of fresh pages: a quarter of a pruned render's
//! time went to the kernel (`perf`). Keeping freed memory in the process removes that.
//! The threshold alone tops out at 32 MiB, below the `paper` preset's activations (a
//! 96 x 96 x 46 x 46 output is 78 MiB), so mapping is switched off altogether: freed
//! blocks of any size go back to the heap and are reused (about a tenth of a `paper`
//! forward had gone to `clear_page` and page faults).

/// glibc's largest accepted mmap threshold (`DEFAULT_MMAP_THRESHOLD_MAX` on 64-bit).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD: libc::c_int = 32 << 20;

/// Serves every allocation from glibc's heap (no per-buffer mappings; the threshold is
/// raised too, for a glibc that ignores `M_MMAP_MAX`) and stops trimming the heap. Call once at
/// the start of `main`, before other threads start. A no-op on other platforms.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters and is called before other threads
    // exist; a failure (return 0) leaves glibc's defaults, which are correct, only slower.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
        libc::mallopt(libc::M_MMAP_MAX, 0);
    }
}
