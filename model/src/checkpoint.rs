//! Checkpoints: one safetensors file of named f32 tensors plus string metadata describing the
//! networks, so a file for another shape or swarm is refused with a clear message.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use candle_core::{Device, Tensor};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use formation_core::config::ObservationModel;

use crate::actor::{ActorHead, ActorShape};

/// Marks files written by this project.
pub const FORMAT: &str = "formation-rl/1";
/// The file name inside a run directory.
pub const FILE_NAME: &str = "checkpoint.safetensors";
/// The best checkpoint (by its selection score, [`SelectionScore`]) inside a run directory.
pub const BEST_FILE_NAME: &str = "best.safetensors";

/// Observation width of the files written before the metadata named their observation model.
const PAPER_OBS_DIM: usize = 12;

/// What a checkpoint describes.
#[derive(Debug, Clone, PartialEq)]
pub struct CheckpointMeta {
    /// Robots the critic was trained for.
    pub n_agents: usize,
    /// What the robots observed (checkpoints from before the models existed: `paper`).
    pub observation: ObservationModel,
    /// Number of actors stored (1 when shared).
    pub n_actors: usize,
    /// The actors' shape.
    pub actor: ActorShape,
    /// Free-form string pairs (training figures).
    pub extra: HashMap<String, String>,
}

impl CheckpointMeta {
    fn to_map(&self) -> HashMap<String, String> {
        let mut map = self.extra.clone();
        map.insert("format".into(), FORMAT.into());
        map.insert("n_agents".into(), self.n_agents.to_string());
        map.insert("n_actors".into(), self.n_actors.to_string());
        map.insert("observation".into(), self.observation.as_str().into());
        map.insert("obs_dim".into(), self.actor.obs_dim.to_string());
        map.insert("history".into(), self.actor.history.to_string());
        map.insert("actor_hidden".into(), format!("{:?}", self.actor.hidden));
        map.insert("actor_head".into(), self.actor.head.as_str().into());
        map
    }

    fn from_map(map: &HashMap<String, String>, path: &Path) -> Result<Self> {
        let field = |key: &str| {
            map.get(key)
                .ok_or_else(|| anyhow::anyhow!("checkpoint {} has no metadata field {key:?}", path.display()))
        };
        if field("format")? != FORMAT {
            bail!(
                "checkpoint {} has format {:?}, expected {FORMAT:?}",
                path.display(),
                field("format")?
            );
        }
        let number = |key: &str| -> Result<usize> {
            field(key)?
                .parse()
                .with_context(|| format!("checkpoint {}: metadata {key} is not a number", path.display()))
        };
        let hidden: Vec<usize> = serde_json::from_str(field("actor_hidden")?)
            .with_context(|| format!("checkpoint {}: metadata actor_hidden is not a list", path.display()))?;
        // Files written before observation models existed hold the paper's 12 floats.
        let observation = match map.get("observation") {
            None => ObservationModel::Paper,
            Some(name) => ObservationModel::from_name(name)
                .with_context(|| format!("checkpoint {}: unknown observation model {name:?}", path.display()))?,
        };
        let obs_dim = if map.contains_key("obs_dim") {
            number("obs_dim")?
        } else {
            PAPER_OBS_DIM
        };
        // Files written before gain-scheduling actors existed output commands.
        let head = match map.get("actor_head") {
            None => ActorHead::Command,
            Some(name) => ActorHead::from_name(name)
                .with_context(|| format!("checkpoint {}: unknown actor head {name:?}", path.display()))?,
        };
        Ok(Self {
            n_agents: number("n_agents")?,
            observation,
            n_actors: number("n_actors")?,
            actor: ActorShape {
                obs_dim,
                history: number("history")?,
                hidden,
                head,
            },
            extra: map.clone(),
        })
    }
}

impl CheckpointMeta {
    /// Refuses a checkpoint trained on another observation than the run's, saying what to do.
    pub fn check_observation(&self, path: &Path, run_model: ObservationModel, run_dim: usize) -> Result<()> {
        if self.observation != run_model || self.actor.obs_dim != run_dim {
            bail!(
                "checkpoint {} was trained on the {:?} observation ({} floats), but this run observes {:?} \
                 ({run_dim} floats): set env.observation = \"{}\" in the --config file, or use a checkpoint \
                 trained on {:?}",
                path.display(),
                self.observation.as_str(),
                self.actor.obs_dim,
                run_model.as_str(),
                self.observation.as_str(),
                run_model.as_str()
            );
        }
        Ok(())
    }
}

impl CheckpointMeta {
    /// The selection score the file was saved with (files from before model selection have none).
    pub fn selection(&self, path: &Path) -> Result<Option<SelectionScore>> {
        SelectionScore::from_metadata(&self.extra)
            .with_context(|| format!("checkpoint {}: selection metadata", path.display()))
    }
}

/// How a checkpoint's weights did on the run's fixed selection episodes: noise-free, played with
/// exactly the weights in the file, `episodes` per swarm size from `seed`.
#[derive(Debug, Clone, PartialEq)]
pub struct SelectionScore {
    /// Seed of the episodes (a sim started with this `--seed` plays the same ones).
    pub seed: u64,
    /// Episodes per swarm size.
    pub episodes: usize,
    /// The figures of each swarm size.
    pub sizes: Vec<SizeScore>,
    /// The `[reality]` the episodes were played under, on one line; `None`: the ideal world.
    pub reality: Option<String>,
    /// Under a reality, the same episodes' figures in the ideal world (reported, not scored).
    pub ideal: Option<Vec<SizeScore>>,
}

/// The selection figures of one swarm size.
#[derive(Debug, Clone, PartialEq)]
pub struct SizeScore {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Fraction of the episodes that reached the goal in formation.
    pub success: f64,
    /// Fraction of the ticks in formation (C1), averaged over the episodes.
    pub formation_held: f64,
    /// Steps per episode (a time limit counts in full).
    pub mean_steps: f64,
}

impl SelectionScore {
    /// The score: the lowest success over the swarm sizes, since one model must serve every N
    /// (a mean would let a size the actor forgot hide behind the others).
    pub fn success(&self) -> f64 {
        self.sizes.iter().map(|s| s.success).reduce(f64::min).unwrap_or(0.0)
    }

    /// A figure averaged over the swarm sizes.
    pub fn mean(&self, figure: impl Fn(&SizeScore) -> f64) -> f64 {
        self.sizes.iter().map(figure).sum::<f64>() / self.sizes.len().max(1) as f64
    }

    /// Whether this beats `best`: a higher score, or the same score and a higher mean success,
    /// or both the same and fewer steps on average (a faster policy; a time limit counts in
    /// full, so this also rewards fewer timeouts).
    pub fn beats(&self, best: Option<&SelectionScore>) -> bool {
        let key = |s: &SelectionScore| (s.success(), s.mean(|s| s.success), -s.mean(|s| s.mean_steps));
        best.is_none_or(|best| key(self) > key(best))
    }

    /// Adds the `selection_*` metadata keys: the score, seed and episodes, the formation-held
    /// rate and steps averaged over the sizes, and `selection_by_size`, each size's
    /// `N:success:formation_held:mean_steps`, comma-separated; under a reality
    /// `selection_reality` (its keys on one line) and `selection_ideal_by_size` (the ideal
    /// world's figures, the same way).
    pub fn to_metadata(&self, extra: &mut HashMap<String, String>) {
        extra.insert("selection_success".into(), format!("{:.3}", self.success()));
        extra.insert("selection_seed".into(), self.seed.to_string());
        extra.insert("selection_episodes".into(), self.episodes.to_string());
        extra.insert(
            "selection_formation_held".into(),
            format!("{:.3}", self.mean(|s| s.formation_held)),
        );
        extra.insert(
            "selection_mean_steps".into(),
            format!("{:.1}", self.mean(|s| s.mean_steps)),
        );
        extra.insert("selection_by_size".into(), by_size(&self.sizes));
        if let Some(reality) = &self.reality {
            extra.insert("selection_reality".into(), reality.clone());
        }
        if let Some(ideal) = &self.ideal {
            extra.insert("selection_ideal_by_size".into(), by_size(ideal));
        }
    }

    /// Reads the keys written by [`SelectionScore::to_metadata`]; `None` when there are none.
    pub fn from_metadata(map: &HashMap<String, String>) -> Result<Option<Self>> {
        let Some(by_size) = map.get("selection_by_size") else {
            return Ok(None);
        };
        let field = |key: &str| map.get(key).with_context(|| format!("no {key}"));
        let sizes = |text: &str| text.split(',').map(SizeScore::parse).collect::<Result<Vec<_>>>();
        Ok(Some(Self {
            seed: field("selection_seed")?.parse().context("selection_seed")?,
            episodes: field("selection_episodes")?.parse().context("selection_episodes")?,
            sizes: sizes(by_size).context("selection_by_size")?,
            reality: map.get("selection_reality").cloned(),
            ideal: map
                .get("selection_ideal_by_size")
                .map(|text| sizes(text))
                .transpose()
                .context("selection_ideal_by_size")?,
        }))
    }
}

/// Each size's `N:success:formation_held:mean_steps`, comma-separated, in shortest round-trip
/// decimals (a score reads back exactly).
fn by_size(sizes: &[SizeScore]) -> String {
    let fields: Vec<String> = sizes
        .iter()
        .map(|s| format!("{}:{}:{}:{}", s.n_agents, s.success, s.formation_held, s.mean_steps))
        .collect();
    fields.join(",")
}

impl SizeScore {
    /// Reads `N:success:formation_held:mean_steps`.
    fn parse(text: &str) -> Result<Self> {
        let fields: Vec<&str> = text.split(':').collect();
        let [n_agents, success, formation_held, mean_steps] = fields[..] else {
            bail!("{text:?} is not N:success:formation_held:mean_steps");
        };
        Ok(Self {
            n_agents: n_agents.parse()?,
            success: success.parse()?,
            formation_held: formation_held.parse()?,
            mean_steps: mean_steps.parse()?,
        })
    }
}

/// `PATH` as given to `--checkpoint`: a file, or a run directory (its best checkpoint if it has
/// one, else its last).
pub fn resolve(path: &Path) -> Result<PathBuf> {
    if path.is_dir() {
        for name in [BEST_FILE_NAME, FILE_NAME] {
            let candidate = path.join(name);
            if candidate.is_file() {
                return Ok(candidate);
            }
        }
        bail!(
            "{} is a directory without {BEST_FILE_NAME} or {FILE_NAME}",
            path.display()
        );
    }
    if !path.is_file() {
        bail!("checkpoint {} does not exist", path.display());
    }
    Ok(path.to_path_buf())
}

/// Writes named tensors and metadata atomically (temporary file, then rename).
pub fn save(path: &Path, tensors: &[(String, Tensor)], meta: &CheckpointMeta) -> Result<()> {
    let mut buffers = Vec::with_capacity(tensors.len());
    for (name, tensor) in tensors {
        let values = tensor.flatten_all()?.to_vec1::<f32>()?;
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        buffers.push((name.clone(), tensor.dims().to_vec(), bytes));
    }
    let views = buffers
        .iter()
        .map(|(name, dims, bytes)| Ok((name.clone(), TensorView::new(Dtype::F32, dims.clone(), bytes)?)))
        .collect::<Result<Vec<_>>>()?;
    let bytes = safetensors::tensor::serialize(views, Some(meta.to_map()))?;
    formation_core::run_dir::write_atomically(path, &bytes)
}

/// A loaded checkpoint.
#[derive(Debug)]
pub struct Checkpoint {
    /// Where it was read from.
    pub path: PathBuf,
    /// Its metadata.
    pub meta: CheckpointMeta,
    /// Every tensor by name.
    pub tensors: HashMap<String, Tensor>,
}

/// Reads and checks a checkpoint file.
pub fn load(path: &Path) -> Result<Checkpoint> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read checkpoint {}", path.display()))?;
    let (_, metadata) = SafeTensors::read_metadata(&bytes)
        .map_err(|err| anyhow::anyhow!("checkpoint {} is not a valid safetensors file: {err}", path.display()))?;
    let map = metadata.metadata().clone().unwrap_or_default();
    let meta = CheckpointMeta::from_map(&map, path)?;
    let file = SafeTensors::deserialize(&bytes)
        .map_err(|err| anyhow::anyhow!("checkpoint {} is corrupted: {err}", path.display()))?;
    let mut tensors = HashMap::new();
    for (name, view) in file.tensors() {
        if view.dtype() != Dtype::F32 {
            bail!(
                "checkpoint {}: tensor {name} is {:?}, expected F32",
                path.display(),
                view.dtype()
            );
        }
        let values: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if values.iter().any(|v| !v.is_finite()) {
            bail!("checkpoint {}: tensor {name} holds non-finite values", path.display());
        }
        tensors.insert(name, Tensor::from_vec(values, view.shape(), &Device::Cpu)?);
    }
    Ok(Checkpoint {
        path: path.to_path_buf(),
        meta,
        tensors,
    })
}

/// Tensor-name prefix of actor `index`.
pub fn actor_prefix(index: usize) -> String {
    format!("actor{index}.")
}

impl Checkpoint {
    /// The flat weights of the actor robot `agent` uses (the shared one, or its own).
    pub fn actor_weights(&self, agent: usize) -> Result<Vec<f32>> {
        let index = if self.meta.n_actors == 1 { 0 } else { agent };
        if index >= self.meta.n_actors {
            bail!(
                "checkpoint {} holds {} independent actors (trained for {} robots); robot {agent} has none. \
                 Use a checkpoint with a shared actor to drive more robots",
                self.path.display(),
                self.meta.n_actors,
                self.meta.n_agents
            );
        }
        crate::actor::flatten_parameters(
            |name| self.tensors.get(name).cloned(),
            &actor_prefix(index),
            &self.meta.actor,
        )
        .with_context(|| format!("checkpoint {}", self.path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("formation-ckpt-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        dir
    }

    #[test]
    fn a_selection_score_beats_another_by_its_worst_size_then_its_mean() {
        let score = |successes: &[f64]| SelectionScore {
            seed: 1,
            episodes: 10,
            sizes: successes
                .iter()
                .enumerate()
                .map(|(k, &success)| SizeScore {
                    n_agents: 3 + k,
                    success,
                    formation_held: 1.0,
                    mean_steps: 50.0,
                })
                .collect(),
            reality: None,
            ideal: None,
        };
        assert_eq!(score(&[1.0, 0.6]).success(), 0.6);
        assert!(score(&[0.1]).beats(None));
        assert!(score(&[0.7, 0.7]).beats(Some(&score(&[1.0, 0.6]))));
        assert!(score(&[0.8, 0.7]).beats(Some(&score(&[0.7, 0.7]))));
        assert!(!score(&[0.7, 0.7]).beats(Some(&score(&[0.7, 0.7]))));
        // Equal success: the faster one.
        let faster = |steps: f64| SelectionScore {
            sizes: score(&[1.0])
                .sizes
                .into_iter()
                .map(|s| SizeScore { mean_steps: steps, ..s })
                .collect(),
            ..score(&[1.0])
        };
        assert!(faster(60.0).beats(Some(&faster(61.0))));
        assert!(!faster(61.0).beats(Some(&faster(60.0))));
        assert!(!faster(60.0).beats(Some(&faster(60.0))));
    }

    #[test]
    fn round_trip_and_bad_files() {
        let dir = temp_dir("rt");
        let shape = ActorShape {
            obs_dim: 14,
            history: 2,
            hidden: vec![4],
            head: ActorHead::Gains,
        };
        let tensors: Vec<(String, Tensor)> = shape
            .parameters()
            .into_iter()
            .map(|(name, dims)| {
                let len: usize = dims.iter().product();
                let values: Vec<f32> = (0..len).map(|i| i as f32 * 0.5).collect();
                (
                    format!("{}{name}", actor_prefix(0)),
                    Tensor::from_vec(values, dims, &Device::Cpu).expect("t"),
                )
            })
            .collect();
        let mut meta = CheckpointMeta {
            n_agents: 3,
            observation: ObservationModel::Slot,
            n_actors: 1,
            actor: shape.clone(),
            extra: HashMap::new(),
        };
        let path = dir.join(FILE_NAME);
        // A file without selection metadata (as written before model selection) loads.
        save(&path, &tensors, &meta).expect("save");
        assert_eq!(load(&path).expect("load").meta.selection(&path).expect("parse"), None);
        let score = SelectionScore {
            seed: 6_168_263,
            episodes: 30,
            sizes: vec![
                SizeScore {
                    n_agents: 3,
                    success: 29.0 / 30.0,
                    formation_held: 0.912_345,
                    mean_steps: 61.3,
                },
                SizeScore {
                    n_agents: 16,
                    success: 0.9,
                    formation_held: 0.8,
                    mean_steps: 70.0,
                },
            ],
            reality: Some("position_noise_m = [0.05, 0.1], dead_robot = \"hold\"".into()),
            ideal: Some(vec![SizeScore {
                n_agents: 3,
                success: 1.0,
                formation_held: 0.95,
                mean_steps: 55.5,
            }]),
        };
        score.to_metadata(&mut meta.extra);
        save(&path, &tensors, &meta).expect("save");
        let loaded = load(&path).expect("load");
        assert_eq!(loaded.meta.selection(&path).expect("parse"), Some(score.clone()));
        assert_eq!(loaded.meta.extra["selection_success"], "0.900");
        assert_eq!(loaded.meta.extra["selection_seed"], "6168263");
        assert_eq!(loaded.meta.extra["selection_episodes"], "30");
        assert_eq!(loaded.meta.actor, shape);
        assert_eq!(loaded.meta.observation, ObservationModel::Slot);
        loaded
            .meta
            .check_observation(&path, ObservationModel::Slot, 14)
            .expect("same observation");
        let refusal = loaded
            .meta
            .check_observation(&path, ObservationModel::Paper, 12)
            .expect_err("another observation is refused")
            .to_string();
        assert!(
            refusal.contains("\"slot\" observation (14 floats)") && refusal.contains("\"paper\" (12 floats)"),
            "{refusal}"
        );
        let flat = loaded.actor_weights(5).expect("shared actor serves any robot");
        assert_eq!(flat.len(), shape.parameter_count());
        assert_eq!(resolve(&dir).expect("dir resolves"), path);

        // Truncated file: a clear error naming the file.
        let bytes = std::fs::read(&path).expect("read");
        let truncated = dir.join("truncated.safetensors");
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).expect("write");
        let err = load(&truncated).expect_err("truncated").to_string();
        assert!(err.contains("truncated.safetensors"), "{err}");
        // Garbage.
        let garbage = dir.join("garbage.safetensors");
        std::fs::write(&garbage, b"not a checkpoint at all").expect("write");
        assert!(load(&garbage).is_err());
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
