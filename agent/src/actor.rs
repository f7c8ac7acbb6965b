//! The actor network pi(o_{t-H+1..t}) -> action in [-1, 1]^2: an MLP over the flattened
//! observation history with ReLU hidden layers and a tanh output.
//!
//! An MLP over the flat window is what the paper's fixed H = 15 calls for and is cheap at
//! batch 1; a recurrent actor would add state to carry across ticks and restarts for no
//! measured gain here.
//!
//! The same type serves the critic (trainable, backed by a `VarMap`) and the agents (frozen,
//! rebuilt from the flat `[f32]` weights the critic streams). Parameters are flattened in the
//! order of [`ActorShape::parameters`].

use std::collections::HashMap;

use candle_core::{DType, Device, Module, Tensor};
use candle_nn::{Linear, VarBuilder};
use formation_protocol::{ACTION_DIM, OBS_DIM};

/// Sizes of an actor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActorShape {
    /// Observations in the input window (H).
    pub history: usize,
    /// Widths of the hidden layers.
    pub hidden: Vec<usize>,
}

impl ActorShape {
    /// Width of the input row: H * OBS_DIM.
    pub fn input_dim(&self) -> usize {
        self.history * OBS_DIM
    }

    fn layer_dims(&self) -> Vec<(usize, usize)> {
        let mut dims = Vec::with_capacity(self.hidden.len() + 1);
        let mut input = self.input_dim();
        for &width in &self.hidden {
            dims.push((input, width));
            input = width;
        }
        dims.push((input, ACTION_DIM));
        dims
    }

    /// (name, shape) of every parameter, in flattening order.
    pub fn parameters(&self) -> Vec<(String, Vec<usize>)> {
        self.layer_dims()
            .iter()
            .enumerate()
            .flat_map(|(i, &(input, output))| {
                [
                    (format!("layer{i}.weight"), vec![output, input]),
                    (format!("layer{i}.bias"), vec![output]),
                ]
            })
            .collect()
    }

    /// Total number of f32 parameters.
    pub fn parameter_count(&self) -> usize {
        self.parameters()
            .iter()
            .map(|(_, shape)| shape.iter().product::<usize>())
            .sum()
    }
}

/// The actor network.
#[derive(Debug, Clone)]
pub struct Actor {
    layers: Vec<Linear>,
}

impl Actor {
    /// Builds (or fetches) the layers under `vb`.
    pub fn new(vb: VarBuilder, shape: &ActorShape) -> candle_core::Result<Self> {
        let layers = shape
            .layer_dims()
            .iter()
            .enumerate()
            .map(|(i, &(input, output))| candle_nn::linear(input, output, vb.pp(format!("layer{i}"))))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self { layers })
    }

    /// A frozen actor from flat weights (as streamed by the critic).
    pub fn from_flat(flat: &[f32], shape: &ActorShape) -> anyhow::Result<Self> {
        anyhow::ensure!(
            flat.len() == shape.parameter_count(),
            "weights have {} values, an actor of shape {shape:?} needs {}",
            flat.len(),
            shape.parameter_count()
        );
        let mut tensors = HashMap::new();
        let mut offset = 0;
        for (name, dims) in shape.parameters() {
            let len: usize = dims.iter().product();
            tensors.insert(
                name,
                Tensor::from_slice(&flat[offset..offset + len], dims, &Device::Cpu)?,
            );
            offset += len;
        }
        Ok(Self::new(
            VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
            shape,
        )?)
    }

    /// Actions in [-1, 1]^2 for a batch of flattened windows (rows of H * OBS_DIM).
    pub fn forward(&self, windows: &Tensor) -> candle_core::Result<Tensor> {
        let mut x = windows.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            x = layer.forward(&x)?;
            x = if i + 1 < self.layers.len() {
                x.relu()?
            } else {
                x.tanh()?
            };
        }
        Ok(x)
    }

    /// The action for one window.
    pub fn act(&self, window: &[f32]) -> anyhow::Result<[f32; ACTION_DIM]> {
        let input = Tensor::from_slice(window, (1, window.len()), &Device::Cpu)?;
        let out = self.forward(&input)?.flatten_all()?.to_vec1::<f32>()?;
        Ok([out[0], out[1]])
    }
}

/// Flattens the actor parameters stored under `prefix` in `tensors` (in flattening order).
pub fn flatten_parameters(
    lookup: impl Fn(&str) -> Option<Tensor>,
    prefix: &str,
    shape: &ActorShape,
) -> anyhow::Result<Vec<f32>> {
    let mut flat = Vec::with_capacity(shape.parameter_count());
    for (name, dims) in shape.parameters() {
        let full = format!("{prefix}{name}");
        let tensor = lookup(&full).ok_or_else(|| anyhow::anyhow!("missing actor parameter {full}"))?;
        anyhow::ensure!(
            tensor.dims() == dims.as_slice(),
            "{full} has shape {:?}, expected {dims:?}",
            tensor.dims()
        );
        flat.extend(tensor.flatten_all()?.to_vec1::<f32>()?);
    }
    Ok(flat)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;

    #[test]
    fn flat_round_trip_gives_the_same_actions() {
        let shape = ActorShape {
            history: 4,
            hidden: vec![16, 8],
        };
        let varmap = VarMap::new();
        let actor = Actor::new(VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu), &shape).expect("actor");
        let data = varmap.data().lock().expect("lock").clone();
        let flat = flatten_parameters(|name| data.get(name).map(|v| v.as_tensor().clone()), "", &shape).expect("flat");
        assert_eq!(flat.len(), shape.parameter_count());
        let frozen = Actor::from_flat(&flat, &shape).expect("from flat");
        let window: Vec<f32> = (0..shape.input_dim()).map(|i| (i as f32 * 0.37).sin()).collect();
        let a = actor.act(&window).expect("act");
        let b = frozen.act(&window).expect("act");
        assert_eq!(a, b);
        assert!(a.iter().all(|v| (-1.0..=1.0).contains(v)));
        assert!(Actor::from_flat(&flat[1..], &shape).is_err());
    }
}
