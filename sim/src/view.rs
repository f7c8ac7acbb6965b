//! The live view of the world in Rerun, fed from the tick loop through a bounded channel so
//! logging never waits on the physics (a full channel drops the state instead of blocking).
//!
//! Entities: `world/robots` (poses, one colour each, labelled with the slot each holds up to 24
//! robots: "robot i → slot s" up to 6, "i→s" up to 24), `world/headings`, `world/edges`
//! (coloured by error), `world/goal`, `world/formation/target` (the formation in force at the
//! goal: a ring around each slot and its tour through the slots), `world/formation/assignment`
//! (a thin light line from each robot to its slot), `world/formation/old` (after
//! a change of formation, the one it replaced, in grey fading out over [`FADE_S`] seconds of
//! simulated time), `world/centroid`, `world/trails`; series `plots/formation/edge_error/*`
//! (one per observed edge up to 8 robots, else mean and max), `plots/formation/goal_distance`,
//! `plots/reward`. Rerun's 2-D views are y-down, so y is flipped when logging.
//!
//! Among obstacles: `world/obstacles` (the episode's obstacles, logged at its first tick and
//! cleared in an episode without any: a disc's outline, a wall's rectangle) and, when the robots
//! observe `slot_proximity_scan`, `world/scans` (each robot's range-sensor hits in its colour:
//! where a ray read less than `env.scan_range_m`, noise and dropouts included, from what the
//! robot was told at that tick).

use std::collections::VecDeque;
use std::path::Path;
use std::sync::mpsc::{Receiver, sync_channel};
use std::thread::JoinHandle;

use anyhow::{Context, Result};
use formation_core::config::EnvConfig;
use formation_core::mission::observed_robots;
use formation_core::observation::{Layout, SCAN_RAYS};
use formation_core::obstacles::Obstacle;
use formation_ipc::cli::ViewerMode;
use formation_protocol::wire::{FLAG_EPISODE_START, StateMsg};
use rerun::RecordingStream;
use rerun::blueprint::{Blueprint, Horizontal, Spatial2DView, TimeSeriesView, Vertical};

use crate::lockstep::{StateTap, Tapped};

/// States the view may fall behind by before the sim starts dropping them.
const TAP_CAPACITY: usize = 4096;
/// Simulated seconds over which a replaced formation fades out.
pub const FADE_S: f64 = 3.0;
/// Radius of the ring drawn around each slot, metres.
const SLOT_RING_M: f32 = 0.18;
/// Sides of the polygon that draws a slot's ring.
const RING_SIDES: usize = 20;
/// The formation in force.
const TARGET_COLOUR: [u8; 3] = [0, 140, 70];
/// The formation replaced, before its fading.
const OLD_COLOUR: [u8; 3] = [110, 110, 110];
/// The lines from the robots to their slots.
const ASSIGNMENT_COLOUR: [u8; 3] = [225, 225, 225];
/// The obstacles' outlines.
const OBSTACLE_COLOUR: [u8; 3] = [150, 160, 175];
/// Sides of the polygon that draws a disc obstacle.
const DISC_SIDES: usize = 32;

/// The default layout: the world beside the formation and training curves.
pub fn blueprint() -> Blueprint {
    Blueprint::new(
        Horizontal::new([
            Spatial2DView::new("World").with_origin("world").into(),
            Vertical::new([
                TimeSeriesView::new("Formation (paper Fig. 5)")
                    .with_origin("plots/formation")
                    .into(),
                TimeSeriesView::new("Reward per tick")
                    .with_origin("plots/reward")
                    .into(),
                TimeSeriesView::new("Training (paper Fig. 4)")
                    .with_origin("plots/training")
                    .into(),
            ])
            .with_row_shares([0.45, 0.2, 0.35])
            .into(),
        ])
        .with_column_shares([0.55, 0.45]),
    )
}

/// A robot's colour.
pub fn robot_colour(agent: usize) -> [u8; 3] {
    const PALETTE: [[u8; 3]; 8] = [
        [230, 25, 75],
        [60, 180, 75],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [128, 128, 0],
    ];
    PALETTE[agent % PALETTE.len()]
}

/// Green at zero error, yellow at eps_form, red from three times eps_form.
fn error_colour(error: f32, eps_form: f32) -> [u8; 3] {
    let x = (error / (3.0 * eps_form)).clamp(0.0, 1.0);
    if x < 1.0 / 3.0 {
        let t = x * 3.0;
        [(40.0 + t * 200.0) as u8, 200, 40]
    } else {
        let t = (x - 1.0 / 3.0) * 1.5;
        [240, (200.0 - t * 180.0) as u8, 40]
    }
}

/// Starts the logging thread; returns the tap the sim offers its states to.
pub fn start(
    mode: &ViewerMode,
    run_id: &str,
    run_dir: &Path,
    env: &EnvConfig,
    n_agents: usize,
    trail_ticks: usize,
) -> Result<Option<(StateTap, JoinHandle<()>)>> {
    let Some(stream) = formation_view::open_recording(mode, run_id, run_dir, "recording", true)? else {
        return Ok(None);
    };
    blueprint().send(
        &stream,
        rerun::blueprint::BlueprintActivation {
            make_active: true,
            make_default: true,
        },
    )?;
    let (tap, states) = sync_channel(TAP_CAPACITY);
    let view = WorldView {
        stream,
        eps_form: env.eps_form_m as f32,
        arena: env.effective_arena_m(n_agents) as f32,
        trails: vec![VecDeque::with_capacity(trail_ticks); n_agents],
        trail_ticks,
        ticks: 0,
        fade_ticks: fade_ticks(env.dt_s),
        target: None,
        old: None,
        scan: Layout::of(env.observation).scan(),
        scan_range: env.scan_range_m as f32,
        obstacles_of: None,
    };
    let handle = std::thread::Builder::new()
        .name("rerun-world".into())
        .spawn(move || view.run(states))
        .context("cannot start the view thread")?;
    Ok(Some((tap, handle)))
}

struct WorldView {
    stream: RecordingStream,
    eps_form: f32,
    arena: f32,
    trails: Vec<VecDeque<[f32; 2]>>,
    trail_ticks: usize,
    ticks: i64,
    /// Ticks a replaced formation takes to fade out.
    fade_ticks: i64,
    /// The formation in force at the last state logged.
    target: Option<Target>,
    /// The formation it replaced and the view tick of the change, while it fades.
    old: Option<(Target, i64)>,
    /// Where the range sensor's rays start in an observation, when the robots have one.
    scan: Option<usize>,
    /// The range a ray reading 1 stands for, metres.
    scan_range: f32,
    /// The episode whose obstacles are drawn.
    obstacles_of: Option<u32>,
}

/// Ticks of `dt_s` seconds in [`FADE_S`] (at least one).
fn fade_ticks(dt_s: f64) -> i64 {
    ((FADE_S / dt_s).ceil() as i64).max(1)
}

/// A formation as a state carries it: the episode, the goal, and each robot's slot and offset.
#[derive(Debug, Clone, PartialEq)]
struct Target {
    episode: u32,
    goal: [f32; 2],
    slot_of: Vec<u32>,
    offsets: Vec<[f32; 2]>,
}

impl Target {
    fn of(state: &StateMsg) -> Self {
        let n = state.n_agents as usize;
        Self {
            episode: state.header.episode,
            goal: state.goal,
            slot_of: state.slot[..n].to_vec(),
            offsets: state.slots[..n].to_vec(),
        }
    }

    /// Whether robot `robot` holds a slot (a robot out of the formation holds none).
    fn holds_slot(&self, robot: usize) -> bool {
        (self.slot_of[robot] as usize) < self.slot_of.len()
    }

    /// Robot `robot`'s place at the goal, y flipped.
    fn place(&self, robot: usize) -> [f32; 2] {
        flip(
            self.goal[0] + self.offsets[robot][0],
            self.goal[1] + self.offsets[robot][1],
        )
    }

    /// The places of the slots held, in slot order (y flipped).
    fn places(&self) -> Vec<[f32; 2]> {
        let mut held: Vec<(u32, [f32; 2])> = (0..self.slot_of.len())
            .filter(|&r| self.holds_slot(r))
            .map(|r| (self.slot_of[r], self.place(r)))
            .collect();
        held.sort_unstable_by_key(|&(slot, _)| slot);
        held.into_iter().map(|(_, place)| place).collect()
    }

    /// The formation's outline: a ring around each slot, then its tour through the slots.
    fn outline(&self) -> Vec<Vec<[f32; 2]>> {
        let places = self.places();
        let mut strips: Vec<Vec<[f32; 2]>> = places
            .iter()
            .map(|c| {
                (0..=RING_SIDES)
                    .map(|k| {
                        let a = std::f32::consts::TAU * k as f32 / RING_SIDES as f32;
                        [c[0] + SLOT_RING_M * a.cos(), c[1] + SLOT_RING_M * a.sin()]
                    })
                    .collect()
            })
            .collect();
        let mut tour = places.clone();
        tour.extend(places.first());
        strips.push(tour);
        strips
    }
}

impl WorldView {
    fn run(mut self, states: Receiver<Tapped>) {
        if let Err(err) = self.log_static() {
            eprintln!("sim: view: {err:#}");
            return;
        }
        for Tapped { state, obstacles } in states {
            if let Err(err) = self.log_state(&state, obstacles.as_deref()) {
                eprintln!("sim: view stopped: {err:#}");
                break;
            }
        }
        let _ = self.stream.flush_blocking();
        self.stream.disconnect();
    }

    fn log_static(&self) -> Result<()> {
        let a = self.arena;
        self.stream.log_static(
            "world/arena",
            &rerun::Boxes2D::from_mins_and_sizes([(0.0, -a)], [(a, a)]).with_colors([[90, 90, 90]]),
        )?;
        for (path, name, colour) in [
            ("plots/formation/goal_distance", "centroid to goal (m)", [30, 30, 30]),
            ("plots/reward", "reward", [120, 120, 120]),
        ] {
            self.stream.log_static(
                path,
                &rerun::SeriesLines::new().with_names([name]).with_colors([colour]),
            )?;
        }
        Ok(())
    }

    fn log_state(&mut self, state: &StateMsg, obstacles: Option<&[Obstacle]>) -> Result<()> {
        let n = state.n_agents as usize;
        if state.header.has(FLAG_EPISODE_START) {
            self.trails.iter_mut().for_each(VecDeque::clear);
        }
        self.ticks += 1;
        self.stream.set_time_sequence("tick", self.ticks);
        self.stream
            .set_time_sequence("episode", i64::from(state.header.episode));
        let positions: Vec<[f32; 2]> = state.poses[..n].iter().map(|p| flip(p[0], p[1])).collect();
        let colours: Vec<[u8; 3]> = (0..n).map(robot_colour).collect();
        self.log_obstacles(state.header.episode, obstacles)?;
        self.log_robots(state, &positions, &colours)?;
        self.log_scans(state, &colours)?;
        self.log_edges(state, &positions)?;
        self.log_formations(state, &positions)?;
        self.log_goal_and_trails(state, &positions, colours)
    }

    /// The formation in force (slot rings and tour), each robot's line to its slot, and the
    /// formation a change replaced, fading out over [`FADE_S`].
    fn log_formations(&mut self, state: &StateMsg, positions: &[[f32; 2]]) -> Result<()> {
        let target = Target::of(state);
        let new_episode =
            state.header.has(FLAG_EPISODE_START) || self.target.as_ref().is_none_or(|t| t.episode != target.episode);
        if new_episode {
            if self.old.take().is_some() {
                self.stream.log("world/formation/old", &rerun::Clear::flat())?;
            }
        } else if let Some(previous) = self.target.take_if(|t| *t != target) {
            // A change reassigns slots or moves the goal; the offsets alone move every tick of
            // the morph after a scheduled change, which continues the same change.
            if previous.slot_of != target.slot_of || previous.goal != target.goal {
                self.old = Some((previous, self.ticks));
            }
        }
        if self.target.as_ref() != Some(&target) {
            let outline = target.outline();
            let tour = outline.len() - 1;
            self.stream.log(
                "world/formation/target",
                &rerun::LineStrips2D::new(outline)
                    .with_colors((0..=tour).map(|k| with_alpha(TARGET_COLOUR, if k < tour { 255 } else { 110 })))
                    .with_radii((0..=tour).map(|k| if k < tour { 0.022 } else { 0.01 }))
                    .with_draw_order(5.0),
            )?;
        }
        self.stream.log(
            "world/formation/assignment",
            &rerun::LineStrips2D::new(
                (0..positions.len())
                    .filter(|&r| target.holds_slot(r))
                    .map(|r| vec![positions[r], target.place(r)]),
            )
            .with_colors([with_alpha(ASSIGNMENT_COLOUR, 150)])
            .with_radii([0.012])
            .with_draw_order(4.0),
        )?;
        self.target = Some(target);
        if let Some((old, changed)) = &self.old {
            let age = self.ticks - changed;
            if age >= self.fade_ticks {
                self.old = None;
                self.stream.log("world/formation/old", &rerun::Clear::flat())?;
            } else {
                let alpha = (220.0 * (1.0 - age as f32 / self.fade_ticks as f32)) as u8;
                self.stream.log(
                    "world/formation/old",
                    &rerun::LineStrips2D::new(old.outline())
                        .with_colors([with_alpha(OLD_COLOUR, alpha)])
                        .with_radii([0.015])
                        .with_draw_order(3.0),
                )?;
            }
        }
        Ok(())
    }

    /// The episode's obstacles at its first tick (`obstacles`); an episode whose first tick the
    /// view missed (the tap was full) shows none rather than the previous episode's.
    fn log_obstacles(&mut self, episode: u32, obstacles: Option<&[Obstacle]>) -> Result<()> {
        if obstacles.is_none() && self.obstacles_of == Some(episode) {
            return Ok(());
        }
        self.obstacles_of = Some(episode);
        match obstacles {
            Some(list) if !list.is_empty() => self.stream.log(
                "world/obstacles",
                &rerun::LineStrips2D::new(list.iter().map(outline))
                    .with_colors([OBSTACLE_COLOUR])
                    .with_radii([0.03])
                    .with_draw_order(2.0),
            )?,
            _ => self.stream.log("world/obstacles", &rerun::Clear::flat())?,
        }
        Ok(())
    }

    /// Each robot's range-sensor hits, in its colour (none for a robot whose observation was
    /// lost: it was told nothing), above the edges and trails and below the robots.
    fn log_scans(&self, state: &StateMsg, colours: &[[u8; 3]]) -> Result<()> {
        let Some(at) = self.scan else {
            return Ok(());
        };
        let (mut points, mut point_colours) = (Vec::new(), Vec::new());
        for (i, colour) in colours.iter().enumerate() {
            if state.observation_lost & (1 << i) != 0 {
                continue;
            }
            let rays = &state.observations[i][at..at + SCAN_RAYS];
            for hit in scan_hits(state.poses[i], rays, self.scan_range) {
                points.push(hit);
                point_colours.push(*colour);
            }
        }
        self.stream.log(
            "world/scans",
            &rerun::Points2D::new(points)
                .with_colors(point_colours)
                .with_radii([0.035])
                .with_draw_order(25.0),
        )?;
        Ok(())
    }

    /// The robots (labelled while the picture stays readable) and their headings.
    fn log_robots(&self, state: &StateMsg, positions: &[[f32; 2]], colours: &[[u8; 3]]) -> Result<()> {
        let n = positions.len();
        let robots = rerun::Points2D::new(positions.iter().copied())
            .with_radii([0.12])
            .with_colors(colours.iter().copied());
        // Labels drown a large swarm's picture: each robot's slot in words up to 6 robots, in
        // numbers up to 24 (a robot out of the formation holds none).
        let slot = |i: usize| (state.slot[i] < state.n_agents).then_some(state.slot[i]);
        let robots = match n {
            0..=6 => robots.with_labels((0..n).map(|i| match slot(i) {
                Some(s) => format!("robot {i} → slot {s}"),
                None => format!("robot {i}"),
            })),
            7..=24 => robots.with_labels((0..n).map(|i| match slot(i) {
                Some(s) => format!("{i}→{s}"),
                None => i.to_string(),
            })),
            _ => robots,
        };
        self.stream.log("world/robots", &robots)?;
        self.stream.log(
            "world/headings",
            &rerun::Arrows2D::from_vectors(state.poses[..n].iter().map(|p| [0.35 * p[2].cos(), -0.35 * p[2].sin()]))
                .with_origins(positions.iter().copied())
                .with_colors(colours.iter().copied()),
        )?;
        Ok(())
    }

    /// Each observed edge coloured by its error, and the edge-error curves.
    fn log_edges(&self, state: &StateMsg, positions: &[[f32; 2]]) -> Result<()> {
        let n = positions.len();
        // Each undirected observed edge once, coloured by its error.
        let mut strips = Vec::with_capacity(2 * n);
        let mut edge_colours = Vec::with_capacity(2 * n);
        let (mut error_sum, mut error_max) = (0.0f32, 0.0f32);
        let slot_of: Vec<usize> = state.slot[..n].iter().map(|&s| s as usize).collect();
        let observed = observed_robots(&slot_of);
        for i in 0..n {
            for (k, j) in observed[i].into_iter().enumerate() {
                if n == 3 && j < i {
                    continue; // N = 3 observes every edge from both ends
                }
                let (dx, dy) = (
                    state.poses[i][0] - state.poses[j][0],
                    state.poses[i][1] - state.poses[j][1],
                );
                let error = ((dx * dx + dy * dy).sqrt() - state.desired[i][k]).abs();
                strips.push(vec![positions[i], positions[j]]);
                edge_colours.push(error_colour(error, self.eps_form));
                error_sum += error;
                error_max = error_max.max(error);
                if n <= 8 {
                    self.stream.log(
                        format!("plots/formation/edge_error/e{i}{j}"),
                        &rerun::Scalars::single(f64::from(error)),
                    )?;
                }
            }
        }
        if n > 8 {
            // One series per edge would be a wall of lines: the mean and the worst instead.
            let mean = error_sum / strips.len().max(1) as f32;
            for (name, value) in [("mean", mean), ("max", error_max)] {
                self.stream.log(
                    format!("plots/formation/edge_error/{name}"),
                    &rerun::Scalars::single(f64::from(value)),
                )?;
            }
        }
        self.stream.log(
            "world/edges",
            &rerun::LineStrips2D::new(strips)
                .with_colors(edge_colours)
                .with_radii([0.02]),
        )?;
        Ok(())
    }

    /// The goal, the centroid, the trails and the task curves.
    fn log_goal_and_trails(&mut self, state: &StateMsg, positions: &[[f32; 2]], colours: Vec<[u8; 3]>) -> Result<()> {
        let n = positions.len();
        let centroid = positions.iter().fold([0.0f32; 2], |acc, p| {
            [acc[0] + p[0] / n as f32, acc[1] + p[1] / n as f32]
        });
        let goal = flip(state.goal[0], state.goal[1]);
        self.stream.log(
            "world/goal",
            &rerun::Points2D::new([goal])
                .with_radii([0.15])
                .with_colors([[255, 200, 0]])
                .with_labels(["goal"]),
        )?;
        self.stream.log(
            "world/centroid",
            &rerun::Points2D::new([centroid])
                .with_radii([0.06])
                .with_colors([[20, 20, 20]]),
        )?;
        for (trail, p) in self.trails.iter_mut().zip(positions) {
            if trail.len() == self.trail_ticks {
                trail.pop_front();
            }
            trail.push_back(*p);
        }
        self.stream.log(
            "world/trails",
            &rerun::LineStrips2D::new(self.trails.iter().map(|t| t.iter().copied().collect::<Vec<_>>()))
                .with_colors(colours)
                .with_radii([0.015]),
        )?;
        let distance = ((centroid[0] - goal[0]).powi(2) + (centroid[1] - goal[1]).powi(2)).sqrt();
        self.stream.log(
            "plots/formation/goal_distance",
            &rerun::Scalars::single(f64::from(distance)),
        )?;
        self.stream
            .log("plots/reward", &rerun::Scalars::single(f64::from(state.reward)))?;
        Ok(())
    }
}

/// An obstacle's outline as a closed strip, y flipped: a disc's polygon, or a wall's rectangle
/// (its centre line from `a` to `b`, `thickness` across, flat ends).
fn outline(obstacle: &Obstacle) -> Vec<[f32; 2]> {
    match *obstacle {
        Obstacle::Disc { centre, radius } => (0..=DISC_SIDES)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / DISC_SIDES as f64;
                flip(
                    (centre[0] + radius * a.cos()) as f32,
                    (centre[1] + radius * a.sin()) as f32,
                )
            })
            .collect(),
        Obstacle::Wall { a, b, thickness } => {
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let length = dx.hypot(dy).max(f64::EPSILON);
            // Half the thickness along the centre line's left normal.
            let (nx, ny) = (-dy / length * thickness / 2.0, dx / length * thickness / 2.0);
            [
                [a[0] + nx, a[1] + ny],
                [b[0] + nx, b[1] + ny],
                [b[0] - nx, b[1] - ny],
                [a[0] - nx, a[1] - ny],
                [a[0] + nx, a[1] + ny],
            ]
            .into_iter()
            .map(|p| flip(p[0] as f32, p[1] as f32))
            .collect()
        }
    }
}

/// Where the rays of a robot at `pose` (x, y, heading) met something, y flipped: ray k points
/// 2 pi k / rays counter-clockwise from the heading and reads its range / `range_m`; a ray
/// reading 1 (or more) met nothing.
fn scan_hits(pose: [f32; 3], rays: &[f32], range_m: f32) -> impl Iterator<Item = [f32; 2]> + '_ {
    rays.iter().enumerate().filter(|&(_, &r)| r < 1.0).map(move |(k, &r)| {
        let angle = pose[2] + std::f32::consts::TAU * k as f32 / rays.len() as f32;
        let d = r * range_m;
        flip(pose[0] + d * angle.cos(), pose[1] + d * angle.sin())
    })
}

/// Rerun's 2-D views are y-down: the world's y goes up.
fn flip(x: f32, y: f32) -> [f32; 2] {
    [x, -y]
}

/// `colour` with opacity `alpha`.
fn with_alpha([r, g, b]: [u8; 3], alpha: u8) -> rerun::Color {
    rerun::Color::from_unmultiplied_rgba(r, g, b, alpha)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(p: [f32; 2], q: [f32; 2]) -> bool {
        (p[0] - q[0]).abs() < 1e-5 && (p[1] - q[1]).abs() < 1e-5
    }

    #[test]
    fn a_wall_is_its_rectangle_with_flat_ends() {
        // A diagonal wall from (1, 1) to (3, 3), 0.2 m thick: corners 0.1 m off the centre line
        // along its normal (-1, 1) / sqrt 2, none beyond the ends; y flipped.
        let h = 0.1 / std::f64::consts::SQRT_2;
        let strip = outline(&Obstacle::Wall {
            a: [1.0, 1.0],
            b: [3.0, 3.0],
            thickness: 0.2,
        });
        let expected = [
            [1.0 - h, 1.0 + h],
            [3.0 - h, 3.0 + h],
            [3.0 + h, 3.0 - h],
            [1.0 + h, 1.0 - h],
            [1.0 - h, 1.0 + h],
        ];
        assert_eq!(strip.len(), expected.len());
        for (p, q) in strip.iter().zip(expected) {
            assert!(close(*p, flip(q[0] as f32, q[1] as f32)), "{p:?} vs {q:?}");
        }
    }

    #[test]
    fn a_disc_is_a_closed_polygon_on_its_circle() {
        let strip = outline(&Obstacle::Disc {
            centre: [2.0, 1.0],
            radius: 0.5,
        });
        assert_eq!(strip.len(), DISC_SIDES + 1);
        assert!(close(strip[0], strip[DISC_SIDES]));
        assert!(close(strip[0], [2.5, -1.0]));
        for p in strip {
            assert!(((p[0] - 2.0).hypot(p[1] + 1.0) - 0.5).abs() < 1e-5, "{p:?}");
        }
    }

    #[test]
    fn scan_hits_lie_along_their_rays_from_the_heading() {
        // Heading +y; 4 rays: ahead (+y) at 0.5 of 2 m, left (-x) at 0.25, behind nothing,
        // right (+x) at 0.
        let hits: Vec<[f32; 2]> =
            scan_hits([1.0, 1.0, std::f32::consts::FRAC_PI_2], &[0.5, 0.25, 1.0, 0.0], 2.0).collect();
        assert_eq!(hits.len(), 3);
        assert!(close(hits[0], [1.0, -2.0]), "{hits:?}");
        assert!(close(hits[1], [0.5, -1.0]), "{hits:?}");
        assert!(close(hits[2], [1.0, -1.0]), "{hits:?}");
    }
}
