//! `wedge`: the `line` band bent at its middle into a V pointing along +x.

/// Half-angle of the V's opening, radians, drawn per episode.
pub(super) const HALF_ANGLE: std::ops::Range<f64> = 0.45..0.7;

/// A band of two files bent at its middle into a V whose arms open at `half_angle` (radians)
/// behind an apex at the front.
pub(super) fn points(band: Vec<[f64; 2]>, half_angle: f64) -> Vec<[f64; 2]> {
    let middle = band.iter().map(|p| p[0]).fold(0.0, f64::max) * 0.5;
    let (s, c) = half_angle.sin_cos();
    band.iter()
        .map(|p| {
            let along = p[0] - middle;
            let across = p[1];
            let side = if along < 0.0 { 1.0 } else { -1.0 };
            // Each arm runs back from the apex; the second file sits on the arm's outer side.
            [-c * along.abs() + s * across, side * (s * along.abs() + c * across)]
        })
        .collect()
}
