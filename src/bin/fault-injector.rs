//! Test tool: publishes malformed commands on one robot's command stream of a running swarm
//! (non-finite values, a tick in the future, another robot's index, another protocol
//! version), beside the real agent, for the given number of seconds. The sim must reject and
//! count every one and never integrate them. With `--greet-with-protocol V` it instead greets
//! as that robot speaking protocol V, which a starting sim must refuse.

use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Parser;
use formation_core::observation::Layout;
use formation_ipc::services::{self, RunIdentity, Sizing};
use formation_protocol::wire::{CommandMsg, FLAG_HELLO, Header, PROTOCOL_VERSION};
use iceoryx2::prelude::*;

/// Publishes malformed commands into a running swarm.
#[derive(Debug, Parser)]
struct Cli {
    /// Run id of the swarm.
    #[arg(long)]
    run_id: String,
    /// Robots in the swarm.
    #[arg(long)]
    agents: usize,
    /// Whose command stream to pollute.
    #[arg(long)]
    agent: usize,
    /// How long to keep sending.
    #[arg(long, default_value_t = 2.0)]
    seconds: f64,
    /// Only greet, as a robot speaking this protocol version.
    #[arg(long)]
    greet_with_protocol: Option<u32>,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let identity = RunIdentity::new(&cli.run_id)?;
    let node = services::create_node::<ipc::Service>(&identity, "fault-injector")?;
    let config = formation_core::config::RunConfig::default();
    let sizing = Sizing::new(
        cli.agents,
        config.ticks.critic_window,
        Layout::of(config.env.observation).dim(),
    );
    let publisher = services::command_stream(&node, &sizing, cli.agent)?
        .publisher_builder()
        .create()
        .context("publisher")?;
    let notifier = services::command_event(&node, &sizing)?
        .notifier_builder()
        .default_event_id(services::agent_event_id(cli.agent))
        .create()
        .context("notifier")?;
    let started = Instant::now();
    let mut sent = 0u64;
    while started.elapsed().as_secs_f64() < cli.seconds {
        let good = CommandMsg {
            header: Header::new(0, 0, 0),
            agent: cli.agent as u32,
            policy_version: 0,
            v: 0.1,
            w: 0.0,
            session: 0,
        };
        if let Some(version) = cli.greet_with_protocol {
            let hello = CommandMsg {
                header: Header {
                    protocol_version: version,
                    ..Header::new(0, 0, FLAG_HELLO)
                },
                session: 1,
                ..good
            };
            publisher.send_copy(hello).context("send")?;
            notifier.notify().context("notify")?;
            sent += 1;
            std::thread::sleep(Duration::from_millis(20));
            continue;
        }
        let bad = [
            CommandMsg { v: f32::NAN, ..good },
            CommandMsg {
                w: f32::INFINITY,
                ..good
            },
            CommandMsg {
                header: Header::new(u32::MAX - 1, 0, 0),
                ..good
            },
            CommandMsg {
                agent: cli.agent as u32 + 1,
                ..good
            },
            CommandMsg {
                header: Header {
                    protocol_version: PROTOCOL_VERSION + 1,
                    ..good.header
                },
                ..good
            },
        ];
        for msg in bad {
            publisher.send_copy(msg).context("send")?;
            sent += 1;
        }
        notifier.notify().context("notify")?;
        std::thread::sleep(Duration::from_millis(20));
    }
    println!("sent {sent} messages");
    Ok(())
}
