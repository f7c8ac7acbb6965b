//! `line`: two staggered files along x; the tour runs forward along the first and back along
//! the second, so every tour step and every second step stays short.

/// How far two files of `n` robots at lattice spacing `spacing` reach from their centre (a
/// wedge bends the same band, so it reaches no further), with `relax` of room for the
/// relaxation.
pub(super) fn reach_m(n: f64, spacing: f64, relax: f64) -> f64 {
    (0.25 * n * spacing).hypot(spacing) + relax
}

/// Two staggered files along x, `spacing` apart along and across: the tour runs forward along
/// the first file and back along the second.
pub(super) fn points(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    let front = n.div_ceil(2);
    let back = n - front;
    let across = spacing;
    let first = (0..front).map(|k| [k as f64 * spacing, 0.0]);
    let second = (0..back).rev().map(|k| [(k as f64 + 0.5) * spacing, across]);
    first.chain(second).collect()
}
