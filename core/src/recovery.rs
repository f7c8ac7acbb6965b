//! Each robot's recovery behaviour among obstacles (`[obstacles] recovery_ticks`), a layer at
//! its motors beside the collision monitor, as a mobile base's navigation stack has one (Nav2's
//! progress checker and its recovery behaviours): a robot that has stopped getting closer to
//! its slot beside an obstacle follows that obstacle's boundary for a while, whatever drives it.
//!
//! It reads only what the robot is told (its slot and its scan) and keeps one robot's memory:
//! how far from its slot the robot was over the last [`PROGRESS_WINDOW_TICKS`], and whether it
//! is recovering, on which side. A controller that reads one tick cannot hold such a choice;
//! docs/RESULTS.md ("Why the obstacle policy fails") measures what that costs.

use std::collections::VecDeque;
use std::f64::consts::{FRAC_PI_2, TAU};

use crate::config::EnvConfig;
use crate::observation::{Layout, ObservationView};
use crate::physics::wrap_angle;
use crate::reality::Command;

/// Ticks over which a robot must come [`MIN_PROGRESS_M`] closer to its slot.
pub const PROGRESS_WINDOW_TICKS: usize = 30;
/// Metres a robot must come closer to its slot over the window not to be stalled.
pub const MIN_PROGRESS_M: f64 = 0.05;
/// A robot that drove further than this over the window, metres (by its own odometry), is
/// not stalled: it is searching along a surface, not held by it.
pub const MAX_DRIVEN_M: f64 = 0.3;
/// A robot within this distance of its slot, metres, is never stalled (it is arriving).
pub const ARRIVING_M: f64 = 1.0;
/// A stalled robot is one whose nearest scan hit lies within this distance, metres.
pub const STALLED_BY_M: f64 = 0.5;
/// A robot that a robot it is told of is nearer than this, metres, is never stalled: it is
/// queueing (at a gap) or passing a robot, which recovery would only disturb.
pub const QUEUEING_M: f64 = 0.6;
/// The forward speed of a recovering robot, m/s, once it faces along the boundary.
pub const RECOVERY_SPEED: f64 = 0.25;
/// Heading error, radians, above which a recovering robot turns in place.
const TURN_IN_PLACE_RAD: f64 = 0.6;
/// The distance, metres, a recovering robot keeps from the surface it follows.
const FOLLOW_DISTANCE_M: f64 = 0.35;
/// A recovery ends early, after at least this many ticks, once the ray towards the slot reads
/// [`CLEAR_WAY_M`] clear.
const MIN_RECOVERY_TICKS: u32 = 5;
/// See [`MIN_RECOVERY_TICKS`].
const CLEAR_WAY_M: f64 = 1.0;

/// What one robot's recovery reads in a tick.
#[derive(Debug, Clone, Copy)]
pub struct Sensed<'a> {
    /// Its told slot, in its own frame, metres.
    pub slot: [f64; 2],
    /// Its told rays, each range / `scan_range` in [0, 1], ray k at 2 pi k / rays.
    pub scan: &'a [f32],
    /// The sensor's range, metres.
    pub scan_range: f64,
    /// The distance to the nearest robot it is told of, metres (infinite for none).
    pub nearest_robot: f64,
    /// How far it drove in the last tick (its odometry), metres.
    pub driven: f64,
}

impl<'a> Sensed<'a> {
    /// What a robot reads from its told observation `told` (of `layout`) when it drove `driven`
    /// metres in the last tick; `None` if its observation holds no slot or no scan.
    pub fn told(layout: Layout, told: &'a [f32], env: &EnvConfig, driven: f64) -> Option<Self> {
        let view = ObservationView::new(layout, told);
        Some(Self {
            slot: view.slot()?,
            scan: view.scan()?,
            scan_range: env.scan_range_m,
            nearest_robot: view
                .robots(env.proximity_range_m)
                .map(|[x, y]| x.hypot(y))
                .fold(f64::INFINITY, f64::min),
            driven,
        })
    }
}

/// One robot's progress checker (Nav2's, in spirit): over the last
/// [`PROGRESS_WINDOW_TICKS`], has it come closer to its slot, or is it held by a surface?
#[derive(Debug, Clone)]
pub struct ProgressChecker {
    /// Its distance to its slot and how far it drove, each of the window's ticks.
    distances: VecDeque<(f64, f64)>,
}

impl Default for ProgressChecker {
    /// An empty window, its room taken at once so a tick allocates nothing.
    fn default() -> Self {
        Self {
            distances: VecDeque::with_capacity(PROGRESS_WINDOW_TICKS + 1),
        }
    }
}

impl ProgressChecker {
    /// Forgets the window (a new episode).
    pub fn clear(&mut self) {
        self.distances.clear();
    }

    /// Records this tick and says whether the robot is stalled: over a full window it came
    /// less than [`MIN_PROGRESS_M`] closer to its slot and drove less than [`MAX_DRIVEN_M`],
    /// it is more than [`ARRIVING_M`] from its slot, a surface lies within [`STALLED_BY_M`],
    /// and no robot it is told of is nearer than [`QUEUEING_M`]. A stall starts a new window.
    pub fn stalled(&mut self, sensed: &Sensed) -> bool {
        let nearest_m = f64::from(sensed.scan.iter().copied().fold(f32::INFINITY, f32::min)) * sensed.scan_range;
        let distance = sensed.slot[0].hypot(sensed.slot[1]);
        self.distances.push_back((distance, sensed.driven));
        if self.distances.len() > PROGRESS_WINDOW_TICKS {
            self.distances.pop_front();
        }
        let stalled = self.distances.len() == PROGRESS_WINDOW_TICKS
            && self.distances[0].0 - distance < MIN_PROGRESS_M
            && self.distances.iter().map(|&(_, driven)| driven).sum::<f64>() < MAX_DRIVEN_M
            && distance > ARRIVING_M
            && nearest_m < STALLED_BY_M
            && sensed.nearest_robot > QUEUEING_M;
        if stalled {
            self.distances.clear();
        }
        stalled
    }
}

/// One robot's recovery memory.
#[derive(Debug, Clone, Default)]
pub struct Recovery {
    /// Whether it is stalled.
    progress: ProgressChecker,
    /// Ticks left in the recovery under way (0: none).
    left: u32,
    /// Ticks since it began.
    done: u32,
    /// +1 keeps the surface on the robot's right (it goes round anticlockwise), -1 on its left.
    side: f64,
    /// Recoveries so far: they alternate sides, left first.
    count: u32,
    /// Whether the last command was the recovery's (not the controller's).
    took_over: bool,
}

impl Recovery {
    /// Whether the last [`Recovery::command`] was the recovery's own, not the controller's.
    pub fn took_over(&self) -> bool {
        self.took_over
    }

    /// The boundary-following command for a robot that reads `scan` (each ray range /
    /// `scan_range`): along the surface its nearest ray hits, on this recovery's side, at
    /// [`FOLLOW_DISTANCE_M`] from it; turning in place first when it faces away.
    fn follow(&self, scan: &[f32], scan_range: f64) -> Command {
        let rays = scan.len();
        let (nearest, nearest_range) =
            scan.iter().enumerate().fold(
                (0, f32::INFINITY),
                |best, (k, &r)| if r < best.1 { (k, r) } else { best },
            );
        let nearest_m = f64::from(nearest_range) * scan_range;
        let away = (FOLLOW_DISTANCE_M - nearest_m).clamp(-0.3, 0.3);
        let heading = wrap_angle(TAU * nearest as f64 / rays as f64 + self.side * (FRAC_PI_2 + away));
        let turn = (2.0 * heading).clamp(-1.0, 1.0);
        let speed = if heading.abs() < TURN_IN_PLACE_RAD {
            RECOVERY_SPEED
        } else {
            0.0
        };
        (speed, turn)
    }

    /// The command the robot's motors take this tick: `command` (its controller's), or while it
    /// recovers, a boundary-following one; `ticks` is the longest recovery.
    pub fn command(&mut self, sensed: &Sensed, ticks: u32, command: Command) -> Command {
        self.took_over = false;
        let &Sensed {
            slot, scan, scan_range, ..
        } = sensed;
        let rays = scan.len();
        let ray_angle = |k: usize| TAU * k as f64 / rays as f64;
        let bearing = slot[1].atan2(slot[0]);
        if self.left > 0 {
            let slot_ray = (bearing.rem_euclid(TAU) / ray_angle(1)).round() as usize % rays;
            let way_clear = f64::from(scan[slot_ray]) * scan_range >= CLEAR_WAY_M;
            if self.done >= MIN_RECOVERY_TICKS && way_clear {
                self.left = 0;
            } else {
                self.left -= 1;
                self.done += 1;
                self.took_over = true;
                return self.follow(scan, scan_range);
            }
        }
        if self.progress.stalled(sensed) {
            self.count += 1;
            self.side = if self.count % 2 == 1 { 1.0 } else { -1.0 };
            self.left = ticks;
            self.done = 0;
        }
        command
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Why a robot is left alone, its slots tick by tick, its scan, the nearest robot, and how
    /// far it drives a tick.
    type Case = (&'static str, Vec<[f64; 2]>, Vec<f32>, f64, f64);

    fn sensed(slot: [f64; 2], scan: &[f32], nearest_robot: f64, driven: f64) -> Sensed<'_> {
        Sensed {
            slot,
            scan,
            scan_range: 2.0,
            nearest_robot,
            driven,
        }
    }

    /// 16 rays of a 2 m sensor reading clear but for a surface `at_m` away on ray `k`, a little
    /// further on its two neighbours.
    fn scan_with_hit(k: usize, at_m: f64) -> Vec<f32> {
        let mut scan = vec![1.0f32; 16];
        scan[(k + 15) % 16] = ((at_m + 0.05) / 2.0) as f32;
        scan[(k + 1) % 16] = ((at_m + 0.05) / 2.0) as f32;
        scan[k] = (at_m / 2.0) as f32;
        scan
    }

    #[test]
    fn a_robot_held_by_a_disc_away_from_its_slot_follows_the_disc_then_hands_back() {
        let mut recovery = Recovery::default();
        let held = (0.0, 0.0);
        // A disc ahead on the left (ray 2), the slot 5 m ahead and to the right, no progress.
        let scan = scan_with_hit(2, 0.2);
        let slot = [4.0, -3.0];
        for _ in 0..PROGRESS_WINDOW_TICKS - 1 {
            assert_eq!(
                recovery.command(&sensed(slot, &scan, f64::INFINITY, 0.0), 30, held),
                held,
                "not stalled yet"
            );
        }
        let (speed, turn) = recovery.command(&sensed(slot, &scan, f64::INFINITY, 0.0), 30, held);
        assert_eq!(
            (speed, turn),
            held,
            "the tick it is found stalled, its controller still acts"
        );
        assert!(!recovery.took_over());
        // Now it recovers: the disc on its right (side +1) means heading about 90 degrees left
        // of the disc's ray (45 degrees): 135 degrees, so it turns left in place first.
        let (speed, turn) = recovery.command(&sensed(slot, &scan, f64::INFINITY, 0.0), 30, held);
        assert_eq!(speed, 0.0);
        assert!(turn > 0.9, "turns left hard: {turn}");
        assert!(recovery.took_over());
        // Facing along the boundary (disc on its right, ray 12 = -90 degrees) it drives.
        let (speed, turn) = recovery.command(&sensed(slot, &scan_with_hit(12, 0.35), f64::INFINITY, 0.0), 30, held);
        assert_eq!(speed, RECOVERY_SPEED);
        assert!(turn.abs() < 0.1, "{turn}");
        // The way to the slot reads clear after the least recovery: the controller is back.
        let clear = scan_with_hit(8, 0.35);
        for _ in 0..MIN_RECOVERY_TICKS {
            recovery.command(&sensed(slot, &clear, f64::INFINITY, 0.0), 30, held);
        }
        let driving = (0.3, 0.1);
        assert_eq!(
            recovery.command(&sensed(slot, &clear, f64::INFINITY, 0.0), 30, driving),
            driving
        );
    }

    #[test]
    fn a_robot_that_makes_progress_arrives_stands_in_the_open_queues_or_searches_is_left_alone() {
        let commanded = (0.2, -0.4);
        let near_disc = scan_with_hit(0, 0.2);
        let held = vec![[5.0, 0.0]; 60];
        // (why, slots, scan, nearest robot, driven a tick)
        let cases: [Case; 5] = [
            (
                "coming closer",
                (0..60).map(|t| [5.0 - 0.01 * t as f64, 0.0]).collect(),
                near_disc.clone(),
                f64::INFINITY,
                0.0,
            ),
            ("arriving", vec![[0.8, 0.0]; 60], near_disc.clone(), f64::INFINITY, 0.0),
            ("in the open", held.clone(), vec![1.0; 16], f64::INFINITY, 0.0),
            ("queueing behind a robot", held.clone(), near_disc.clone(), 0.4, 0.0),
            (
                "searching along the surface",
                held.clone(),
                near_disc.clone(),
                f64::INFINITY,
                0.02,
            ),
        ];
        for (why, slots, scan, nearest_robot, driven) in cases {
            let mut recovery = Recovery::default();
            for slot in slots {
                assert_eq!(
                    recovery.command(&sensed(slot, &scan, nearest_robot, driven), 30, commanded),
                    commanded,
                    "{why}"
                );
            }
        }
        // The same robot held alone by the disc does recover.
        let mut recovery = Recovery::default();
        let recovered = held
            .iter()
            .map(|&slot| recovery.command(&sensed(slot, &near_disc, f64::INFINITY, 0.0), 30, commanded))
            .any(|command| command != commanded);
        assert!(recovered);
    }

    #[test]
    fn a_recovery_lasts_at_most_its_ticks_and_the_next_goes_round_the_other_side() {
        let mut recovery = Recovery::default();
        let scan = scan_with_hit(0, 0.2);
        let slot = [5.0, 0.0];
        let commands: Vec<Command> = (0..PROGRESS_WINDOW_TICKS + 10)
            .map(|_| recovery.command(&sensed(slot, &scan, f64::INFINITY, 0.0), 10, (0.0, 0.0)))
            .collect();
        // Stalled at tick 29; ticks 30-39 recover (turning left in place: the disc is ahead).
        assert!(commands[..PROGRESS_WINDOW_TICKS].iter().all(|&c| c == (0.0, 0.0)));
        assert!(commands[PROGRESS_WINDOW_TICKS..].iter().all(|&(_, w)| w > 0.9));
        // Stalled again after another window: this time it turns right.
        let next: Vec<Command> = (0..PROGRESS_WINDOW_TICKS + 1)
            .map(|_| recovery.command(&sensed(slot, &scan, f64::INFINITY, 0.0), 10, (0.0, 0.0)))
            .collect();
        assert!(
            next[PROGRESS_WINDOW_TICKS].1 < -0.9,
            "{:?}",
            next[PROGRESS_WINDOW_TICKS]
        );
    }
}
