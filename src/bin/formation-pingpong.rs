//! Benchmark floor: the round trip between two processes, over an iceoryx2 event pair (what a
//! lockstep tick costs at least) and over a Unix domain datagram socket for comparison.
//! Benchmark code only; the product has one transport. Prints one JSON line per transport.

use std::os::unix::net::UnixDatagram;
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::{Parser, ValueEnum};
use formation_protocol::placement::{self, Placement, Role};
use formation_protocol::services::RunIdentity;
use iceoryx2::prelude::*;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Transport {
    /// iceoryx2 events (Unix datagrams under the hood, plus shared-memory bookkeeping).
    Iceoryx2,
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
    let node = formation_protocol::services::create_node::<ipc::Service>(&identity, "pingpong")?;
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
