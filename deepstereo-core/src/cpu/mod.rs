//! CPU pieces shared by the convolution kernels (`conv`) and the fused ops (`fused`): the
//! pointer wrapper their threads write through, the run-time check for the AVX2 kernels,
//! the selection softmax over a block of columns and branch-free `exp` / `tanh`.
//!
//! A leaf: it imports neither `conv` nor `fused` (both import it, never each other).

pub(crate) mod fastmath;
mod softmax;

pub(crate) use softmax::softmax_columns;

/// A pointer shared by threads that write disjoint parts of its buffer.
#[derive(Clone, Copy)]
pub(crate) struct SharedMut<T>(pub *mut T);
unsafe impl<T> Send for SharedMut<T> {}
unsafe impl<T> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    /// The pointer (a method, so that closures capture the `Sync` wrapper).
    pub fn get(self) -> *mut T {
        self.0
    }
}

/// Whether this CPU runs the AVX2 + FMA kernels (checked once; the answer is cached by
/// std).
pub(crate) fn avx2_fma_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
