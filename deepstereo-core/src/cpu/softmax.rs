//! The selection softmax over depth, `softmax_D(tanh(x) a)`, on a block of columns: the
//! fused head's (`fused/head.rs`, `select_softmax`) and the fused depth head's
//! (`conv/chain.rs`, `depth_head`).

use num_traits::Float;

/// Softmax over `d` of `tanh(x) a` for columns `j0..j1` of one batch item (`x`, `s`:
/// `[d, p]`).
///
/// # Safety
/// `s` addresses `d * p` values of which no other thread touches these columns.
pub(crate) unsafe fn softmax_columns<T: Float>(
    x: &[T],
    s: *mut T,
    a: T,
    (d, p): (usize, usize),
    j0: usize,
    j1: usize,
) {
    let mut m = vec![T::neg_infinity(); j1 - j0];
    for i in 0..d {
        for (j, mj) in (j0..j1).zip(m.iter_mut()) {
            let z = x[i * p + j].tanh() * a;
            *s.add(i * p + j) = z;
            *mj = mj.max(z);
        }
    }
    let mut sum = vec![T::zero(); j1 - j0];
    for i in 0..d {
        for ((j, &mj), sj) in (j0..j1).zip(&m).zip(sum.iter_mut()) {
            let e = (*s.add(i * p + j) - mj).exp();
            *s.add(i * p + j) = e;
            *sj = *sj + e;
        }
    }
    for i in 0..d {
        for (j, &sj) in (j0..j1).zip(&sum) {
            *s.add(i * p + j) = *s.add(i * p + j) / sj;
        }
    }
}
