//! The two Winograd algorithms, their transforms as constants (from Toom-Cook on the
//! points given; `B^T = (V^-1)^T` for the Vandermonde matrix `V` of the points and
//! infinity, `G` and `A^T` their evaluation matrices).

use super::A;

/// One algorithm F(M x M, R x R) on `A x A` tiles: its transforms as constants, so that
/// the transform loops compile to straight-line code without the zero terms.
pub(super) trait Algo {
    /// Outputs per tile side.
    const M: usize;
    /// Kernel side.
    const R: usize;
    /// `B^T` (`[A, A]`).
    const BT: [[f32; A]; A];
    /// `G` (`[A, R]`, columns past `R` zero).
    const G: [[f64; 5]; A];
    /// `A^T` (`[M, A]`, rows past `M` unused).
    const AT: [[f32; A]; 4];
}

/// F(2x2, 5x5), points 0, 1, -1, 1/2, -1/2, infinity.
pub(super) struct F25;

impl Algo for F25 {
    const M: usize = 2;
    const R: usize = 5;
    const BT: [[f32; A]; A] = [
        [1.0, 0.0, -5.0, 0.0, 4.0, 0.0],
        [0.0, -1.0 / 6.0, -1.0 / 6.0, 2.0 / 3.0, 2.0 / 3.0, 0.0],
        [0.0, 1.0 / 6.0, -1.0 / 6.0, -2.0 / 3.0, 2.0 / 3.0, 0.0],
        [0.0, 4.0 / 3.0, 8.0 / 3.0, -4.0 / 3.0, -8.0 / 3.0, 0.0],
        [0.0, -4.0 / 3.0, 8.0 / 3.0, 4.0 / 3.0, -8.0 / 3.0, 0.0],
        [0.0, 0.25, 0.0, -1.25, 0.0, 1.0],
    ];
    const G: [[f64; 5]; A] = [
        [1.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0, 1.0, 1.0],
        [1.0, -1.0, 1.0, -1.0, 1.0],
        [1.0, 0.5, 0.25, 0.125, 0.0625],
        [1.0, -0.5, 0.25, -0.125, 0.0625],
        [0.0, 0.0, 0.0, 0.0, 1.0],
    ];
    const AT: [[f32; A]; 4] = [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 0.5, -0.5, 1.0],
        [0.0; A],
        [0.0; A],
    ];
}

/// F(4x4, 3x3), points 0, 1, -1, 1/2, -2, infinity.
pub(super) struct F43;

impl Algo for F43 {
    const M: usize = 4;
    const R: usize = 3;
    const BT: [[f32; A]; A] = [
        [1.0, -1.5, -2.0, 1.5, 1.0, 0.0],
        [0.0, -1.0 / 3.0, 1.0 / 6.0, 5.0 / 6.0, 1.0 / 3.0, 0.0],
        [0.0, -1.0 / 3.0, 5.0 / 6.0, -1.0 / 6.0, -1.0 / 3.0, 0.0],
        [
            0.0,
            32.0 / 15.0,
            16.0 / 15.0,
            -32.0 / 15.0,
            -16.0 / 15.0,
            0.0,
        ],
        [0.0, 1.0 / 30.0, -1.0 / 15.0, -1.0 / 30.0, 1.0 / 15.0, 0.0],
        [0.0, 1.0, -1.5, -2.0, 1.5, 1.0],
    ];
    const G: [[f64; 5]; A] = [
        [1.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0, 0.0, 0.0],
        [1.0, -1.0, 1.0, 0.0, 0.0],
        [1.0, 0.5, 0.25, 0.0, 0.0],
        [1.0, -2.0, 4.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0, 0.0],
    ];
    const AT: [[f32; A]; 4] = [
        [1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
        [0.0, 1.0, -1.0, 0.5, -2.0, 0.0],
        [0.0, 1.0, 1.0, 0.25, 4.0, 0.0],
        [0.0, 1.0, -1.0, 0.125, -8.0, 1.0],
    ];
}
