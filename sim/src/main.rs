//! `formation-sim`: the physics process of a run. Usually started by `scripts/run_swarm.sh`.

use std::process::ExitCode;

use anyhow::Result;
use clap::Parser;
use formation_core::run_dir::prepare_run_dir;
use formation_ipc::cli::{Mode, RunArgs, ViewerMode, parse_robot_set};
use formation_ipc::placement::Role;
use formation_sim::lockstep::{SimOptions, run};
use formation_sim::view;
use iceoryx2::prelude::*;

/// Steps the unicycle physics, scores the paper's reward and drives N agent processes in
/// lockstep over iceoryx2 shared memory.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// Stop after this many episodes (default: 100 in eval mode, unlimited in train mode).
    #[arg(long)]
    episodes: Option<u64>,
    /// Stop after this many minutes of wall clock (default: 30 in train mode, none with
    /// --open-ended).
    #[arg(long)]
    minutes: Option<f64>,
    /// Train mode: no default time limit; the run ends on Ctrl-C (the launcher's `--updates`
    /// sends it once the critic has done its updates).
    #[arg(long, conflicts_with_all = ["episodes", "minutes"])]
    open_ended: bool,
    /// Pace ticks at dt of wall-clock time (real robots) instead of as fast as possible.
    #[arg(long)]
    realtime: bool,
    /// Run without a critic process (no flow control, nothing recorded but the sim's figures).
    #[arg(long)]
    no_critic: bool,
    /// Wait for an MCAP recorder (the launcher's `--record mcap`) as for the critic: never run
    /// more than `ticks.critic_window` states ahead of it, so its file loses nothing.
    #[arg(long)]
    expect_recorder: bool,
    /// Which agents run the scripted baseline, as recorded in the summary: `all` or `0,2`.
    #[arg(long, default_value = "")]
    scripted: String,
    /// Which robots were left to outside processes (`--external` of the launcher), as
    /// recorded in the summary: `all` or `0,2`.
    #[arg(long, default_value = "")]
    external: String,
    /// Live view: spawn (start the `rerun` viewer), save (a .rrd in the run directory),
    /// off, or connect=URL (a running viewer).
    #[arg(long, default_value = "off")]
    viewer: String,
    /// Only validate the flags and the configuration, then exit.
    #[arg(long)]
    check_config: bool,
}

fn main() -> ExitCode {
    // The launcher's Ctrl-C may come at any tick, the first included: the sim then closes the
    // run (its end announced to every robot) instead of dying of the signal.
    formation_ipc::catch_termination_signals();
    let cli = Cli::parse();
    match try_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-sim: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, config) = cli.run.load()?;
    let scripted = parse_robot_set("--scripted", &cli.scripted, cli.run.agents)?;
    let external = parse_robot_set("--external", &cli.external, cli.run.agents)?;
    if let Some(minutes) = cli.minutes {
        anyhow::ensure!(
            minutes.is_finite() && minutes > 0.0,
            "--minutes must be > 0, got {minutes}"
        );
    }
    anyhow::ensure!(
        !cli.open_ended || cli.run.mode == Mode::Train,
        "--open-ended is for training: an eval ends after its episodes"
    );
    ViewerMode::parse(&cli.viewer)?;
    if cli.check_config {
        return Ok(());
    }
    let (episodes, minutes) = match (cli.run.mode, cli.episodes, cli.minutes) {
        (Mode::Eval, None, None) => (Some(100), None),
        (Mode::Train, None, None) if cli.open_ended => (None, None),
        (Mode::Train, None, None) => (None, Some(30.0)),
        (_, e, m) => (e, m),
    };
    prepare_run_dir(&cli.run.run_dir, &config)?;
    identity.write_iceoryx_config(&cli.run.run_dir)?;
    set_log_level_from_env_or(LogLevel::Warn);
    let options = SimOptions {
        n_agents: cli.run.agents,
        mode: cli.run.mode,
        episodes,
        minutes,
        seed: cli.run.seed,
        realtime: cli.realtime,
        expect_critic: !cli.no_critic,
        expect_recorder: cli.expect_recorder,
        scripted,
        external,
        run_dir: cli.run.run_dir.clone(),
        plots: true,
        config,
    };
    let viewer = ViewerMode::parse(&cli.viewer)?;
    // The view's threads (started next) work beside the critic, the tick thread on its own CPU.
    cli.run.place(Role::Background)?;
    let view = view::start(
        &viewer,
        &identity.run_id,
        &options.run_dir,
        &options.config.env,
        options.n_agents,
        options.config.view.trail_ticks,
    )?;
    let (tap, view_thread) = view.unzip();
    if let Some(cpus) = cli.run.place(Role::Sim)? {
        eprintln!("sim: tick thread on CPU {cpus:?} (--placement off leaves placement to the OS)");
    }
    let summary = run::<ipc::Service>(&identity, &options, tap);
    if let Some(thread) = view_thread {
        // The tap was dropped with the loop: the thread flushes the recording and ends.
        let _ = thread.join();
    }
    let summary = summary?;
    if cli.no_critic {
        print!("{}", summary.table());
    }
    Ok(())
}
