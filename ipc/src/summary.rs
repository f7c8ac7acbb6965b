//! What a run leaves behind in `summary.json`, and the table printed at its end.

use serde::{Deserialize, Serialize};

/// Figures of a whole run. The sim fills the episode figures, the critic the stream and
/// training figures; missing parts stay `None` and are written as `null`.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
pub struct Summary {
    /// `train` or `eval`.
    pub mode: String,
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Seed of the episode generator.
    pub seed: u64,
    /// Which robots ran the scripted baseline.
    pub scripted_agents: Vec<usize>,
    /// Which robots were played by outside processes (`--external`).
    #[serde(default)]
    pub external_agents: Vec<usize>,
    /// Episodes finished.
    pub episodes: u64,
    /// Fraction of episodes that reached C3.
    pub success_rate: f64,
    /// Fraction of episodes that ended in a collision (between robots, or of a robot with an
    /// obstacle).
    pub collision_rate: f64,
    /// Episodes that ended because a robot touched an obstacle (counted in `collision_rate`
    /// too).
    #[serde(default)]
    pub obstacle_collisions: u64,
    /// The episodes' obstacles (`[obstacles]` kind: `none` in the open arena).
    #[serde(default)]
    pub obstacles: String,
    /// Fraction of episodes that hit the time limit.
    pub timeout_rate: f64,
    /// Mean over episodes of the mean |d_ij - dbar_ij| at the last tick, metres.
    pub mean_final_edge_error_m: f64,
    /// Mean over episodes of the centroid-to-goal distance at the last tick, metres.
    pub mean_final_goal_distance_m: f64,
    /// Mean steps of the successful episodes (`null` when none succeeded).
    pub mean_steps_to_goal: Option<f64>,
    /// Fraction of ticks on which C1 held.
    pub formation_hold_rate: f64,
    /// Mean undiscounted episode return.
    pub mean_return: f64,
    /// The mission planner's slot reassignments over the episodes: shape changes
    /// (`env.shape_changes`, the control service), goal moves and team changes.
    #[serde(default)]
    pub reconfigurations: u64,
    /// Robots that left the formation (controller failure, removed, 10 silent ticks).
    #[serde(default)]
    pub departures: u64,
    /// Robots that came back into the formation (5 answers in a row, restored).
    #[serde(default)]
    pub returns: u64,
    /// Changes after which the swarm re-formed within its episode: every observed edge within
    /// `eps_form_m` for 5 consecutive ticks.
    #[serde(default)]
    pub reforms: u64,
    /// Mean ticks from a change to the first of those 5 ticks, over the changes that re-formed
    /// (`null` when none did).
    #[serde(default)]
    pub mean_reform_ticks: Option<f64>,
    /// Physics steps taken.
    pub env_steps: u64,
    /// Physics steps per wall-clock second of the stepping loop.
    pub env_steps_per_s: f64,
    /// Median tick duration (publish observations to all commands in), microseconds.
    pub tick_p50_us: f64,
    /// 99th percentile tick duration, microseconds.
    pub tick_p99_us: f64,
    /// Robot-ticks missed: nothing new arrived by the deadline (no answer to the tick, no newer
    /// late one, nothing lost), so the command in use stayed.
    pub missed_ticks: u64,
    /// Robot-ticks that took up a late answer to an earlier tick (docs/PROTOCOL.md).
    #[serde(default)]
    pub late_commands: u64,
    /// Commands lost on the way (`[reality]`'s `command_loss`); not counted as missed.
    #[serde(default)]
    pub lost_commands: u64,
    /// Observations not delivered (`[reality]`'s `observation_loss`); not counted as missed.
    #[serde(default)]
    pub lost_observations: u64,
    /// Commands rejected as malformed (non-finite, wrong tick or protocol).
    pub rejected_commands: u64,
    /// Robots played by ROS 2 nodes (`--ros2`); the `ros2_*` counts below are the ROS 2
    /// side's (`formation-ros2`), added by the launcher at the run's end.
    #[serde(default)]
    pub ros2_agents: Vec<usize>,
    /// `cmd_vel` Twists passed to the sim as a robot's command.
    #[serde(default)]
    pub ros2_twists: Option<u64>,
    /// Twists dropped because none of their robot's observations had been published yet.
    #[serde(default)]
    pub ros2_twists_dropped: Option<u64>,
    /// Twists not passed on: a newer one for the same robot came with it, or the robot's newest
    /// observation was already answered.
    #[serde(default)]
    pub ros2_twists_superseded: Option<u64>,
    /// Twists rejected: malformed (bad CDR header or length, non-finite values, no rmw_zenoh
    /// attachment) or for a robot the ROS 2 side does not carry.
    #[serde(default)]
    pub ros2_twists_rejected: Option<u64>,
    /// Robots that greeted again after being absent (restarted agent processes).
    pub rejoined_agents: u64,
    /// Real-time mode: ticks that overran their deadline.
    pub deadline_misses: u64,
    /// Wall-clock seconds of the run.
    pub wall_s: f64,
    /// Times the sim's tick thread slept and was woken, per tick (1 is the floor: woken once
    /// when the tick's last command is in).
    #[serde(default)]
    pub sim_wakeups_per_tick: Option<f64>,
    /// The sim's tick thread's context switches (voluntary and involuntary) per tick.
    #[serde(default)]
    pub sim_switches_per_tick: Option<f64>,
    /// Context switches of the whole machine per tick (every process of the swarm, and
    /// anything else running).
    #[serde(default)]
    pub machine_switches_per_tick: Option<f64>,
    /// Robots woken by the tick bell per tick (one futex wake for all of them); the others
    /// were woken by their own event.
    #[serde(default)]
    pub bell_robots_per_tick: Option<f64>,
    /// Ticks the critic took into its replay.
    pub transitions_received: Option<u64>,
    /// Ticks the critic should have seen but did not (gaps, missing observations).
    pub lost_transitions: Option<u64>,
    /// Gradient updates.
    pub updates: Option<u64>,
    /// Gradient updates per second of the critic's run.
    pub updates_per_s: Option<f64>,
    /// Last critic loss.
    pub critic_loss: Option<f64>,
    /// Last actor loss.
    pub actor_loss: Option<f64>,
    /// Latest weights version published.
    pub weights_version: Option<u32>,
    /// Checkpoint written at the end, relative to the run directory.
    pub checkpoint: Option<String>,
}

impl Summary {
    /// The end-of-run table.
    pub fn table(&self) -> String {
        let opt = |value: Option<f64>, digits: usize| match value {
            Some(v) => format!("{v:.digits$}"),
            None => "-".into(),
        };
        let rows: Vec<(&str, String)> = vec![
            ("mode", self.mode.clone()),
            ("robots", self.n_agents.to_string()),
            ("scripted robots", format!("{:?}", self.scripted_agents)),
            ("outside robots", format!("{:?}", self.external_agents)),
            ("episodes", self.episodes.to_string()),
            ("success rate", format!("{:.3}", self.success_rate)),
            ("collision rate", format!("{:.3}", self.collision_rate)),
            ("obstacle collisions", self.obstacle_collisions.to_string()),
            ("timeout rate", format!("{:.3}", self.timeout_rate)),
            ("final edge error (m)", format!("{:.4}", self.mean_final_edge_error_m)),
            (
                "final goal distance (m)",
                format!("{:.4}", self.mean_final_goal_distance_m),
            ),
            ("steps to goal", opt(self.mean_steps_to_goal, 1)),
            ("formation held (ticks)", format!("{:.3}", self.formation_hold_rate)),
            ("mean return", format!("{:.2}", self.mean_return)),
            (
                "shape changes / re-formed",
                format!("{} / {}", self.reconfigurations, self.reforms),
            ),
            ("ticks to re-form", opt(self.mean_reform_ticks, 1)),
            (
                "robots left / came back",
                format!("{} / {}", self.departures, self.returns),
            ),
            ("env steps", self.env_steps.to_string()),
            ("env steps / s", format!("{:.0}", self.env_steps_per_s)),
            (
                "tick p50 / p99 (us)",
                format!("{:.1} / {:.1}", self.tick_p50_us, self.tick_p99_us),
            ),
            ("missed ticks", self.missed_ticks.to_string()),
            (
                "late / lost commands",
                format!("{} / {}", self.late_commands, self.lost_commands),
            ),
            ("lost observations", self.lost_observations.to_string()),
            ("rejected commands", self.rejected_commands.to_string()),
            ("deadline misses", self.deadline_misses.to_string()),
            ("rejoined robots", self.rejoined_agents.to_string()),
            ("sim wake-ups / tick", opt(self.sim_wakeups_per_tick, 2)),
            ("machine switches / tick", opt(self.machine_switches_per_tick, 1)),
            ("robots woken by the bell / tick", opt(self.bell_robots_per_tick, 2)),
            (
                "transitions received",
                self.transitions_received.map_or("-".into(), |v| v.to_string()),
            ),
            (
                "lost transitions",
                self.lost_transitions.map_or("-".into(), |v| v.to_string()),
            ),
            ("gradient updates", self.updates.map_or("-".into(), |v| v.to_string())),
            ("updates / s", opt(self.updates_per_s, 1)),
            (
                "weights version",
                self.weights_version.map_or("-".into(), |v| v.to_string()),
            ),
        ];
        let width = rows.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
        rows.iter().map(|(k, v)| format!("  {k:<width$}  {v}\n")).collect()
    }
}
