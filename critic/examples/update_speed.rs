//! Times the critic's two costs per gradient update, sampling a batch and the update itself,
//! on a replay filled with random-action episodes (no IPC), and sets the update against its
//! compute floor: the matrix-product FLOPs of one update (counted from the layer shapes)
//! divided by the rate candle's matmul reaches on the critic's widest layer on this core:
//! `cargo run --release -p formation-critic --example update_speed -- [BATCH] [UPDATES] [HISTORY] [ROBOTS] [mlp|pooled] [parallel|serial] [team|robot]`.
//! Threads: `RAYON_NUM_THREADS` (as the critic's `learn.threads` sets it) for each matrix
//! product; `parallel` runs TD3's twin critics on two threads, `serial` one after the other
//! (default: as `learn.parallel_critics` defaults); `robot` learns a value per robot
//! (`learn.credit`, pooled only). The floor is one core's.

use std::time::Instant;

use candle_core::{Device, Tensor};
use formation_core::config::{Algorithm, Credit, CriticArchitecture, EnvConfig, LearnConfig};
use formation_core::formation::random_episode;
use formation_core::world::World;
use formation_critic::learner::Learner;
use formation_protocol::ACTION_DIM;
use formation_replay::buffer::ReplayBuffer;
use formation_replay::record::record_episode;
use formation_replay::sample::Sampler;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn main() -> anyhow::Result<()> {
    formation_critic::tune_allocator();
    let mut args = std::env::args().skip(1);
    let batch_size: usize = args.next().map_or(Ok(128), |a| a.parse())?;
    let updates: usize = args.next().map_or(Ok(200), |a| a.parse())?;
    let history: usize = args.next().map_or(Ok(15), |a| a.parse())?;
    let n: usize = args.next().map_or(Ok(3), |a| a.parse())?;
    let critic = match args.next().as_deref() {
        None | Some("mlp") => CriticArchitecture::Mlp,
        Some("pooled") => CriticArchitecture::Pooled,
        Some(other) => anyhow::bail!("critic must be mlp or pooled, got {other}"),
    };
    let parallel_critics = match args.next().as_deref() {
        None => LearnConfig::default().parallel_critics,
        Some("parallel") => true,
        Some("serial") => false,
        Some(other) => anyhow::bail!("the twin critics run parallel or serial, got {other}"),
    };
    let credit = match args.next().as_deref() {
        None | Some("team") => Credit::Team,
        Some("robot") if critic == CriticArchitecture::Pooled => Credit::Robot,
        Some(other) => anyhow::bail!("credit must be team, or robot with the pooled critic, got {other}"),
    };
    let env = EnvConfig {
        history,
        ..EnvConfig::default()
    };
    let learn = LearnConfig {
        batch_size,
        critic,
        parallel_critics,
        credit,
        ..LearnConfig::default()
    };
    let mut rng = StdRng::seed_from_u64(1);
    let mut replay = ReplayBuffer::new(learn.replay_capacity);
    for number in 0..200 {
        let world = World::new(&env, random_episode(n, &env, &mut rng));
        replay.push(record_episode(number, world, env.max_steps, |w| {
            (0..w.n_agents())
                .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
                .collect()
        }));
    }
    let sampler = Sampler {
        history: env.history,
        her_probability: learn.her_probability,
        n_step: learn.n_step,
        gamma: learn.gamma,
        env: env.clone(),
        critic: learn.critic,
        critic_map_points: learn.critic_map_points,
    };
    let mut learner = Learner::new(n, &env, &learn, 1)?;
    let probe = sampler.sample(&replay, batch_size, &mut rng).expect("batch");
    let flops = flops_per_update(
        &learn,
        n,
        probe.window_dim(),
        probe.state_window_dim() + probe.action_window_dim(),
    );
    let (mut sampling, mut updating) = (0.0, 0.0);
    for _ in 0..updates {
        let t0 = Instant::now();
        let batch = sampler.sample(&replay, batch_size, &mut rng).expect("batch");
        let t1 = Instant::now();
        learner.update(&batch, 0)?;
        sampling += (t1 - t0).as_secs_f64();
        updating += t1.elapsed().as_secs_f64();
    }
    println!(
        "N = {n}, H = {history}, B = {batch_size}, {critic:?} critic, {credit:?} credit, twin critics {}: sample {:.2} ms, update {:.2} ms, {:.0} updates/s",
        if parallel_critics {
            "on two threads"
        } else {
            "on one thread"
        },
        1e3 * sampling / updates as f64,
        1e3 * updating / updates as f64,
        updates as f64 / (sampling + updating)
    );
    let widest = *learn.critic_hidden.iter().max().expect("validated: not empty");
    let gflops = matmul_gflops(batch_size, widest)?;
    let floor_ms = 1e3 * flops / (gflops * 1e9);
    println!(
        "matrix products: {:.0} MFLOP per update; candle's matmul [{batch_size} x {widest}] x [{widest} x {widest}]: {gflops:.1} GFLOP/s; floor {floor_ms:.2} ms per update ({:.0} updates/s), the update at {:.2} of it",
        flops / 1e6,
        1e3 / floor_ms,
        floor_ms / (1e3 * updating / updates as f64)
    );
    Ok(())
}

/// FLOPs of a dense stack's forward pass over `rows` inputs of width `input`.
fn dense_flops(rows: usize, input: usize, widths: &[usize]) -> f64 {
    let mut width = input;
    let mut flops = 0.0;
    for &w in widths {
        flops += 2.0 * (rows * width * w) as f64;
        width = w;
    }
    flops
}

/// Matrix-product FLOPs of one update (a backward pass counted as twice its forward): the
/// target actor and the target critics for y, the critics' forward and backward, and every
/// `policy_delay`-th update the actor's forward and backward through the first critic.
fn flops_per_update(learn: &LearnConfig, n: usize, window: usize, critic_input: usize) -> f64 {
    let b = learn.batch_size;
    let actor_widths: Vec<usize> = learn.actor_hidden.iter().copied().chain([ACTION_DIM]).collect();
    let actor = dense_flops(b * n, window, &actor_widths);
    let head: Vec<usize> = learn.critic_hidden.iter().copied().chain([1]).collect();
    let critic = match learn.critic {
        CriticArchitecture::Mlp => dense_flops(b, critic_input, &head),
        CriticArchitecture::Pooled => {
            let encoded = *learn.critic_encoder.last().expect("validated: not empty");
            let head_flops = match learn.credit {
                Credit::Team => dense_flops(b, encoded, &head),
                Credit::Robot => dense_flops(b * n, 2 * encoded, &head),
            };
            dense_flops(b * n, critic_input / n, &learn.critic_encoder) + head_flops
        }
    };
    let (critics, delay) = match learn.algorithm {
        Algorithm::Ddpg => (1.0, 1.0),
        Algorithm::Td3 => (2.0, f64::from(learn.policy_delay)),
    };
    actor + critics * critic + 3.0 * critics * critic + 3.0 * (actor + critic) / delay
}

/// GFLOP/s of candle's f32 matmul [rows x width] x [width x width] on this core (best of 5
/// rounds of 200 products).
fn matmul_gflops(rows: usize, width: usize) -> anyhow::Result<f64> {
    let a = Tensor::randn(0f32, 1.0, (rows, width), &Device::Cpu)?;
    let w = Tensor::randn(0f32, 1.0, (width, width), &Device::Cpu)?;
    let flops = 2.0 * (rows * width * width) as f64;
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let started = Instant::now();
        for _ in 0..200 {
            std::hint::black_box(a.matmul(&w)?);
        }
        best = best.min(started.elapsed().as_secs_f64() / 200.0);
    }
    Ok(flops / best / 1e9)
}
