//! Robustness to a neighbour's sudden turn: plays held-out episodes of a checkpoint noise-free,
//! in-process and exactly as model selection does, once as they are and once with robot ROBOT
//! driving at full speed on a full-rate turn for TICKS ticks from step AT (whatever its actor
//! says), and prints success, formation held and steps for both:
//! `cargo run --release -p formation-critic --example sudden_turn -- CHECKPOINT [N] [ROBOT] [AT] [TICKS] [EPISODES] [SEED]`
//! (defaults: 3 robots, robot 0, step 15, 5 ticks, 100 episodes, seed 1000). The checkpoint's
//! window (H) and observation model set the environment; everything else is the default.

use std::path::PathBuf;

use anyhow::{Context, Result, ensure};
use formation_core::config::EnvConfig;
use formation_core::reality::RealityConfig;
use formation_critic::selection::{Played, SuddenTurn, play};
use formation_model::actor::FrozenActor;
use formation_model::checkpoint;

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let path = PathBuf::from(
        args.next()
            .context("usage: sudden_turn CHECKPOINT [N] [ROBOT] [AT] [TICKS] [EPISODES] [SEED]")?,
    );
    let mut next = |default: u64| -> Result<u64> { args.next().map_or(Ok(default), |a| Ok(a.parse()?)) };
    let n = usize::try_from(next(3)?)?;
    let turn = SuddenTurn {
        robot: usize::try_from(next(0)?)?,
        at_step: u32::try_from(next(15)?)?,
        ticks: u32::try_from(next(5)?)?,
    };
    let episodes = usize::try_from(next(100)?)?;
    let seed = next(1000)?;
    let model = checkpoint::load(&path)?;
    ensure!(
        model.meta.n_actors == 1 || model.meta.n_actors == n,
        "{} has {} independent actors; it drives only {} robots",
        path.display(),
        model.meta.n_actors,
        model.meta.n_actors
    );
    let env = EnvConfig {
        history: model.meta.actor.history,
        observation: model.meta.observation,
        ..EnvConfig::default()
    };
    let shape = &model.meta.actor;
    println!(
        "{} (H = {}), N = {n}, {episodes} episodes of seed {seed}; robot {} turns for {} ticks from step {}",
        path.display(),
        shape.history,
        turn.robot,
        turn.ticks,
        turn.at_step
    );
    for (label, disturbance) in [("undisturbed", None), ("sudden turn", Some(turn))] {
        let mut actors = (0..model.meta.n_actors)
            .map(|k| FrozenActor::from_flat(&model.actor_weights(k)?, shape))
            .collect::<Result<Vec<_>>>()?;
        let played = Played {
            seed,
            count: episodes,
            reality: &RealityConfig::default(),
        };
        let score = play(&env, n, &played, &mut actors, shape, disturbance)?;
        println!(
            "{label:>12}: success {:.2}, formation held {:.2}, mean steps {:.1}",
            score.success, score.formation_held, score.mean_steps
        );
    }
    Ok(())
}
