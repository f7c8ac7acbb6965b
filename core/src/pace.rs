//! How fast any controller could possibly be: a lower bound on the steps an episode needs.
//!
//! Comparing controllers by their steps to the goal needs a floor to read the numbers against:
//! "49.9 steps" is slow or fast only next to what the physics allows. [`steps_floor`] bounds it
//! from below for one episode, under the motors a [`Reality`] drew; `formation-pace-floor`
//! prints it for a run's episodes.

use crate::config::EnvConfig;
use crate::formation::EpisodeInit;
use crate::physics::wrap_angle;
use crate::reality::Reality;
use crate::task::centroid;

/// The fewest steps in which any controller could bring the centroid of `init`'s robots within
/// `env.eps_goal_m` of the goal, under the motors `reality` drew for the episode (its delay line
/// and acceleration limits); `None` if not within the episode's time limit.
///
/// A bound, not a plan. Every robot is credited with the largest speed and turn rate its motors
/// reach from rest ((v_max, w_max) commanded at every tick, through [`Reality::actuate`]), and
/// with a heading error towards the goal that shrinks as fast as that turn rate allows; along
/// the line from the start centroid to the goal it then advances at most v dt cos(the smallest
/// heading error it can have reached by the end of the tick) per tick. The centroid advances
/// the mean of its robots' advances, and success needs it to have covered the goal distance
/// less `eps_goal_m`. Holding the formation, avoiding collisions, noise and lost messages only
/// slow a controller down, so they are left out: every episode any controller succeeds in takes
/// at least this many steps. One thing is not modelled: a robot pushed along the arena's wall
/// (the sim keeps positions inside) could advance up to v dt whatever its heading; episodes
/// start and end well inside the arena.
///
/// `reality` must be fresh for the episode (no tick actuated yet); it is spent by this call.
pub fn steps_floor(env: &EnvConfig, init: &EpisodeInit, reality: &mut Reality) -> Option<u32> {
    let n = init.poses.len();
    let start = centroid(&init.poses);
    let to_goal = [init.goal[0] - start[0], init.goal[1] - start[1]];
    let needed = to_goal[0].hypot(to_goal[1]) - env.eps_goal_m;
    let direction = to_goal[1].atan2(to_goal[0]);
    // Each robot's heading error left to turn away, and the team's summed advance.
    let mut heading_error: Vec<f64> = init
        .poses
        .iter()
        .map(|pose| wrap_angle(pose.theta - direction).abs())
        .collect();
    let mut advanced = 0.0;
    for tick in 0..env.episode_steps(n) {
        for (agent, error) in heading_error.iter_mut().enumerate() {
            let (v, w) = reality.actuate(agent, tick, (env.v_max, env.w_max), true);
            let (v, w) = env.clamp_command(v, w);
            *error = (*error - w.abs() * env.dt_s).max(0.0);
            advanced += v * env.dt_s * error.cos().max(0.0);
        }
        if advanced / n as f64 >= needed {
            return Some(tick + 1);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baseline::{BaselineGains, ScriptedBaseline};
    use crate::config::FormationShape;
    use crate::formation::Episodes;
    use crate::observation::Layout;
    use crate::reality::{RealityConfig, Spread};
    use crate::task::Outcome;
    use crate::world::World;

    fn env() -> EnvConfig {
        EnvConfig {
            shape: FormationShape::Mixed,
            ..EnvConfig::default()
        }
    }

    /// The field preset's harsh motors (no noise or loss: they cannot speed anybody up).
    fn slow_motors() -> RealityConfig {
        RealityConfig {
            actuation_delay_ticks: Spread::range(1.0, 3.0),
            max_linear_accel_mps2: Spread::range(0.5, 1.0),
            max_angular_accel_radps2: Spread::range(1.5, 3.0),
            ..RealityConfig::default()
        }
    }

    #[test]
    fn a_team_facing_the_goal_in_the_ideal_world_needs_the_distance_at_top_speed() {
        let env = env();
        for (episode, mut init) in Episodes::new(5, &env, 7).take(10).enumerate() {
            let start = centroid(&init.poses);
            let to_goal = [init.goal[0] - start[0], init.goal[1] - start[1]];
            for pose in &mut init.poses {
                pose.theta = to_goal[1].atan2(to_goal[0]);
            }
            let mut reality = Reality::new(&RealityConfig::default(), &env, 7, episode as u64, 5);
            let distance = to_goal[0].hypot(to_goal[1]) - env.eps_goal_m;
            let expected = (distance / (env.v_max * env.dt_s) - 1e-9).ceil() as u32;
            assert_eq!(steps_floor(&env, &init, &mut reality), Some(expected));
        }
    }

    #[test]
    fn turning_and_slow_motors_raise_the_floor() {
        let env = env();
        let init = Episodes::new(6, &env, 3).next().expect("episodes never end");
        let ideal = RealityConfig::default();
        let floor = |init: &EpisodeInit, config: &RealityConfig| {
            steps_floor(&env, init, &mut Reality::new(config, &env, 3, 0, 6)).expect("within the time limit")
        };
        let mut facing = init.clone();
        let mut facing_away = init.clone();
        let start = centroid(&init.poses);
        let direction = (init.goal[1] - start[1]).atan2(init.goal[0] - start[0]);
        for (towards, away) in facing.poses.iter_mut().zip(&mut facing_away.poses) {
            towards.theta = direction;
            away.theta = wrap_angle(direction + std::f64::consts::PI);
        }
        // Turning half a circle at 1 rad/s takes 32 ticks before the first full-speed tick.
        assert!(floor(&facing_away, &ideal) >= floor(&facing, &ideal) + 20);
        assert!(floor(&facing, &slow_motors()) >= floor(&facing, &ideal) + 3);
    }

    /// Plays one episode with the baseline on every robot under `config` (told observations,
    /// delays and lag; losses too), returning the outcome and the steps it took.
    fn play_baseline(env: &EnvConfig, init: EpisodeInit, gains: BaselineGains, mut reality: Reality) -> (Outcome, u32) {
        let n = init.poses.len();
        let layout = Layout::of(env.observation);
        let baseline = ScriptedBaseline::new(env, gains);
        let mut world = World::new(env, init);
        let mut in_use = vec![(0.0, 0.0); n];
        loop {
            let mut acting = Vec::with_capacity(n);
            for (agent, command) in in_use.iter_mut().enumerate() {
                let mut obs = world.observation(agent);
                reality.tell(agent, layout, &mut obs);
                if !reality.observation_lost(agent) && !reality.command_lost(agent) {
                    *command = baseline.command(&obs);
                }
                acting.push(reality.actuate(agent, world.steps, *command, true));
            }
            let result = world.step(&acting);
            if result.outcome != Outcome::Running {
                return (result.outcome, world.steps);
            }
        }
    }

    #[test]
    fn no_baseline_episode_beats_its_floor_and_the_floor_is_not_far_below() {
        let env = env();
        let fast = BaselineGains {
            k_form: 0.15,
            k_goal: 1.12,
            k_turn: 1.36,
            repulsion_range: 0.3,
            k_repulsion: 2.48,
            ..BaselineGains::default()
        };
        for (config, gains) in [
            (RealityConfig::default(), BaselineGains::default()),
            (slow_motors(), fast),
        ] {
            let (mut floors, mut steps) = (0u32, 0u32);
            for (episode, init) in Episodes::new(6, &env, 11).take(30).enumerate() {
                let floor = steps_floor(&env, &init, &mut Reality::new(&config, &env, 11, episode as u64, 6))
                    .expect("within the time limit");
                let reality = Reality::new(&config, &env, 11, episode as u64, 6);
                let (outcome, took) = play_baseline(&env, init, gains, reality);
                if outcome == Outcome::Success {
                    assert!(
                        took >= floor,
                        "episode {episode}: {took} steps under a floor of {floor}"
                    );
                    floors += floor;
                    steps += took;
                }
            }
            assert!(steps > 0, "no episode succeeded");
            // A bound that says nothing (say 1 step) would pass the first check: it must also
            // be within reach of a real controller.
            assert!(
                f64::from(floors) >= 0.6 * f64::from(steps),
                "floors {floors} against {steps} steps"
            );
        }
    }
}
