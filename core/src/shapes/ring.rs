//! `ring`: robots evenly on a circle, toured around it.

/// How far a ring of `n` robots at lattice spacing `spacing` reaches from its centre, with
/// `relax` of room for what the relaxation moves.
pub(super) fn reach_m(n: f64, spacing: f64, relax: f64) -> f64 {
    spacing / (2.0 * (std::f64::consts::PI / n).sin()) + relax
}

/// Robots evenly on a circle whose chord between tour neighbours is `spacing`.
pub(super) fn points(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    let step = std::f64::consts::TAU / n as f64;
    let radius = spacing / (2.0 * (0.5 * step).sin());
    (0..n)
        .map(|i| [radius * (i as f64 * step).cos(), radius * (i as f64 * step).sin()])
        .collect()
}
