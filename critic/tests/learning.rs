//! Learning mechanics on fixed batches: the TD target, the soft update and the critic fit.

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use formation_core::baseline::BaselineGains;
use formation_core::config::{
    ActorUpdate, Algorithm, Credit, CriticArchitecture, EnvConfig, ImitationTeacher, LearnConfig, QGradientActions,
};
use formation_core::features::CriticFeatures;
use formation_core::observation::Layout;
use formation_critic::learner::{Learner, soft_update};
use formation_model::checkpoint;
use formation_protocol::ACTION_DIM;
use formation_replay::sample::Batch;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn small_config(algorithm: Algorithm) -> (EnvConfig, LearnConfig) {
    let env = EnvConfig {
        history: 3,
        ..EnvConfig::default()
    };
    let learn = LearnConfig {
        algorithm,
        actor_hidden: vec![16],
        critic_hidden: vec![32, 32],
        batch_size: 32,
        target_noise: 0.0,
        imitation_alpha: 0.0,
        ..LearnConfig::default()
    };
    (env, learn)
}

fn random_batch(env: &EnvConfig, n: usize, b: usize, seed: u64) -> Batch {
    random_batch_for(env, CriticArchitecture::Mlp, n, b, seed)
}

fn random_batch_for(env: &EnvConfig, critic: CriticArchitecture, n: usize, b: usize, seed: u64) -> Batch {
    random_batch_of(env, CriticFeatures::new(n, env.observation, critic), b, seed)
}

/// A batch of random floats laid out for `features`.
fn random_batch_of(env: &EnvConfig, features: CriticFeatures, b: usize, seed: u64) -> Batch {
    let n = features.n_agents;
    let mut rng = StdRng::seed_from_u64(seed);
    let mut fill = |len: usize| (0..len).map(|_| rng.random_range(-1.0f32..1.0)).collect::<Vec<_>>();
    let h = env.history;
    let od = Layout::of(env.observation).dim();
    let sd = features.dim();
    Batch {
        batch_size: b,
        n_agents: n,
        history: h,
        obs_dim: od,
        state_dim: sd,
        observations: fill(b * n * h * od),
        next_observations: fill(b * n * h * od),
        states: fill(b * h * sd),
        next_states: fill(b * h * sd),
        actions: fill(b * h * n * ACTION_DIM),
        bootstrap_actions: fill(b * h * n * ACTION_DIM),
        rewards: fill(b),
        robot_rewards: Vec::new(),
        discounts: vec![LearnConfig::default().gamma as f32; b],
        terminals: vec![0.0; b],
        origins: vec![(0, 0); b],
        goals: vec![[0.0; 2]; b],
        relabelled: vec![false; b],
        present: Vec::new(),
        next_present: Vec::new(),
    }
}

/// The TD targets of a batch as plain numbers.
fn td_targets(learner: &mut Learner, batch: &Batch) -> Vec<f32> {
    learner
        .td_target(batch)
        .expect("target")
        .flatten_all()
        .expect("flat")
        .to_vec1::<f32>()
        .expect("vec")
}

#[test]
fn terminal_masks_the_target_and_truncation_does_not() {
    let (env, learn) = small_config(Algorithm::Ddpg);
    let mut learner = Learner::new(3, &env, &learn, 1).expect("learner");
    let mut batch = random_batch(&env, 3, 8, 2);
    for b in 0..8 {
        batch.terminals[b] = if b % 2 == 0 { 1.0 } else { 0.0 };
    }
    let y = td_targets(&mut learner, &batch);
    for (b, (target, reward)) in y.iter().zip(&batch.rewards).enumerate() {
        if b % 2 == 0 {
            assert!((target - reward).abs() < 1e-6, "terminal: y = r exactly");
        } else {
            assert!(
                (target - reward).abs() > 1e-6,
                "non-terminal (incl. time limit): y bootstraps from Q'"
            );
        }
    }
    // The bootstrapped part scales with the sample's discount (gamma^k with k rewards summed):
    // y - r = discount * Q'(s', pi'(o')) for non-terminals.
    let halved_discounts = Batch {
        discounts: batch.discounts.iter().map(|d| d / 2.0).collect(),
        ..batch.clone()
    };
    let y_half = td_targets(&mut learner, &halved_discounts);
    for b in (1..8).step_by(2) {
        let full = y[b] - batch.rewards[b];
        let halved = y_half[b] - batch.rewards[b];
        assert!((full - 2.0 * halved).abs() < 1e-4, "{full} vs 2 * {halved}");
    }
}

#[test]
fn soft_update_moves_targets_by_exactly_tau() {
    let device = Device::Cpu;
    let online = VarMap::new();
    let target = VarMap::new();
    let _ = VarBuilder::from_varmap(&online, DType::F32, &device)
        .get_with_hints(4, "w", candle_nn::Init::Const(1.0))
        .expect("online");
    let _ = VarBuilder::from_varmap(&target, DType::F32, &device)
        .get_with_hints(4, "w", candle_nn::Init::Const(0.0))
        .expect("target");
    soft_update(&online, &target, 0.25).expect("update");
    let value = |map: &VarMap| {
        map.data().lock().expect("lock")["w"]
            .as_tensor()
            .to_vec1::<f32>()
            .expect("vec")
    };
    assert_eq!(value(&target), vec![0.25; 4]);
    soft_update(&online, &target, 0.25).expect("update");
    assert_eq!(value(&target), vec![0.4375; 4]);
    assert_eq!(value(&online), vec![1.0; 4], "the online network is untouched");
}

#[test]
fn critic_loss_falls_on_a_fixed_batch() {
    for algorithm in [Algorithm::Ddpg, Algorithm::Td3] {
        let (env, learn) = small_config(algorithm);
        let mut learner = Learner::new(3, &env, &learn, 3).expect("learner");
        let mut batch = random_batch(&env, 3, 32, 4);
        batch.terminals = vec![1.0; 32]; // y = r: a fixed regression target
        let target = Tensor::from_slice(&batch.rewards, (32, 1), &Device::Cpu).expect("target");
        let before = learner
            .critic_loss(&batch, &target)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar");
        for _ in 0..200 {
            learner.update(&batch, 0).expect("update");
        }
        let after = learner
            .critic_loss(&batch, &target)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar");
        assert!(after < 0.2 * before, "{algorithm:?}: loss {before} -> {after}");
    }
}

#[test]
fn checkpoint_round_trip_and_shape_mismatch() {
    let (env, learn) = small_config(Algorithm::Td3);
    let learner = Learner::new(3, &env, &learn, 5).expect("learner");
    let dir = std::env::temp_dir().join(format!("formation-learner-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("checkpoint.safetensors");
    learner.save(&path, Default::default()).expect("save");
    let mut other = Learner::new(3, &env, &learn, 6).expect("learner");
    assert_ne!(other.actor_weights(0).expect("w"), learner.actor_weights(0).expect("w"));
    other.load(&path).expect("load");
    assert_eq!(other.actor_weights(0).expect("w"), learner.actor_weights(0).expect("w"));
    // A different actor width is refused with a message naming the file.
    let wider = LearnConfig {
        actor_hidden: vec![32],
        ..learn.clone()
    };
    let mut mismatched = Learner::new(3, &env, &wider, 7).expect("learner");
    let err = mismatched.load(&path).expect_err("shape mismatch").to_string();
    assert!(err.contains("checkpoint.safetensors"), "{err}");
    // Another swarm size takes the shared actor (it is N-agnostic); the critic starts fresh.
    let mut six = Learner::new(6, &env, &learn, 7).expect("learner");
    six.load(&path).expect("a shared actor carries over to another N");
    assert_eq!(six.actor_weights(0).expect("w"), learner.actor_weights(0).expect("w"));
    // Independent actors are one per robot, so another swarm size is refused.
    let independent = LearnConfig {
        shared_actor: false,
        ..learn.clone()
    };
    let three_independent = Learner::new(3, &env, &independent, 8).expect("learner");
    let independent_path = dir.join("independent.safetensors");
    three_independent
        .save(&independent_path, Default::default())
        .expect("save");
    let mut six_independent = Learner::new(6, &env, &independent, 9).expect("learner");
    let err = six_independent
        .load(&independent_path)
        .expect_err("robots differ")
        .to_string();
    assert!(err.contains("3 robots"), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn independent_actors_have_one_network_per_robot() {
    let (env, learn) = small_config(Algorithm::Ddpg);
    let learn = LearnConfig {
        shared_actor: false,
        ..learn
    };
    let mut learner = Learner::new(3, &env, &learn, 8).expect("learner");
    assert_eq!(learner.n_actors(), 3);
    let batch = random_batch(&env, 3, 16, 9);
    let losses = learner.update(&batch, 0).expect("update");
    assert!(losses.critic.is_finite() && losses.actor.is_some());
}

#[test]
fn a_teacher_pulls_the_actor_towards_the_baseline() {
    let (env, learn) = small_config(Algorithm::Td3);
    let env = EnvConfig { history: 1, ..env };
    let taught = LearnConfig {
        imitation_alpha: 0.1,
        policy_delay: 1,
        actor_lr: 1e-3,
        ..learn.clone()
    };
    let batch = random_batch(&env, 3, 64, 21);
    let mut learner = Learner::new(3, &env, &taught, 22).expect("learner");
    let before = learner.imitation_error(&batch).expect("error").expect("a teacher");
    for _ in 0..300 {
        learner.update(&batch, 0).expect("update");
    }
    let after = learner.imitation_error(&batch).expect("error").expect("a teacher");
    assert!(after < 0.7 * before, "imitation error {before} -> {after}");
    // Without a teacher there is nothing to imitate.
    let plain = Learner::new(3, &env, &learn, 22).expect("learner");
    assert!(plain.imitation_error(&batch).expect("error").is_none());
}

#[test]
fn the_teacher_commands_with_the_runs_baseline_gains() {
    let (env, learn) = small_config(Algorithm::Td3);
    let env = EnvConfig { history: 1, ..env };
    let taught = LearnConfig {
        imitation_alpha: 0.1,
        ..learn
    };
    let batch = random_batch(&env, 3, 64, 31);
    let error = |learner: &Learner| learner.imitation_error(&batch).expect("error").expect("a teacher");
    let default_teacher = error(&Learner::new(3, &env, &taught, 32).expect("learner"));
    let same = Learner::new(3, &env, &taught, 32)
        .expect("learner")
        .with_teacher_gains(BaselineGains::default());
    assert_eq!(error(&same), default_teacher, "same actor, same teacher");
    let goal_only = BaselineGains {
        k_form: 0.0,
        k_repulsion: 0.0,
        ..BaselineGains::default()
    };
    let tuned = Learner::new(3, &env, &taught, 32)
        .expect("learner")
        .with_teacher_gains(goal_only);
    assert_ne!(error(&tuned), default_teacher, "the same actor against another teacher");
}

#[test]
fn the_start_teacher_is_the_actor_as_frozen_and_holds_it_there() {
    let (env, learn) = small_config(Algorithm::Td3);
    let env = EnvConfig { history: 1, ..env };
    let anchored = LearnConfig {
        imitation_alpha: 0.1,
        imitation_teacher: ImitationTeacher::Start,
        policy_delay: 1,
        actor_lr: 1e-3,
        ..learn.clone()
    };
    let batch = random_batch(&env, 3, 64, 41);
    let mut learner = Learner::new(3, &env, &anchored, 42).expect("learner");
    assert!(
        learner.imitation_error(&batch).is_err(),
        "not frozen yet: no teacher to ask"
    );
    learner.freeze_start().expect("freeze");
    let error = |learner: &Learner| learner.imitation_error(&batch).expect("error").expect("a teacher");
    assert_eq!(error(&learner), 0.0, "the teacher is the actor as it was frozen");
    let moved = |alpha: f64| {
        let config = LearnConfig {
            imitation_alpha: alpha,
            ..anchored.clone()
        };
        let mut learner = Learner::new(3, &env, &config, 42).expect("learner");
        learner.freeze_start().expect("freeze");
        for _ in 0..200 {
            learner.update(&batch, 0).expect("update");
        }
        error(&learner)
    };
    // The Q term moves the actor away from its start; a strong pull (small alpha) holds it near.
    let (held, free) = (moved(0.01), moved(100.0));
    assert!(
        held > 0.0 && held < 0.25 * free,
        "off the start: pulled {held}, nearly free {free}"
    );
}

#[test]
fn td3_bootstraps_from_the_smaller_of_its_twin_critics() {
    // Same seed: TD3's first critic is DDPG's only critic (variables are drawn in name order),
    // so TD3's target can only be the same (its first critic is the smaller) or lower.
    let (env, ddpg_config) = small_config(Algorithm::Ddpg);
    let (_, td3_config) = small_config(Algorithm::Td3);
    let batch = random_batch(&env, 3, 64, 31);
    let (mut same, mut lower) = (0, 0);
    for seed in 30..40 {
        let mut ddpg = Learner::new(3, &env, &ddpg_config, seed).expect("learner");
        let mut td3 = Learner::new(3, &env, &td3_config, seed).expect("learner");
        let (single, twin) = (td_targets(&mut ddpg, &batch), td_targets(&mut td3, &batch));
        for (s, t) in single.iter().zip(&twin) {
            assert!(
                t <= &(s + 1e-6),
                "seed {seed}: a twin target {t} above the single one {s}"
            );
            if (s - t).abs() < 1e-6 { same += 1 } else { lower += 1 }
        }
    }
    assert!(
        same > 0 && lower > 0,
        "each critic should be the minimum somewhere: {same} same, {lower} lower"
    );
}

#[test]
fn twin_critics_on_two_threads_learn_exactly_what_one_thread_learns() {
    let (env, mut config) = small_config(Algorithm::Td3);
    config.target_noise = 0.2;
    let learners: Vec<Learner> = [false, true]
        .into_iter()
        .map(|parallel| {
            let config = LearnConfig {
                parallel_critics: parallel,
                ..config.clone()
            };
            let mut learner = Learner::new(3, &env, &config, 5).expect("learner");
            for step in 0..6 {
                learner
                    .update(&random_batch(&env, 3, 32, 100 + step), 0)
                    .expect("update");
            }
            learner
        })
        .collect();
    let [mut sequential, mut parallel] = <[Learner; 2]>::try_from(learners).ok().expect("two learners");
    let probe = random_batch(&env, 3, 32, 7);
    let target = td_targets(&mut sequential, &probe);
    assert_eq!(target, td_targets(&mut parallel, &probe), "target critics differ");
    let fixed = Tensor::from_slice(&target, (32, 1), &Device::Cpu).expect("target");
    let loss = |learner: &Learner| {
        learner
            .critic_loss(&probe, &fixed)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar")
    };
    assert_eq!(loss(&sequential), loss(&parallel), "online critics differ");
    assert_eq!(
        sequential.actor_weights(0).expect("actor"),
        parallel.actor_weights(0).expect("actor"),
        "actors differ"
    );
    // And the updates did something: a fresh learner's actor is not the trained one.
    let fresh = Learner::new(3, &env, &config, 5).expect("learner");
    assert_ne!(
        fresh.actor_weights(0).expect("actor"),
        parallel.actor_weights(0).expect("actor")
    );
}

#[test]
fn an_actor_step_raises_q_and_leaves_the_critic_alone() {
    let (env, learn) = small_config(Algorithm::Td3);
    let mut learner = Learner::new(3, &env, &learn, 40).expect("learner");
    let batch = random_batch(&env, 3, 64, 41);
    let target = Tensor::from_slice(&batch.rewards, (64, 1), &Device::Cpu).expect("target");
    let critic_loss = |learner: &Learner| {
        learner
            .critic_loss(&batch, &target)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar")
    };
    let (q_before, loss_before) = (learner.policy_value(&batch).expect("q"), critic_loss(&learner));
    for _ in 0..20 {
        learner.actor_step(&batch).expect("actor step");
    }
    let q_after = learner.policy_value(&batch).expect("q");
    assert!(q_after > q_before, "Q of the policy {q_before} -> {q_after}");
    assert_eq!(critic_loss(&learner), loss_before, "the critic moved");
}

/// Rms change between two flat weight vectors.
fn rms_move(before: &[f32], after: &[f32]) -> f64 {
    let sum: f64 = before.iter().zip(after).map(|(a, b)| f64::from(b - a).powi(2)).sum();
    (sum / before.len() as f64).sqrt()
}

#[test]
fn adam_moves_every_weight_by_the_rate_and_a_large_epsilon_scales_the_step_with_the_gradient() {
    let (env, mut learn) = small_config(Algorithm::Td3);
    let batch = random_batch(&env, 3, 64, 43);
    // Adam's first step is lr x g / (|g| + eps) on each weight: about lr on every weight with a
    // gradient at the default epsilon, whatever its size.
    let mut sign_like = Learner::new(3, &env, &learn, 42).expect("learner");
    let start = sign_like.actor_weights(0).expect("actor");
    let step = sign_like.actor_step(&batch).expect("step");
    assert!(
        step.gradient_rms > 0.0 && step.gradient_rms < 1e-2,
        "gradient rms {}",
        step.gradient_rms
    );
    let moved = rms_move(&start, &sign_like.actor_weights(0).expect("actor"));
    assert!(
        moved > 0.5 * learn.actor_lr && moved <= 1.0001 * learn.actor_lr,
        "rms move {moved} at lr {}",
        learn.actor_lr
    );
    // An epsilon far above every gradient: plain SGD at lr / eps, so the rms move is lr x the
    // gradient's rms / eps.
    learn.actor_adam_eps = 1.0;
    let mut scaled = Learner::new(3, &env, &learn, 42).expect("learner");
    assert_eq!(scaled.actor_weights(0).expect("actor"), start, "the same start");
    let step = scaled.actor_step(&batch).expect("step");
    let moved = rms_move(&start, &scaled.actor_weights(0).expect("actor"));
    let sgd = learn.actor_lr * step.gradient_rms / learn.actor_adam_eps;
    assert!((moved - sgd).abs() < 0.05 * sgd, "rms move {moved}, plain SGD's {sgd}");
}

/// Reverses the order of the `n` robots in every tick of a robot-major array.
fn reverse_robots(values: &[f32], n: usize, width: usize) -> Vec<f32> {
    values
        .chunks_exact(n * width)
        .flat_map(|tick| tick.chunks_exact(width).rev().flatten().copied())
        .collect()
}

#[test]
fn a_critic_with_map_points_reads_them_and_takes_a_plain_checkpoints_actor_with_a_fresh_critic() {
    let (env, learn) = small_config(Algorithm::Td3);
    let plain = LearnConfig {
        critic: CriticArchitecture::Pooled,
        critic_encoder: vec![32, 32],
        ..learn
    };
    let mapped = LearnConfig {
        critic_map_points: 4,
        ..plain.clone()
    };
    let features = CriticFeatures::new(3, env.observation, CriticArchitecture::Pooled).with_map_points(4);
    let mut batch = random_batch_of(&env, features, 32, 71);
    batch.terminals = vec![1.0; 32];
    let mut learner = Learner::new(3, &env, &mapped, 72).expect("learner");
    let target = Tensor::from_slice(&batch.rewards, (32, 1), &Device::Cpu).expect("target");
    let loss = |learner: &Learner, batch: &Batch| {
        learner
            .critic_loss(batch, &target)
            .expect("a batch with map points fits the critic")
            .to_scalar::<f32>()
            .expect("scalar")
    };
    // The critic reads the map points: changing only them changes its value.
    let before = loss(&learner, &batch);
    let mut moved = batch.clone();
    let token = features.token_dim();
    for (i, value) in moved.states.iter_mut().enumerate() {
        if i % token >= token - 3 * 4 {
            *value += 1.0;
        }
    }
    assert_ne!(loss(&learner, &moved), before, "the map points do not reach the critic");
    for _ in 0..50 {
        learner.update(&batch, 0).expect("update");
    }
    assert!(
        loss(&learner, &batch) < before,
        "the critic does not learn with map points"
    );
    // A checkpoint whose critic had no map points gives its actor; the critic starts fresh.
    let dir = std::env::temp_dir().join(format!("formation-learner-map-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("plain.safetensors");
    let source = Learner::new(3, &env, &plain, 73).expect("learner");
    source.save(&path, Default::default()).expect("save");
    let mut fresh = Learner::new(3, &env, &mapped, 74).expect("learner");
    let fresh_loss = loss(&fresh, &batch);
    fresh.load(&path).expect("the actor carries over");
    assert_eq!(fresh.actor_weights(0).expect("w"), source.actor_weights(0).expect("w"));
    assert_eq!(loss(&fresh, &batch), fresh_loss, "the critic was not left fresh");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn one_pooled_critic_fits_two_swarm_sizes_ignores_robot_order_and_carries_over() {
    let (env, learn) = small_config(Algorithm::Td3);
    let learn = LearnConfig {
        critic: CriticArchitecture::Pooled,
        critic_encoder: vec![32, 32],
        ..learn
    };
    let mut learner = Learner::new(3, &env, &learn, 11).expect("learner");
    let mut batches = [3, 5].map(|n| random_batch_for(&env, CriticArchitecture::Pooled, n, 32, n as u64));
    for batch in &mut batches {
        batch.terminals = vec![1.0; 32]; // y = r: a fixed regression target per size
    }
    let loss = |learner: &Learner, batch: &Batch| {
        let target = Tensor::from_slice(&batch.rewards, (32, 1), &Device::Cpu).expect("target");
        learner
            .critic_loss(batch, &target)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar")
    };
    let before = batches.each_ref().map(|b| loss(&learner, b));
    for step in 0..400 {
        learner.update(&batches[step % 2], step % 2).expect("update");
    }
    let after = batches.each_ref().map(|b| loss(&learner, b));
    for k in 0..2 {
        assert!(
            after[k] < 0.3 * before[k],
            "N = {}: loss {} -> {}",
            batches[k].n_agents,
            before[k],
            after[k]
        );
    }
    // A set function: the robots' order does not change Q.
    let token = batches[1].state_dim / 5;
    let reversed = Batch {
        states: reverse_robots(&batches[1].states, 5, token),
        actions: reverse_robots(&batches[1].actions, 5, ACTION_DIM),
        ..batches[1].clone()
    };
    assert_ne!(reversed.states, batches[1].states);
    assert!((loss(&learner, &reversed) - after[1]).abs() < 1e-4 * after[1].max(1.0));
    // The whole learner, critic included, loads into a run of another N.
    let dir = std::env::temp_dir().join(format!("formation-pooled-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("checkpoint.safetensors");
    learner.save(&path, Default::default()).expect("save");
    let mut five = Learner::new(5, &env, &learn, 12).expect("learner");
    assert_ne!(loss(&five, &batches[1]), after[1]);
    five.load(&path).expect("load");
    assert_eq!(loss(&five, &batches[1]), after[1], "the critic carried over");
    assert_eq!(five.updates(), 0, "no `updates` in the metadata given");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn with_two_swarms_taken_in_turn_each_gets_its_share_of_actor_and_teacher_steps() {
    let (env, learn) = small_config(Algorithm::Td3);
    let env = EnvConfig { history: 1, ..env };
    let learn = LearnConfig {
        critic: CriticArchitecture::Pooled,
        critic_encoder: vec![16],
        critic_hidden: vec![16],
        policy_delay: 2,
        imitation_alpha: 2.5,
        ..learn
    };
    let mut learner = Learner::new(3, &env, &learn, 12).expect("learner");
    let batches = [3, 4].map(|n| random_batch_for(&env, CriticArchitecture::Pooled, n, 8, n as u64));
    // Two swarms owed equally: the trainer's round robin alternates them.
    let mut actor_steps = [0u64; 2];
    for update in 0..200 {
        let swarm = update % 2;
        let losses = learner.update(&batches[swarm], swarm).expect("update");
        actor_steps[swarm] += u64::from(losses.actor.is_some());
    }
    for (swarm, &stepped) in actor_steps.iter().enumerate() {
        let steps = learner.swarm_steps(swarm);
        assert_eq!(steps.updates, 100, "swarm {swarm}");
        assert!(steps.actor.abs_diff(50) <= 1, "swarm {swarm}: {steps:?}");
        assert_eq!(steps.teacher, steps.actor, "swarm {swarm}: every actor step is taught");
        assert_eq!(stepped, steps.actor, "swarm {swarm}: the actor stepped on its batches");
    }
    assert_eq!(learner.updates(), 200);
}

/// A small pooled learner config with every actor term on: the teacher's pull and the action
/// penalty.
fn pooled_config() -> (EnvConfig, LearnConfig) {
    let (env, learn) = small_config(Algorithm::Td3);
    let learn = LearnConfig {
        critic: CriticArchitecture::Pooled,
        critic_encoder: vec![16, 16],
        policy_delay: 2,
        imitation_alpha: 2.5,
        action_l2: 0.1,
        ..learn
    };
    (env, learn)
}

/// Adds `delta` to robot `robot`'s entries (`width` floats a tick, `n` robots a tick) at every
/// tick of sample `b` of a tick-major [B, H * N * width] array.
fn shift_robot(values: &mut [f32], b: usize, h: usize, n: usize, width: usize, robot: usize, delta: f32) {
    for k in 0..h {
        let at = ((b * h + k) * n + robot) * width;
        values[at..at + width].iter_mut().for_each(|v| *v += delta);
    }
}

/// Adds `delta` to robot `robot`'s observation window in sample `b` of a [B, N, H * od] array.
fn shift_observations(values: &mut [f32], b: usize, n: usize, window: usize, robot: usize, delta: f32) {
    let at = (b * n + robot) * window;
    values[at..at + window].iter_mut().for_each(|v| *v += delta);
}

#[test]
fn the_pooled_critic_and_the_actor_terms_leave_a_robot_out_of_the_formation_out() {
    let (env, learn) = pooled_config();
    let (n, b, h) = (4, 16, env.history);
    let mut learner = Learner::new(n, &env, &learn, 21).expect("learner");
    let mut batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 22);
    // Robot 2 is out of the formation in every sample, at t and at t+k.
    let mask: Vec<f32> = (0..b * n).map(|i| if i % n == 2 { 0.0 } else { 1.0 }).collect();
    batch.present = mask.clone();
    batch.next_present = mask;
    let token = batch.state_dim / n;
    let window = batch.window_dim();
    // Everything robot 2 is and does, moved.
    let mut moved = batch.clone();
    for sample in 0..b {
        shift_robot(&mut moved.states, sample, h, n, token, 2, 3.0);
        shift_robot(&mut moved.next_states, sample, h, n, token, 2, -2.0);
        shift_robot(&mut moved.actions, sample, h, n, ACTION_DIM, 2, 0.5);
        shift_robot(&mut moved.bootstrap_actions, sample, h, n, ACTION_DIM, 2, 0.5);
        shift_observations(&mut moved.observations, sample, n, window, 2, 1.5);
        shift_observations(&mut moved.next_observations, sample, n, window, 2, 1.5);
    }
    let target = Tensor::from_slice(&batch.rewards, (b, 1), &Device::Cpu).expect("target");
    let loss = |learner: &Learner, batch: &Batch| {
        learner
            .critic_loss(batch, &target)
            .expect("loss")
            .to_scalar::<f32>()
            .expect("scalar")
    };
    // The masked mean: the critics' values, the TD target, the policy's value and the
    // teacher's pull ignore robot 2.
    assert_eq!(loss(&learner, &moved), loss(&learner, &batch));
    assert_eq!(td_targets(&mut learner, &moved), td_targets(&mut learner, &batch));
    assert_eq!(
        learner.policy_value(&moved).expect("q"),
        learner.policy_value(&batch).expect("q")
    );
    assert_eq!(
        learner.imitation_error(&moved).expect("error"),
        learner.imitation_error(&batch).expect("error")
    );
    // With robot 2 in the formation, the same moves change all of them.
    let members = |batch: &Batch| Batch {
        present: vec![1.0; b * n],
        next_present: vec![1.0; b * n],
        ..batch.clone()
    };
    let (all, all_moved) = (members(&batch), members(&moved));
    assert_ne!(loss(&learner, &all_moved), loss(&learner, &all));
    assert_ne!(td_targets(&mut learner, &all_moved), td_targets(&mut learner, &all));
    assert_ne!(
        learner.policy_value(&all_moved).expect("q"),
        learner.policy_value(&all).expect("q")
    );
    assert_ne!(
        learner.imitation_error(&all_moved).expect("error"),
        learner.imitation_error(&all).expect("error")
    );
    // Whole updates (critic and actor steps) learn exactly the same from both batches.
    let mut twin = Learner::new(n, &env, &learn, 21).expect("learner");
    for _ in 0..4 {
        assert_eq!(
            learner.update(&batch, 0).expect("update"),
            twin.update(&moved, 0).expect("update")
        );
    }
    assert_eq!(
        learner.actor_weights(0).expect("actor"),
        twin.actor_weights(0).expect("actor")
    );
}

#[test]
fn with_every_robot_present_the_masked_updates_are_bit_identical_to_the_plain_ones() {
    let (env, learn) = pooled_config();
    let (n, b) = (4, 16);
    let plain = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 31);
    let masked = Batch {
        present: vec![1.0; b * n],
        next_present: vec![1.0; b * n],
        ..plain.clone()
    };
    let mut without = Learner::new(n, &env, &learn, 32).expect("learner");
    let mut with = Learner::new(n, &env, &learn, 32).expect("learner");
    let mut actor_steps = 0;
    for _ in 0..6 {
        let (a, m) = (
            without.update(&plain, 0).expect("update"),
            with.update(&masked, 0).expect("update"),
        );
        assert_eq!(a, m, "losses");
        actor_steps += usize::from(a.actor.is_some());
    }
    assert_eq!(actor_steps, 3);
    assert_eq!(td_targets(&mut without, &plain), td_targets(&mut with, &masked));
    assert_eq!(
        without.imitation_error(&plain).expect("error"),
        with.imitation_error(&masked).expect("error")
    );
    assert_eq!(
        without.actor_weights(0).expect("actor"),
        with.actor_weights(0).expect("actor")
    );
    let dir = std::env::temp_dir().join(format!("formation-masked-ckpt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    for (name, learner) in [("without", &without), ("with", &with)] {
        learner.save(&dir.join(name), Default::default()).expect("save");
    }
    let [without, with] = ["without", "with"].map(|name| checkpoint::load(&dir.join(name)).expect("load"));
    let mut names: Vec<&String> = without.tensors.keys().collect();
    names.sort();
    for name in names {
        let values = |loaded: &checkpoint::Checkpoint| {
            loaded.tensors[name]
                .flatten_all()
                .expect("flat")
                .to_vec1::<f32>()
                .expect("values")
        };
        assert_eq!(values(&without), values(&with), "{name}");
    }
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn during_the_critic_warmup_the_actor_is_held_and_the_critic_learns() {
    let (env, learn) = pooled_config();
    let learn = LearnConfig {
        critic_warmup_updates: 6,
        ..learn
    };
    let mut learner = Learner::new(3, &env, &learn, 31).expect("learner");
    let batch = random_batch_for(&env, CriticArchitecture::Pooled, 3, 8, 32);
    let start = learner.actor_weights(0).expect("weights");
    let mut critic_losses = Vec::new();
    for _ in 0..6 {
        let losses = learner.update(&batch, 0).expect("update");
        assert!(losses.actor.is_none(), "no actor step during the warm-up");
        critic_losses.push(losses.critic);
    }
    assert_eq!(learner.actor_weights(0).expect("weights"), start, "the actor is held");
    assert!(!learner.actor_has_stepped(), "no checkpoint is scored yet");
    assert!(
        critic_losses[5] < critic_losses[0],
        "the critic stepped: {critic_losses:?}"
    );
    // After it, the actor steps on the policy delay's schedule.
    let stepped: Vec<(bool, bool)> = (0..4)
        .map(|_| {
            let actor = learner.update(&batch, 0).expect("update").actor.is_some();
            (actor, learner.actor_has_stepped())
        })
        .collect();
    // The first update after the warm-up waits for the policy delay: still the start.
    assert_eq!(stepped, [(false, false), (true, true), (false, true), (true, true)]);
    assert_ne!(
        learner.actor_weights(0).expect("weights"),
        start,
        "then the actor moves"
    );
    assert_eq!(learner.updates(), 10);
}

/// Robot `robot`'s action at t (the window's last tick) in sample `b` of a tick-major
/// [B, H * N * 2] action array.
fn action_at_t(actions: &mut [f32], b: usize, h: usize, n: usize, robot: usize) -> &mut [f32] {
    let at = ((b * h + h - 1) * n + robot) * ACTION_DIM;
    &mut actions[at..at + ACTION_DIM]
}

/// A learner of `learn` whose critics (only) have fitted `batch`'s rewards for 40 updates, so
/// that Q depends on the actions.
fn with_a_fitted_critic(n: usize, env: &EnvConfig, learn: &LearnConfig, seed: u64, batch: &Batch) -> Learner {
    let learn = LearnConfig {
        critic_warmup_updates: 1000,
        ..learn.clone()
    };
    let mut learner = Learner::new(n, env, &learn, seed).expect("learner");
    for _ in 0..40 {
        learner.update(batch, 0).expect("update");
    }
    learner
}

#[test]
fn each_robot_s_swap_advantage_is_q_as_played_minus_q_with_its_action_at_t_the_actor_s() {
    let (env, learn) = pooled_config();
    let (n, b, h) = (4, 8, env.history);
    let mut batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 52);
    let learner = with_a_fitted_critic(n, &env, &learn, 51, &batch);
    for present in [
        Vec::new(),
        (0..b * n).map(|i| if i % n == 1 { 0.0 } else { 1.0 }).collect(),
    ] {
        batch.present = present.clone();
        let advantages = learner.advantages(&batch).expect("advantages");
        let policy = learner.policy_actions(&batch).expect("actions");
        let played = learner.played_value(&batch).expect("q");
        for robot in 0..n {
            // The same batch with only this robot's action at t replaced by its actor's.
            let mut swapped = batch.clone();
            for sample in 0..b {
                let at = (sample * n + robot) * ACTION_DIM;
                action_at_t(&mut swapped.actions, sample, h, n, robot).copy_from_slice(&policy[at..at + ACTION_DIM]);
            }
            let q_swapped = learner.played_value(&swapped).expect("q");
            for sample in 0..b {
                let expected = played[sample] - q_swapped[sample];
                let got = advantages[sample * n + robot];
                assert!(
                    (got - expected).abs() < 1e-4,
                    "sample {sample} robot {robot}: {got} vs {expected}"
                );
                if !present.is_empty() && robot == 1 {
                    assert!(got.abs() < 1e-6, "a robot out of the formation changes nothing: {got}");
                }
            }
        }
        assert!(advantages.iter().any(|&a| a > 1e-3) && advantages.iter().any(|&a| a < -1e-3));
    }
}

#[test]
fn an_advantage_filtered_step_copies_the_played_actions_the_critic_rates_higher_and_only_those() {
    let (env, learn) = pooled_config();
    let learn = LearnConfig {
        actor_update: ActorUpdate::AdvantageFiltered,
        imitation_alpha: 0.0,
        action_l2: 0.0,
        actor_lr: 1e-3,
        ..learn
    };
    let (n, b, h) = (3, 32, env.history);
    let batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 62);
    let mut learner = with_a_fitted_critic(n, &env, &learn, 61, &batch);
    let better: Vec<bool> = learner
        .advantages(&batch)
        .expect("advantages")
        .iter()
        .map(|&a| a > 0.0)
        .collect();
    assert!(better.iter().any(|&x| x) && !better.iter().all(|&x| x), "{better:?}");
    // The squared distance to the played actions rated higher, per action component.
    let copy_error = |learner: &Learner| {
        let policy = learner.policy_actions(&batch).expect("actions");
        let mut played = batch.actions.clone();
        let mut sum = 0.0f64;
        for sample in 0..b {
            for robot in (0..n).filter(|&robot| better[sample * n + robot]) {
                let action = action_at_t(&mut played, sample, h, n, robot);
                for (k, &a) in action.iter().enumerate() {
                    sum += f64::from(policy[(sample * n + robot) * ACTION_DIM + k] - a).powi(2);
                }
            }
        }
        sum / (b * n * ACTION_DIM) as f64
    };
    let before = copy_error(&learner);
    let loss = learner.actor_step(&batch).expect("step").loss;
    assert!(
        (loss - before).abs() < 1e-5,
        "the actor's loss {loss} is the filtered copy {before}"
    );
    for _ in 0..30 {
        learner.actor_step(&batch).expect("step");
    }
    let after = copy_error(&learner);
    assert!(
        after < 0.7 * before,
        "towards the better played actions: {before} -> {after}"
    );
}

#[test]
fn with_q_gradient_actions_turn_the_critic_moves_the_turn_rates_and_leaves_the_speeds_output_row_alone() {
    let (env, learn) = pooled_config();
    let (n, b) = (3, 16);
    let batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 72);
    // The output layer's rows in the flat weights: [.., W (2 x hidden, the speed's row first), b].
    let hidden = *learn.actor_hidden.last().expect("a hidden layer");
    let rows = |w: &[f32]| {
        let (weights, biases) = w.split_at(w.len() - ACTION_DIM);
        let output = &weights[weights.len() - ACTION_DIM * hidden..];
        let row = |k: usize| -> Vec<f32> {
            output[k * hidden..(k + 1) * hidden]
                .iter()
                .chain([&biases[k]])
                .copied()
                .collect()
        };
        (row(0), row(1), weights[..weights.len() - ACTION_DIM * hidden].to_vec())
    };
    for (actions, speed_moves) in [(QGradientActions::Both, true), (QGradientActions::Turn, false)] {
        let learn = LearnConfig {
            q_gradient_actions: actions,
            imitation_alpha: 0.0,
            action_l2: 0.0,
            ..learn.clone()
        };
        let mut learner = with_a_fitted_critic(n, &env, &learn, 71, &batch);
        let (speed, turn, hidden_layers) = rows(&learner.actor_weights(0).expect("weights"));
        for _ in 0..5 {
            learner.actor_step(&batch).expect("step");
        }
        let (speed_after, turn_after, hidden_after) = rows(&learner.actor_weights(0).expect("weights"));
        assert_eq!(speed != speed_after, speed_moves, "{actions:?}: the speed's output row");
        assert_ne!(turn, turn_after, "{actions:?}: the turn rate's output row moves");
        assert_ne!(hidden_layers, hidden_after, "{actions:?}: the hidden layers move");
    }
}

#[test]
fn with_actor_output_layer_only_an_actor_step_moves_the_output_layer_and_holds_the_hidden_ones() {
    let (env, learn) = pooled_config();
    let (n, b) = (3, 16);
    let batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 74);
    let hidden = *learn.actor_hidden.last().expect("a hidden layer");
    // The flat weights end with the output layer: W (2 x hidden), then b (2).
    let output_start = |w: &[f32]| w.len() - ACTION_DIM * hidden - ACTION_DIM;
    for (only, hidden_moves) in [(false, true), (true, false)] {
        let learn = LearnConfig {
            actor_output_layer_only: only,
            ..learn.clone()
        };
        let mut learner = with_a_fitted_critic(n, &env, &learn, 73, &batch);
        let before = learner.actor_weights(0).expect("weights");
        for _ in 0..5 {
            learner.actor_step(&batch).expect("step");
        }
        let after = learner.actor_weights(0).expect("weights");
        let split = output_start(&before);
        assert_eq!(
            before[..split] != after[..split],
            hidden_moves,
            "output layer only = {only}: the hidden layers"
        );
        assert_ne!(
            before[split..],
            after[split..],
            "output layer only = {only}: the output layer moves"
        );
    }
}

/// The critic loss on `batch` against a target of zeros.
fn zero_target_loss(learner: &Learner, batch: &Batch) -> f32 {
    let zeros = Tensor::zeros((batch.batch_size, 1), DType::F32, &Device::Cpu).expect("zeros");
    let loss = learner.critic_loss(batch, &zeros).expect("loss");
    loss.to_scalar::<f32>().expect("scalar")
}

#[test]
fn with_a_range_sensor_the_critics_read_every_robots_rays_and_nothing_else_of_its_observation() {
    use formation_core::config::ObservationModel;
    for critic in [CriticArchitecture::Pooled, CriticArchitecture::Mlp] {
        let (env, learn) = small_config(Algorithm::Td3);
        let env = EnvConfig {
            observation: ObservationModel::SlotProximityScan,
            history: 2,
            ..env
        };
        let learn = LearnConfig {
            critic,
            critic_encoder: vec![16],
            ..learn
        };
        let (n, b) = (3, 8);
        let learner = Learner::new(n, &env, &learn, 41).expect("learner");
        let batch = random_batch_for(&env, critic, n, b, 42);
        let layout = Layout::of(env.observation);
        let (od, scan) = (layout.dim(), layout.scan().expect("a range sensor"));
        let at =
            |sample: usize, robot: usize, tick: usize, k: usize| ((sample * n + robot) * env.history + tick) * od + k;
        let base = zero_target_loss(&learner, &batch);
        // One ray of robot 2 at the window's first tick: the value changes.
        let mut ray = batch.clone();
        ray.observations[at(0, 2, 0, scan + 5)] += 0.5;
        assert_ne!(
            zero_target_loss(&learner, &ray),
            base,
            "{critic:?}: a ray moves the value"
        );
        // The goal and slot the robot observes: the state already holds them, the critic ignores them.
        let mut goal = batch.clone();
        for k in 0..scan {
            goal.observations[at(0, 2, 1, k)] += 0.5;
        }
        assert_eq!(
            zero_target_loss(&learner, &goal),
            base,
            "{critic:?}: only the rays are read"
        );
    }
}

#[test]
fn a_resumed_learner_counts_its_own_updates_apart_from_the_checkpoints() {
    let (env, learn) = pooled_config();
    let mut first = Learner::new(3, &env, &learn, 51).expect("learner");
    let batch = random_batch_for(&env, CriticArchitecture::Pooled, 3, 8, 52);
    for _ in 0..3 {
        first.update(&batch, 0).expect("update");
    }
    let dir = std::env::temp_dir().join(format!("formation-resumed-updates-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("dir");
    let path = dir.join("checkpoint.safetensors");
    let meta = [("updates".to_string(), first.updates().to_string())]
        .into_iter()
        .collect();
    first.save(&path, meta).expect("save");
    let mut resumed = Learner::new(3, &env, &learn, 53).expect("learner");
    resumed.load(&path).expect("load");
    assert_eq!((resumed.updates(), resumed.run_updates()), (3, 0));
    resumed.update(&batch, 0).expect("update");
    assert_eq!(
        (resumed.updates(), resumed.run_updates()),
        (4, 1),
        "rates count this run's updates only"
    );
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn with_per_robot_credit_each_robot_s_target_answers_for_its_own_reward() {
    let (env, learn) = pooled_config();
    let learn = LearnConfig {
        credit: Credit::Robot,
        ..learn
    };
    let (n, b) = (4, 8);
    let mut batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 71);
    batch.robot_rewards = (0..b * n).map(|i| batch.rewards[i / n]).collect();
    let mut learner = Learner::new(n, &env, &learn, 72).expect("learner");
    let before = td_targets(&mut learner, &batch);
    assert_eq!(before.len(), b * n, "one target per robot");
    // Robot 1's own reward moves robot 1's target alone, by as much.
    let mut raised = batch.clone();
    (0..b).for_each(|s| raised.robot_rewards[s * n + 1] += 1.0);
    let after = td_targets(&mut learner, &raised);
    for (i, (x, y)) in before.iter().zip(&after).enumerate() {
        let expected = if i % n == 1 { 1.0 } else { 0.0 };
        assert!((y - x - expected).abs() < 1e-5, "entry {i}: {x} -> {y}");
    }
    // Without per-robot rewards every robot's target takes the shared one.
    let shared = Batch {
        robot_rewards: Vec::new(),
        ..batch.clone()
    };
    assert_eq!(td_targets(&mut learner, &shared), before);
}

#[test]
fn a_per_robot_critic_learns_which_robot_s_reward_is_high_where_the_team_s_cannot() {
    let (env, learn) = pooled_config();
    let (n, b) = (4, 32);
    let mut batch = random_batch_for(&env, CriticArchitecture::Pooled, n, b, 81);
    // Terminal samples: the target is the reward alone. Robot 2 earns 1, the others -1.
    batch.terminals = vec![1.0; b];
    batch.robot_rewards = (0..b * n).map(|i| if i % n == 2 { 1.0 } else { -1.0 }).collect();
    batch.rewards = vec![-0.5; b];
    for (credit, values) in [(Credit::Team, b), (Credit::Robot, b * n)] {
        let learn = LearnConfig {
            credit,
            critic_warmup_updates: 1_000,
            ..learn.clone()
        };
        let mut learner = Learner::new(n, &env, &learn, 82).expect("learner");
        for _ in 0..400 {
            learner.update(&batch, 0).expect("update");
        }
        let q = learner.played_value(&batch).expect("q");
        assert_eq!(q.len(), values);
        if credit == Credit::Robot {
            let mean_of = |robot: usize| q.iter().skip(robot).step_by(n).sum::<f32>() / b as f32;
            assert!((mean_of(2) - 1.0).abs() < 0.2, "robot 2's value {}", mean_of(2));
            for robot in [0, 1, 3] {
                assert!(
                    (mean_of(robot) + 1.0).abs() < 0.2,
                    "robot {robot}'s value {}",
                    mean_of(robot)
                );
            }
        } else {
            let mean = q.iter().sum::<f32>() / b as f32;
            assert!((mean + 0.5).abs() < 0.2, "the team's value {mean}");
        }
    }
}
