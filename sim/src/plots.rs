//! PNG figures like the paper's, written into the run directory at the end of a run:
//! `learning_curve.png` (Fig. 4: average reward per episode, with the rolling success rate)
//! and `episode_errors.png` (Fig. 5: each edge's error and the centroid-to-goal distance
//! against time for one evaluation episode).

use std::path::Path;

use anyhow::{Result, anyhow};
use plotters::prelude::*;

use formation_core::physics::Pose;
use formation_core::task::{Outcome, edge_error};
use formation_protocol::NEIGHBOURS;

use crate::report::EpisodeRecord;

/// Size of every figure, pixels.
pub const FIGURE_SIZE: (u32, u32) = (1200, 500);
/// Episodes in the rolling mean and success rate.
const ROLLING: usize = 100;

/// DejaVu Sans, embedded so the figures render on a machine without fonts.
static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

fn register_font() -> Result<()> {
    plotters::style::register_font("sans-serif", FontStyle::Normal, FONT)
        .map_err(|_| anyhow!("the embedded font is invalid"))
}

/// Per-tick errors of one episode.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EpisodeTrace {
    /// Episode number.
    pub episode: u32,
    /// Seconds per tick.
    pub dt: f64,
    /// Names of the traced edges after the robots they join, e.g. `e01`; after a change of
    /// formation gave the first robot another neighbour, `e01→e03` (`→out` when it left).
    pub edge_names: Vec<String>,
    /// The robot each traced edge joins its first robot to at the latest tick.
    pub edge_partners: Vec<usize>,
    /// Per tick, the error of each traced edge, metres: rows of `edge_names.len()` values, flat
    /// so the tick loop allocates nothing.
    pub edge_errors: Vec<f64>,
    /// Per tick, the mean error over all observed edges, metres.
    pub mean_edge_error: Vec<f64>,
    /// Per tick, the centroid-to-goal distance, metres.
    pub goal_distance: Vec<f64>,
}

impl EpisodeTrace {
    /// Starts tracing episode `episode` (the buffers keep their room).
    pub fn begin(&mut self, episode: u32) {
        self.episode = episode;
        self.edge_errors.clear();
        self.mean_edge_error.clear();
        self.goal_distance.clear();
    }

    /// Appends one tick of the traced edges (`traced`: robot i's k-th observed edge, as `(i, k,
    /// _)`), naming each after the robots it joins: renamed at an episode's first tick (an
    /// empty trace) when the last episode changed it, extended when the robot's neighbour
    /// changes (allocating only then).
    pub fn push_edges(
        &mut self,
        traced: &[(usize, usize, usize)],
        poses: &[Pose],
        desired: &[[f64; NEIGHBOURS]],
        observed: &[[usize; NEIGHBOURS]],
    ) {
        let first_tick = self.edge_errors.is_empty();
        self.edge_names.resize(traced.len(), String::new());
        self.edge_partners.resize(traced.len(), usize::MAX);
        for (e, &(i, k, _)) in traced.iter().enumerate() {
            let partner = observed[i][k];
            let name = &mut self.edge_names[e];
            if first_tick && (self.edge_partners[e] != partner || name.contains('→')) {
                *name = format!("e{i}{partner}");
            } else if self.edge_partners[e] != partner {
                match partner == i {
                    true => name.push_str("→out"),
                    false => name.push_str(&format!("→e{i}{partner}")),
                }
            }
            self.edge_partners[e] = partner;
            self.edge_errors.push(edge_error(i, k, poses, desired, observed));
        }
    }
}

fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if lo > hi {
        (0.0, 1.0)
    } else if (hi - lo).abs() < 1e-9 {
        (lo - 0.5, hi + 0.5)
    } else {
        (lo, hi)
    }
}

fn rolling(values: &[f64]) -> Vec<f64> {
    let mut out = Vec::with_capacity(values.len());
    let mut sum = 0.0;
    for (i, v) in values.iter().enumerate() {
        sum += v;
        if i >= ROLLING {
            sum -= values[i - ROLLING];
        }
        out.push(sum / (i + 1).min(ROLLING) as f64);
    }
    out
}

/// Average reward per episode (raw and rolling mean) and the rolling success rate.
pub fn learning_curve(path: &Path, records: &[EpisodeRecord]) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, FIGURE_SIZE).into_drawing_area();
    root.fill(&WHITE)?;
    let (left, right) = root.split_horizontally(FIGURE_SIZE.0 / 2);
    let returns: Vec<f64> = records.iter().map(|r| r.episode_return).collect();
    let successes: Vec<f64> = records
        .iter()
        .map(|r| if r.outcome == Outcome::Success { 1.0 } else { 0.0 })
        .collect();
    let episodes = records.len().max(2) as f64;
    let (lo, hi) = range(returns.iter().copied());
    let mut chart = ChartBuilder::on(&left)
        .caption("Reward per episode", ("sans-serif", 24))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..episodes, lo..hi)?;
    chart
        .configure_mesh()
        .x_desc("episode")
        .y_desc("episode return")
        .draw()?;
    chart
        .draw_series(LineSeries::new(
            returns.iter().enumerate().map(|(i, &r)| (i as f64, r)),
            BLUE.mix(0.3),
        ))?
        .label("per episode")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.mix(0.3)));
    chart
        .draw_series(LineSeries::new(
            rolling(&returns).into_iter().enumerate().map(|(i, r)| (i as f64, r)),
            BLUE.stroke_width(2),
        ))?
        .label(format!("mean of last {ROLLING}"))
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;

    let mut chart = ChartBuilder::on(&right)
        .caption("Success rate", ("sans-serif", 24))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..episodes, 0f64..1.05)?;
    chart
        .configure_mesh()
        .x_desc("episode")
        .y_desc(format!("success, last {ROLLING} episodes"))
        .draw()?;
    chart.draw_series(LineSeries::new(
        rolling(&successes).into_iter().enumerate().map(|(i, r)| (i as f64, r)),
        GREEN.stroke_width(2),
    ))?;
    root.present()?;
    Ok(())
}

/// Each edge's error and the centroid-to-goal distance against time (the paper's Fig. 5).
pub fn episode_errors(path: &Path, trace: &EpisodeTrace) -> Result<()> {
    register_font()?;
    let root = BitMapBackend::new(path, FIGURE_SIZE).into_drawing_area();
    root.fill(&WHITE)?;
    let (left, right) = root.split_horizontally(FIGURE_SIZE.0 / 2);
    let ticks = trace.goal_distance.len().max(2);
    let t_max = (ticks - 1) as f64 * trace.dt;
    let time = |i: usize| i as f64 * trace.dt;
    let edges = trace.edge_names.len().max(1);
    let (_, err_hi) = range(
        trace
            .edge_errors
            .iter()
            .copied()
            .chain(trace.mean_edge_error.iter().copied()),
    );
    let mut chart = ChartBuilder::on(&left)
        .caption(format!("Edge errors, episode {}", trace.episode), ("sans-serif", 24))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..t_max, 0f64..err_hi.max(0.01) * 1.05)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("|d - d*| (m)")
        .draw()?;
    for (e, name) in trace.edge_names.iter().enumerate() {
        let colour = Palette99::pick(e).to_rgba();
        chart
            .draw_series(LineSeries::new(
                trace
                    .edge_errors
                    .chunks_exact(edges)
                    .enumerate()
                    .map(|(i, row)| (time(i), row[e])),
                colour,
            ))?
            .label(name.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
    }
    chart
        .draw_series(DashedLineSeries::new(
            trace.mean_edge_error.iter().enumerate().map(|(i, &m)| (time(i), m)),
            6,
            4,
            RED.stroke_width(2),
        ))?
        .label("mean")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;

    let (_, dist_hi) = range(trace.goal_distance.iter().copied());
    let mut chart = ChartBuilder::on(&right)
        .caption("Centroid to goal", ("sans-serif", 24))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..t_max, 0f64..dist_hi * 1.05)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("distance (m)")
        .draw()?;
    chart.draw_series(LineSeries::new(
        trace.goal_distance.iter().enumerate().map(|(i, &d)| (time(i), d)),
        BLACK.stroke_width(2),
    ))?;
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_are_decodable_pngs_of_the_expected_size() {
        let dir = std::env::temp_dir().join(format!("formation-plots-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let records: Vec<EpisodeRecord> = (0..150)
            .map(|i| EpisodeRecord {
                episode: i,
                outcome: if i % 3 == 0 { Outcome::Success } else { Outcome::Timeout },
                steps: 100,
                episode_return: f64::from(i) * 0.1 - 5.0,
                final_edge_error_m: 0.01,
                final_goal_distance_m: 0.2,
                formation_hold_rate: 0.9,
                missed_ticks: 0,
                late_commands: 0,
                lost_commands: 0,
                lost_observations: 0,
                reconfigurations: 0,
                reforms: 0,
                mean_reform_ticks: None,
                reform_ticks_sum: 0,
                departures: 0,
                returns: 0,
                wall_s: f64::from(i),
                obstacle_collisions: 0,
            })
            .collect();
        let curve = dir.join("learning_curve.png");
        learning_curve(&curve, &records).expect("learning curve");
        let trace = EpisodeTrace {
            episode: 3,
            dt: 0.1,
            edge_names: vec!["e01".into(), "e12→e13".into(), "e20".into()],
            edge_partners: vec![1, 3, 0],
            edge_errors: (0..50).flat_map(|t| [0.01 * f64::from(t % 7), 0.02, 0.005]).collect(),
            mean_edge_error: (0..50).map(|_| 0.015).collect(),
            goal_distance: (0..50).map(|t| 2.0 - 0.04 * f64::from(t)).collect(),
        };
        let errors = dir.join("episode_errors.png");
        episode_errors(&errors, &trace).expect("episode errors");
        for path in [curve, errors] {
            let image = image::open(&path).expect("decodable PNG");
            assert_eq!((image.width(), image.height()), FIGURE_SIZE, "{}", path.display());
            let pixels = image.to_rgb8();
            let non_white = pixels.pixels().filter(|p| p.0 != [255, 255, 255]).count();
            assert!(non_white > 10_000, "{} is nearly blank", path.display());
        }
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn traced_edges_are_renamed_when_a_change_gives_a_robot_other_neighbours() {
        let poses: Vec<Pose> = (0..4)
            .map(|i| Pose {
                x: f64::from(i),
                y: 0.0,
                theta: 0.0,
            })
            .collect();
        let desired = vec![[1.0, 2.0]; 4];
        let by_index = formation_core::scene::index_neighbours(4);
        let traced = [(0, 0, 1), (1, 0, 2)];
        let mut trace = EpisodeTrace::default();
        trace.push_edges(&traced, &poses, &desired, &by_index);
        assert_eq!(trace.edge_names, ["e01", "e12"]);
        // Robot 0 takes another slot: its first neighbour is now robot 3; robot 1 leaves.
        let changed = vec![[3, 1], [1, 1], [0, 3], [2, 0]];
        trace.push_edges(&traced, &poses, &desired, &changed);
        trace.push_edges(&traced, &poses, &desired, &changed);
        assert_eq!(trace.edge_names, ["e01→e03", "e12→out"]);
        assert_eq!(trace.edge_errors, [0.0, 0.0, 2.0, 1.0, 2.0, 1.0]);
        // The next episode starts by index again: the plain names come back.
        trace.edge_errors.clear();
        trace.push_edges(&traced, &poses, &desired, &by_index);
        assert_eq!(trace.edge_names, ["e01", "e12"]);
    }
}
