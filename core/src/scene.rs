//! One tick of a swarm, the one type every consumer of a tick reads: the physics step writes
//! it ([`crate::world::World::scene`]), and the reward ([`crate::task::score`]), the
//! observation models ([`crate::observation::Observer`]), the critic's features
//! ([`crate::features::CriticFeatures`]), the critic's collector, the recorder and the replay
//! (with HER's recomputations) read it.
//!
//! A scene carries the commands applied in the transition into its tick, so a reward term or
//! an observation that depends on the robots' actions reads them here, and HER recomputes it
//! with the same code.
//!
//! A scene borrows its storage, in `f64` everywhere: the sim's `World` owns the live episode;
//! the replay's episodes hold the `f32` values the state stream carried, widened exactly
//! (`f64` costs the replay 20 more bytes per robot and tick than `f32` poses and normalised
//! actions, next to the 64 bytes of each robot's observation), so HER runs the sim's own
//! functions on them without a conversion or an allocation.

use formation_protocol::{NEIGHBOURS, neighbours};

use crate::geodesic::Ways;
use crate::obstacles::Obstacles;
use crate::physics::Pose;
use crate::task::present_centroid;

/// The true state of one tick and the commands that led to it.
#[derive(Debug, Clone, Copy)]
pub struct Scene<'a> {
    /// Every robot's pose, world frame.
    pub poses: &'a [Pose],
    /// Every robot's command (v, w) applied in the transition into this tick, clamped to the
    /// limits (held for a robot that missed the tick); zero at an episode's first tick.
    pub commands: &'a [(f64, f64)],
    /// Desired length of each robot's two observed edges.
    pub desired: &'a [[f64; NEIGHBOURS]],
    /// The robots each robot observes: those in the next two slots of the formation
    /// ([`index_neighbours`] while robot i holds slot i, as every episode starts); a robot out
    /// of the formation observes only itself ([`crate::task::is_present`]).
    pub observed: &'a [[usize; NEIGHBOURS]],
    /// Goal of the centroid, world frame.
    pub goal: [f64; 2],
    /// Each robot's offset from the goal in the goal formation, world frame.
    pub slots: &'a [[f64; 2]],
    /// The episode's obstacles (none in the open arena).
    pub obstacles: &'a Obstacles,
    /// Side of the square arena the robots are kept in, metres (what a range sensor sees as
    /// walls).
    pub arena_m: f64,
    /// Each robot's way round the obstacles to its slot, for `env.geodesic_progress` (the
    /// sim's; `None` where the progress is measured straight).
    pub ways: Option<&'a Ways>,
}

/// The robots each of `n` robots observes when robot i holds slot i: (i+1) and (i+2) mod N.
pub fn index_neighbours(n: usize) -> Vec<[usize; NEIGHBOURS]> {
    (0..n).map(|i| neighbours(i, n)).collect()
}

impl Scene<'_> {
    /// Centroid of the positions of the robots in the formation (of every robot while all
    /// are, as without departures).
    pub fn centroid(&self) -> [f64; 2] {
        present_centroid(self.poses, self.observed)
    }
}
