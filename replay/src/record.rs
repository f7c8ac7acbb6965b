//! Plays an episode in-process (no IPC) and records it as the critic's collector would
//! assemble it from the streams: for tests, benchmarks and offline experiments.

use formation_core::mission::{Mission, NO_SLOT};
use formation_core::physics::Pose;
use formation_core::task::Outcome;
use formation_core::world::World;
use formation_protocol::ACTION_DIM;

use crate::buffer::{Episode, Formation, Tick};

/// A value as the state stream carries it (`f32`), widened back.
fn wire(value: f64) -> f64 {
    f64::from(value as f32)
}

/// The world's poses as the state stream carries them (f32).
pub fn wire_poses(world: &World) -> Vec<Pose> {
    world
        .poses
        .iter()
        .map(|p| Pose::from([p.x as f32, p.y as f32, p.theta as f32]))
        .collect()
}

/// The world's current scene as the collector reads it from the state stream.
fn snapshot(world: &World, reward: f64) -> Tick {
    let n = world.n_agents();
    Tick {
        poses: wire_poses(world),
        commands: world.commands.iter().map(|&(v, w)| (wire(v), wire(w))).collect(),
        observations: (0..n).map(|agent| world.observation(agent)).collect(),
        reward: reward as f32,
    }
}

/// The world's formation as the state stream carries it, in force from `from_tick`.
pub fn formation(world: &World, from_tick: usize) -> Formation {
    Formation {
        from_tick,
        desired: world.desired.iter().map(|d| d.map(wire)).collect(),
        slots: world.slots.iter().map(|s| s.map(wire)).collect(),
        observed: world.observed.clone(),
        present: world.slot_of.iter().map(|&slot| slot != NO_SLOT).collect(),
    }
}

/// Plays `world` for at most `max_steps` steps with the normalised actions `act` picks for
/// every robot, and records the episode as number `number` (one formation: no shape changes).
pub fn record_episode(
    number: u32,
    world: World,
    max_steps: u32,
    act: impl FnMut(&World) -> Vec<[f32; ACTION_DIM]>,
) -> Episode {
    record(number, world, None, max_steps, act)
}

/// [`record_episode`] with the episode's `mission`, as the sim's tick loop plays it: each step
/// judged by the mission (no success before the last change), its changes applied on schedule
/// and recorded as the collector does, a new formation from the tick whose state carries it.
pub fn record_mission_episode(
    number: u32,
    world: World,
    mission: Mission,
    max_steps: u32,
    act: impl FnMut(&World) -> Vec<[f32; ACTION_DIM]>,
) -> Episode {
    record(number, world, Some(mission), max_steps, act)
}

fn record(
    number: u32,
    mut world: World,
    mut mission: Option<Mission>,
    max_steps: u32,
    mut act: impl FnMut(&World) -> Vec<[f32; ACTION_DIM]>,
) -> Episode {
    let mut formations = vec![formation(&world, 0)];
    let mut ticks = vec![snapshot(&world, 0.0)];
    let mut terminal = false;
    for _ in 0..max_steps {
        let commands: Vec<(f64, f64)> = act(&world)
            .into_iter()
            .map(|a| world.env.command_from_action(a))
            .collect();
        let mut result = world.step(&commands);
        if let Some(mission) = &mut mission {
            result = mission.judge(result, world.steps, &world.env);
            let running = result.outcome == Outcome::Running;
            if mission.after_step(&mut world, result.conditions.in_formation, running) {
                formations.push(formation(&world, world.steps as usize));
            }
        }
        ticks.push(snapshot(&world, result.reward));
        if result.outcome.is_terminal() {
            terminal = true;
            break;
        }
    }
    Episode {
        number,
        goal: world.goal.map(wire),
        formations,
        ticks,
        terminal,
        arena_m: world.arena_m,
        time_limit: world.env.max_steps,
        obstacles: world.obstacles,
    }
}
