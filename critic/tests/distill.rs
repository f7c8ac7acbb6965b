//! Distillation: the student comes closer to its teacher round by round, is saved as a
//! checkpoint the agents load, and the tool refuses bad input naming it.

mod common;

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::Command;

use formation_core::baseline::BaselineGains;
use formation_core::config::{ObservationModel, RunConfig};
use formation_critic::distill::{DistillOptions, Distiller, teacher_samples};
use formation_model::actor::{ActorHead, FrozenActor};
use formation_model::checkpoint;

fn small_options() -> DistillOptions {
    DistillOptions {
        sizes: vec![3],
        robots_per_round: 12,
        updates_per_round: 400,
        batch: 256,
        rounds: 10,
        capacity: 100_000,
        seed: 5,
        ..DistillOptions::default()
    }
}

fn field_config() -> RunConfig {
    let preset = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../configs/reality-field.toml");
    let mut config = RunConfig::from_toml_file(&preset).expect("the field preset");
    config.env.observation = ObservationModel::SlotProximity;
    config
}

#[test]
fn a_few_rounds_bring_a_fresh_student_close_to_its_teacher_under_the_field_preset() {
    let config = field_config();
    // The yardstick: the teacher's own episodes, on a seed distillation does not play.
    let yardstick = teacher_samples(&config, 3, 77, 4).expect("teacher samples");
    assert!(yardstick.len() > 100, "{} samples", yardstick.len());
    let mut distiller = Distiller::new(&config, small_options(), None).expect("a distiller");
    let before = distiller.mean_squared_error(&yardstick).expect("error");
    let mut reports = Vec::new();
    for _ in 0..10 {
        reports.push(distiller.round().expect("a round"));
    }
    let after = distiller.mean_squared_error(&yardstick).expect("error");
    assert!(after < 0.25 * before, "squared error {before:.4} -> {after:.4}");
    // The teacher drives the first round alone; the student drives most of the later ones.
    assert_eq!(reports[0].student[0].success, None);
    assert!(reports[1..].iter().any(|r| r.student[0].success.is_some()));
    assert!(reports.windows(2).all(|w| w[1].samples > w[0].samples));
    assert!(reports[9].lr < reports[0].lr);
    // The round's error is the mean of its per-output errors (v, w), each of them falling too.
    for report in &reports {
        let [v, w] = report.loss_per_output[..] else {
            panic!("{:?}", report.loss_per_output)
        };
        assert!(
            (report.loss - (v + w) / 2.0).abs() < 1e-9 * report.loss.max(1.0),
            "{report:?}"
        );
    }
    for output in 0..2 {
        assert!(
            reports[9].loss_per_output[output] < reports[0].loss_per_output[output],
            "{reports:?}"
        );
    }
}

#[test]
fn a_gain_schedule_student_is_taught_its_teacher_s_gains() {
    // The field's fast gains teach, under the field preset.
    let mut config = field_config();
    let fast = BaselineGains {
        k_form: 0.45,
        k_goal: 1.07,
        k_turn: 1.3,
        repulsion_range: 0.51,
        k_repulsion: 1.58,
        ..BaselineGains::default()
    };
    config.baseline = fast;
    let options = DistillOptions {
        head: ActorHead::Gains,
        rounds: 4,
        ..small_options()
    };
    // A teacher outside the schedule's ranges is refused, naming the gain.
    let mut too_fast = config.clone();
    too_fast.baseline.k_goal = 3.0;
    let refused = Distiller::new(&too_fast, options.clone(), None).err().expect("refused");
    assert!(format!("{refused:#}").contains("k_goal = 3"), "{refused:#}");
    let mut distiller = Distiller::new(&config, options, None).expect("a distiller");
    assert_eq!(distiller.shape().head.outputs(), 5);
    for _ in 0..4 {
        distiller.round().expect("a round");
    }
    let mut student =
        FrozenActor::from_flat(&distiller.actor_weights().expect("weights"), distiller.shape()).expect("actor");
    // On episodes it never played, every window is answered with the teacher's gains.
    let samples = teacher_samples(&config, 3, 77, 2).expect("samples");
    for i in (0..samples.len()).step_by(5) {
        let answered = BaselineGains::from_unit(student.act(samples.get(i).0).expect("acts"));
        for (got, want) in [
            (answered.k_form, fast.k_form),
            (answered.k_goal, fast.k_goal),
            (answered.k_turn, fast.k_turn),
            (answered.repulsion_range, fast.repulsion_range),
            (answered.k_repulsion, fast.k_repulsion),
        ] {
            assert!(
                (got / want - 1.0).abs() < 0.05,
                "answered {answered:?}, taught {fast:?}"
            );
        }
    }
}

#[test]
fn the_gain_profile_reports_the_gains_a_schedule_picks() {
    use formation_core::reality::RealityConfig;
    use formation_critic::distill::gain_profile;
    use formation_model::actor::ActorShape;
    let config = field_config();
    let shape = ActorShape {
        obs_dim: formation_core::observation::Layout::of(config.env.observation).dim(),
        history: 2,
        hidden: vec![8],
        head: ActorHead::Gains,
    };
    // Zero weights and a last bias of atanh(unit gains): the same gains for every window.
    let picked = BaselineGains {
        k_form: 0.9,
        k_goal: 0.85,
        k_turn: 2.0,
        repulsion_range: 0.5,
        k_repulsion: 2.0,
        ..BaselineGains::default()
    };
    let mut weights = vec![0.0f32; shape.parameter_count()];
    let tail = weights.len() - 5;
    for (slot, unit) in weights[tail..].iter_mut().zip(picked.to_unit()) {
        *slot = unit.atanh();
    }
    let mut env = config.env.clone();
    env.history = 2;
    let profile = gain_profile(&env, &RealityConfig::default(), &shape, &weights, (3, 1000, 2)).expect("a profile");
    for ((mean, spread), want) in profile.iter().zip(picked.values()) {
        assert!((mean / want - 1.0).abs() < 1e-4, "{profile:?} against {picked:?}");
        assert!(*spread < 1e-4, "{profile:?}");
    }
    // A command actor has no gain profile.
    let command = ActorShape {
        head: ActorHead::Command,
        ..shape.clone()
    };
    let weights = vec![0.0f32; command.parameter_count()];
    assert!(gain_profile(&env, &RealityConfig::default(), &command, &weights, (3, 1000, 1)).is_err());
}

#[test]
fn the_saved_student_is_a_checkpoint_the_agents_load_with_its_teacher_recorded() {
    let config = field_config();
    let options = DistillOptions {
        rounds: 1,
        ..small_options()
    };
    let mut distiller = Distiller::new(&config, options, None).expect("a distiller");
    distiller.round().expect("a round");
    let dir = common::tempdir("formation-distill");
    let path = dir.join("student.safetensors");
    distiller.save(&path, HashMap::new()).expect("saved");
    let loaded = checkpoint::load(&path).expect("loads");
    assert_eq!(&loaded.meta.actor, distiller.shape());
    assert_eq!(loaded.meta.n_actors, 1);
    assert_eq!(loaded.meta.observation, ObservationModel::SlotProximity);
    assert!(loaded.meta.extra["distilled_from"].contains("k_form 1.5"));
    let weights = distiller.actor_weights().expect("weights");
    assert_eq!(loaded.actor_weights(0).expect("weights"), weights);
    // An agent's actor built from the file answers as the student does.
    let mut agent =
        FrozenActor::from_flat(&loaded.actor_weights(0).expect("weights"), &loaded.meta.actor).expect("actor");
    let window = vec![0.25_f32; distiller.shape().input_dim()];
    let mut student = FrozenActor::from_flat(&weights, distiller.shape()).expect("actor");
    assert_eq!(agent.act(&window).expect("acts"), student.act(&window).expect("acts"));
    // Training can carry it on: its start is refused only for another shape.
    let mut other = config.clone();
    other.learn.actor_hidden = vec![32];
    let refused = Distiller::new(&other, small_options(), Some(&path))
        .err()
        .expect("refused");
    assert!(format!("{refused:#}").contains("shape"), "{refused:#}");
    Distiller::new(&config, small_options(), Some(&path)).expect("same shape carries over");
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn the_tool_refuses_bad_sizes_and_an_existing_output_naming_them() {
    let dir = common::tempdir("formation-distill");
    let out = dir.join("student.safetensors");
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_formation-distill"))
            .args(args)
            .output()
            .expect("runs")
    };
    let out_arg = out.to_str().expect("utf-8");
    let bad_size = run(&["--out", out_arg, "--sizes", "3,2"]);
    assert!(!bad_size.status.success());
    assert!(String::from_utf8_lossy(&bad_size.stderr).contains("--sizes"));
    // An interrupted run keeps its last student: --save-every writes it as it goes.
    let partial = dir.join("partial.safetensors");
    let two_rounds = run(&[
        "--out",
        partial.to_str().expect("utf-8"),
        "--sizes",
        "3",
        "--rounds",
        "2",
        "--robots-per-round",
        "6",
        "--updates",
        "5",
        "--batch",
        "64",
        "--save-every",
        "1",
        "--head",
        "gains",
    ]);
    assert!(
        two_rounds.status.success(),
        "{}",
        String::from_utf8_lossy(&two_rounds.stderr)
    );
    let saved = checkpoint::load(&partial).expect("the finished student");
    assert!(
        saved.meta.extra.contains_key("selection_success"),
        "{:?}",
        saved.meta.extra
    );
    assert!(!saved.meta.extra.contains_key("distill_unfinished"));
    assert_eq!(saved.meta.actor.head, ActorHead::Gains);
    std::fs::write(&out, b"keep me").expect("written");
    let exists = run(&["--out", out_arg, "--rounds", "1"]);
    assert!(!exists.status.success());
    assert!(String::from_utf8_lossy(&exists.stderr).contains("--force"));
    assert_eq!(std::fs::read(&out).expect("still there"), b"keep me");
    std::fs::remove_dir_all(dir).ok();
}
