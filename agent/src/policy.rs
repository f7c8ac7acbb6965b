//! What drives a robot: the scripted baseline or the learned actor, behind one trait.

use anyhow::Result;
use formation_core::config::EnvConfig;
use formation_core::observation::Layout;
use formation_core::recovery::{ProgressChecker, Sensed};
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
    /// Std of the offset held at a stall (`learn.stall_noise_std`; 0: off).
    pub stall_std: f64,
    /// Ticks a stall's offset is held (`learn.stall_noise_ticks`).
    pub stall_ticks: u32,
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
    /// Whether this episode explores (train mode, not a noise-free evaluation episode).
    exploring: bool,
    /// Exploration at stalls ([`Exploration::stall_std`]).
    stall: StallBurst,
    rng: StdRng,
}

/// A robot's temporally extended exploration at stalls: its own progress checker over its
/// told observations, and the offset it holds while a burst lasts.
#[derive(Debug, Clone, Default)]
struct StallBurst {
    checker: ProgressChecker,
    offset: [f64; 2],
    left: u32,
    /// The forward speed it commanded last tick (its odometry for the checker), m/s.
    last_speed: f64,
    /// Bursts started so far.
    count: u64,
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
            exploring: exploration.is_some(),
            stall: StallBurst::default(),
            rng,
        }
    }

    /// The offset a stall adds to this tick's normalised command (zero outside a burst): a
    /// burst starts when the robot's progress checker finds it stalled in `told`, its newest
    /// observation, and holds one draw for [`Exploration::stall_ticks`].
    fn stall_offset(&mut self, told: &[f32]) -> Result<[f64; 2]> {
        let Some(exploration) = self.exploration.filter(|e| self.exploring && e.stall_std > 0.0) else {
            return Ok([0.0; 2]);
        };
        let burst = &mut self.stall;
        if burst.left > 0 {
            burst.left -= 1;
            return Ok(burst.offset);
        }
        let driven = burst.last_speed.abs() * self.env.dt_s;
        let layout = Layout::of(self.env.observation);
        let Some(sensed) = Sensed::told(layout, told, &self.env, driven) else {
            return Ok([0.0; 2]);
        };
        if !burst.checker.stalled(&sensed) {
            return Ok([0.0; 2]);
        }
        let normal = Normal::new(0.0, exploration.stall_std)?;
        burst.offset = [normal.sample(&mut self.rng), normal.sample(&mut self.rng)];
        burst.left = exploration.stall_ticks - 1;
        burst.count += 1;
        Ok(burst.offset)
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

    /// Stalls explored with a held offset so far ([`Exploration::stall_std`]).
    pub fn stall_bursts(&self) -> u64 {
        self.stall.count
    }
}

impl Policy for LearnedPolicy {
    fn command(&mut self, history: &ObservationHistory) -> Result<(f64, f64)> {
        if self.actor.is_none() {
            // Train mode before the first weights: uniformly random commands.
            let action = [self.rng.random_range(-1.0..=1.0), self.rng.random_range(-1.0..=1.0)];
            return Ok(self.env.command_from_action(action));
        }
        let stall = self.stall_offset(history.latest())?;
        let actor = self.actor.as_mut().expect("weights, checked above");
        if self.noise_std == 0.0 && stall == [0.0; 2] {
            let command = actor.command(history.as_flat(), &self.env)?;
            self.stall.last_speed = command.0;
            return Ok(command);
        }
        // Exploring (train mode, whose actors output commands): Gaussian noise on the
        // normalised command, white or an AR(1) process of std `noise_std` (the innovation's
        // std keeps the process's own at `noise_std`), plus a stall's held offset.
        let carry = self.exploration.map_or(0.0, |e| e.carry());
        let normal = Normal::new(0.0, self.noise_std * (1.0 - carry * carry).sqrt())?;
        for noise in &mut self.noise {
            *noise = carry * *noise + normal.sample(&mut self.rng);
        }
        let outputs = actor.act(history.as_flat())?;
        let action = [0, 1].map(|k| (outputs[k] + (self.noise[k] + stall[k]) as f32).clamp(-1.0, 1.0));
        let command = self.env.command_from_action(action);
        self.stall.last_speed = command.0;
        Ok(command)
    }

    fn version(&self) -> u32 {
        self.version
    }

    fn begin_episode(&mut self, episode: u32, explore: bool) {
        if let Some(exploration) = self.exploration {
            self.exploring = explore;
            self.stall.checker.clear();
            self.stall.left = 0;
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

    /// A command actor of one hidden layer of 8 reading one observation of `obs_dim` floats.
    fn small_actor(obs_dim: usize) -> ActorShape {
        ActorShape {
            obs_dim,
            history: 1,
            hidden: vec![8],
            head: ActorHead::Command,
        }
    }

    /// The turn-rate noise of 20,000 exploring ticks of an actor whose outputs are all 0 (so the
    /// command is the noise alone), normalised by `w_max`.
    fn turn_noise(correlation_ticks: f64) -> Vec<f64> {
        let env = EnvConfig::default();
        let shape = small_actor(16);
        let exploration = Exploration {
            std_start: 0.2,
            std_end: 0.2,
            decay_episodes: 1,
            correlation_ticks,
            stall_std: 0.0,
            stall_ticks: 30,
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

    /// A robot 5 m from its slot with a disc 0.2 m off its front left, standing still: what
    /// its progress checker finds stalled (the observation of `slot_proximity_scan`).
    fn stalled_observation(env: &EnvConfig) -> Vec<f32> {
        let layout = Layout::of(env.observation);
        let mut obs = vec![0.0f32; layout.dim()];
        for (k, x) in [(0, 3.0f32), (1, -3.0)] {
            obs[layout.neighbour(k)..layout.neighbour(k) + 5].copy_from_slice(&[x, 3.0, 1.0, 0.0, 1.0]);
        }
        obs[layout.goal()..layout.goal() + 2].copy_from_slice(&[5.0, 0.0]);
        let slot = layout.slot().expect("a slot");
        obs[slot..slot + 2].copy_from_slice(&[4.0, -3.0]);
        let scan = layout.scan().expect("a scan");
        obs[scan..scan + formation_core::observation::SCAN_RAYS].fill(1.0);
        obs[scan + 2] = (0.2 / env.scan_range_m) as f32;
        obs
    }

    #[test]
    fn a_stalled_exploring_robot_holds_one_drawn_offset_for_the_stall_ticks_then_checks_again() {
        use formation_core::config::ObservationModel;
        use formation_core::recovery::PROGRESS_WINDOW_TICKS;
        let env = EnvConfig {
            observation: ObservationModel::SlotProximityScan,
            ..EnvConfig::default()
        };
        let shape = small_actor(Layout::of(env.observation).dim());
        let exploration = Exploration {
            std_start: 0.0,
            std_end: 0.0,
            decay_episodes: 1,
            correlation_ticks: 0.0,
            stall_std: 0.5,
            stall_ticks: 20,
        };
        let obs = stalled_observation(&env);
        let mut policy = LearnedPolicy::new(&env, shape, Some(exploration), StdRng::seed_from_u64(9));
        policy.begin_episode(0, true);
        let offsets: Vec<[f64; 2]> = (0..PROGRESS_WINDOW_TICKS + 2 * 20)
            .map(|_| policy.stall_offset(&obs).expect("an offset"))
            .collect();
        let quiet = PROGRESS_WINDOW_TICKS - 1;
        assert!(
            offsets[..quiet].iter().all(|o| *o == [0.0; 2]),
            "no offset before a full window"
        );
        let burst = offsets[quiet];
        assert!(
            burst[0] != 0.0 && burst[1] != 0.0,
            "the stall draws an offset: {burst:?}"
        );
        assert!(
            offsets[quiet..quiet + 20].iter().all(|o| *o == burst),
            "held for the stall ticks"
        );
        assert!(
            offsets[quiet + 20..].iter().all(|o| *o == [0.0; 2]),
            "then a fresh window before the next stall"
        );
        assert_eq!(policy.stall_bursts(), 1);

        // A noise-free episode, or a robot that comes closer to its slot, never draws one.
        policy.begin_episode(1, false);
        assert!((0..2 * PROGRESS_WINDOW_TICKS).all(|_| policy.stall_offset(&obs).expect("an offset") == [0.0; 2]));
        policy.begin_episode(2, true);
        let slot = Layout::of(env.observation).slot().expect("a slot");
        let mut approaching = obs.clone();
        for t in 0..2 * PROGRESS_WINDOW_TICKS {
            approaching[slot] = 4.0 - 0.02 * t as f32;
            assert_eq!(policy.stall_offset(&approaching).expect("an offset"), [0.0; 2]);
        }
    }
}
