//! Benchmark floor: the round trip between two processes, over an iceoryx2 event pair, over a
//! pair of tick bells (the futex with which the sim wakes the Rust robots) and over a Unix
//! domain datagram socket for comparison. Benchmark code only. Prints one JSON line per run.

use std::os::unix::net::UnixDatagram;
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::{Parser, ValueEnum};
use formation_ipc::placement::{self, Placement, Role};
use formation_ipc::services::RunIdentity;
use formation_ipc::tick_gate::TickGate;
use iceoryx2::prelude::*;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Transport {
    /// iceoryx2 events (Unix datagrams under the hood, plus shared-memory bookkeeping).
    Iceoryx2,
    /// Two tick gates' bells (a futex each way), as the sim wakes the robots.
    Bell,
    /// A bare Unix domain datagram socket.
    Uds,
}

/// Times process-to-process round trips.
#[derive(Debug, Parser)]
struct Cli {
    /// Transport to time.
    #[arg(long, value_enum, default_value_t = Transport::Iceoryx2)]
    transport: Transport,
    /// Round trips to time (after 1000 warm-up ones).
    #[arg(long, default_value_t = 20_000)]
    round_trips: usize,
    /// auto: both processes on one CPU (the lockstep CPU of a swarm); off: the OS places them.
    #[arg(long, value_enum, default_value_t = Placement::Auto)]
    placement: Placement,
    /// Internal: run as the echoing child with this rendezvous name.
    #[arg(long, hide = true)]
    child: Option<String>,
}

const WARMUP: usize = 1000;

fn iox_events(
    name: &str,
) -> Result<(
    Node<ipc::Service>,
    [iceoryx2::service::port_factory::event::PortFactory<ipc::Service>; 2],
)> {
    let identity = RunIdentity::new(name)?;
    let node = formation_ipc::services::create_node::<ipc::Service>(&identity, "pingpong")?;
    let open = |suffix: &str| {
        node.service_builder(&ServiceName::new(&format!("pingpong/{suffix}")).map_err(anyhow::Error::from)?)
            .event()
            .open_or_create()
            .with_context(|| format!("event {suffix}"))
    };
    let ping = open("ping")?;
    let pong = open("pong")?;
    Ok((node, [ping, pong]))
}

fn child(cli: &Cli, name: &str) -> Result<()> {
    let total = cli.round_trips + WARMUP;
    match cli.transport {
        Transport::Iceoryx2 => {
            let (_node, [ping, pong]) = iox_events(name)?;
            let listener = ping.listener_builder().create().map_err(anyhow::Error::from)?;
            let notifier = pong.notifier_builder().create().map_err(anyhow::Error::from)?;
            notifier.notify().map_err(anyhow::Error::from)?; // ready
            for _ in 0..total {
                listener.blocking_wait(|_| {}).map_err(anyhow::Error::from)?;
                notifier.notify().map_err(anyhow::Error::from)?;
            }
        }
        Transport::Bell => {
            let theirs = attach_bell(&format!("{name}a"))?;
            let mut seen = theirs.bell_count();
            // Created only after `seen` is read: the parent rings once this exists.
            let ours = TickGate::create(&RunIdentity::new(&format!("{name}b"))?)?;
            for _ in 0..total {
                seen = wait_past(&theirs, seen)?;
                ours.ring()?;
            }
        }
        Transport::Uds => {
            let dir = PathBuf::from(name);
            let socket = UnixDatagram::bind(dir.join("child"))?;
            socket.connect(dir.join("parent"))?;
            socket.send(&[0])?;
            let mut byte = [0u8; 1];
            for _ in 0..total {
                socket.recv(&mut byte)?;
                socket.send(&byte)?;
            }
        }
    }
    Ok(())
}

/// The gate another process created for `name`, waited for up to 10 s.
fn attach_bell(name: &str) -> Result<TickGate> {
    let identity = RunIdentity::new(name)?;
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(gate) = TickGate::attach(&identity, 0, 1, true)? {
            return Ok(gate);
        }
        anyhow::ensure!(Instant::now() < deadline, "no tick gate {name} after 10 s");
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// Sleeps on `gate`'s bell until it rings past `seen`; returns its new count.
fn wait_past(gate: &TickGate, seen: u32) -> Result<u32> {
    loop {
        gate.wait_for_bell(seen, Duration::from_secs(1))?;
        let now = gate.bell_count();
        if now != seen {
            return Ok(now);
        }
    }
}

fn quantile(sorted: &[Duration], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q) as usize].as_secs_f64() * 1e6
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    if let Some(name) = &cli.child {
        return child(&cli, name);
    }
    // The echoing child inherits this placement.
    placement::apply(cli.placement, Role::Sim)?;
    let name = format!("pp{}", std::process::id());
    let exe = std::env::current_exe()?;
    let spawn_child = |rendezvous: &str| {
        Command::new(&exe)
            .args([
                "--transport",
                match cli.transport {
                    Transport::Iceoryx2 => "iceoryx2",
                    Transport::Bell => "bell",
                    Transport::Uds => "uds",
                },
            ])
            .args(["--round-trips", &cli.round_trips.to_string(), "--child", rendezvous])
            .spawn()
            .context("cannot start the echo child")
    };
    let mut samples = Vec::with_capacity(cli.round_trips);
    match cli.transport {
        Transport::Iceoryx2 => {
            let (_node, [ping, pong]) = iox_events(&name)?;
            let notifier = ping.notifier_builder().create().map_err(anyhow::Error::from)?;
            let listener = pong.listener_builder().create().map_err(anyhow::Error::from)?;
            let mut echo = spawn_child(&name)?;
            listener.blocking_wait(|_| {}).map_err(anyhow::Error::from)?;
            for i in 0..cli.round_trips + WARMUP {
                let start = Instant::now();
                notifier.notify().map_err(anyhow::Error::from)?;
                listener.blocking_wait(|_| {}).map_err(anyhow::Error::from)?;
                if i >= WARMUP {
                    samples.push(start.elapsed());
                }
            }
            echo.wait()?;
        }
        Transport::Bell => {
            let ours = TickGate::create(&RunIdentity::new(&format!("{name}a"))?)?;
            let mut echo = spawn_child(&name)?;
            let theirs = attach_bell(&format!("{name}b"))?;
            let mut seen = theirs.bell_count();
            for i in 0..cli.round_trips + WARMUP {
                let start = Instant::now();
                ours.ring()?;
                seen = wait_past(&theirs, seen)?;
                if i >= WARMUP {
                    samples.push(start.elapsed());
                }
            }
            echo.wait()?;
        }
        Transport::Uds => {
            let dir = std::env::temp_dir().join(&name);
            std::fs::create_dir_all(&dir)?;
            let socket = UnixDatagram::bind(dir.join("parent"))?;
            let mut echo = spawn_child(dir.to_str().context("utf8 path")?)?;
            let mut byte = [0u8; 1];
            socket.recv(&mut byte)?;
            socket.connect(dir.join("child"))?;
            for i in 0..cli.round_trips + WARMUP {
                let start = Instant::now();
                socket.send(&byte)?;
                socket.recv(&mut byte)?;
                if i >= WARMUP {
                    samples.push(start.elapsed());
                }
            }
            echo.wait()?;
            std::fs::remove_dir_all(&dir)?;
        }
    }
    // Every node of the pair is gone now; remove what iceoryx2 leaves of a run.
    RunIdentity::new(&name)?.remove_leftovers();
    let total: Duration = samples.iter().sum();
    samples.sort_unstable();
    println!(
        "{{\"transport\": \"{:?}\", \"placement\": \"{:?}\", \"round_trips\": {}, \"p50_us\": {:.2}, \"p99_us\": {:.2}, \"round_trips_per_s\": {:.0}}}",
        cli.transport,
        cli.placement,
        samples.len(),
        quantile(&samples, 0.5),
        quantile(&samples, 0.99),
        samples.len() as f64 / total.as_secs_f64()
    );
    Ok(())
}
