//! Assembles the sim's state stream into whole episodes of joint ticks, and counts what went
//! missing.
//!
//! State(t) carries what every robot was told at tick t (its observation after the sensor
//! noise of `[reality]`, the one the sim published on its `obs/i` stream, or would have when
//! it was lost), so the actor trains on what robots see; the critic does not subscribe to the
//! observation streams. The sim waits for commands(t) before it publishes state(t+1), which
//! carries the command in use for that transition (the robot's answer to tick t when on time,
//! else the one the accounting rule kept or took up late; clamped): the replay's action. So the
//! critic does not subscribe to the command streams either. Each state becomes one replay
//! tick, the sim's [`formation_core::scene::Scene`] of that tick with the commands and the reward of the transition
//! into it.

use anyhow::{Context, Result};
use formation_core::config::EnvConfig;
use formation_core::mission::observed_robots;
use formation_core::obstacles::Obstacles;
use formation_core::physics::Pose;
use formation_core::task::Outcome;
use formation_ipc::services::{self, FileDescriptorBased, Sizing};
use formation_protocol::NEIGHBOURS;
use formation_protocol::wire::*;
use formation_replay::buffer::{Episode, Formation, Tick};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

/// Counters of the stream.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct CollectorStats {
    /// State messages taken in (one per tick).
    pub ticks_received: u64,
    /// Ticks that could not be used whole (a gap in the stream, an unknown outcome).
    pub lost_transitions: u64,
    /// The sim announced the end of the run.
    pub run_ended: bool,
    /// `StateMsg::sequence` of the latest state taken in.
    pub latest_sequence: Option<u64>,
}

impl CollectorStats {
    /// The state sequence the critic may acknowledge: the latest it has read, less the ticks
    /// read but not yet paid for by updates (`paid_ticks` of `ticks_received`). Counting back
    /// from the latest, not forward from the first, keeps states lost in a gap (a critic that
    /// fell behind) from being owed forever, which would hold the sim at its window for good.
    pub fn acknowledgeable(&self, paid_ticks: u64) -> u64 {
        let unpaid = self.ticks_received.saturating_sub(paid_ticks);
        self.latest_sequence
            .map_or(0, |last| last.min((last + 1).saturating_sub(unpaid)))
    }
}

/// An episode as it ended.
#[derive(Debug, Clone)]
pub struct FinishedEpisode {
    /// Its ticks.
    pub episode: Episode,
    /// How its last transition ended.
    pub outcome: Outcome,
    /// Undiscounted return.
    pub episode_return: f64,
    /// Played without exploration noise.
    pub eval: bool,
}

struct EpisodeBuilder {
    episode: Episode,
    last_tick: u32,
    episode_return: f64,
    eval: bool,
}

/// The critic's subscriptions.
pub struct Collector<S: Service> {
    state: Subscriber<S, StateMsg, ()>,
    obstacles: Subscriber<S, ObstaclesMsg, ()>,
    wake: Listener<S>,
    /// The run's task (an episode's arena and, without obstacles, its time limit).
    env: EnvConfig,
    /// The latest episode's obstacles: its number, the obstacles and its time limit.
    latest_obstacles: Option<(u32, Obstacles, u32)>,
    current: Option<EpisodeBuilder>,
    /// Counters so far.
    pub stats: CollectorStats,
}

impl<S: Service> Collector<S>
where
    Listener<S>: FileDescriptorBased,
{
    /// Subscribes to the state stream and the episodes' obstacles of a run of `env`.
    pub fn new(node: &Node<S>, sizing: &Sizing, env: &EnvConfig) -> Result<Self> {
        Ok(Self {
            state: services::state_stream(node, sizing)?
                .subscriber_builder()
                .buffer_size(sizing.stream_buffer)
                .create()
                .context("critic: state subscriber")?,
            obstacles: services::obstacles_stream(node, sizing)?
                .subscriber_builder()
                .create()
                .context("critic: obstacles subscriber")?,
            env: env.clone(),
            latest_obstacles: None,
            wake: services::critic_wake_event(node, sizing)?
                .listener_builder()
                .create()
                .context("critic: wake listener")?,
            current: None,
            stats: CollectorStats::default(),
        })
    }

    /// Blocks until the sim signals new data or `timeout` passes.
    pub fn wait(&self, timeout: std::time::Duration) -> Result<()> {
        services::wait_for_event(&self.wake, timeout)
    }

    /// The event the sim raises when it has published a tick (to wait on several sims at once).
    pub fn wake_listener(&self) -> &Listener<S> {
        &self.wake
    }

    /// Takes in everything waiting; returns the episodes that ended.
    pub fn drain(&mut self) -> Result<Vec<FinishedEpisode>> {
        let mut finished = Vec::new();
        while let Some(sample) = self.state.receive().context("critic: state")? {
            let state = *sample.payload();
            drop(sample);
            services::check_sim_protocol(&state.header, "critic", "critic")?;
            if state.header.has(FLAG_RUN_END) {
                self.stats.run_ended = true;
                break;
            }
            self.stats.ticks_received += 1;
            self.stats.latest_sequence = Some(state.sequence);
            if let Some(done) = self.take_tick(&state) {
                finished.push(done);
            }
        }
        Ok(finished)
    }

    /// Episode `episode`'s obstacles and time limit: from the obstacles stream (the sim sends
    /// them before the episode's first state), or in an open-arena run the open episode's.
    fn obstacles_of(&mut self, episode: u32, n: usize) -> Option<(Obstacles, u32)> {
        while let Ok(Some(sample)) = self.obstacles.receive() {
            let msg = sample.payload();
            self.latest_obstacles = Some((msg.header.episode, Obstacles::from_wire(msg), msg.time_limit));
        }
        match &self.latest_obstacles {
            Some((number, obstacles, time_limit)) if *number == episode => Some((obstacles.clone(), *time_limit)),
            _ if !self.env.has_obstacles() => Some((Obstacles::none(), self.env.episode_steps(n))),
            _ => None,
        }
    }

    fn take_tick(&mut self, state: &StateMsg) -> Option<FinishedEpisode> {
        let n = state.n_agents as usize;
        let poses: Vec<Pose> = state.poses[..n].iter().map(|&p| Pose::from(p)).collect();
        let commands: Vec<(f64, f64)> = state.applied[..n]
            .iter()
            .map(|&[v, w]| (f64::from(v), f64::from(w)))
            .collect();
        let desired: Vec<[f64; NEIGHBOURS]> = state.desired[..n].iter().map(|d| d.map(f64::from)).collect();
        let slots: Vec<[f64; 2]> = state.slots[..n].iter().map(|s| s.map(f64::from)).collect();
        let slot_of: Vec<usize> = state.slot[..n].iter().map(|&s| s as usize).collect();
        let formation = Formation {
            from_tick: state.header.tick as usize,
            desired,
            slots,
            observed: observed_robots(&slot_of),
            present: (0..n).map(|agent| state.present >> agent & 1 == 1).collect(),
        };
        let goal = state.goal.map(f64::from);
        let observations = state.observations[..n].to_vec();
        let tick = Tick {
            poses,
            commands,
            observations,
            reward: state.reward,
        };
        if state.header.tick == 0 {
            if let Some(cut) = self.current.take() {
                self.stats.lost_transitions += cut.episode.ticks.len() as u64;
            }
            let Some((obstacles, time_limit)) = self.obstacles_of(state.header.episode, n) else {
                // Published before the episode's first state; without them its collisions
                // and time limit are unknown.
                self.stats.lost_transitions += 1;
                return None;
            };
            self.current = Some(EpisodeBuilder {
                episode: Episode {
                    number: state.header.episode,
                    goal,
                    formations: vec![formation],
                    ticks: vec![tick],
                    terminal: false,
                    obstacles,
                    arena_m: self.env.effective_arena_m(n),
                    time_limit,
                },
                last_tick: 0,
                episode_return: 0.0,
                eval: state.header.has(FLAG_EVAL_EPISODE),
            });
        } else {
            let Some(builder) = self
                .current
                .as_mut()
                .filter(|b| b.episode.number == state.header.episode && b.last_tick + 1 == state.header.tick)
            else {
                // A gap: this episode cannot be assembled whole.
                self.stats.lost_transitions += 1;
                self.current = None;
                return None;
            };
            builder.episode_return += f64::from(state.reward);
            builder.episode.ticks.push(tick);
            // A shape or team change: the formation in force from this tick on.
            let last = builder.episode.formation(formation.from_tick);
            if !last.same_as(&formation) {
                builder.episode.formations.push(formation);
            }
            builder.last_tick = state.header.tick;
        }
        let outcome = match Outcome::try_from(state.outcome) {
            Ok(Outcome::Running) => return None,
            Ok(outcome) => outcome,
            Err(code) => {
                // Not a state this build can read: the episode cannot be trusted.
                eprintln!(
                    "critic: unknown outcome code {code} in episode {}; dropped",
                    state.header.episode
                );
                self.stats.lost_transitions += 1;
                self.current = None;
                return None;
            }
        };
        let mut builder = self.current.take()?;
        builder.episode.terminal = outcome.is_terminal();
        Some(FinishedEpisode {
            episode: builder.episode,
            outcome,
            episode_return: builder.episode_return,
            eval: builder.eval,
        })
    }
}

#[cfg(test)]
mod tests {
    use formation_core::config::EnvConfig;
    use formation_ipc::services::{RunIdentity, Sizing};
    use iceoryx2::port::publisher::Publisher;

    use super::*;

    fn stats(last: u64, received: u64) -> CollectorStats {
        CollectorStats {
            ticks_received: received,
            latest_sequence: Some(last),
            ..CollectorStats::default()
        }
    }

    #[test]
    fn acknowledges_what_updates_paid_for_and_never_owes_lost_states() {
        assert_eq!(CollectorStats::default().acknowledgeable(10), 0, "nothing read yet");
        // No gap: states 100..=199 read, 50 paid for.
        assert_eq!(stats(199, 100).acknowledgeable(50), 150);
        assert_eq!(stats(199, 100).acknowledgeable(100), 199);
        assert_eq!(stats(199, 100).acknowledgeable(u64::MAX), 199, "eval: everything read");
        // 100 of states 100..=299 lost in a gap: the 10 unpaid ones are the newest, not 110.
        assert_eq!(stats(299, 100).acknowledgeable(90), 290);
        assert_eq!(stats(299, 100).acknowledgeable(100), 299);
    }

    /// A fake sim over iceoryx2's in-process `local` service, facing a real collector.
    struct FakeSim {
        state: Publisher<local::Service, StateMsg, ()>,
        sequence: u64,
    }

    impl FakeSim {
        /// Publishes the state of tick `tick` as the sim does: the outcome, reward and commands
        /// of the transition into it, what each robot was told (robot `lost`'s observation
        /// marked lost), and a velocity acting on the physics unlike the command in use.
        fn tick(&mut self, episode: u32, tick: u32, applied: f32, reward: f32, outcome: u32, lost: Option<usize>) {
            self.sequence += 1;
            let mut state = StateMsg {
                header: Header::new(episode, tick, 0),
                n_agents: 3,
                outcome,
                reward,
                sequence: self.sequence,
                observation_lost: lost.map_or(0, |agent| 1 << agent),
                ..StateMsg::default()
            };
            for agent in 0..3 {
                state.poses[agent] = [agent as f32, tick as f32, 0.0];
                state.applied[agent] = [applied, -applied];
                state.acting[agent] = [applied / 2.0, 0.0];
                state.observations[agent][0] = tick as f32 + agent as f32 / 10.0;
            }
            self.state.send_copy(state).expect("state");
        }
    }

    fn collector_and_sim(run: &str) -> (Node<local::Service>, Collector<local::Service>, FakeSim, EnvConfig) {
        let identity = RunIdentity::new(&format!("{run}{}", std::process::id())).expect("id");
        let node = services::create_node::<local::Service>(&identity, "critic").expect("node");
        let sizing = Sizing::new(3, 8, 12);
        let env = EnvConfig::default();
        let collector = Collector::new(&node, &sizing, &env).expect("collector");
        let sim = FakeSim {
            state: services::state_stream(&node, &sizing)
                .expect("stream")
                .publisher_builder()
                .create()
                .expect("publisher"),
            sequence: 0,
        };
        (node, collector, sim, env)
    }

    #[test]
    fn a_shape_change_in_the_state_stream_starts_a_new_formation_from_its_tick() {
        let (_node, mut collector, mut sim, _env) = collector_and_sim("collchange");
        // Ticks 0-2 in slots 0, 1, 2 with 1 m edges; from tick 2 robots 0 and 2 swap slots
        // and the edges are 1.5 m.
        for tick in 0..4u32 {
            sim.sequence += 1;
            let changed = tick >= 2;
            let mut state = StateMsg {
                header: Header::new(0, tick, 0),
                n_agents: 3,
                outcome: if tick == 3 { OUTCOME_SUCCESS } else { OUTCOME_RUNNING },
                sequence: sim.sequence,
                // Robot 1 leaves the formation at the change.
                present: if changed { 0b101 } else { 0b111 },
                ..StateMsg::default()
            };
            for agent in 0..3 {
                state.slot[agent] = if changed { [2, 1, 0][agent] } else { agent as u32 };
                state.desired[agent] = [if changed { 1.5 } else { 1.0 }; NEIGHBOURS];
            }
            sim.state.send_copy(state).expect("state");
        }
        let finished = collector.drain().expect("drain");
        let episode = &finished[0].episode;
        assert_eq!(
            episode.formations.iter().map(|f| f.from_tick).collect::<Vec<_>>(),
            [0, 2]
        );
        assert_eq!(episode.scene(1, episode.goal).desired[0], [1.0; NEIGHBOURS]);
        assert_eq!(episode.scene(1, episode.goal).observed[0], [1, 2]);
        assert_eq!(episode.scene(3, episode.goal).desired[0], [1.5; NEIGHBOURS]);
        // Robot 0 holds slot 2: it observes the robots in slots 0 and 1, robots 2 and 1.
        assert_eq!(episode.scene(2, episode.goal).observed[0], [2, 1]);
        // The state's presence mask, recorded with the formation.
        assert_eq!(episode.present(1), [true; 3]);
        assert_eq!(episode.present(3), [true, false, true]);
    }

    #[test]
    fn state_t_plus_1_carries_the_commands_and_reward_of_tick_t() {
        let (_node, mut collector, mut sim, env) = collector_and_sim("collshift");
        sim.tick(0, 0, 0.0, 0.0, OUTCOME_RUNNING, None);
        sim.tick(0, 1, 0.2, 1.5, OUTCOME_RUNNING, None);
        sim.tick(0, 2, 0.4, 2.5, OUTCOME_SUCCESS, None);
        let finished = collector.drain().expect("drain");
        assert_eq!(finished.len(), 1);
        let done = &finished[0];
        assert_eq!(done.outcome, Outcome::Success);
        assert!(done.episode.terminal, "a success is terminal");
        assert_eq!(done.episode_return, 4.0);
        let episode = &done.episode;
        let ticks = &episode.ticks;
        assert_eq!(ticks.len(), 3);
        // Tick t + 1's scene holds the commands and the reward its state carries, those of
        // the transition from t; tick 0 has none.
        assert_eq!((ticks[0].reward, ticks[0].commands[1]), (0.0, (0.0, 0.0)));
        assert_eq!(ticks[1].reward, 1.5);
        assert_eq!(
            episode.scene(1, episode.goal).commands[1],
            (0.2f32.into(), (-0.2f32).into())
        );
        assert_eq!(ticks[2].reward, 2.5);
        assert_eq!(
            episode.scene(2, episode.goal).commands[2],
            (0.4f32.into(), (-0.4f32).into())
        );
        // The action the robots chose from tick t (the command in use, not the velocity that
        // acted on the physics), as the learner sees it.
        assert_eq!(
            episode.action(0, 1, &env),
            env.action_from_command(0.2f32.into(), (-0.2f32).into())
        );
        assert_eq!(
            episode.action(1, 2, &env),
            env.action_from_command(0.4f32.into(), (-0.4f32).into())
        );
        // Each tick holds what the robots were told at that tick.
        assert!((ticks[1].observations[2][0] - 1.2).abs() < 1e-6);
        assert_eq!(collector.stats.lost_transitions, 0);
        assert_eq!(collector.stats.ticks_received, 3);
        assert_eq!(collector.stats.latest_sequence, Some(3));
    }

    #[test]
    fn a_lost_observation_costs_nothing_and_a_gap_is_counted_as_lost() {
        let (_node, mut collector, mut sim, _env) = collector_and_sim("colllost");
        // Robot 1's observation of tick 1 was lost on the way to it: the state still says what
        // it would have been told, so the tick is whole.
        sim.tick(0, 0, 0.0, 0.0, OUTCOME_RUNNING, None);
        sim.tick(0, 1, 0.1, 1.0, OUTCOME_RUNNING, Some(1));
        sim.tick(0, 2, 0.1, 1.0, OUTCOME_TIMEOUT, None);
        let finished = collector.drain().expect("drain");
        assert_eq!(collector.stats.lost_transitions, 0);
        assert_eq!(finished.len(), 1);
        assert!((finished[0].episode.ticks[1].observations[1][0] - 1.1).abs() < 1e-6);
        assert!(!finished[0].episode.terminal, "a time limit is a truncation");
        // A gap (tick 1 of episode 1 never published): the episode is dropped.
        sim.tick(1, 0, 0.0, 0.0, OUTCOME_RUNNING, None);
        sim.tick(1, 2, 0.1, 1.0, OUTCOME_SUCCESS, None);
        assert!(collector.drain().expect("drain").is_empty());
        assert_eq!(collector.stats.lost_transitions, 1);
    }
}
