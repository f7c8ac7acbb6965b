//! `grid`: a lattice block toured by a boustrophedon that returns along its first column
//! (below five robots, a ring).

/// How far a block of `n` robots at lattice spacing `spacing` reaches from its centre, with
/// `relax` of room for the relaxation.
pub(super) fn reach_m(n: f64, spacing: f64, relax: f64) -> f64 {
    0.75 * spacing * (n + 4.0).sqrt() + spacing + relax
}

/// A block of `rows` (even) by `columns` lattice points `spacing` apart, toured by a
/// boustrophedon over columns 1.. that returns along column 0; odd `n` gets a nose robot ahead
/// of the block's first row.
pub(super) fn points(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    if n < 5 {
        return super::ring::points(n, spacing);
    }
    let even = n - n % 2;
    let mut rows = 2;
    while (rows + 2) * (rows + 2) <= even {
        rows += 2;
    }
    let columns = even.div_ceil(rows);
    // Lattice points the block leaves out: pairs of rows at the end of the last column.
    let missing_pairs = (rows * columns - even) / 2;
    let present = |row: usize, column: usize| column + 1 < columns || row < rows - 2 * missing_pairs;
    let point = |row: usize, column: usize| [column as f64 * spacing, -(row as f64) * spacing];
    let mut tour = Vec::with_capacity(n);
    for row in 0..rows {
        let columns_of_row: Vec<usize> = if row % 2 == 0 {
            (1..columns).collect()
        } else {
            (1..columns).rev().collect()
        };
        tour.extend(
            columns_of_row
                .into_iter()
                .filter(|&column| present(row, column))
                .map(|column| point(row, column)),
        );
    }
    tour.extend((0..rows).rev().map(|row| point(row, 0)));
    // The tour ends at (0, 0); rotate it to start there, then put the nose between (0, 0) and
    // (0, 1), half a spacing ahead of the first row.
    tour.rotate_right(1);
    if n % 2 == 1 {
        tour.insert(1, [0.5 * spacing, 0.9 * spacing]);
    }
    tour
}
