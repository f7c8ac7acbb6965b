//! `formation-play`: plays the episodes a lockstep evaluation with the same seed and config
//! plays, in-process (no swarm, no IPC), with one team: the scripted baseline, the privileged
//! planner, each robot's own planner or a checkpoint's actor, and writes each swarm size's `episodes.csv` rows and one
//! summary line. What the grids in docs/RESULTS.md are measured with.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Parser, ValueEnum};
use formation_core::config::{RunConfig, validate_agent_count};
use formation_core::obstacles::{Obstacle, ObstacleKind};
use formation_core::reality::RealityConfig;
use formation_core::stepper::EpisodeRecord;
use formation_core::task::Outcome;
use formation_core::world::World;
use formation_critic::selection::{PlannerKind, Played, Team, episode_records_watched};
use formation_model::actor::FrozenActor;
use formation_model::checkpoint;

/// Who drives every robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum TeamKind {
    /// The scripted baseline with the config's [baseline] gains (a potential field among
    /// obstacles when the robots observe their range sensor).
    Scripted,
    /// The privileged planner that knows the map (`--oracle all` of the launcher).
    Oracle,
    /// Each robot's own planner over the map, no team plan (the decentralised teacher of
    /// `formation-distill --teacher solo`).
    Solo,
    /// Each robot's own planner over only the obstacles within its range sensor's reach.
    SoloLocal,
    /// The actor of --checkpoint (default: the shipped model of the world, as the launcher's eval:
    /// models/formation-obstacles-passage.safetensors in the passage,
    /// models/formation-obstacles.safetensors among other obstacles), with its own observation
    /// model and window.
    Model,
}

impl TeamKind {
    /// The planner that drives every robot, for the planners.
    fn planner(self) -> Option<PlannerKind> {
        match self {
            Self::Oracle => Some(PlannerKind::Team),
            Self::Solo => Some(PlannerKind::Solo),
            Self::SoloLocal => Some(PlannerKind::SoloLocal),
            Self::Scripted | Self::Model => None,
        }
    }
}

/// Plays the episodes `scripts/run_swarm.sh N --mode eval --seed S --episodes E` plays (same
/// config, reality and obstacles), in-process, with one team, and writes OUT/n<N>.csv (the
/// lockstep eval's `episodes.csv` rows, but for wall time and the transport's counts) and one
/// JSON line per size on stdout. Among obstacles the scripted baseline and the planner observe
/// slot_proximity_scan unless the config names another model, as the launcher does.
#[derive(Debug, Parser)]
#[command(version, about, long_about)]
struct Cli {
    /// Run config (the defaults without it).
    #[arg(long)]
    config: Option<PathBuf>,
    /// A file holding only a [reality] section (as the presets configs/reality-*.toml) that
    /// replaces the config's.
    #[arg(long)]
    reality: Option<PathBuf>,
    /// Obstacles (overrides the config's [obstacles] kind).
    #[arg(long, value_enum)]
    obstacles: Option<ObstacleKind>,
    /// Who drives the robots.
    #[arg(long, value_enum)]
    team: TeamKind,
    /// The actor of `--team model` (a file or run directory; default: the shipped model).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Swarm sizes.
    #[arg(long, value_delimiter = ',', default_value = "8")]
    n: Vec<usize>,
    /// Episodes per size.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// The eval's --seed.
    #[arg(long, default_value_t = 1000)]
    seed: u64,
    /// Where the per-size CSV files go (created; nothing written without it).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write these episodes' trajectories, goal, slots and obstacles (episodes from 0) as
    /// OUT/trace-n<N>-e<K>.json, one file each (for pictures and scripts/failure_census.py).
    #[arg(long, value_name = "K[,K...]", value_delimiter = ',', requires = "out")]
    trace_episode: Vec<usize>,
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-play: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let mut config = match &cli.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(path) = &cli.reality {
        let text = std::fs::read_to_string(path).with_context(|| format!("--reality {}", path.display()))?;
        config.reality =
            RealityConfig::from_toml_str(&text).with_context(|| format!("--reality {}", path.display()))?;
    }
    if let Some(kind) = cli.obstacles {
        config.env.obstacles.kind = kind;
    }
    for &n in &cli.n {
        validate_agent_count(n)?;
    }
    if let Some(episode) = cli.trace_episode.iter().find(|&&k| k >= cli.episodes) {
        bail!(
            "--trace-episode {episode}: there are only {} episodes (from 0)",
            cli.episodes
        );
    }
    if let Some(out) = &cli.out {
        std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    }
    let mut env = config.env.clone();
    let loaded = match cli.team {
        TeamKind::Model => {
            let path = match &cli.checkpoint {
                Some(path) => checkpoint::resolve(path)?,
                None => PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../models")).join(env.shipped_model_file()),
            };
            let loaded = checkpoint::load(&path)?;
            env.observation = loaded.meta.observation;
            env.history = loaded.meta.actor.history;
            Some(loaded)
        }
        _ => {
            env.scan_among_obstacles();
            if cli.checkpoint.is_some() {
                bail!("--checkpoint is for --team model");
            }
            None
        }
    };
    for &n in &cli.n {
        let played = Played {
            seed: cli.seed,
            count: cli.episodes,
            reality: &config.reality,
        };
        let mut traces: BTreeMap<usize, Trace> = cli.trace_episode.iter().map(|&k| (k, Trace::default())).collect();
        let watch = |episode: usize, world: &World| {
            if let Some(trace) = traces.get_mut(&episode) {
                trace.record(world);
            }
        };
        let records = match &loaded {
            None => {
                let team = match cli.team.planner() {
                    Some(kind) => Team::Planner(kind, &config.baseline),
                    None => Team::Scripted(&config.baseline),
                };
                episode_records_watched(&env, n, &played, team, watch)?
            }
            Some(loaded) => {
                let shape = loaded.meta.actor.clone();
                let mut actors = (0..loaded.meta.n_actors)
                    .map(|index| FrozenActor::from_flat(&loaded.actor_weights(index)?, &shape))
                    .collect::<Result<Vec<_>>>()?;
                episode_records_watched(&env, n, &played, Team::Actors(&mut actors, &shape), watch)?
            }
        };
        if let Some(out) = &cli.out {
            for (episode, trace) in &traces {
                let path = out.join(format!("trace-n{n}-e{episode}.json"));
                std::fs::write(&path, serde_json::to_string(trace)?)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
            let path = out.join(format!("n{n}.csv"));
            let mut writer =
                csv::Writer::from_path(&path).with_context(|| format!("cannot create {}", path.display()))?;
            for record in &records {
                writer.serialize(record)?;
            }
            writer.flush()?;
        }
        println!("{}", summary_line(n, &records));
    }
    Ok(())
}

/// One episode's course: every robot's pose at every tick, the goal, the slots in force at its
/// end and the obstacles.
#[derive(Default, serde::Serialize)]
struct Trace {
    poses: Vec<Vec<[f64; 3]>>,
    goal: [f64; 2],
    slots: Vec<[f64; 2]>,
    obstacles: Vec<Obstacle>,
    arena_m: f64,
}

impl Trace {
    fn record(&mut self, world: &World) {
        self.poses
            .push(world.poses.iter().map(|p| [p.x, p.y, p.theta]).collect());
        self.goal = world.goal;
        self.slots.clone_from(&world.slots);
        self.obstacles = world.obstacles.list().to_vec();
        self.arena_m = world.arena_m;
    }
}

/// One size's figures as a JSON object.
fn summary_line(n: usize, records: &[EpisodeRecord]) -> serde_json::Value {
    let count = records.len().max(1) as f64;
    let rate = |outcome: Outcome| records.iter().filter(|r| r.outcome == outcome).count() as f64 / count;
    let obstacle = records.iter().map(|r| f64::from(r.obstacle_collisions)).sum::<f64>() / count;
    let successes: Vec<&EpisodeRecord> = records.iter().filter(|r| r.outcome == Outcome::Success).collect();
    let mean = |values: Vec<f64>| (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64);
    serde_json::json!({
        "n": n,
        "episodes": records.len(),
        "success": rate(Outcome::Success),
        "robot_collisions": rate(Outcome::Collision) - obstacle,
        "obstacle_collisions": obstacle,
        "timeouts": rate(Outcome::Timeout),
        "steps_to_goal": mean(successes.iter().map(|r| f64::from(r.steps)).collect()),
        "final_edge_error_m": mean(records.iter().map(|r| r.final_edge_error_m).collect()),
    })
}
