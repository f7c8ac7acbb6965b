use super::*;
use crate::baseline::BaselineGains;
use crate::config::FormationShape;
use crate::formation::{EpisodeInit, Episodes};
use crate::planner::{FILE_MARGIN_M, FORMATION_MARGIN_M, PlanMode, Planner};

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ObstaclesFile {
    obstacles: ObstacleConfig,
}

fn parse(text: &str) -> Result<ObstacleConfig, toml::de::Error> {
    toml::from_str::<ObstaclesFile>(text).map(|file| file.obstacles)
}

#[test]
fn kinds_parse_by_name_and_a_bad_name_is_named_in_the_error() {
    for kind in ObstacleKind::ALL {
        assert_eq!(kind.as_str().parse::<ObstacleKind>(), Ok(kind));
        let config = parse(&format!("[obstacles]\nkind = \"{kind}\"\n")).expect("parses");
        assert_eq!(config.kind, kind);
    }
    let err = "forrest".parse::<ObstacleKind>().expect_err("unknown");
    assert!(err.to_string().contains("\"forrest\""), "{err}");
    assert!(parse("[obstacles]\nkind = \"wall\"\n").is_err());
}

/// `KINDS` is every kind but `none` and `mixed` and `ALL` every kind, as clap's derive lists
/// them: a kind added to the enum and not to the lists fails here.
#[test]
fn the_kind_lists_are_exhaustive() {
    let all = <ObstacleKind as clap::ValueEnum>::value_variants();
    assert_eq!(ObstacleKind::ALL.as_slice(), all);
    let drawn: Vec<ObstacleKind> = all
        .iter()
        .copied()
        .filter(|kind| !matches!(kind, ObstacleKind::None | ObstacleKind::Mixed))
        .collect();
    assert_eq!(ObstacleKind::KINDS.as_slice(), drawn.as_slice());
}

#[test]
fn the_section_defaults_to_none_takes_ranges_and_refuses_bad_values_naming_the_key() {
    let default = parse("[obstacles]\n").expect("parses");
    assert_eq!(default, ObstacleConfig::default());
    assert_eq!(default.kind, ObstacleKind::None);
    default.validate().expect("defaults are valid");
    let tuned =
        parse("[obstacles]\nkind = \"passage\"\ngap_width_m = [0.4, 0.45]\nwall_thickness_m = 0.2\n").expect("parses");
    assert_eq!(tuned.gap_width_m, Spread::range(0.4, 0.45));
    assert_eq!(tuned.wall_thickness_m, Spread::fixed(0.2));
    assert_eq!(tuned.trap_depth_m, ObstacleConfig::default().trap_depth_m);
    let text = toml::to_string(&ObstaclesFile {
        obstacles: tuned.clone(),
    })
    .expect("serialises");
    assert_eq!(parse(&text).expect("round trip"), tuned, "{text}");
    let err = parse("[obstacles]\ngap_width = 0.4\n").expect_err("unknown key");
    assert!(err.to_string().contains("unknown field"), "{err}");
    for (text, field) in [
        ("forest_radius_m = 0.0", "obstacles.forest_radius_m"),
        ("forest_density = [0.1, 0.6]", "obstacles.forest_density"),
        ("gap_width_m = [0.5, 0.4]", "obstacles.gap_width_m"),
        ("wall_thickness_m = -0.1", "obstacles.wall_thickness_m"),
        ("trap_depth_m = nan", "obstacles.trap_depth_m"),
        ("trap_margin_m = -0.2", "obstacles.trap_margin_m"),
        ("collision_monitor_m = -0.5", "obstacles.collision_monitor_m"),
    ] {
        let config = parse(&format!("[obstacles]\n{text}\n")).expect(text);
        let message = config.validate().expect_err(text).to_string();
        assert!(message.contains(field), "{text}: {message}");
    }
}

#[test]
fn distances_and_hits_match_the_shapes() {
    let obstacles = Obstacles::new(vec![
        Obstacle::Disc {
            centre: [2.0, 2.0],
            radius: 0.5,
        },
        Obstacle::Wall {
            a: [5.0, 0.0],
            b: [5.0, 4.0],
            thickness: 0.2,
        },
    ]);
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9;
    assert!(close(obstacles.distance([2.0, 3.0]), 0.5));
    assert!(close(obstacles.distance([4.0, 2.0]), 0.9), "the wall's face at 4.9");
    assert!(
        close(obstacles.distance([5.0, 5.0]), 1.0),
        "the wall's flat end at y = 4"
    );
    assert_eq!(obstacles.distance([2.1, 2.0]), 0.0, "inside a disc");
    assert!(obstacles.hits_robot([2.0, 2.59], 0.1));
    assert!(!obstacles.hits_robot([2.0, 2.61], 0.1));
    assert!(obstacles.hits_robot([4.81, 1.0], 0.1) && !obstacles.hits_robot([4.79, 1.0], 0.1));
    assert!(close(
        obstacles.cast_ray([0.0, 2.0], [1.0, 0.0], 10.0).expect("hits the disc"),
        1.5
    ));
    assert!(close(
        obstacles.cast_ray([3.0, 3.0], [1.0, 0.0], 10.0).expect("hits the wall"),
        1.9
    ));
    assert_eq!(obstacles.cast_ray([3.0, 3.0], [1.0, 0.0], 1.0), None, "beyond max");
    assert_eq!(
        obstacles.cast_ray([3.0, 4.5], [1.0, 0.0], 10.0),
        None,
        "passes the wall's end"
    );
    assert!(obstacles.segment_is_clear([0.0, 3.0], [4.0, 3.0], 0.49));
    assert!(!obstacles.segment_is_clear([0.0, 3.0], [4.0, 3.0], 0.51));
    assert!(
        !obstacles.segment_is_clear([4.0, 4.0], [6.0, 4.0], 0.1),
        "crosses the wall's end"
    );
    assert!(Obstacles::none().distance([1.0, 1.0]).is_infinite());
}

/// An environment whose goals lie far enough for `kind` at `n` robots (what validation will ask
/// of a run with obstacles): goals from the kind's minimum to 1 m beyond.
fn env_for(kind: ObstacleKind, n: usize, shape: FormationShape) -> EnvConfig {
    let env = EnvConfig {
        shape,
        ..EnvConfig::default()
    };
    let nearest = min_goal_distance_m(&ObstacleConfig::default(), kind, n, &env);
    EnvConfig {
        goal_min_m: nearest,
        goal_max_m: nearest + 1.0,
        ..env
    }
}

fn draw_for(kind: ObstacleKind, init: &EpisodeInit, env: &EnvConfig, seed: u64) -> Obstacles {
    let starts: Vec<[f64; 2]> = init.poses.iter().map(|p| [p.x, p.y]).collect();
    draw(
        &ObstacleConfig::default(),
        kind,
        &starts,
        init.goal,
        &init.slots,
        env,
        seed,
    )
}

#[test]
fn kind_none_draws_nothing() {
    let env = EnvConfig::default();
    for (episode, init) in Episodes::new(6, &env, 1000).take(50).enumerate() {
        assert!(draw_for(ObstacleKind::None, &init, &env, obstacle_seed(1000, episode as u64)).is_empty());
    }
    assert_eq!(
        min_goal_distance_m(&ObstacleConfig::default(), ObstacleKind::None, 6, &env),
        0.0
    );
    assert_eq!(
        episode_steps_with_obstacles(ObstacleKind::None, 2.0, 6, &env),
        env.episode_steps(6)
    );
}

/// 1,000 draws of each kind (over 4, 8 and 16 robots of every shape): reproducible from the
/// seed, every start position and goal slot clear by 2 eps_coll, and obstacles drawn (a goal
/// at the kind's minimum distance always has room).
#[test]
fn draws_are_reproducible_and_keep_starts_and_goal_slots_clear() {
    for kind in ObstacleKind::KINDS.into_iter().chain([ObstacleKind::Mixed]) {
        let mut drawn = 0;
        for (n, shape, episodes) in [
            (4, FormationShape::Mixed, 500),
            (8, FormationShape::Mixed, 300),
            (16, FormationShape::Ring, 200),
        ] {
            let env = env_for(kind, n, shape);
            for (episode, init) in Episodes::new(n, &env, 7).take(episodes).enumerate() {
                let seed = obstacle_seed(7, episode as u64);
                let obstacles = draw_for(kind, &init, &env, seed);
                assert!(!obstacles.is_empty(), "{kind} n={n} episode {episode}: nothing drawn");
                assert_eq!(obstacles, draw_for(kind, &init, &env, seed), "same seed, same draw");
                assert_ne!(
                    obstacles,
                    draw_for(kind, &init, &env, seed ^ 1),
                    "another seed, another draw"
                );
                let goal_slots = init.slots.iter().map(|o| [init.goal[0] + o[0], init.goal[1] + o[1]]);
                for p in init.poses.iter().map(|p| [p.x, p.y]).chain(goal_slots) {
                    let distance = obstacles.distance(p);
                    assert!(
                        distance >= 2.0 * env.eps_coll_m,
                        "{kind} n={n} episode {episode}: {p:?} {distance} from a surface"
                    );
                }
                drawn += 1;
            }
        }
        assert_eq!(drawn, 1000);
    }
}

#[test]
fn mixed_draws_every_kind_and_drawn_kind_names_the_one_drawn() {
    let env = env_for(ObstacleKind::Mixed, 4, FormationShape::Mixed);
    let mut seen = Vec::new();
    for (episode, init) in Episodes::new(4, &env, 5).take(60).enumerate() {
        let seed = obstacle_seed(5, episode as u64);
        let kind = drawn_kind(ObstacleKind::Mixed, seed);
        assert!(ObstacleKind::KINDS.contains(&kind));
        let mixed = draw_for(ObstacleKind::Mixed, &init, &env, seed);
        // A forest has no walls, a passage two, a trap three.
        let walls = mixed
            .list()
            .iter()
            .filter(|o| matches!(o, Obstacle::Wall { .. }))
            .count();
        let expected = match kind {
            ObstacleKind::Forest => 0,
            ObstacleKind::Passage => 2,
            _ => 3,
        };
        assert_eq!(walls, expected, "{kind}: {:?}", mixed.list());
        if !seen.contains(&kind) {
            seen.push(kind);
        }
    }
    assert_eq!(seen.len(), 3, "{seen:?}");
    assert_eq!(drawn_kind(ObstacleKind::Trap, 9), ObstacleKind::Trap);
}

#[test]
fn passages_leave_one_gap_of_the_drawn_width_near_the_straight_line() {
    let env = env_for(ObstacleKind::Passage, 6, FormationShape::Mixed);
    let config = ObstacleConfig::default();
    for (episode, init) in Episodes::new(6, &env, 3).take(200).enumerate() {
        let obstacles = draw_for(ObstacleKind::Passage, &init, &env, obstacle_seed(3, episode as u64));
        let [Obstacle::Wall { b: left_end, .. }, Obstacle::Wall { a: right_end, .. }] = obstacles.list() else {
            panic!("two walls: {:?}", obstacles.list());
        };
        let width = (left_end[0] - right_end[0]).hypot(left_end[1] - right_end[1]);
        assert!(
            (config.gap_width_m.lo - 1e-9..=config.gap_width_m.hi + 1e-9).contains(&width),
            "gap {width}"
        );
        let gap = [0.5 * (left_end[0] + right_end[0]), 0.5 * (left_end[1] + right_end[1])];
        let start = crate::task::centroid(&init.poses);
        let (dx, dy) = (init.goal[0] - start[0], init.goal[1] - start[1]);
        let off_line = ((gap[0] - start[0]) * dy - (gap[1] - start[1]) * dx).abs() / dx.hypot(dy);
        assert!(off_line <= MAX_GAP_OFFSET_M + 1e-9, "gap {off_line} m off the line");
    }
}

#[test]
fn time_limits_grow_with_distance_and_the_file_and_mixed_takes_the_largest() {
    let env = EnvConfig::default();
    for kind in ObstacleKind::KINDS {
        let near = episode_steps_with_obstacles(kind, 4.0, 8, &env);
        let far = episode_steps_with_obstacles(kind, 8.0, 8, &env);
        assert!(env.episode_steps(8) < near && near < far, "{kind}: {near} {far}");
        assert!(episode_steps_with_obstacles(ObstacleKind::Mixed, 8.0, 8, &env) >= far);
    }
    let few = episode_steps_with_obstacles(ObstacleKind::Passage, 6.0, 4, &env);
    let many = episode_steps_with_obstacles(ObstacleKind::Passage, 6.0, 16, &env);
    assert!(few < many, "a longer file takes longer: {few} {many}");
}

/// Samples a leg every centimetre: the planner's clearance, checked by point distances alone.
fn leg_clearance(obstacles: &Obstacles, a: [f64; 2], b: [f64; 2]) -> f64 {
    let steps = ((b[0] - a[0]).hypot(b[1] - a[1]) / 0.01).ceil().max(1.0) as usize;
    (0..=steps)
        .map(|k| {
            let t = k as f64 / steps as f64;
            obstacles.distance([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])])
        })
        .fold(f64::INFINITY, f64::min)
}

/// 1,000 draws of `mixed` obstacles over 4, 8 and 16 robots: the planner finds a path every
/// time, and none of its legs comes nearer a surface than its inflation (the formation's
/// radius, or a robot's in file).
#[test]
fn the_planners_paths_never_cross_an_inflated_obstacle() {
    let mut modes = [0usize; 3];
    for (n, shape, episodes) in [
        (4, FormationShape::Mixed, 500),
        (8, FormationShape::Mixed, 300),
        (16, FormationShape::Ring, 200),
    ] {
        let env = env_for(ObstacleKind::Mixed, n, shape);
        for (episode, init) in Episodes::new(n, &env, 11).take(episodes).enumerate() {
            let obstacles = draw_for(ObstacleKind::Mixed, &init, &env, obstacle_seed(11, episode as u64));
            let planner = Planner::new(
                &init.poses,
                init.goal,
                &init.slots,
                &obstacles,
                &env,
                BaselineGains::default(),
            );
            let reach = init.slots.iter().map(|o| o[0].hypot(o[1])).fold(0.0, f64::max);
            let least = match planner.mode() {
                PlanMode::Formation => reach + robot_radius_m(&env) + FORMATION_MARGIN_M,
                PlanMode::Column => robot_radius_m(&env) + FILE_MARGIN_M,
                PlanMode::Direct => panic!("n={n} episode {episode}: no path through {:?}", obstacles.list()),
            };
            let inflation = planner.inflation();
            assert!(inflation >= least - 1e-12, "{inflation} < {least}");
            modes[planner.mode() as usize] += 1;
            for leg in planner.path().windows(2) {
                let clearance = leg_clearance(&obstacles, leg[0], leg[1]);
                assert!(
                    clearance >= inflation - 1e-9,
                    "n={n} episode {episode}: leg {leg:?} {clearance} from a surface, inflation {inflation}"
                );
            }
        }
    }
    // Both ways of moving come up.
    assert!(modes[0] > 0 && modes[1] > 0, "{modes:?}");
}

/// The episodes of a run with obstacles carry them: `Episodes` draws them per episode from the
/// run's seed (the same again for the same seed), goals at least the kind's distance away, the
/// time limit the kind's formula; and a robot driven into one ends the episode as a collision,
/// counted apart in the episode's record.
#[test]
fn episodes_carry_their_obstacles_and_driving_into_one_ends_the_episode_counted_apart() {
    use crate::reality::RealityConfig;
    use crate::stepper::{EpisodeStepper, TransportCounts};
    use crate::task::{Outcome, centroid};
    let env = EnvConfig {
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Passage,
            ..ObstacleConfig::default()
        },
        ..EnvConfig::default()
    };
    let first: Vec<EpisodeInit> = Episodes::new(4, &env, 3).take(5).collect();
    assert_eq!(first, Episodes::new(4, &env, 3).take(5).collect::<Vec<_>>());
    let mut hits = 0;
    for (episode, init) in first.into_iter().enumerate() {
        assert!(!init.obstacles.is_empty() && init.obstacle_kind == ObstacleKind::Passage);
        let c = centroid(&init.poses);
        let distance = (init.goal[0] - c[0]).hypot(init.goal[1] - c[1]);
        assert!(distance >= env.goal_range_m(4).0 - 1e-9);
        assert_eq!(
            init.time_limit,
            episode_steps_with_obstacles(ObstacleKind::Passage, distance, 4, &env)
        );
        // Every robot heads straight for its own slot: the wall is in the way.
        let mut stepper = EpisodeStepper::new(&env, &RealityConfig::default(), 3, episode as u32, init);
        while stepper.running() {
            let commands = straight_for_the_slots(stepper.world());
            stepper.step(&commands, |_| true);
        }
        let record = stepper.record(episode as u32, TransportCounts::default());
        let hit = stepper.last().conditions.obstacle_collision;
        assert_eq!(record.obstacle_collisions, u32::from(hit));
        if hit {
            assert_eq!(record.outcome, Outcome::Collision);
            assert_eq!(stepper.last().reward, env.r_collision);
            hits += 1;
        }
    }
    assert!(hits >= 3, "{hits} of 5 straight drives hit the wall");
}

/// Every robot of `stepper`'s episode drives at full speed straight for its own slot, told its
/// observation each tick, to the episode's end; returns the closest any robot's disc came to an
/// obstacle, metres (negative inside one).
fn drive_straight_for_the_slots(stepper: &mut crate::stepper::EpisodeStepper) -> f64 {
    let mut closest = f64::INFINITY;
    while stepper.running() {
        stepper.tell();
        let world = stepper.world();
        let radius = robot_radius_m(&world.env);
        for p in &world.poses {
            closest = closest.min(world.obstacles.distance([p.x, p.y]) - radius);
        }
        let commands = straight_for_the_slots(world);
        stepper.step(&commands, |_| true);
    }
    closest
}

/// Each robot's command at full speed straight for its own slot (turning towards it; no speed
/// while it faces away).
fn straight_for_the_slots(world: &crate::world::World) -> Vec<(f64, f64)> {
    world
        .poses
        .iter()
        .zip(&world.slots)
        .map(|(p, s)| {
            let bearing = (world.goal[1] + s[1] - p.y).atan2(world.goal[0] + s[0] - p.x) - p.theta;
            let bearing = bearing.sin().atan2(bearing.cos());
            (world.env.v_max * bearing.cos().max(0.0), 2.0 * bearing)
        })
        .collect()
}

#[test]
fn the_collision_monitor_stops_straight_drives_short_of_the_wall_they_hit_without_it() {
    use crate::config::ObservationModel;
    use crate::reality::RealityConfig;
    use crate::stepper::EpisodeStepper;
    let with_monitor = |collision_monitor_m: f64| EnvConfig {
        observation: ObservationModel::SlotProximityScan,
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Passage,
            collision_monitor_m,
            ..ObstacleConfig::default()
        },
        ..EnvConfig::default()
    };
    let (mut hits_without, mut hits_with) = (0, 0);
    for (episode, init) in Episodes::new(4, &with_monitor(0.0), 3).take(5).enumerate() {
        for (monitor, hits) in [(0.0, &mut hits_without), (0.5, &mut hits_with)] {
            let env = with_monitor(monitor);
            let mut stepper = EpisodeStepper::new(&env, &RealityConfig::default(), 3, episode as u32, init.clone());
            let closest = drive_straight_for_the_slots(&mut stepper);
            if stepper.last().conditions.obstacle_collision {
                *hits += 1;
            } else if monitor > 0.0 {
                // Stopped at the wall, not before it: within the margin and a tick's travel.
                assert!(closest < 0.12, "episode {episode}: stayed {closest:.3} m from the wall");
            }
        }
    }
    assert!(
        hits_without >= 3,
        "{hits_without} of 5 straight drives hit the wall without a monitor"
    );
    assert_eq!(hits_with, 0, "the monitor let {hits_with} of 5 drives hit the wall");
}

/// Discounted return of `rewards` (the first at t = 0).
fn discounted(rewards: &[f64], gamma: f64) -> f64 {
    rewards.iter().rev().fold(0.0, |sum, r| r + gamma * sum)
}

/// The rewards from the wall on of one passage episode of 8 robots: the formation drives
/// straight at the goal (the blind baseline) until a robot comes within 0.5 m of the wall;
/// from there it waits (stands still, in formation, to the time limit) or passes (the planner,
/// planning from there, takes it through the gap in file to the goal).
fn waiting_and_passing(env: &EnvConfig, seed: u64) -> (Vec<f64>, Vec<f64>) {
    use crate::baseline::ScriptedBaseline;
    use crate::config::ObservationModel;
    use crate::task::Outcome;
    use crate::world::World;
    let blind = EnvConfig {
        observation: ObservationModel::SlotProximity,
        ..env.clone()
    };
    let init = Episodes::new(8, &blind, seed).next().expect("an episode");
    let baseline = ScriptedBaseline::new(&blind, BaselineGains::default());
    let mut world = World::new(&blind, init);
    while !world.poses.iter().any(|p| world.obstacles.distance([p.x, p.y]) < 0.5) {
        let commands: Vec<(f64, f64)> = (0..8)
            .map(|agent| baseline.command(&world.observation(agent)))
            .collect();
        assert_eq!(world.step(&commands).outcome, Outcome::Running, "reached the wall");
    }
    fn play(mut world: World, mut drive: impl FnMut(&World) -> Vec<(f64, f64)>) -> Vec<f64> {
        let mut rewards = Vec::new();
        loop {
            let commands = drive(&world);
            let result = world.step(&commands);
            rewards.push(result.reward);
            if result.outcome != Outcome::Running {
                return rewards;
            }
        }
    }
    let waiting = play(world.clone(), |_| vec![(0.0, 0.0); 8]);
    let mut planner = Planner::new(
        &world.poses,
        world.goal,
        &world.slots,
        &world.obstacles,
        env,
        BaselineGains::default(),
    );
    let passing = play(world, |world| planner.commands(&world.poses, world.steps).to_vec());
    (waiting, passing)
}

#[test]
fn the_obstacle_reward_makes_passing_worth_more_than_waiting() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/obstacles-train.toml");
    let config = crate::config::RunConfig::from_toml_file(&path).expect("the training config");
    let env = EnvConfig {
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Passage,
            ..config.env.obstacles.clone()
        },
        ..config.env.clone()
    };
    let table = EnvConfig::default();
    let paper = EnvConfig {
        r_edge: table.r_edge,
        r_progress: table.r_progress,
        formation_excuse_m: table.formation_excuse_m,
        ..env.clone()
    };
    for seed in [5, 6, 7] {
        let gamma = config.learn.gamma;
        let (wait, pass) = waiting_and_passing(&paper, seed);
        let (paper_wait, paper_pass) = (discounted(&wait, gamma), discounted(&pass, gamma));
        let (wait, pass) = waiting_and_passing(&env, seed);
        let (ours_wait, ours_pass) = (discounted(&wait, gamma), discounted(&pass, gamma));
        println!(
            "seed {seed}, gamma {gamma}: paper's reward: waiting {paper_wait:.2}, passing {paper_pass:.2} \
             ({} ticks); obstacle reward: waiting {ours_wait:.2}, passing {ours_pass:.2}",
            pass.len()
        );
        assert!(
            paper_wait > paper_pass,
            "the paper's reward pays waiting more (seed {seed})"
        );
        assert!(
            ours_pass > ours_wait,
            "the obstacle reward pays passing more (seed {seed})"
        );
    }
}

#[test]
fn a_cost_of_distance_from_the_slots_makes_waiting_cost_and_passing_worth_more_still() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/obstacles-distance.toml");
    let config = crate::config::RunConfig::from_toml_file(&path).expect("the distance config");
    assert!(config.env.r_distance < 0.0);
    let env = EnvConfig {
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Passage,
            ..config.env.obstacles.clone()
        },
        ..config.env.clone()
    };
    let free = EnvConfig {
        r_distance: 0.0,
        ..env.clone()
    };
    let gamma = config.learn.gamma;
    for seed in [5, 6, 7] {
        let (wait, pass) = waiting_and_passing(&free, seed);
        let free_margin = discounted(&pass, gamma) - discounted(&wait, gamma);
        let (wait, pass) = waiting_and_passing(&env, seed);
        let (costed_wait, costed_pass) = (discounted(&wait, gamma), discounted(&pass, gamma));
        println!(
            "seed {seed}, gamma {gamma}: with the distance cost waiting {costed_wait:.2}, passing {costed_pass:.2}; \
             passing's margin {:.2} against {free_margin:.2} without it",
            costed_pass - costed_wait
        );
        assert!(
            costed_wait < -1.0,
            "waiting short of the slots costs (seed {seed}): {costed_wait}"
        );
        assert!(
            costed_pass - costed_wait > free_margin,
            "passing gains more over waiting (seed {seed})"
        );
    }
}

#[test]
fn progress_round_the_obstacles_pays_passing_more_than_the_straight_measure_and_waiting_nothing_more() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/obstacles-geodesic.toml");
    let config = crate::config::RunConfig::from_toml_file(&path).expect("the geodesic config");
    assert!(config.env.geodesic_progress);
    let env = EnvConfig {
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Passage,
            ..config.env.obstacles.clone()
        },
        ..config.env.clone()
    };
    let straight = EnvConfig {
        geodesic_progress: false,
        ..env.clone()
    };
    let gamma = config.learn.gamma;
    for seed in [5, 6, 7] {
        let (straight_wait, straight_pass) = waiting_and_passing(&straight, seed);
        let (wait, pass) = waiting_and_passing(&env, seed);
        let (straight_wait, straight_pass) = (discounted(&straight_wait, gamma), discounted(&straight_pass, gamma));
        let (round_wait, round_pass) = (discounted(&wait, gamma), discounted(&pass, gamma));
        println!(
            "seed {seed}, gamma {gamma}: straight progress: waiting {straight_wait:.2}, passing {straight_pass:.2}; \
             round the obstacles: waiting {round_wait:.2}, passing {round_pass:.2}"
        );
        assert_eq!(round_wait, straight_wait, "standing still earns the same (seed {seed})");
        assert!(
            round_pass > straight_pass + 0.1,
            "the file's way through the gap is paid more round the obstacles (seed {seed})"
        );
    }
}

#[test]
fn within_keeps_the_obstacles_whose_surface_is_in_range_and_walls_whole() {
    let wall = Obstacle::Wall {
        a: [3.0, 0.0],
        b: [3.0, 10.0],
        thickness: 0.2,
    };
    let obstacles = Obstacles::new(vec![
        Obstacle::Disc {
            centre: [1.0, 0.0],
            radius: 0.5,
        },
        Obstacle::Disc {
            centre: [2.4, 0.0],
            radius: 0.5,
        },
        wall,
    ]);
    // From the origin: the first disc's surface is 0.5 m away, the second's 1.9 m, the wall's 2.9 m.
    let seen = obstacles.within([0.0, 0.0], 2.0);
    assert_eq!(seen.list().len(), 2);
    assert!(seen.list().iter().all(|o| !matches!(o, Obstacle::Wall { .. })));
    let near_the_wall = obstacles.within([2.5, 9.0], 0.5);
    assert_eq!(
        near_the_wall.list(),
        &[wall],
        "the whole wall, though 0.4 m of it is in range"
    );
    assert!(obstacles.within([0.0, 5.0], 0.5).is_empty());
}

/// Plays `episodes` episodes of `n` robots among obstacles of `kind` in `base`'s world (goals at
/// the kind's least distance and up to 1 m beyond, the kind's time limit), every robot driven by a controller
/// that `start` makes for each episode from its start (poses, goal, slots, obstacles) and that
/// answers every robot's (v, w) for the world at each tick: success, robot collisions and
/// obstacle hits, as fractions of the episodes. The planners' tests measure themselves with it.
pub(crate) fn rates_among_obstacles<D: FnMut(&crate::world::World) -> Vec<(f64, f64)>>(
    base: EnvConfig,
    kind: ObstacleKind,
    n: usize,
    episodes: usize,
    seed: u64,
    mut start: impl FnMut(&EpisodeInit, &EnvConfig) -> D,
) -> [f64; 3] {
    use crate::task::Outcome;
    let nearest = min_goal_distance_m(&ObstacleConfig::default(), kind, n, &base);
    let env = EnvConfig {
        goal_min_m: nearest,
        goal_max_m: nearest + 1.0,
        ..base
    };
    let radius = robot_radius_m(&env);
    let mut counts = [0usize; 3];
    for (episode, mut init) in Episodes::new(n, &env, seed).take(episodes).enumerate() {
        let starts: Vec<[f64; 2]> = init.poses.iter().map(|p| [p.x, p.y]).collect();
        let obstacles = draw(
            &ObstacleConfig::default(),
            kind,
            &starts,
            init.goal,
            &init.slots,
            &env,
            obstacle_seed(seed, episode as u64),
        );
        let centre = crate::task::centroid(&init.poses);
        let distance = (init.goal[0] - centre[0]).hypot(init.goal[1] - centre[1]);
        init.time_limit = episode_steps_with_obstacles(kind, distance, n, &env);
        init.obstacles = obstacles.clone();
        let mut drive = start(&init, &env);
        let mut world = crate::world::World::new(&env, init);
        loop {
            let commands = drive(&world);
            let outcome = world.step(&commands).outcome;
            if world.poses.iter().any(|p| obstacles.hits_robot([p.x, p.y], radius)) {
                counts[2] += 1;
                break;
            }
            match outcome {
                Outcome::Running => continue,
                Outcome::Success => counts[0] += 1,
                Outcome::Collision => counts[1] += 1,
                Outcome::Timeout | Outcome::Aborted => {}
            }
            break;
        }
    }
    counts.map(|c| c as f64 / episodes as f64)
}

#[test]
fn the_recovery_behaviour_takes_straight_drives_held_by_discs_round_them() {
    use crate::config::ObservationModel;
    use crate::reality::RealityConfig;
    use crate::stepper::EpisodeStepper;
    let with_recovery = |recovery_ticks: u32| EnvConfig {
        observation: ObservationModel::SlotProximityScan,
        obstacles: ObstacleConfig {
            kind: ObstacleKind::Forest,
            recovery_ticks,
            ..ObstacleConfig::default()
        },
        ..EnvConfig::default()
    };
    // Robots driving straight for their slots stop at a disc in their way (the monitor) and stay
    // there; with recovery each follows the disc round and drives on.
    let (mut mean_without, mut mean_with) = (0.0, 0.0);
    let mut taken_over_in_all = 0;
    for (episode, init) in Episodes::new(4, &with_recovery(0), 5).take(5).enumerate() {
        for (ticks, mean) in [(0, &mut mean_without), (30, &mut mean_with)] {
            let env = with_recovery(ticks);
            let mut stepper = EpisodeStepper::new(&env, &RealityConfig::default(), 5, episode as u32, init.clone());
            let mut taken_over = 0;
            while stepper.running() {
                stepper.tell();
                let commands = straight_for_the_slots(stepper.world());
                stepper.step(&commands, |_| true);
                // The replay's action is the command in use: the recovery's while it recovers.
                taken_over += stepper
                    .applied()
                    .iter()
                    .zip(&commands)
                    .filter(|&(&applied, &(v, w))| applied != env.clamp_command(v, w))
                    .count();
            }
            if ticks == 0 {
                assert_eq!(taken_over, 0, "episode {episode}: no recovery, yet commands taken over");
            }
            taken_over_in_all += taken_over;
            assert!(!stepper.last().conditions.obstacle_collision, "episode {episode}");
            let world = stepper.world();
            *mean += world
                .poses
                .iter()
                .zip(&world.slots)
                .map(|(p, s)| (world.goal[0] + s[0] - p.x).hypot(world.goal[1] + s[1] - p.y))
                .sum::<f64>()
                / 20.0;
        }
    }
    eprintln!("mean distance to the slots: {mean_with:.2} m with recovery, {mean_without:.2} m without");
    assert!(taken_over_in_all > 0, "the recovery never took a command over");
    assert!(
        mean_with < mean_without - 0.5,
        "mean distance to the slots at the end: {mean_with:.2} m with recovery, {mean_without:.2} m without"
    );
}
