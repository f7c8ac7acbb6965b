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
}

impl Exploration {
    /// Noise std in `episode`.
    pub fn std_at(&self, episode: u32) -> f64 {
        let progress = (f64::from(episode) / f64::from(self.decay_episodes.max(1))).min(1.0);
        self.std_start + (self.std_end - self.std_start) * progress
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
        // normalised command.
        let outputs = actor.act(history.as_flat())?;
        let normal = Normal::new(0.0, self.noise_std as f32)?;
        let action = [outputs[0], outputs[1]].map(|a| (a + normal.sample(&mut self.rng)).clamp(-1.0, 1.0));
        Ok(self.env.command_from_action(action))
    }

    fn version(&self) -> u32 {
        self.version
    }

    fn begin_episode(&mut self, episode: u32, explore: bool) {
        if let Some(exploration) = self.exploration {
            self.noise_std = if explore { exploration.std_at(episode) } else { 0.0 };
        }
    }
}
