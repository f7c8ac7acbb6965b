//! What drives a robot: the scripted baseline or the learned actor, behind one trait.

use anyhow::Result;
use formation_core::config::EnvConfig;
use rand::Rng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

use formation_model::actor::{ActorShape, FrozenActor};
use formation_model::history::ObservationHistory;

use formation_core::baseline::ScriptedBaseline;

/// A robot's controller: a command from its observation window.
pub trait Policy: Send {
    /// (v, w) for the window (newest observation last).
    fn command(&mut self, history: &ObservationHistory) -> Result<(f64, f64)>;
    /// Version of the weights in use (0 for scripted or not yet trained).
    fn version(&self) -> u32;
    /// Starts a new episode; `explore` is false on the noise-free evaluation episodes.
    fn begin_episode(&mut self, _episode: u32, _explore: bool) {}
}

impl Policy for ScriptedBaseline {
    fn command(&mut self, history: &ObservationHistory) -> Result<(f64, f64)> {
        Ok(self.command_in(history.as_flat()))
    }

    fn version(&self) -> u32 {
        0
    }
}

/// Exploration of a learned policy in train mode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Exploration {
    /// Std of the Gaussian action noise at episode 0 (normalised action units).
    pub std_start: f64,
    /// Std it decays to.
    pub std_end: f64,
    /// Episodes over which it decays linearly.
    pub decay_episodes: u32,
    /// Correlation time of the noise, ticks (0: white noise).
    pub correlation_ticks: f64,
}

impl Exploration {
    /// Noise std in `episode`.
    pub fn std_at(&self, episode: u32) -> f64 {
        let progress = (f64::from(episode) / f64::from(self.decay_episodes.max(1))).min(1.0);
        self.std_start + (self.std_end - self.std_start) * progress
    }

    /// How much of the last tick's noise the next keeps: exp(-1 / correlation_ticks), 0 for
    /// white noise.
    pub fn carry(&self) -> f64 {
        if self.correlation_ticks > 0.0 {
            (-1.0 / self.correlation_ticks).exp()
        } else {
            0.0
        }
    }
}

/// The learned actor, updated between ticks when the critic publishes new weights.
#[derive(Clone)]
pub struct LearnedPolicy {
    env: EnvConfig,
    shape: ActorShape,
    actor: Option<FrozenActor>,
    version: u32,
    exploration: Option<Exploration>,
    noise_std: f64,
    /// The exploration noise of the last tick (normalised action units), carried over by
    /// [`Exploration::carry`].
    noise: [f64; 2],
    rng: StdRng,
}

impl LearnedPolicy {
    /// A policy with no weights yet: in train mode it acts uniformly at random until the first
    /// weights arrive; in eval mode weights must be given with [`LearnedPolicy::load`].
    pub fn new(env: &EnvConfig, shape: ActorShape, exploration: Option<Exploration>, rng: StdRng) -> Self {
        Self {
            env: env.clone(),
            shape,
            actor: None,
            version: 0,
            exploration,
            noise_std: exploration.map_or(0.0, |e| e.std_start),
            noise: [0.0; 2],
            rng,
        }
    }

    /// Installs new flat weights with their version (in place once an actor exists).
    pub fn load(&mut self, flat: &[f32], version: u32) -> Result<()> {
        match &mut self.actor {
            Some(actor) => actor.load(flat)?,
            None => self.actor = Some(FrozenActor::from_flat(flat, &self.shape)?),
        }
        self.version = version;
        Ok(())
    }

    /// The network's input shape.
    pub fn shape(&self) -> &ActorShape {
        &self.shape
    }
}

impl Policy for LearnedPolicy {
    fn command(&mut self, history: &ObservationHistory) -> Result<(f64, f64)> {
        let Some(actor) = &mut self.actor else {
            // Train mode before the first weights: uniformly random commands.
            let action = [self.rng.random_range(-1.0..=1.0), self.rng.random_range(-1.0..=1.0)];
            return Ok(self.env.command_from_action(action));
        };
        if self.noise_std == 0.0 {
            return actor.command(history.as_flat(), &self.env);
        }
        // Exploring (train mode, whose actors output commands): Gaussian noise on the
        // normalised command, white or an AR(1) process of std `noise_std` (the innovation's
        // std keeps the process's own at `noise_std`).
        let carry = self.exploration.map_or(0.0, |e| e.carry());
        let normal = Normal::new(0.0, self.noise_std * (1.0 - carry * carry).sqrt())?;
        for noise in &mut self.noise {
            *noise = carry * *noise + normal.sample(&mut self.rng);
        }
        let outputs = actor.act(history.as_flat())?;
        let action = [0, 1].map(|k| (outputs[k] + self.noise[k] as f32).clamp(-1.0, 1.0));
        Ok(self.env.command_from_action(action))
    }

    fn version(&self) -> u32 {
        self.version
    }

    fn begin_episode(&mut self, episode: u32, explore: bool) {
        if let Some(exploration) = self.exploration {
            self.noise_std = if explore { exploration.std_at(episode) } else { 0.0 };
            // Coloured noise starts each episode from the process's stationary law.
            if exploration.carry() > 0.0 {
                let normal = Normal::new(0.0, self.noise_std).expect("a std >= 0");
                self.noise = [normal.sample(&mut self.rng), normal.sample(&mut self.rng)];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_model::actor::ActorHead;
    use rand::SeedableRng;

    /// The turn-rate noise of 20,000 exploring ticks of an actor whose outputs are all 0 (so the
    /// command is the noise alone), normalised by `w_max`.
    fn turn_noise(correlation_ticks: f64) -> Vec<f64> {
        let env = EnvConfig::default();
        let shape = ActorShape {
            obs_dim: 16,
            history: 1,
            hidden: vec![8],
            head: ActorHead::Command,
        };
        let exploration = Exploration {
            std_start: 0.2,
            std_end: 0.2,
            decay_episodes: 1,
            correlation_ticks,
        };
        let mut policy = LearnedPolicy::new(&env, shape.clone(), Some(exploration), StdRng::seed_from_u64(5));
        policy.load(&vec![0.0; shape.parameter_count()], 1).expect("weights");
        let history = ObservationHistory::new(1, 16);
        policy.begin_episode(0, true);
        (0..20_000)
            .map(|_| policy.command(&history).expect("a command").1 / env.w_max)
            .collect()
    }

    fn std_and_lag_one_correlation(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        let cov = xs.windows(2).map(|p| (p[0] - mean) * (p[1] - mean)).sum::<f64>() / (n - 1.0);
        (var.sqrt(), cov / var)
    }

    #[test]
    fn coloured_exploration_keeps_the_noise_std_and_carries_each_tick_over_to_the_next() {
        let (white_std, white_corr) = std_and_lag_one_correlation(&turn_noise(0.0));
        assert!((white_std - 0.2).abs() < 0.01, "white std {white_std}");
        assert!(white_corr.abs() < 0.03, "white noise is uncorrelated: {white_corr}");
        let (std, corr) = std_and_lag_one_correlation(&turn_noise(10.0));
        assert!((std - 0.2).abs() < 0.03, "coloured std {std}");
        let carry = (-0.1f64).exp();
        assert!(
            (corr - carry).abs() < 0.03,
            "lag-one correlation {corr}, expected {carry}"
        );
    }
}
