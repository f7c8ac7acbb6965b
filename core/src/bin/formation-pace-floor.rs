//! `formation-pace-floor`: the fewest steps any controller could need on a run's episodes (a
//! lower bound, see `formation_core::pace`), as JSON: one object per swarm size with the mean
//! floor and every episode's.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use formation_core::config::{FormationShape, RunConfig, validate_agent_count};
use formation_core::formation::Episodes;
use formation_core::pace::steps_floor;
use formation_core::reality::{Reality, RealityConfig};

/// Prints, for the episodes a run of `--seed` plays, the fewest steps to the goal that any
/// controller could need (its robots' motors as `[reality]` draws them, every robot at top speed
/// and turning at once, formation and collisions ignored): the floor under steps-to-goal figures.
/// Episodes and motors are those of `formation N --seed S --config C --reality R --shape K`.
#[derive(Parser, Debug)]
#[command(name = "formation-pace-floor", version)]
struct Cli {
    /// Swarm sizes, e.g. 3,12,32.
    #[arg(long, value_name = "N1,N2", value_delimiter = ',', default_value = "3")]
    n: Vec<usize>,
    /// Episodes per size, from the run's first.
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// The run's --seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The run's --config ([env] sets shapes and limits; its [reality] the motors).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// A file whose [reality] replaces the config's, as the launcher's --reality.
    #[arg(long, value_name = "FILE")]
    reality: Option<PathBuf>,
    /// The run's --shape (replaces the config's env.shape).
    #[arg(long, value_enum)]
    shape: Option<FormationShape>,
}

fn run(cli: &Cli) -> anyhow::Result<String> {
    let mut config = match &cli.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(path) = &cli.reality {
        let text =
            std::fs::read_to_string(path).map_err(|err| anyhow::anyhow!("--reality {}: {err}", path.display()))?;
        config.reality = RealityConfig::from_toml_str(&text)
            .map_err(|err| anyhow::anyhow!("--reality {}: {err}", path.display()))?;
    }
    if let Some(shape) = cli.shape {
        config.env.shape = shape;
    }
    anyhow::ensure!(cli.episodes > 0, "--episodes must be at least 1");
    let mut lines = Vec::new();
    for &n in &cli.n {
        validate_agent_count(n)?;
        let floors: Vec<Option<u32>> = Episodes::new(n, &config.env, cli.seed)
            .take(cli.episodes)
            .enumerate()
            .map(|(episode, init)| {
                let mut reality = Reality::new(&config.reality, &config.env, cli.seed, episode as u64, n);
                steps_floor(&config.env, &init, &mut reality)
            })
            .collect();
        let reached: Vec<u32> = floors.iter().flatten().copied().collect();
        let mean = reached.iter().map(|&s| f64::from(s)).sum::<f64>() / reached.len().max(1) as f64;
        lines.push(
            serde_json::json!({
                "n_agents": n,
                "seed": cli.seed,
                "episodes": cli.episodes,
                "mean_floor_steps": (mean * 100.0).round() / 100.0,
                "out_of_time": floors.len() - reached.len(),
                "floor_steps": floors,
            })
            .to_string(),
        );
    }
    Ok(lines.join("\n"))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(text) => {
            println!("{text}");
            ExitCode::SUCCESS
        }
        Err(err) => {
            eprintln!("formation-pace-floor: error: {err:#}");
            ExitCode::from(2)
        }
    }
}
