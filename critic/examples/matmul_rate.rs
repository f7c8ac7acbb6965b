//! The compute floor of a gradient update: candle's matrix-product rate on this core at the
//! shapes of the default networks, and the multiply-adds of one update counted from them.
//! `cargo run --release -p formation-critic --example matmul_rate -- [BATCH] [ROBOTS]`
//!
//! The count (default config: TD3, twin `mlp` critics of widths 256-256 on the critic state of
//! H = 1, a shared actor 128-128 on each robot's 16 floats, policy delay 2) takes a backward
//! pass as twice its forward pass, and counts only matrix products (the element-wise work is
//! what separates a real update from this floor).

use std::time::Instant;

use candle_core::{Device, Tensor};
use formation_core::features::CriticFeatures;
use formation_core::observation::Layout;
use formation_protocol::config::{CriticArchitecture, ObservationModel};

/// Multiply-add FLOPs of one forward pass of an MLP with these layer widths, per row.
fn forward_flops(widths: &[usize]) -> f64 {
    widths.windows(2).map(|w| 2.0 * (w[0] * w[1]) as f64).sum()
}

/// FLOP/s of `rows x inner` times `inner x out`, median of several timings.
fn rate(rows: usize, inner: usize, out: usize) -> candle_core::Result<f64> {
    let a = Tensor::randn(0f32, 1.0, (rows, inner), &Device::Cpu)?;
    let b = Tensor::randn(0f32, 1.0, (inner, out), &Device::Cpu)?;
    let repeats = (2e8 / (2.0 * (rows * inner * out) as f64)).ceil() as usize;
    let mut samples = Vec::new();
    for _ in 0..7 {
        let started = Instant::now();
        for _ in 0..repeats {
            std::hint::black_box(a.matmul(&b)?);
        }
        samples.push(2.0 * (rows * inner * out * repeats) as f64 / started.elapsed().as_secs_f64());
    }
    samples.sort_by(f64::total_cmp);
    Ok(samples[samples.len() / 2])
}

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let batch: usize = args.next().map_or(Ok(256), |a| a.parse())?;
    let robots: usize = args.next().map_or(Ok(3), |a| a.parse())?;
    let observation = ObservationModel::default();
    let state = CriticFeatures::new(robots, observation, CriticArchitecture::Mlp).dim();
    let critic = [state + 2 * robots, 256, 256, 1];
    let actor = [Layout::of(observation).dim(), 128, 128, 2];
    let (critic_fwd, actor_fwd) = (
        batch as f64 * forward_flops(&critic),
        (batch * robots) as f64 * forward_flops(&actor),
    );
    // Target: target actor and two target critics forward. Critic step: two critics forward
    // and backward. Actor step (every second update): actor forward and backward, critic 1
    // forward and backward.
    let per_update = (actor_fwd + 2.0 * critic_fwd) + 2.0 * 3.0 * critic_fwd + 0.5 * 3.0 * (actor_fwd + critic_fwd);
    println!(
        "one update, B = {batch}, N = {robots}: {:.0} MFLOP in matrix products",
        per_update / 1e6
    );
    let mut weighted = 0.0;
    for (name, rows, widths, share) in [
        ("critic", batch, &critic[..], 2.0 + 6.0 + 1.5),
        ("actor", batch * robots, &actor[..], 1.0 + 1.5),
    ] {
        for w in widths.windows(2) {
            let flops = share * 2.0 * (rows * w[0] * w[1]) as f64;
            let r = rate(rows, w[0], w[1])?;
            weighted += flops / r;
            println!("  {name} {rows} x {} x {}: {:.1} GFLOP/s", w[0], w[1], r / 1e9);
        }
    }
    println!(
        "floor at these rates: {:.2} ms per update ({:.0} updates/s), {:.1} GFLOP/s overall",
        weighted * 1e3,
        1.0 / weighted,
        per_update / weighted / 1e9
    );
    Ok(())
}
