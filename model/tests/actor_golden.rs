//! Golden values of the shipped actors for other implementations (the numpy actor of the Python
//! package, `python/formation_swarm/policy.py`): each checkpoint is played on a fixed sequence of
//! observations over three episodes, through the agent's own window ([`ObservationHistory`]:
//! padded with an episode's first observation, then sliding) and the agent's own command
//! ([`FrozenActor::command`], the default `[env]`), and every step's window, raw outputs and
//! (v, w) are compared with `python/tests/actor_golden.json`. `FORMATION_WRITE_GOLDEN=1 cargo
//! test --workspace --test actor_golden` writes the file instead.

use std::path::{Path, PathBuf};

use formation_core::config::RunConfig;
use formation_core::observation::Layout;
use formation_model::actor::FrozenActor;
use formation_model::checkpoint;
use formation_model::history::ObservationHistory;
use serde_json::{Value, json};

/// The shipped gains head (H = 4) and the distilled command head (H = 1). (The paper model's
/// outputs saturate, so its commands would tell little.)
const MODELS: [&str; 2] = ["formation.safetensors", "formation-field-distilled.safetensors"];
/// Steps of each episode: the first longer than the largest window, the second shorter.
const EPISODES: [usize; 3] = [6, 2, 5];

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A smooth, deterministic observation of `dim` floats for step `step`, shaped like a real one
/// of `slot_proximity` (`paper` is its first 12 floats): neighbours behind-left and behind-right
/// near their desired distance with their headings' (cos, sin), the goal and the robot's slot
/// ahead, from near to far, a faint nearest other robot. Inside what the actors were trained on,
/// so that their outputs are not all saturated.
fn observation(dim: usize, step: usize) -> Vec<f32> {
    let p = 0.45 * step as f64;
    let template = [
        -0.6 + 0.2 * p.sin(),
        0.5 + 0.1 * p.cos(),
        (0.3 * p.sin()).cos(),
        (0.3 * p.sin()).sin(),
        0.8,
        -0.6 + 0.1 * p.cos(),
        -0.5 + 0.2 * (1.3 * p).sin(),
        (0.2 * p.cos()).cos(),
        (0.2 * p.cos()).sin(),
        0.8,
        0.9 + 0.7 * (0.7 * p).sin(),
        0.6 * p.sin(),
        1.0 + 0.6 * (0.7 * p).sin(),
        -0.2 + 0.5 * p.sin(),
        0.15 * p.sin(),
        0.1 * p.cos(),
    ];
    assert!(dim <= template.len(), "no template for {dim} floats");
    template[..dim].iter().map(|&x| x as f32).collect()
}

fn play(model: &str) -> Value {
    let loaded = checkpoint::load(&repo().join("models").join(model)).expect("checkpoint");
    let shape = loaded.meta.actor.clone();
    let mut env = RunConfig::default().env;
    env.observation = loaded.meta.observation;
    assert_eq!(Layout::of(env.observation).dim(), shape.obs_dim);
    let mut actor = FrozenActor::from_flat(&loaded.actor_weights(0).expect("weights"), &shape).expect("actor");
    let mut history = ObservationHistory::new(shape.history, shape.obs_dim);
    let mut steps = Vec::new();
    let mut step = 0;
    for (episode, &length) in EPISODES.iter().enumerate() {
        for tick in 0..length {
            let obs = observation(shape.obs_dim, step);
            if tick == 0 {
                history.reset(&obs);
            } else {
                history.push(&obs);
            }
            let window = history.as_flat().to_vec();
            let outputs = actor.act(&window).expect("act").to_vec();
            let (v, w) = actor.command(&window, &env).expect("command");
            steps.push(json!({
                "episode": episode,
                "tick": tick,
                "obs": obs.iter().map(|&x| f64::from(x)).collect::<Vec<_>>(),
                "window": window.iter().map(|&x| f64::from(x)).collect::<Vec<_>>(),
                "outputs": outputs.iter().map(|&x| f64::from(x)).collect::<Vec<_>>(),
                "v": v,
                "w": w,
            }));
            step += 1;
        }
    }
    json!({
        "model": model,
        "observation": env.observation.as_str(),
        "head": shape.head.as_str(),
        "history": shape.history,
        "v_max": env.v_max,
        "w_max": env.w_max,
        "steps": steps,
    })
}

#[test]
fn the_shipped_actors_golden_values_are_what_the_agent_computes() {
    let golden = json!({
        "about": "written by model/tests/actor_golden.rs (FORMATION_WRITE_GOLDEN=1 cargo test --workspace --test actor_golden)",
        "models": MODELS.iter().map(|m| play(m)).collect::<Vec<_>>(),
    });
    let path = repo().join("python").join("tests").join("actor_golden.json");
    if std::env::var_os("FORMATION_WRITE_GOLDEN").is_some() {
        let text = serde_json::to_string_pretty(&golden).expect("json") + "\n";
        std::fs::write(&path, text).expect("write golden file");
        return;
    }
    let text = std::fs::read_to_string(&path).expect("golden file (FORMATION_WRITE_GOLDEN=1 writes it)");
    let stored: Value = serde_json::from_str(&text).expect("golden json");
    if let Err(at) = close(&stored, &golden, "") {
        panic!(
            "{} is not what the agent computes today (at {at}): rerun with FORMATION_WRITE_GOLDEN=1",
            path.display()
        );
    }
}

/// The same JSON, numbers within 1e-6 (f32 sums may be ordered otherwise on another CPU); else
/// where they differ.
fn close(a: &Value, b: &Value, at: &str) -> Result<(), String> {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap_or(f64::NAN), y.as_f64().unwrap_or(f64::NAN));
            if (x - y).abs() <= 1e-6 * x.abs().max(1.0) {
                Ok(())
            } else {
                Err(format!("{at}: {x} vs {y}"))
            }
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => x
            .iter()
            .zip(y)
            .enumerate()
            .try_for_each(|(i, (x, y))| close(x, y, &format!("{at}[{i}]"))),
        (Value::Object(x), Value::Object(y)) if x.len() == y.len() => x.iter().try_for_each(|(key, x)| {
            let y = y.get(key).ok_or_else(|| format!("{at}.{key} missing"))?;
            close(x, y, &format!("{at}.{key}"))
        }),
        _ if a == b => Ok(()),
        _ => Err(format!("{at}: {a} vs {b}")),
    }
}
