//! `formation-distill`: teaches the shared actor its teacher, the scripted baseline with the
//! config's `[baseline]` gains, by DAgger under the config's `[reality]`, in-process (no
//! swarm, no IPC), and saves it as a checkpoint the launcher and agents load like any other.

use std::collections::HashMap;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::{Parser, ValueEnum};
use formation_core::baseline::BaselineGains;
use formation_core::config::{RunConfig, validate_agent_count};
use formation_core::reality::RealityConfig;
use formation_critic::distill::{DistillOptions, Distiller, ImitationLoss, RoundReport, gain_profile};
use formation_critic::selection::{PlannerKind, Selector};
use formation_model::actor::ActorHead;
use formation_model::checkpoint::{SelectionScore, SizeScore};
use indicatif::{ProgressBar, ProgressStyle};

/// Who teaches the student.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Teacher {
    /// The config's [baseline] gains (the scripted baseline; a potential field among obstacles).
    Baseline,
    /// The team's planner that knows the map (the launcher's oracle).
    Planner,
    /// Each robot's own planner over the map, no team plan.
    Solo,
    /// Each robot's own planner over only the obstacles its range sensor could reach.
    SoloLocal,
}

/// Distils a teacher (the scripted baseline with the config's `[baseline]` gains, or with
/// --teacher a planner that knows the map) into the shared actor:
/// each round plays episodes of every swarm size in-process, exactly as a lockstep sim plays
/// them under the config's `[reality]`, labels every robot's window with the teacher's command,
/// and takes gradient steps on the error to those labels (--loss). The teacher drives the first
/// round; after it, the student drives most episodes (DAgger), so it learns the way back from its
/// own mistakes.
/// At the end the student is scored by model selection (learn.selection_*, under the reality
/// and in the ideal world) and saved with that score.
///
/// The shipped model, models/formation.safetensors, a gain schedule (29-33 minutes a seed with
/// three seeds at once on two CPUs here; models/README.md):
/// `formation-distill --config configs/field-gains.toml --head gains --quiet-teacher configs/quiet-gains.toml --quiet-below-m 0.02 --out runs/gains/s1.safetensors --seed 1`
#[derive(Debug, Parser)]
#[command(version, about, long_about)]
struct Cli {
    /// Run config: [env] (observation model, shapes, history), [learn] (actor_hidden,
    /// selection_*), [reality] (the episodes' randomised reality) and [baseline] (the teacher).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Start from this checkpoint's shared actor (a file or run directory) instead of fresh
    /// weights; its shape must be the config's.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Where to write the student (a .safetensors file; refused if it exists, unless --force).
    #[arg(long)]
    out: PathBuf,
    /// Overwrite --out.
    #[arg(long)]
    force: bool,
    /// Swarm sizes played every round.
    #[arg(long, value_delimiter = ',', default_value = "3,12,32")]
    sizes: Vec<usize>,
    /// Rounds (each: episodes, then --updates gradient steps).
    #[arg(long, default_value_t = 400)]
    rounds: usize,
    /// Robots per size and round (each size plays ceil(this / N) episodes a round).
    #[arg(long, default_value_t = 96)]
    robots_per_round: usize,
    /// Gradient steps per round.
    #[arg(long, default_value_t = 400)]
    updates: usize,
    /// Samples per gradient step.
    #[arg(long, default_value_t = 1024)]
    batch: usize,
    /// Share of episodes after the first round the teacher drives.
    #[arg(long, default_value_t = 0.2)]
    teacher_share: f64,
    /// Learning rate of the first round (Adam), decaying exponentially to --lr-end.
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    /// Learning rate of the last round.
    #[arg(long, default_value_t = 3e-5)]
    lr_end: f64,
    /// Seeds the episodes (far from the held-out seeds), the sampling and fresh weights.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// A privileged teacher: a TOML file whose [baseline] gains teach the robots the episode
    /// drew no position noise for (--quiet-below-m or less); the config's [baseline] teaches
    /// those with --noise-scale-m or more, the gains blended linearly between. The student cannot read
    /// the noise: with an observation history (env.history > 1) it can see it.
    #[arg(long, value_name = "FILE")]
    quiet_teacher: Option<PathBuf>,
    /// With --quiet-teacher: the position noise (metres) from which the config's gains apply.
    #[arg(long, default_value_t = 0.05)]
    noise_scale_m: f64,
    /// With --quiet-teacher: the position noise (metres) up to which the quiet gains apply in
    /// full (blended from there to --noise-scale-m).
    #[arg(long, default_value_t = 0.0)]
    quiet_below_m: f64,
    /// With --quiet-teacher: robots whose drawn actuation delay is this many ticks or more are
    /// taught the config's gains whatever their noise (default: the noise alone chooses).
    #[arg(long, value_name = "TICKS")]
    soft_from_delay_ticks: Option<u32>,
    /// What the student outputs: "command" (v, w), as the paper's actor; or "gains", the five
    /// [baseline] gains, taught the teacher's gains, which the baseline's law then turns into
    /// the command (a learned gain schedule: the formation's equilibrium is the law's, exact).
    /// With --checkpoint, the checkpoint's head.
    #[arg(long, default_value = "command", value_parser = ["command", "gains"])]
    head: String,
    /// Who teaches: the config's [baseline] (a potential field among obstacles), the team's
    /// planner that knows the map (`planner`, the launcher's oracle), or each robot's own
    /// planner over the map (`solo`) or over what its range sensor could reach of it
    /// (`solo-local`). A planner teaches its command for each robot from the true state: the
    /// imitation start of a policy among obstacles (a config with [obstacles] and
    /// env.observation = "slot_proximity_scan"; command head only).
    #[arg(long, value_enum, default_value_t = Teacher::Baseline)]
    teacher: Teacher,
    /// The student's error to its labels: `squared` learns the teacher's mean answer for what
    /// it sees; `absolute` its median, so where the teacher answers one of two ways for windows
    /// the student cannot tell apart (stop or go, left or right) it takes the more frequent one.
    #[arg(long, value_enum, default_value_t = ImitationLoss::Squared)]
    loss: ImitationLoss,
    /// A teacher with memory: every robot's recovery behaviour (docs/OBSTACLES.md, "The
    /// recovery behaviour") runs in the rounds' episodes with this longest recovery, and where
    /// it takes a robot's motors over, its command is the label, so the student learns to go
    /// round an obstacle that holds it (command head, a config with a scan). The student is
    /// scored, and plays, without it.
    #[arg(long, value_name = "TICKS")]
    teach_recovery: Option<u32>,
    /// A learned teacher: this checkpoint's shared actor (a command head reading the config's
    /// window) labels every window instead of the [baseline] gains. With --teach-recovery the
    /// recovery labels the ticks it takes over: the student learns its teacher and the recovery
    /// together (expert iteration; start it from the teacher with --checkpoint).
    #[arg(long, value_name = "FILE")]
    teacher_checkpoint: Option<PathBuf>,
    /// Also write the student to --out every this many rounds (unscored; its metadata says the
    /// rounds done), so an interrupted run keeps its work; 0: only at the end.
    #[arg(long, default_value_t = 50)]
    save_every: usize,
}

fn main() -> ExitCode {
    match try_main(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-distill: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    // SAFETY: no other thread runs yet; candle reads this for its matmul thread count.
    unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    let config = match &cli.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    check_sizes_and_out(&cli)?;
    let mut distiller = Distiller::new(&config, distill_options(&cli)?, cli.checkpoint.as_deref())?;
    let began = Instant::now();
    play_rounds(&cli, &mut distiller)?;
    let took = began.elapsed();
    let selector = Selector::new(&config.env, &config.learn, &config.reality, &cli.sizes);
    let score = selector.score(&[distiller.actor_weights()?], distiller.shape())?;
    let extra = student_metadata(&cli, &config, &distiller, &score, took)?;
    distiller.save(&cli.out, extra)?;
    print_summary(&cli, &score, took);
    Ok(())
}

/// Refuses a swarm size the wire cannot carry and an existing `--out` (unless `--force`);
/// creates `--out`'s directory.
fn check_sizes_and_out(cli: &Cli) -> Result<()> {
    for &n in &cli.sizes {
        validate_agent_count(n).context("--sizes")?;
    }
    if cli.out.exists() && !cli.force {
        anyhow::bail!("{} exists; pass --force to overwrite it", cli.out.display());
    }
    if let Some(parent) = cli.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("cannot create {}", parent.display()))?;
    }
    Ok(())
}

/// The distiller's options from the flags (reading `--quiet-teacher`'s `[baseline]`).
fn distill_options(cli: &Cli) -> Result<DistillOptions> {
    Ok(DistillOptions {
        sizes: cli.sizes.clone(),
        robots_per_round: cli.robots_per_round,
        updates_per_round: cli.updates,
        batch: cli.batch,
        teacher_share: cli.teacher_share,
        lr_start: cli.lr,
        lr_end: cli.lr_end,
        rounds: cli.rounds,
        seed: cli.seed,
        quiet_teacher: match &cli.quiet_teacher {
            Some(path) => Some(RunConfig::from_toml_file(path).context("--quiet-teacher")?.baseline),
            None => None,
        },
        noise_scale_m: cli.noise_scale_m,
        quiet_below_m: cli.quiet_below_m,
        planner_teacher: match cli.teacher {
            Teacher::Baseline => None,
            Teacher::Planner => Some(PlannerKind::Team),
            Teacher::Solo => Some(PlannerKind::Solo),
            Teacher::SoloLocal => Some(PlannerKind::SoloLocal),
        },
        soft_from_delay_ticks: cli.soft_from_delay_ticks,
        head: ActorHead::from_name(&cli.head).context("--head")?,
        loss: cli.loss,
        teach_recovery_ticks: cli.teach_recovery,
        actor_teacher: cli.teacher_checkpoint.clone(),
        ..DistillOptions::default()
    })
}

/// Plays the `--rounds` rounds, writing the unfinished student every `--save-every` rounds and
/// showing progress: a bar on a terminal, else a line every 20 rounds and at the last.
fn play_rounds(cli: &Cli, distiller: &mut Distiller) -> Result<()> {
    let bar = progress_bar(cli.rounds as u64);
    for _ in 0..cli.rounds {
        let report = distiller.round()?;
        if cli.save_every > 0 && report.round % cli.save_every == 0 && report.round < cli.rounds {
            let mut extra = HashMap::new();
            extra.insert(
                "distill_unfinished".into(),
                format!("{} of {} rounds", report.round, cli.rounds),
            );
            distiller.save(&cli.out, extra)?;
        }
        let line = describe(&report);
        match &bar {
            Some(bar) => {
                bar.set_message(line);
                bar.inc(1);
            }
            None if report.round % 20 == 0 || report.round == cli.rounds => {
                eprintln!("formation-distill: round {}/{}: {line}", report.round, cli.rounds);
            }
            None => {}
        }
    }
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    Ok(())
}

/// The finished student's metadata: its selection score, the wall time, the checkpoint it
/// started from, a reality other than the ideal world and, for a gain schedule, its gain
/// profiles.
fn student_metadata(
    cli: &Cli,
    config: &RunConfig,
    distiller: &Distiller,
    score: &SelectionScore,
    took: Duration,
) -> Result<HashMap<String, String>> {
    let mut extra = HashMap::new();
    score.to_metadata(&mut extra);
    extra.insert("distill_seconds".into(), format!("{:.0}", took.as_secs_f64()));
    if let Some(start) = &cli.checkpoint {
        extra.insert("distill_start".into(), start.display().to_string());
    }
    if !config.reality.is_ideal() {
        extra.insert("reality".into(), config.reality.one_line());
    }
    if cli.loss != ImitationLoss::default()
        && let Some(name) = cli.loss.to_possible_value()
    {
        extra.insert("distill_loss".into(), name.get_name().into());
    }
    if let Some(ticks) = cli.teach_recovery {
        extra.insert("distill_recovery_ticks".into(), ticks.to_string());
    }
    if distiller.shape().head == ActorHead::Gains {
        record_gain_profiles(cli, config, distiller, &mut extra)?;
    }
    Ok(extra)
}

/// What the schedule picks, in the ideal world and under the reality, on the selection's
/// episodes of the largest size: printed, and recorded as `gain_profile_ideal` and
/// `gain_profile_reality`.
fn record_gain_profiles(
    cli: &Cli,
    config: &RunConfig,
    distiller: &Distiller,
    extra: &mut HashMap<String, String>,
) -> Result<()> {
    let n = *cli.sizes.iter().max().expect("sizes checked non-empty");
    let episodes = (n, config.learn.selection_seed, config.learn.selection_episodes);
    for (world, reality) in [("ideal", RealityConfig::default()), ("reality", config.reality.clone())] {
        let profile = gain_profile(
            &config.env,
            &reality,
            distiller.shape(),
            &distiller.actor_weights()?,
            episodes,
        )?;
        let line = BaselineGains::NAMES
            .iter()
            .zip(profile)
            .map(|(name, (mean, std))| format!("{name} {mean:.3} +- {std:.3}"))
            .collect::<Vec<_>>()
            .join(", ");
        println!("formation-distill: gains picked at N = {n}, {world}: {line}");
        extra.insert(format!("gain_profile_{world}"), line);
    }
    Ok(())
}

/// The closing line: rounds, wall time, the selection score by size (and in the ideal world,
/// when the score has it) and where the student was saved.
fn print_summary(cli: &Cli, score: &SelectionScore, took: Duration) {
    println!(
        "formation-distill: {} rounds in {:.0} s; selection {}{}; saved {}",
        cli.rounds,
        took.as_secs_f64(),
        by_size(&score.sizes),
        score
            .ideal
            .as_ref()
            .map_or(String::new(), |ideal| format!(" (ideal world {})", by_size(ideal))),
        cli.out.display()
    );
}

/// Each size's success and mean steps, in a line.
fn by_size(sizes: &[SizeScore]) -> String {
    sizes
        .iter()
        .map(|s| format!("N={} {:.2} in {:.1} steps", s.n_agents, s.success, s.mean_steps))
        .collect::<Vec<_>>()
        .join(", ")
}

/// A bar over the rounds on a terminal; `None` elsewhere (a line every 20 rounds instead).
fn progress_bar(rounds: u64) -> Option<ProgressBar> {
    std::io::stderr().is_terminal().then(|| {
        let bar = ProgressBar::new(rounds);
        bar.set_style(
            ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} rounds, ~{eta} left  {msg}")
                .expect("a valid template")
                .progress_chars("=> "),
        );
        bar
    })
}

/// One round in a line: the buffer, the loss and how the student drove.
fn describe(report: &RoundReport) -> String {
    let student: Vec<String> = report
        .student
        .iter()
        .map(|s| match s.success {
            Some(success) => format!("N={} {success:.2}", s.n_agents),
            None => format!("N={} -", s.n_agents),
        })
        .collect();
    let per_output: Vec<String> = report
        .loss_per_output
        .iter()
        .map(|loss| format!("{loss:.2e}"))
        .collect();
    format!(
        "{} samples, loss {:.2e} (per output {}), lr {:.1e}, student success {}",
        report.samples,
        report.loss,
        per_output.join(" / "),
        report.lr,
        student.join(" ")
    )
}
