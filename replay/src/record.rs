//! Plays an episode in-process (no IPC) and records it as the critic's collector would
//! assemble it from the streams: for tests, benchmarks and offline experiments.

use formation_core::world::World;
use formation_protocol::ACTION_DIM;

use crate::buffer::{Episode, Tick};

fn snapshot(world: &World) -> Tick {
    let n = world.n_agents();
    Tick {
        poses: world
            .poses
            .iter()
            .map(|p| [p.x as f32, p.y as f32, p.theta as f32])
            .collect(),
        observations: (0..n).map(|agent| world.observation(agent)).collect(),
        actions: vec![[0.0; ACTION_DIM]; n],
        reward: 0.0,
    }
}

/// Plays `world` for at most `max_steps` steps with the normalised actions `act` picks for
/// every robot, and records the episode as number `number`.
pub fn record_episode(
    number: u32,
    mut world: World,
    max_steps: u32,
    mut act: impl FnMut(&World) -> Vec<[f32; ACTION_DIM]>,
) -> Episode {
    let mut ticks = vec![snapshot(&world)];
    let mut terminal = false;
    for _ in 0..max_steps {
        let actions = act(&world);
        let commands: Vec<(f64, f64)> = actions.iter().map(|a| world.env.command_from_action(*a)).collect();
        let result = world.step(&commands);
        if let Some(last) = ticks.last_mut() {
            last.actions = actions;
            last.reward = result.reward as f32;
        }
        ticks.push(snapshot(&world));
        if result.outcome.is_terminal() {
            terminal = true;
            break;
        }
    }
    Episode {
        number,
        desired: world.desired.iter().map(|d| d.map(|v| v as f32)).collect(),
        goal: world.goal.map(|v| v as f32),
        slots: world.slots.iter().map(|s| s.map(|v| v as f32)).collect(),
        ticks,
        terminal,
    }
}
