//! `formation-bridge`: joins robots on other hosts to a swarm over Zenoh. One runs on the sim's
//! host (`--side sim`, serving the robots that live elsewhere) and one on each robot's host
//! (`--side robot`, recreating the robot's services there so the unchanged `formation-agent`
//! runs on it). Within a host everything stays iceoryx2 shared memory; only what crosses hosts
//! is sent, in the payloads' own fixed layouts.

mod link;
mod robot_side;
mod sim_side;

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, anyhow, ensure};
use clap::{Parser, ValueEnum};
use formation_core::observation::Layout;
use formation_ipc::cli::{Mode, RunArgs, parse_robot_set};
use formation_ipc::services::{RunIdentity, Sizing};
use formation_protocol::wire::{FLAG_HELLO, FLAG_RUN_END, Header};
use iceoryx2::prelude::*;
use zenoh::{Session, Wait};

use crate::link::{Endpoints, Keys, NetEmulation};

/// Which host this bridge runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Side {
    /// The sim's host: serves the robots that live on other hosts.
    Sim,
    /// A robot's host: stands for the sim there.
    Robot,
}

/// Joins robots on other hosts to a swarm over Zenoh (peer mode, only the endpoints given, no
/// discovery). Started by the launcher for `--remote`; by hand on a real second computer (see
/// docs/REMOTE.md).
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// sim: on the sim's host; robot: on a robot's host.
    #[arg(long, value_enum)]
    side: Side,
    /// The robots this bridge carries: on the sim's host those that live elsewhere, on a robot's
    /// host those that live here (`2` or `2,3`).
    #[arg(long, value_name = "i,j")]
    robots: String,
    /// The run id of the sim's host (names the Zenoh keys); default: this bridge's --run-id.
    #[arg(long, value_name = "RUN_ID")]
    swarm: Option<String>,
    /// Zenoh endpoint to accept links on, e.g. tcp/192.168.1.10:7447 (repeatable; none: this
    /// bridge only dials).
    #[arg(long, value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// Zenoh endpoint to dial, and redial after a lost link (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Vec<String>,
    /// Zenoh JSON5 configuration (TLS, access control); the endpoints are always those of
    /// --listen and --connect, discovery stays off.
    #[arg(long, value_name = "FILE")]
    zenoh_config: Option<PathBuf>,
    /// Emulated network: every message this bridge sends leaves this many milliseconds late.
    #[arg(long, default_value_t = 0.0, value_name = "MS")]
    net_delay_ms: f64,
    /// Emulated network: every message this bridge sends is lost with this probability.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    net_loss: f64,
}

/// What a bridge carries, on which host.
#[derive(Debug, Clone)]
pub struct Bridged {
    /// This host's run identity (its iceoryx2 prefix and root path).
    pub identity: RunIdentity,
    /// The robots carried.
    pub robots: Vec<usize>,
    /// The services' sizing and contract.
    pub sizing: Sizing,
    /// Learned robots in train mode follow weights; else none are carried.
    pub follows_weights: bool,
    /// One actor for every robot, or one each.
    pub shared_actor: bool,
    /// The emulated network on the messages this bridge sends.
    pub emulation: NetEmulation,
    /// How long a sim may be silent before its process is checked.
    pub sim_silence: Duration,
    /// How long a sim (or the sim's host) may be away at all.
    pub startup_timeout: Duration,
}

impl Bridged {
    /// The actors whose weights the carried robots follow.
    pub fn actors(&self) -> Vec<usize> {
        match (self.follows_weights, self.shared_actor) {
            (false, _) => Vec::new(),
            (true, true) => vec![0],
            (true, false) => self.robots.clone(),
        }
    }
}

/// What a bridge did, printed when it ends.
#[derive(Debug, Default)]
pub struct Counters {
    /// Observations forwarded.
    pub observations: AtomicU64,
    /// Commands forwarded.
    pub commands: AtomicU64,
    /// Weights messages forwarded.
    pub weights: AtomicU64,
    /// Stale or duplicated messages dropped.
    pub dropped: AtomicU64,
    /// Messages refused: for a robot this bridge does not carry, or malformed.
    pub rejected: AtomicU64,
    /// Messages the emulated network lost.
    pub lost: AtomicU64,
}

/// Admits each message of one robot once and in order: a message older than the last one
/// forwarded (episode, then tick), or the same bytes again, is dropped. A greeting (a restarted
/// robot's `FLAG_HELLO`) and the run's end always pass.
#[derive(Debug, Default)]
pub struct Freshness {
    last: Option<((u32, u32), Vec<u8>)>,
}

impl Freshness {
    /// True when `header` (of the message `bytes`) is to be forwarded; remembers it.
    pub fn admit(&mut self, header: &Header, bytes: &[u8]) -> bool {
        let position = (header.episode, header.tick);
        if let Some((last, last_bytes)) = &self.last {
            let always = header.has(FLAG_HELLO) || header.has(FLAG_RUN_END);
            if last_bytes.as_slice() == bytes || (!always && position < *last) {
                return false;
            }
        }
        if !header.has(FLAG_HELLO) {
            match &mut self.last {
                Some((last, last_bytes)) => {
                    *last = position;
                    last_bytes.clear();
                    last_bytes.extend_from_slice(bytes);
                }
                None => self.last = Some((position, bytes.to_vec())),
            }
        }
        true
    }
}

/// One direction of a bridge, run on its own thread until `stop` is set.
pub type CommandDirection = fn(&Bridged, &Session, &Keys, &Counters, &AtomicBool) -> Result<()>;

/// Runs `commands` on a thread of its own beside `observations` on this one; when
/// `observations` returns, stops and joins `commands`. Returns the first error of the two.
pub fn beside_the_commands(
    bridged: &Bridged,
    session: &Session,
    keys: &Keys,
    counters: &Arc<Counters>,
    commands: CommandDirection,
    observations: impl FnOnce() -> Result<()>,
) -> Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (bridged, session, keys) = (bridged.clone(), session.clone(), keys.clone());
        let (counters, stop) = (Arc::clone(counters), Arc::clone(&stop));
        std::thread::Builder::new()
            .name("commands".into())
            .spawn(move || commands(&bridged, &session, &keys, &counters, &stop))
            .context("cannot start the command thread")?
    };
    let outcome = observations();
    stop.store(true, Ordering::Release);
    let commands = thread.join().map_err(|_| anyhow!("the command thread panicked"))?;
    outcome.and(commands)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match try_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-bridge: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, config) = cli.run.load()?;
    let robots = parse_robot_set("--robots", &cli.robots, cli.run.agents)?;
    ensure!(!robots.is_empty(), "--robots names no robot");
    ensure!(
        (0.0..=60_000.0).contains(&cli.net_delay_ms),
        "--net-delay-ms must be 0 to 60000, got {}",
        cli.net_delay_ms
    );
    ensure!(
        (0.0..=1.0).contains(&cli.net_loss),
        "--net-loss must be a probability, got {}",
        cli.net_loss
    );
    if cli.side == Side::Sim {
        ensure!(
            !cli.listen.is_empty() || !cli.connect.is_empty(),
            "the sim's bridge needs --listen or --connect (e.g. --listen tcp/127.0.0.1:7447)"
        );
    }
    set_log_level_from_env_or(LogLevel::Warn);
    let obs_dim = Layout::of(config.env.observation).dim();
    let bridged = Bridged {
        identity: identity.clone(),
        robots,
        sizing: Sizing::new(cli.run.agents, config.ticks.critic_window, obs_dim),
        follows_weights: cli.run.mode == Mode::Train,
        shared_actor: config.learn.shared_actor,
        emulation: NetEmulation {
            delay: Duration::from_secs_f64(cli.net_delay_ms / 1e3),
            loss: cli.net_loss,
        },
        sim_silence: Duration::from_millis(config.ticks.sim_silence_ms),
        startup_timeout: Duration::from_secs(config.ticks.startup_timeout_s),
    };
    let keys = Keys::new(cli.swarm.as_deref().unwrap_or(&identity.run_id));
    let session = link::open_session(&Endpoints {
        listen: cli.listen.clone(),
        connect: cli.connect.clone(),
        config_file: cli.zenoh_config.clone(),
    })?;
    eprintln!(
        "bridge ({:?} side, robots {:?}): zenoh {} listening on {:?}, dialling {:?}",
        cli.side,
        bridged.robots,
        session.zid(),
        cli.listen,
        cli.connect
    );
    let outcome = match cli.side {
        Side::Sim => sim_side::run(&bridged, &session, &keys),
        Side::Robot => robot_side::run(&bridged, &session, &keys),
    };
    let closed = session.close().wait().map_err(|err| anyhow!("closing zenoh: {err}"));
    let counters = outcome?;
    let load = |counter: &AtomicU64| counter.load(Ordering::Relaxed);
    eprintln!(
        "bridge ({:?} side): forwarded {} observations, {} commands, {} weights; dropped {} stale or duplicated, rejected {}, lost {} (emulated)",
        cli.side,
        load(&counters.observations),
        load(&counters.commands),
        load(&counters.weights),
        load(&counters.dropped),
        load(&counters.rejected),
        load(&counters.lost)
    );
    closed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_message_passes_once_and_in_order_but_greetings_and_the_run_end_always() {
        let mut freshness = Freshness::default();
        let at = |episode, tick, flags| Header::new(episode, tick, flags);
        assert!(freshness.admit(&at(0, 5, 0), b"a"));
        assert!(!freshness.admit(&at(0, 5, 0), b"a"), "a duplicate");
        assert!(!freshness.admit(&at(0, 4, 0), b"b"), "a stale tick");
        assert!(freshness.admit(&at(1, 0, 0), b"c"), "the next episode");
        assert!(!freshness.admit(&at(0, 9, 0), b"d"), "an older episode");
        assert!(
            freshness.admit(&at(0, 0, FLAG_HELLO), b"hello"),
            "a restarted robot greets"
        );
        assert!(
            freshness.admit(&at(1, 1, 0), b"e"),
            "a greeting does not move the order"
        );
        assert!(
            freshness.admit(&at(1, 0, FLAG_RUN_END), b"end"),
            "the run end always passes"
        );
    }
}
