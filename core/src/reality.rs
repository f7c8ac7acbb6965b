//! The real world between the truth and the robots: sensor noise, lost messages, actuation
//! delay, motor lag and dying controllers (the `[reality]` section).
//!
//! The sim calls this between the true state and what it publishes ([`Reality::tell`],
//! [`Reality::observation_lost`]) and between the commands it received and the physics
//! ([`Reality::command_lost`], [`Reality::actuate`]). Robot processes stay generic: they read
//! what they are told. Everything is off by default ([`RealityConfig::default`]), which is the
//! ideal world: every function here is then the identity and draws no random number.
//!
//! Each key is a number or `[lo, hi]` ([`Spread`]), drawn uniformly per episode and robot (the
//! domain randomisation). Every draw comes from random streams of this module's own, seeded by
//! (seed, episode, robot) and a purpose, so switching reality on changes no start, goal or
//! shape, and a scripted and a learned run of one seed meet the same noise, the same losses and
//! the same failure. Each call draws a fixed number of values whatever the state it sees, so
//! the streams stay aligned between policies.

use std::collections::VecDeque;
use std::fmt;

use crate::config::{ConfigError, EnvConfig};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeSeq;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::observation::{Layout, Quantity};

/// The largest actuation delay accepted, ticks (the state message's room for queued commands).
pub const MAX_DELAY_TICKS: u32 = formation_protocol::MAX_DELAY_TICKS as u32;

/// A unicycle command or velocity: (linear m/s, angular rad/s).
pub type Command = (f64, f64);

/// A value fixed in the config (`0.05`) or drawn uniformly from `[lo, hi]` per episode and
/// robot (`[0.05, 0.1]`). A fixed value is `lo == hi`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// The low end (the value itself when fixed).
    pub lo: f64,
    /// The high end (the value itself when fixed).
    pub hi: f64,
}

impl Spread {
    /// Always `value`.
    pub const fn fixed(value: f64) -> Self {
        Self { lo: value, hi: value }
    }

    /// Uniform on `[lo, hi]`.
    pub const fn range(lo: f64, hi: f64) -> Self {
        Self { lo, hi }
    }

    /// Whether this is exactly zero (the key is off).
    pub fn is_off(&self) -> bool {
        self.lo == 0.0 && self.hi == 0.0
    }

    /// One value; draws from `rng` only when `lo < hi`.
    fn draw(&self, rng: &mut StdRng) -> f64 {
        if self.lo < self.hi {
            rng.random_range(self.lo..=self.hi)
        } else {
            self.lo
        }
    }

    /// One whole number of `[lo, hi]` (both validated as whole), uniform over them.
    fn draw_whole(&self, rng: &mut StdRng) -> u32 {
        // Validated whole numbers in 0..=MAX_DELAY_TICKS: the casts are exact.
        let (lo, hi) = (self.lo as u32, self.hi as u32);
        if lo < hi { rng.random_range(lo..=hi) } else { lo }
    }

    /// Refuses the spread unless both ends are finite, `lo <= hi`, and `ok` holds for both.
    fn check(&self, field: &'static str, ok: impl Fn(f64) -> bool, reason: &'static str) -> Result<(), ConfigError> {
        let invalid = |reason| {
            Err(ConfigError::Invalid {
                field,
                value: self.to_string(),
                reason,
            })
        };
        if !(self.lo.is_finite() && self.hi.is_finite()) {
            invalid("must be finite")
        } else if self.lo > self.hi {
            invalid("needs lo <= hi")
        } else if !(ok(self.lo) && ok(self.hi)) {
            invalid(reason)
        } else {
            Ok(())
        }
    }
}

impl Default for Spread {
    fn default() -> Self {
        Self::fixed(0.0)
    }
}

impl fmt::Display for Spread {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.lo == self.hi {
            write!(f, "{}", self.lo)
        } else {
            write!(f, "[{}, {}]", self.lo, self.hi)
        }
    }
}

impl Serialize for Spread {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        if self.lo == self.hi {
            serializer.serialize_f64(self.lo)
        } else {
            let mut seq = serializer.serialize_seq(Some(2))?;
            seq.serialize_element(&self.lo)?;
            seq.serialize_element(&self.hi)?;
            seq.end()
        }
    }
}

impl<'de> Deserialize<'de> for Spread {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct SpreadVisitor;

        impl<'de> Visitor<'de> for SpreadVisitor {
            type Value = Spread;

            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a number or a [lo, hi] pair of numbers")
            }

            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Spread, E> {
                Ok(Spread::fixed(v))
            }

            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Spread, E> {
                Ok(Spread::fixed(v as f64))
            }

            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Spread, E> {
                Ok(Spread::fixed(v as f64))
            }

            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Spread, A::Error> {
                let lo: f64 = seq.next_element()?.ok_or_else(|| de::Error::invalid_length(0, &self))?;
                let hi: f64 = seq.next_element()?.ok_or_else(|| de::Error::invalid_length(1, &self))?;
                if seq.next_element::<f64>()?.is_some() {
                    return Err(de::Error::invalid_length(3, &self));
                }
                Ok(Spread::range(lo, hi))
            }
        }

        deserializer.deserialize_any(SpreadVisitor)
    }
}

/// What a robot whose controller died, or that the sim found absent, does.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum DeadRobot {
    /// Brakes to rest within the acceleration limit and stays there (a motor watchdog).
    Stop,
    /// Keeps its last command (the ideal world's behaviour).
    #[default]
    Hold,
}

/// The `[reality]` section: the robots' own sensors, radio and motors. All off by default.
/// Unknown keys are rejected.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct RealityConfig {
    /// Standard deviation of the white Gaussian noise added each tick, independently on x and
    /// y, to every relative position a robot is told (neighbours, goal, slot, the proximity
    /// term's robot), metres.
    pub position_noise_m: Spread,
    /// Standard deviation of the noise on each neighbour's relative heading angle, radians.
    pub heading_noise_rad: Spread,
    /// The command in use at tick t drives the physics from tick t + d; whole ticks, 0..=10.
    pub actuation_delay_ticks: Spread,
    /// The acting linear velocity moves towards the delayed command at most this fast, m/s^2
    /// (0 = instant).
    pub max_linear_accel_mps2: Spread,
    /// The acting angular velocity moves towards the delayed command at most this fast,
    /// rad/s^2 (0 = instant).
    pub max_angular_accel_radps2: Spread,
    /// Probability that one command message is lost (independent per message), in [0, 1).
    pub command_loss: Spread,
    /// Probability that one observation message is lost (independent per message), in [0, 1).
    pub observation_loss: Spread,
    /// Probability per episode that one robot's controller dies at a drawn tick mid-episode
    /// (its commands are ignored from then on), in [0, 1].
    pub controller_failure: Spread,
    /// What a robot whose controller died, or that the sim found absent, does.
    pub dead_robot: DeadRobot,
    /// Standard deviation of the white Gaussian noise on each ray of a range sensor
    /// (`slot_proximity_scan`), metres; a noisy range stays in [0, `env.scan_range_m`].
    pub range_noise_m: Spread,
    /// Probability that one ray reads nothing (`env.scan_range_m`) at a tick, in [0, 1).
    pub range_dropout: Spread,
}

/// A file holding only a `[reality]` table (the presets `configs/reality-lab.toml` and
/// `configs/reality-field.toml`).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RealityFile {
    reality: RealityConfig,
}

impl RealityConfig {
    /// Parses a TOML document whose only table is `[reality]`, then validates it.
    pub fn from_toml_str(text: &str) -> Result<Self, ConfigError> {
        let file: RealityFile = toml::from_str(text).map_err(|err| ConfigError::Parse {
            path: "<string>".into(),
            message: err.to_string(),
        })?;
        file.reality.validate()?;
        Ok(file.reality)
    }

    /// Whether every effect is off: the ideal world (`dead_robot` then only matters for robots
    /// the sim finds absent).
    pub fn is_ideal(&self) -> bool {
        [
            self.position_noise_m,
            self.heading_noise_rad,
            self.actuation_delay_ticks,
            self.max_linear_accel_mps2,
            self.max_angular_accel_radps2,
            self.command_loss,
            self.observation_loss,
            self.controller_failure,
            self.range_noise_m,
            self.range_dropout,
        ]
        .iter()
        .all(Spread::is_off)
    }

    /// The section on one line, `key = value, ...` (how a checkpoint records the reality its
    /// selection episodes were played under).
    pub fn one_line(&self) -> String {
        toml::to_string(self)
            .unwrap_or_default()
            .lines()
            .filter(|line| !line.trim().is_empty())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Refuses out-of-range values, naming the field: noise >= 0, losses in [0, 1), failure in
    /// [0, 1], delays whole ticks in 0..=10, accelerations >= 0, and lo <= hi everywhere.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let non_negative = |v: f64| v >= 0.0;
        let loss = |v: f64| (0.0..1.0).contains(&v);
        self.position_noise_m
            .check("reality.position_noise_m", non_negative, "must be >= 0")?;
        self.heading_noise_rad
            .check("reality.heading_noise_rad", non_negative, "must be >= 0")?;
        self.actuation_delay_ticks.check(
            "reality.actuation_delay_ticks",
            |v| v.fract() == 0.0 && (0.0..=f64::from(MAX_DELAY_TICKS)).contains(&v),
            "must be whole ticks in 0..=10",
        )?;
        self.max_linear_accel_mps2.check(
            "reality.max_linear_accel_mps2",
            non_negative,
            "must be >= 0 (0 = instant)",
        )?;
        self.max_angular_accel_radps2.check(
            "reality.max_angular_accel_radps2",
            non_negative,
            "must be >= 0 (0 = instant)",
        )?;
        self.command_loss
            .check("reality.command_loss", loss, "must be a probability in [0, 1)")?;
        self.observation_loss
            .check("reality.observation_loss", loss, "must be a probability in [0, 1)")?;
        self.controller_failure.check(
            "reality.controller_failure",
            |v| (0.0..=1.0).contains(&v),
            "must be a probability in [0, 1]",
        )?;
        self.range_noise_m
            .check("reality.range_noise_m", non_negative, "must be >= 0")?;
        self.range_dropout
            .check("reality.range_dropout", loss, "must be a probability in [0, 1)")
    }
}

/// The purposes of the random streams: each has its own, so that how often one is used never
/// shifts another's draws.
#[derive(Debug, Clone, Copy)]
enum Stream {
    /// A robot's drawn parameters, once per episode.
    Parameters = 1,
    /// A robot's sensor noise.
    Sensing = 2,
    /// A robot's observation losses.
    ObservationRadio = 3,
    /// A robot's command losses.
    CommandRadio = 4,
    /// The episode's controller failure (robot index unused).
    Failure = 5,
    /// A robot's range sensor noise and dropouts.
    Ranging = 6,
}

/// The splitmix64 finaliser: a bijective mix of 64 bits.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The random stream of one purpose for (seed, episode, robot).
fn stream(seed: u64, episode: u64, robot: u64, purpose: Stream) -> StdRng {
    // A constant of this module's own, so no other stream seeded from `seed` coincides.
    let mut h = mix(seed ^ 0x7265_616c_6974_7921);
    for part in [episode, robot, purpose as u64] {
        h = mix(h ^ part);
    }
    StdRng::seed_from_u64(h)
}

/// One robot's motors: the delay line, then the acceleration limits.
#[derive(Debug, Clone)]
struct Actuator {
    /// The commands that will act next, oldest first; always `delay` long.
    queue: VecDeque<Command>,
    /// The velocity acting on the physics.
    acting: Command,
    /// The command in use at the last tick the controller was alive.
    last_alive: Command,
    /// Largest change of the acting linear velocity per tick, m/s (0 = instant).
    linear_step: f64,
    /// Largest change of the acting angular velocity per tick, rad/s (0 = instant).
    angular_step: f64,
}

/// Moves `current` towards `target` by at most `step` (0 = all the way).
fn approach(current: f64, target: f64, step: f64) -> f64 {
    let gap = target - current;
    // Within a step (and its rounding dust) the target itself is reached.
    if step <= 0.0 || gap.abs() <= step * (1.0 + 1e-12) {
        target
    } else {
        current + step.copysign(gap)
    }
}

impl Actuator {
    /// A robot at rest with `delay` ticks of rest queued.
    fn new(delay: u32, linear_step: f64, angular_step: f64) -> Self {
        let mut queue = VecDeque::with_capacity(delay as usize + 1);
        queue.extend(std::iter::repeat_n((0.0, 0.0), delay as usize));
        Self {
            queue,
            acting: (0.0, 0.0),
            last_alive: (0.0, 0.0),
            linear_step,
            angular_step,
        }
    }

    /// One tick: `in_use` enters the delay line and the oldest queued command is tracked; a
    /// braking robot tracks rest directly (its watchdog sits at the motors) and queues rest.
    /// `speed_cap` caps the forward speed tracked (a collision monitor at the motors; the
    /// queue keeps the commands as sent).
    fn step(&mut self, in_use: Command, brake: bool, speed_cap: f64) -> Command {
        let queued = if brake { (0.0, 0.0) } else { in_use };
        self.queue.push_back(queued);
        let delayed = self.queue.pop_front().unwrap_or(queued);
        let target = if brake {
            (0.0, 0.0)
        } else {
            (delayed.0.min(speed_cap), delayed.1)
        };
        self.acting = (
            approach(self.acting.0, target.0, self.linear_step),
            approach(self.acting.1, target.1, self.angular_step),
        );
        self.acting
    }
}

/// One robot's drawn reality for an episode.
#[derive(Debug, Clone)]
struct RobotReality {
    /// Position noise, None when off.
    position_noise: Option<Normal<f64>>,
    /// Heading noise, None when off.
    heading_noise: Option<Normal<f64>>,
    /// Probability that one observation is lost.
    observation_loss: f64,
    /// Probability that one command is lost.
    command_loss: f64,
    /// Range sensor noise, None when off.
    range_noise: Option<Normal<f64>>,
    /// Probability that one ray reads nothing.
    range_dropout: f64,
    ranging: StdRng,
    /// The drawn delay, ticks.
    delay: u32,
    actuator: Actuator,
    sensing: StdRng,
    observation_radio: StdRng,
    command_radio: StdRng,
}

/// A zero-mean Gaussian of standard deviation `sigma`, None when `sigma` is 0.
fn gaussian(sigma: f64) -> Option<Normal<f64>> {
    // Validated: sigma is finite and >= 0, which Normal accepts.
    (sigma > 0.0).then(|| Normal::new(0.0, sigma).ok()).flatten()
}

/// One robot's controller dies: from `tick` on, its commands are ignored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControllerFailure {
    /// The robot.
    pub agent: usize,
    /// The first tick at which its commands are ignored.
    pub tick: u32,
}

/// One episode's reality for every robot, drawn from a [`RealityConfig`].
#[derive(Debug, Clone)]
pub struct Reality {
    robots: Vec<RobotReality>,
    failure: Option<ControllerFailure>,
    dead_robot: DeadRobot,
    proximity_range_m: f64,
    scan_range_m: f64,
}

impl Reality {
    /// Draws episode `episode`'s reality for `n_agents` robots of a run seeded `seed`, with the
    /// tick length, episode length and proximity range of `env`. `config` must be validated.
    ///
    /// A controller failure (with probability `controller_failure`) hits a uniformly drawn
    /// robot at a tick drawn uniformly in `[max_steps / 4, max_steps / 2]`: mid-episode, while
    /// a typical episode's robots are still on their way.
    pub fn new(config: &RealityConfig, env: &EnvConfig, seed: u64, episode: u64, n_agents: usize) -> Self {
        let robots = (0..n_agents)
            .map(|agent| {
                let robot = agent as u64;
                let mut draw = stream(seed, episode, robot, Stream::Parameters);
                let position_sigma = config.position_noise_m.draw(&mut draw);
                let heading_sigma = config.heading_noise_rad.draw(&mut draw);
                let delay = config.actuation_delay_ticks.draw_whole(&mut draw);
                let linear_accel = config.max_linear_accel_mps2.draw(&mut draw);
                let angular_accel = config.max_angular_accel_radps2.draw(&mut draw);
                let observation_loss = config.observation_loss.draw(&mut draw);
                let command_loss = config.command_loss.draw(&mut draw);
                let range_sigma = config.range_noise_m.draw(&mut draw);
                let range_dropout = config.range_dropout.draw(&mut draw);
                RobotReality {
                    range_noise: gaussian(range_sigma),
                    range_dropout,
                    ranging: stream(seed, episode, robot, Stream::Ranging),
                    position_noise: gaussian(position_sigma),
                    heading_noise: gaussian(heading_sigma),
                    observation_loss,
                    command_loss,
                    delay,
                    actuator: Actuator::new(delay, linear_accel * env.dt_s, angular_accel * env.dt_s),
                    sensing: stream(seed, episode, robot, Stream::Sensing),
                    observation_radio: stream(seed, episode, robot, Stream::ObservationRadio),
                    command_radio: stream(seed, episode, robot, Stream::CommandRadio),
                }
            })
            .collect();
        let failure = if config.controller_failure.is_off() || n_agents == 0 {
            None
        } else {
            let mut draw = stream(seed, episode, 0, Stream::Failure);
            let p = config.controller_failure.draw(&mut draw);
            let fails = draw.random::<f64>() < p;
            let agent = draw.random_range(0..n_agents);
            let tick = draw.random_range(env.max_steps / 4..=env.max_steps / 2);
            fails.then_some(ControllerFailure { agent, tick })
        };
        Self {
            robots,
            failure,
            dead_robot: config.dead_robot,
            proximity_range_m: env.proximity_range_m,
            scan_range_m: env.scan_range_m,
        }
    }

    /// Adds robot `agent`'s sensor noise to `obs` (an observation of `layout`, in its frame),
    /// by what each float measures ([`Quantity`], declared by the layout's blocks): independent
    /// Gaussian noise on x and y of every position; noise on every relative heading angle
    /// (cos/sin recomputed); closeness terms recomputed from a noisy relative position. Other
    /// floats and those past the layout are untouched. With both noises off, `obs` is left as it
    /// is. Positions are drawn first, block by block, then headings, from one stream.
    ///
    /// A zero closeness term (no robot within range) stays zero: the true position behind it is
    /// unknown here, so noise cannot bring a robot from beyond the range into it. Range readings
    /// (normalised by `env.scan_range_m`) drop out to the full range or take Gaussian noise in
    /// metres, kept within [0, range], from a stream of their own.
    pub fn tell(&mut self, agent: usize, layout: Layout, obs: &mut [f32]) {
        self.tell_ranges(agent, layout, obs);
        let range = self.proximity_range_m;
        let robot = &mut self.robots[agent];
        let pairs = |kind: Quantity| {
            layout.kinds().flat_map(move |(offset, kinds)| {
                (0..kinds.len().saturating_sub(1))
                    .step_by(2)
                    .filter(move |&i| kinds[i] == kind && kinds[i + 1] == kind)
                    .map(move |i| offset + i)
            })
        };
        if let Some(noise) = robot.position_noise {
            let rng = &mut robot.sensing;
            for at in pairs(Quantity::Position) {
                for v in &mut obs[at..at + 2] {
                    *v = (f64::from(*v) + noise.sample(rng)) as f32;
                }
            }
            for at in pairs(Quantity::Closeness) {
                let near = [f64::from(obs[at]), f64::from(obs[at + 1])];
                let noisy = noisy_proximity(near, range, [noise.sample(rng), noise.sample(rng)]);
                obs[at..at + 2].copy_from_slice(&noisy.map(|v| v as f32));
            }
        }
        if let Some(noise) = robot.heading_noise {
            for at in pairs(Quantity::Heading) {
                let angle = f64::from(obs[at + 1]).atan2(f64::from(obs[at])) + noise.sample(&mut robot.sensing);
                let (s, c) = angle.sin_cos();
                obs[at..at + 2].copy_from_slice(&[c as f32, s as f32]);
            }
        }
    }

    /// Robot `agent`'s range sensor effects on the `Range` floats of `obs`.
    fn tell_ranges(&mut self, agent: usize, layout: Layout, obs: &mut [f32]) {
        let robot = &mut self.robots[agent];
        if robot.range_noise.is_none() && robot.range_dropout <= 0.0 {
            return;
        }
        let scale = self.scan_range_m;
        for (offset, kinds) in layout.kinds() {
            for (value, _) in obs[offset..offset + kinds.len()]
                .iter_mut()
                .zip(kinds)
                .filter(|(_, kind)| **kind == Quantity::Range)
            {
                if robot.range_dropout > 0.0 && robot.ranging.random::<f64>() < robot.range_dropout {
                    *value = 1.0;
                } else if let Some(noise) = robot.range_noise {
                    let metres = f64::from(*value) * scale + noise.sample(&mut robot.ranging);
                    *value = (metres / scale).clamp(0.0, 1.0) as f32;
                }
            }
        }
    }

    /// Whether the next observation sent to robot `agent` is lost (one draw per message).
    pub fn observation_lost(&mut self, agent: usize) -> bool {
        let robot = &mut self.robots[agent];
        robot.observation_loss > 0.0 && robot.observation_radio.random::<f64>() < robot.observation_loss
    }

    /// Whether the next command robot `agent` sends is lost (one draw per message).
    pub fn command_lost(&mut self, agent: usize) -> bool {
        let robot = &mut self.robots[agent];
        robot.command_loss > 0.0 && robot.command_radio.random::<f64>() < robot.command_loss
    }

    /// The episode's controller failure, if one was drawn.
    pub fn failure(&self) -> Option<ControllerFailure> {
        self.failure
    }

    /// Whether robot `agent`'s controller is dead at `tick` (its commands are ignored).
    pub fn controller_failed(&self, agent: usize, tick: u32) -> bool {
        self.failure.is_some_and(|f| f.agent == agent && tick >= f.tick)
    }

    /// Robot `agent`'s motors for tick `tick`, given the command in use (the sim's accounting
    /// decides which) and whether the sim found its controller present: returns the velocity
    /// acting on the physics. A dead controller (failed, or `present` false) is handled as
    /// `dead_robot` says: `Hold` keeps the last command in use while alive, `Stop` brakes to
    /// rest within the acceleration limit. Otherwise the command enters the delay line and the
    /// acting velocity moves towards the command of `delay` ticks before, within the limits.
    /// With every key off this returns `in_use` unchanged.
    pub fn actuate(&mut self, agent: usize, tick: u32, in_use: Command, present: bool) -> Command {
        self.actuate_within(agent, tick, in_use, present, f64::INFINITY)
    }

    /// [`Reality::actuate`] with the forward speed the motors track capped at `speed_cap`, m/s:
    /// what a collision monitor at the motors allows this tick.
    pub fn actuate_within(
        &mut self,
        agent: usize,
        tick: u32,
        in_use: Command,
        present: bool,
        speed_cap: f64,
    ) -> Command {
        let dead = !present || self.controller_failed(agent, tick);
        let actuator = &mut self.robots[agent].actuator;
        if dead {
            match self.dead_robot {
                DeadRobot::Hold => {
                    let last = actuator.last_alive;
                    actuator.step(last, false, speed_cap)
                }
                DeadRobot::Stop => actuator.step((0.0, 0.0), true, speed_cap),
            }
        } else {
            actuator.last_alive = in_use;
            actuator.step(in_use, false, speed_cap)
        }
    }

    /// The velocity acting on robot `agent`'s physics since the last [`Reality::actuate`].
    pub fn acting(&self, agent: usize) -> Command {
        self.robots[agent].actuator.acting
    }

    /// Robot `agent`'s drawn actuation delay, ticks.
    pub fn delay(&self, agent: usize) -> u32 {
        self.robots[agent].delay
    }

    /// Robot `agent`'s drawn position noise (standard deviation, metres; 0 when off): what a
    /// privileged teacher may know of the episode (`formation_critic::distill`).
    pub fn position_noise_m(&self, agent: usize) -> f64 {
        self.robots[agent].position_noise.map_or(0.0, |normal| normal.std_dev())
    }

    /// The commands queued at robot `agent`'s motors, the next to act first (`delay` of them):
    /// with the acting velocity, what the critic needs to stay Markov under delay and lag.
    pub fn queued(&self, agent: usize) -> impl ExactSizeIterator<Item = Command> + '_ {
        self.robots[agent].actuator.queue.iter().copied()
    }
}

/// The proximity term `near` = (1 - d/R) * unit vector (zero beyond R) recomputed after adding
/// `noise` to the relative position it stands for. Zero stays zero.
fn noisy_proximity(near: [f64; 2], range: f64, noise: [f64; 2]) -> [f64; 2] {
    let closeness = near[0].hypot(near[1]);
    if closeness <= 0.0 {
        return [0.0, 0.0];
    }
    let distance = (1.0 - closeness) * range;
    let rel = [
        near[0] / closeness * distance + noise[0],
        near[1] / closeness * distance + noise[1],
    ];
    let d = rel[0].hypot(rel[1]);
    if d >= range {
        [0.0, 0.0]
    } else if d <= 1e-9 {
        // On top of the robot: as close as it gets, in the direction it was seen.
        [near[0] / closeness, near[1] / closeness]
    } else {
        let weight = (1.0 - d / range) / d;
        [rel[0] * weight, rel[1] * weight]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ObservationModel;
    use formation_protocol::{MAX_OBS_DIM, NEIGHBOURS};

    fn env() -> EnvConfig {
        EnvConfig::default()
    }

    fn reality(config: &RealityConfig, n: usize) -> Reality {
        config.validate().expect("valid config");
        Reality::new(config, &env(), 7, 3, n)
    }

    /// A plausible slot_proximity observation with every float distinct; zeros past `dim`.
    fn observation() -> [f32; MAX_OBS_DIM] {
        let layout = Layout::of(ObservationModel::SlotProximity);
        let mut obs = [0.0f32; MAX_OBS_DIM];
        let heading = [0.3f32.cos(), 0.3f32.sin(), (-2.0f32).cos(), (-2.0f32).sin()];
        obs[..layout.dim()].copy_from_slice(&[
            0.8, 0.6, heading[0], heading[1], 1.0, //
            -0.4, 0.9, heading[2], heading[3], 1.1, //
            3.0, -1.5, 2.5, -1.0, 0.3, 0.4,
        ]);
        obs
    }

    #[test]
    fn all_off_is_the_identity() {
        let config = RealityConfig::default();
        let mut reality = reality(&config, 5);
        assert_eq!(reality.failure(), None);
        let mut rng = StdRng::seed_from_u64(1);
        for tick in 0..200 {
            for agent in 0..5 {
                for model in [
                    ObservationModel::Paper,
                    ObservationModel::Slot,
                    ObservationModel::SlotProximity,
                ] {
                    let truth = observation();
                    let mut told = truth;
                    reality.tell(agent, Layout::of(model), &mut told);
                    assert_eq!(told.map(f32::to_bits), truth.map(f32::to_bits));
                }
                assert!(!reality.observation_lost(agent) && !reality.command_lost(agent));
                assert!(!reality.controller_failed(agent, tick));
                let command = (rng.random_range(0.0..0.5), rng.random_range(-1.0..1.0));
                assert_eq!(reality.actuate(agent, tick, command, true), command);
                assert_eq!(reality.acting(agent), command);
                assert_eq!(reality.queued(agent).len(), 0);
            }
        }
    }

    #[test]
    fn a_delay_of_two_ticks_acts_the_command_of_two_ticks_before() {
        let config = RealityConfig {
            actuation_delay_ticks: Spread::range(2.0, 2.0),
            ..RealityConfig::default()
        };
        let mut reality = reality(&config, 3);
        let commands: Vec<Command> = (0..30).map(|t| (0.01 * t as f64, 0.1 - 0.02 * t as f64)).collect();
        for (tick, &command) in commands.iter().enumerate() {
            let acting = reality.actuate(1, tick as u32, command, true);
            let expected = if tick >= 2 { commands[tick - 2] } else { (0.0, 0.0) };
            assert_eq!(acting, expected, "tick {tick}");
            let queued: Vec<Command> = reality.queued(1).collect();
            let next = [tick.checked_sub(1).map_or((0.0, 0.0), |t| commands[t]), command];
            assert_eq!(queued, next, "tick {tick}: the next two to act, oldest first");
        }
        assert_eq!(reality.delay(1), 2);
    }

    #[test]
    fn the_acceleration_limit_bounds_the_change_per_tick() {
        let (linear, angular) = (1.0, 3.0);
        let config = RealityConfig {
            max_linear_accel_mps2: Spread::fixed(linear),
            max_angular_accel_radps2: Spread::fixed(angular),
            ..RealityConfig::default()
        };
        let env = env();
        let mut reality = reality(&config, 2);
        let mut rng = StdRng::seed_from_u64(2);
        let mut before = (0.0, 0.0);
        let (mut saturated_v, mut saturated_w) = (0, 0);
        for tick in 0..500 {
            let command = (
                rng.random_range(0.0..env.v_max),
                rng.random_range(-env.w_max..env.w_max),
            );
            let acting = reality.actuate(0, tick, command, true);
            let (dv, dw) = ((acting.0 - before.0).abs(), (acting.1 - before.1).abs());
            assert!(dv <= linear * env.dt_s + 1e-12, "tick {tick}: dv {dv}");
            assert!(dw <= angular * env.dt_s + 1e-12, "tick {tick}: dw {dw}");
            saturated_v += usize::from(dv > linear * env.dt_s - 1e-12);
            saturated_w += usize::from(dw > angular * env.dt_s - 1e-12);
            before = acting;
        }
        assert!(
            saturated_v > 50 && saturated_w > 50,
            "the limit was reached: {saturated_v}, {saturated_w}"
        );
        // A held command is reached and then tracked exactly.
        for tick in 500..520 {
            reality.actuate(0, tick, (0.25, -0.5), true);
        }
        assert_eq!(reality.acting(0), (0.25, -0.5));
    }

    #[test]
    fn loss_counts_lie_within_four_sigma_of_p_times_messages() {
        let (p_command, p_observation) = (0.05, 0.2);
        let config = RealityConfig {
            command_loss: Spread::fixed(p_command),
            observation_loss: Spread::fixed(p_observation),
            ..RealityConfig::default()
        };
        let (n, ticks) = (12, 1000);
        let mut reality = reality(&config, n);
        let (mut commands, mut observations) = (0usize, 0usize);
        for _ in 0..ticks {
            for agent in 0..n {
                commands += usize::from(reality.command_lost(agent));
                observations += usize::from(reality.observation_lost(agent));
            }
        }
        let messages = (n * ticks) as f64;
        for (lost, p, what) in [
            (commands, p_command, "commands"),
            (observations, p_observation, "observations"),
        ] {
            let sigma = (messages * p * (1.0 - p)).sqrt();
            let off = (lost as f64 - messages * p).abs();
            assert!(
                off <= 4.0 * sigma,
                "{what}: {lost} lost of {messages}, p {p}, sigma {sigma}"
            );
        }
    }

    /// Sample mean and standard deviation.
    fn moments(samples: &[f64]) -> (f64, f64) {
        let n = samples.len() as f64;
        let mean = samples.iter().sum::<f64>() / n;
        let var = samples.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / (n - 1.0);
        (mean, var.sqrt())
    }

    #[test]
    fn noise_spread_matches_the_configured_sigma_and_leaves_the_rest_alone() {
        let (sigma, heading_sigma) = (0.05, 0.08);
        let config = RealityConfig {
            position_noise_m: Spread::fixed(sigma),
            heading_noise_rad: Spread::fixed(heading_sigma),
            ..RealityConfig::default()
        };
        let layout = Layout::of(ObservationModel::SlotProximity);
        let mut reality = reality(&config, 3);
        let truth = observation();
        let positions = [
            layout.neighbour(0),
            layout.neighbour(1),
            layout.goal(),
            layout.slot().expect("slot"),
        ];
        let mut errors: Vec<Vec<f64>> = vec![Vec::new(); positions.len() * 2 + NEIGHBOURS];
        let mut proximity_distance = Vec::new();
        let range = env().proximity_range_m;
        for _ in 0..20_000 {
            let mut told = truth;
            reality.tell(2, layout, &mut told);
            for (i, &at) in positions.iter().enumerate() {
                for axis in 0..2 {
                    errors[2 * i + axis].push(f64::from(told[at + axis]) - f64::from(truth[at + axis]));
                }
            }
            for k in 0..NEIGHBOURS {
                let at = layout.neighbour(k) + 2;
                let (c, s) = (f64::from(told[at]), f64::from(told[at + 1]));
                assert!((c.hypot(s) - 1.0).abs() < 1e-6, "cos/sin of an angle");
                let truth_angle = f64::from(truth[at + 1]).atan2(f64::from(truth[at]));
                let diff = s.atan2(c) - truth_angle;
                errors[positions.len() * 2 + k].push(diff.sin().atan2(diff.cos()));
                assert_eq!(told[at + 2], truth[at + 2], "desired distance untouched");
            }
            assert!(
                told[layout.dim()..].iter().all(|&v| v == 0.0),
                "nothing past the layout"
            );
            let at = layout.proximity().expect("proximity");
            let closeness = f64::from(told[at]).hypot(f64::from(told[at + 1]));
            proximity_distance.push((1.0 - closeness) * range);
        }
        for (i, samples) in errors.iter().enumerate() {
            let want = if i < positions.len() * 2 { sigma } else { heading_sigma };
            let (mean, sd) = moments(samples);
            assert!(mean.abs() < 0.05 * want, "component {i}: mean {mean}");
            assert!(
                (sd / want - 1.0).abs() < 0.05,
                "component {i}: sd {sd}, configured {want}"
            );
        }
        // The proximity term stands for a robot 0.5 m away: its noisy distance spreads by
        // about sigma along the line of sight.
        let (mean, sd) = moments(&proximity_distance);
        let true_distance = (1.0 - 0.5) * range;
        assert!((mean - true_distance).abs() < 0.01, "mean distance {mean}");
        assert!((sd / sigma - 1.0).abs() < 0.1, "distance sd {sd}");
    }

    /// The noise reaches a float by the kind its block declares: in every model, position
    /// noise moves positions and closeness terms only, heading noise headings only; a desired
    /// distance never moves.
    #[test]
    fn noise_follows_each_float_s_declared_kind_in_every_model() {
        let position_only = RealityConfig {
            position_noise_m: Spread::fixed(0.05),
            ..RealityConfig::default()
        };
        let heading_only = RealityConfig {
            heading_noise_rad: Spread::fixed(0.08),
            ..RealityConfig::default()
        };
        for model in crate::observation::MODELS {
            let layout = Layout::of(model);
            let mut kind_of = vec![None; layout.dim()];
            for (offset, kinds) in layout.kinds() {
                for (i, &kind) in kinds.iter().enumerate() {
                    assert!(
                        kind_of[offset + i].is_none(),
                        "{model:?}: float {} in two blocks",
                        offset + i
                    );
                    kind_of[offset + i] = Some(kind);
                }
            }
            assert!(
                kind_of.iter().all(Option::is_some),
                "{model:?}: the blocks cover every float"
            );
            for (config, moved) in [
                (&position_only, [Quantity::Position, Quantity::Closeness]),
                (&heading_only, [Quantity::Heading, Quantity::Heading]),
            ] {
                let mut reality = reality(config, 3);
                let mut truth = observation();
                truth[layout.dim()..].fill(0.0);
                let mut changed = vec![false; layout.dim()];
                for _ in 0..50 {
                    let mut told = truth;
                    reality.tell(1, layout, &mut told);
                    for (i, flag) in changed.iter_mut().enumerate() {
                        *flag |= told[i] != truth[i];
                    }
                    assert!(
                        told[layout.dim()..].iter().all(|&v| v == 0.0),
                        "nothing past the layout"
                    );
                }
                for (i, kind) in kind_of.iter().enumerate() {
                    let kind = kind.expect("covered");
                    assert_eq!(
                        changed[i],
                        moved.contains(&kind),
                        "{model:?}: float {i} ({kind:?}) under {config:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_zero_proximity_term_stays_zero_and_a_noisy_one_stays_in_range() {
        assert_eq!(noisy_proximity([0.0, 0.0], 1.0, [0.3, -0.2]), [0.0, 0.0]);
        // 0.9 m away, pushed 0.2 m further: beyond the 1 m range.
        assert_eq!(noisy_proximity([0.1, 0.0], 1.0, [0.2, 0.0]), [0.0, 0.0]);
        // 0.5 m ahead, pushed 0.1 m to the left.
        let near = noisy_proximity([0.5, 0.0], 1.0, [0.0, 0.1]);
        let d = 0.5f64.hypot(0.1);
        assert!((near[0] - (1.0 - d) * 0.5 / d).abs() < 1e-12 && (near[1] - (1.0 - d) * 0.1 / d).abs() < 1e-12);
        // Without noise the term is reproduced.
        let same = noisy_proximity([0.3, -0.4], 1.0, [0.0, 0.0]);
        assert!(
            (same[0] - 0.3).abs() < 1e-12 && (same[1] + 0.4).abs() < 1e-12,
            "{same:?}"
        );
    }

    fn refused(toml_text: &str) -> String {
        match RealityConfig::from_toml_str(&format!("[reality]\n{toml_text}\n")) {
            Ok(config) => panic!("{toml_text} accepted: {config:?}"),
            Err(err) => err.to_string(),
        }
    }

    #[test]
    fn out_of_range_values_are_refused_naming_the_field() {
        for (text, field) in [
            ("position_noise_m = -0.01", "reality.position_noise_m"),
            ("position_noise_m = [0.1, 0.05]", "reality.position_noise_m"),
            ("heading_noise_rad = [-0.1, 0.1]", "reality.heading_noise_rad"),
            ("actuation_delay_ticks = 1.5", "reality.actuation_delay_ticks"),
            ("actuation_delay_ticks = [0, 11]", "reality.actuation_delay_ticks"),
            ("actuation_delay_ticks = [3, 1]", "reality.actuation_delay_ticks"),
            ("actuation_delay_ticks = -1", "reality.actuation_delay_ticks"),
            ("max_linear_accel_mps2 = -1.0", "reality.max_linear_accel_mps2"),
            ("max_angular_accel_radps2 = [-3, 3]", "reality.max_angular_accel_radps2"),
            ("command_loss = 1.0", "reality.command_loss"),
            ("observation_loss = -0.1", "reality.observation_loss"),
            ("controller_failure = 1.5", "reality.controller_failure"),
            ("position_noise_m = nan", "reality.position_noise_m"),
        ] {
            let message = refused(text);
            assert!(message.contains(field), "{text}: {message}");
        }
        // Parse errors name the key too.
        for (text, key) in [
            ("dead_robot = \"brake\"", "dead_robot"),
            ("command_loss = [0.1, 0.2, 0.3]", "command_loss"),
            ("command_loss = \"high\"", "command_loss"),
            ("motor_lag = 1.0", "motor_lag"),
        ] {
            let message = refused(text);
            assert!(message.contains(key), "{text}: {message}");
        }
        // The edges that are allowed.
        let config = RealityConfig::from_toml_str(
            "[reality]\nactuation_delay_ticks = [0, 10]\ncontroller_failure = 1\ncommand_loss = 0.999\n\
             dead_robot = \"stop\"",
        )
        .expect("edges are valid");
        assert_eq!(config.actuation_delay_ticks, Spread::range(0.0, 10.0));
        assert_eq!(config.controller_failure, Spread::fixed(1.0));
        assert_eq!(config.dead_robot, DeadRobot::Stop);
    }

    #[test]
    fn config_round_trips_with_numbers_and_ranges() {
        let config = RealityConfig {
            position_noise_m: Spread::range(0.05, 0.08),
            actuation_delay_ticks: Spread::fixed(2.0),
            dead_robot: DeadRobot::Stop,
            ..RealityConfig::default()
        };
        #[derive(Serialize)]
        struct File<'a> {
            reality: &'a RealityConfig,
        }
        let text = toml::to_string(&File { reality: &config }).expect("serialises");
        assert!(text.contains("position_noise_m = [0.05, 0.08]"), "{text}");
        assert_eq!(RealityConfig::from_toml_str(&text).expect("parses"), config);
        assert_eq!(
            RealityConfig::default().dead_robot,
            DeadRobot::Hold,
            "today's behaviour"
        );
    }

    /// Everything a robot's streams give for a few ticks.
    fn draws(reality: &mut Reality, agent: usize) -> Vec<f64> {
        let layout = Layout::of(ObservationModel::SlotProximity);
        let mut out = vec![f64::from(reality.delay(agent))];
        for tick in 0..20 {
            let mut obs = observation();
            reality.tell(agent, layout, &mut obs);
            out.extend(obs.iter().map(|&v| f64::from(v)));
            out.push(f64::from(u8::from(reality.observation_lost(agent))));
            out.push(f64::from(u8::from(reality.command_lost(agent))));
            let acting = reality.actuate(agent, tick, (0.5, 1.0), true);
            out.extend([acting.0, acting.1]);
        }
        out
    }

    #[test]
    fn one_seed_episode_and_robot_give_the_same_draws_and_another_robot_others() {
        let config = RealityConfig {
            position_noise_m: Spread::range(0.02, 0.08),
            heading_noise_rad: Spread::fixed(0.05),
            actuation_delay_ticks: Spread::range(0.0, 10.0),
            max_linear_accel_mps2: Spread::range(0.5, 1.0),
            max_angular_accel_radps2: Spread::range(1.0, 3.0),
            command_loss: Spread::range(0.1, 0.3),
            observation_loss: Spread::range(0.1, 0.3),
            controller_failure: Spread::fixed(1.0),
            dead_robot: DeadRobot::Stop,
            range_noise_m: Spread::fixed(0.05),
            range_dropout: Spread::fixed(0.05),
        };
        config.validate().expect("valid");
        let env = env();
        let n = 16;
        let run = |seed, episode, agent| draws(&mut Reality::new(&config, &env, seed, episode, n), agent);
        assert_eq!(run(5, 2, 3), run(5, 2, 3));
        assert_ne!(run(5, 2, 3), run(5, 2, 4), "another robot");
        assert_ne!(run(5, 2, 3), run(5, 3, 3), "another episode");
        assert_ne!(run(5, 2, 3), run(6, 2, 3), "another seed");
        // One robot's stream does not depend on how many robots there are or on others' use.
        let mut alone = Reality::new(&config, &env, 5, 2, 4);
        assert_eq!(draws(&mut alone, 3), run(5, 2, 3));
        // Ranges are drawn per robot, within their ends.
        let reality = Reality::new(&config, &env, 5, 2, 64);
        let delays: Vec<u32> = (0..64).map(|a| reality.delay(a)).collect();
        assert!(delays.iter().all(|&d| d <= 10), "{delays:?}");
        assert!(delays.iter().any(|&d| d != delays[0]), "{delays:?}");
        // The failure is the same for one (seed, episode), drawn mid-episode.
        let failure = reality.failure().expect("controller_failure = 1 always fails");
        assert_eq!(Reality::new(&config, &env, 5, 2, 64).failure(), Some(failure));
        assert!(failure.agent < 64);
        assert!(
            (env.max_steps / 4..=env.max_steps / 2).contains(&failure.tick),
            "{failure:?}"
        );
    }

    #[test]
    fn a_failed_controller_with_stop_brakes_to_rest_within_the_limit_and_stays() {
        let accel = 1.0;
        let config = RealityConfig {
            max_linear_accel_mps2: Spread::fixed(accel),
            max_angular_accel_radps2: Spread::fixed(3.0),
            actuation_delay_ticks: Spread::fixed(1.0),
            controller_failure: Spread::fixed(1.0),
            dead_robot: DeadRobot::Stop,
            ..RealityConfig::default()
        };
        let env = env();
        let mut reality = reality(&config, 3);
        let failure = reality.failure().expect("fails");
        let top = (env.v_max, env.w_max);
        let mut before = (0.0, 0.0);
        let mut at_rest = None;
        for tick in 0..env.max_steps {
            let acting = reality.actuate(failure.agent, tick, top, true);
            if tick < failure.tick {
                assert!(!reality.controller_failed(failure.agent, tick));
            } else {
                assert!(reality.controller_failed(failure.agent, tick));
                assert!(acting.0 <= before.0 && (acting.0 - before.0).abs() <= accel * env.dt_s + 1e-12);
                if acting == (0.0, 0.0) {
                    at_rest.get_or_insert(tick);
                } else {
                    assert!(at_rest.is_none(), "stays at rest once there");
                }
            }
            before = acting;
        }
        let stopped = at_rest.expect("comes to rest");
        let seconds = f64::from(stopped + 1 - failure.tick) * env.dt_s;
        assert!(seconds <= env.v_max / accel + 1e-9, "rest after {seconds} s");
        // The other robots are untouched by it.
        let other = (failure.agent + 1) % 3;
        assert!(!reality.controller_failed(other, env.max_steps));
    }

    #[test]
    fn a_dead_robot_with_hold_keeps_its_last_command() {
        let config = RealityConfig {
            actuation_delay_ticks: Spread::fixed(2.0),
            ..RealityConfig::default()
        };
        let mut reality = reality(&config, 2);
        for tick in 0..5 {
            reality.actuate(0, tick, (0.3, 0.2), true);
        }
        // The sim finds it absent: the commands it may still pass are ignored.
        for tick in 5..10 {
            assert_eq!(reality.actuate(0, tick, (0.0, -1.0), false), (0.3, 0.2));
        }
    }

    #[test]
    fn the_presets_parse_validate_and_the_field_one_is_as_harsh_as_the_issue_asks() {
        let lab = RealityConfig::from_toml_str(include_str!("../../configs/reality-lab.toml")).expect("lab");
        let field = RealityConfig::from_toml_str(include_str!("../../configs/reality-field.toml")).expect("field");
        // Mild ends: the low end of noise, delay and loss, the high end of the accelerations.
        assert!(field.position_noise_m.lo >= 0.05 && field.heading_noise_rad.lo >= 0.05);
        assert!(field.actuation_delay_ticks.lo >= 1.0 && field.actuation_delay_ticks.hi >= 3.0);
        assert!(field.command_loss.lo >= 0.05 && field.observation_loss.lo >= 0.05);
        for (accel, top) in [
            (field.max_linear_accel_mps2, 1.0),
            (field.max_angular_accel_radps2, 3.0),
        ] {
            assert!(accel.lo > 0.0 && accel.hi <= top, "{accel}");
        }
        // The lab is milder than the field on every key.
        assert!(lab.position_noise_m.hi < field.position_noise_m.lo);
        assert!(lab.heading_noise_rad.hi < field.heading_noise_rad.lo);
        assert!(lab.actuation_delay_ticks.hi <= field.actuation_delay_ticks.lo);
        assert!(lab.command_loss.hi < field.command_loss.lo && lab.observation_loss.hi < field.observation_loss.lo);
        assert!(lab.max_linear_accel_mps2.lo > field.max_linear_accel_mps2.hi);
        assert!(lab.max_angular_accel_radps2.lo > field.max_angular_accel_radps2.hi);
        // Neither is the ideal world; the default is, whatever robots do when found absent.
        assert!(!lab.is_ideal() && !field.is_ideal());
        assert!(RealityConfig::default().is_ideal());
        let stopping = RealityConfig {
            dead_robot: DeadRobot::Stop,
            ..RealityConfig::default()
        };
        assert!(stopping.is_ideal());
        assert!(
            !RealityConfig {
                controller_failure: Spread::fixed(0.1),
                ..RealityConfig::default()
            }
            .is_ideal()
        );
        // On one line, every key as the preset gives it.
        let line = field.one_line();
        assert!(!line.contains('\n'), "{line}");
        for key in [
            "position_noise_m = [0.05, 0.1]",
            "actuation_delay_ticks = [1.0, 3.0]",
            "dead_robot = \"stop\"",
        ] {
            assert!(line.contains(key), "{key} in {line}");
        }
    }
}
