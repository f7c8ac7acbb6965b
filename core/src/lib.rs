//! The formation-control task, free of any transport: what the sim computes online and what
//! the critic's replay recomputes for HER are the same functions from here.
//!
//! * [`baseline`]: the scripted controller, the yardstick and the learner's optional teacher;
//! * [`physics`]: unicycle poses and their exact integration over a step;
//! * [`scene`]: one tick of a swarm (poses, the commands applied into it, formation, goal), the
//!   one type the step, the reward, the observation, the critic's features and the replay read;
//! * [`shapes`]: the formation shapes, one file each, and what every shape must satisfy;
//! * [`formation`]: random episodes (a shape at a random place, size and heading, and a goal);
//! * [`observation`]: the observation models, their named layout and what a robot sees;
//! * [`layout`]: `layout.json`, the payloads' and the observation models' layout for other
//!   languages (printed by `formation-layout`);
//! * [`task`]: conditions C1-C3, the paper's reward and the episode [`task::Outcome`];
//! * [`reality`]: sensor noise, lost messages, actuation delay, motor lag and dying
//!   controllers between the truth and the robots (the `[reality]` section, off by default);
//! * [`world`]: one episode's true state and the step that applies the robots' commands;
//! * [`mission`]: the mission planner: an episode's shape changes, the optimal reassignment of
//!   robots to the new slots, and when the swarm has re-formed;
//! * [`planner`] and [`solo_planner`]: the planners that know the map (the team's, and each
//!   robot's own, a teacher for a decentralised student);
//! * [`features`]: the critic's view of a scene (poses relative to the centroid);
//! * [`pace`]: a lower bound on the steps any controller needs for an episode (the physics'
//!   floor under steps-to-goal figures, printed by `formation-pace-floor`).

pub mod baseline;
pub mod config;
pub mod features;
pub mod formation;
pub mod gap_search;
pub mod geodesic;
pub mod layout;
pub mod mission;
pub mod observation;
pub mod obstacles;
pub mod pace;
pub mod physics;
pub mod planner;
pub mod range_sensor;
pub mod reality;
pub mod recovery;
pub mod run_dir;
pub mod scene;
pub mod shapes;
pub mod solo_planner;
pub mod stepper;
pub mod task;
pub mod world;
