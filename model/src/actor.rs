//! The actor network pi(o_{t-H+1..t}) -> outputs in [-1, 1]: an MLP over the flattened
//! observation history with ReLU hidden layers and a tanh output. Its [`ActorHead`] says what the
//! outputs are: the command itself (v, w), as the paper's actor, or the five gains of the
//! baseline's control law, which then turns the newest observation into the command (a learned
//! gain schedule).
//!
//! An MLP over the flat window is what the paper's fixed H = 15 calls for and is cheap at
//! batch 1; a recurrent actor would add state to carry across ticks and restarts for no
//! measured gain here.
//!
//! [`Actor`] is the trainable candle network of the critic; [`FrozenActor`] is the same network
//! as the agents run it, rebuilt from the flat `[f32]` weights the critic streams. Parameters
//! are flattened in the order of [`ActorShape::parameters`].

use candle_core::Tensor;
use candle_nn::{Linear, VarBuilder};
use formation_core::baseline::{BaselineGains, SCHEDULED_GAIN_RANGES, ScriptedBaseline};
use formation_core::config::EnvConfig;
use formation_protocol::ACTION_DIM;
use nalgebra::{DMatrix, DMatrixView, DVector, DVectorView};

/// What an actor's outputs mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ActorHead {
    /// The command (v, w), normalised to [-1, 1]^2 ([`EnvConfig::command_from_action`]).
    #[default]
    Command,
    /// The baseline's gains ([`BaselineGains::from_unit`]); the baseline's law with them turns
    /// the newest observation into the command. Trained by distillation only.
    Gains,
}

impl ActorHead {
    /// Outputs of the network.
    pub fn outputs(self) -> usize {
        match self {
            Self::Command => ACTION_DIM,
            Self::Gains => SCHEDULED_GAIN_RANGES.len(),
        }
    }

    /// The head's name in checkpoints and on command lines.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Command => "command",
            Self::Gains => "gains",
        }
    }

    /// The head called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Command, Self::Gains]
            .into_iter()
            .find(|head| head.as_str() == name)
    }
}

/// Sizes of an actor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActorShape {
    /// Floats per observation (the observation model's dimension).
    pub obs_dim: usize,
    /// Observations in the input window (H).
    pub history: usize,
    /// Widths of the hidden layers.
    pub hidden: Vec<usize>,
    /// What the outputs mean.
    pub head: ActorHead,
}

impl ActorShape {
    /// Width of the input row: H * obs_dim.
    pub fn input_dim(&self) -> usize {
        self.history * self.obs_dim
    }

    fn layer_dims(&self) -> Vec<(usize, usize)> {
        let mut dims = Vec::with_capacity(self.hidden.len() + 1);
        let mut input = self.input_dim();
        for &width in &self.hidden {
            dims.push((input, width));
            input = width;
        }
        dims.push((input, self.head.outputs()));
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

/// `x W^T + b` for rows of `x` (any leading dimensions), as `candle_nn::Linear` computes it,
/// with the bias added through a matrix product (`1 b`) instead of a broadcast: the gradient of
/// a broadcast bias is a sum over the batch rows, which candle's CPU backend reduces one strided
/// element at a time (14 % of a training update, profiled), while `1^T grad` is one gemm call.
/// Same parameters, same values; only the backward pass is cheaper.
pub fn dense(layer: &Linear, x: &Tensor) -> candle_core::Result<Tensor> {
    let weight = layer.weight();
    let (outputs, inputs) = weight.dims2()?;
    let mut dims = x.dims().to_vec();
    let rows = x.elem_count() / inputs;
    let flat = x.reshape((rows, inputs))?;
    let mut y = flat.matmul(&weight.t()?)?;
    if let Some(bias) = layer.bias() {
        let ones = Tensor::ones((rows, 1), x.dtype(), x.device())?;
        y = (y + ones.matmul(&bias.reshape((1, outputs))?)?)?;
    }
    *dims.last_mut().expect("x has a dimension") = outputs;
    y.reshape(dims)
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

    /// Outputs in [-1, 1] for a batch of flattened windows (rows of H * obs_dim).
    pub fn forward(&self, windows: &Tensor) -> candle_core::Result<Tensor> {
        let mut x = windows.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            x = dense(layer, &x)?;
            x = if i + 1 < self.layers.len() {
                x.relu()?
            } else {
                x.tanh()?
            };
        }
        Ok(x)
    }
}

/// The actor at batch 1, as the agents run it: the same network as [`Actor`], evaluated with
/// nalgebra's matrix-vector product into buffers allocated once, so a tick allocates nothing
/// (candle allocates a tensor per operation).
#[derive(Debug, Clone)]
pub struct FrozenActor {
    shape: ActorShape,
    /// (weight [out x in], bias [out]) of every layer.
    layers: Vec<(DMatrix<f32>, DVector<f32>)>,
    /// Every layer's output.
    outputs: Vec<DVector<f32>>,
}

impl FrozenActor {
    /// An actor from flat weights (as the critic streams them).
    pub fn from_flat(flat: &[f32], shape: &ActorShape) -> anyhow::Result<Self> {
        let dims = shape.layer_dims();
        let mut actor = Self {
            shape: shape.clone(),
            layers: dims
                .iter()
                .map(|&(input, output)| (DMatrix::zeros(output, input), DVector::zeros(output)))
                .collect(),
            outputs: dims.iter().map(|&(_, output)| DVector::zeros(output)).collect(),
        };
        actor.load(flat)?;
        Ok(actor)
    }

    /// Replaces the weights in place (flattened in the order of [`ActorShape::parameters`]).
    pub fn load(&mut self, flat: &[f32]) -> anyhow::Result<()> {
        anyhow::ensure!(
            flat.len() == self.shape.parameter_count(),
            "weights have {} values, an actor of shape {:?} needs {}",
            flat.len(),
            self.shape,
            self.shape.parameter_count()
        );
        let mut offset = 0;
        for (weight, bias) in &mut self.layers {
            let (rows, cols) = weight.shape();
            // Row-major [out, in] read as column-major [in, out] is the transpose.
            weight.tr_copy_from(&DMatrixView::from_slice(
                &flat[offset..offset + rows * cols],
                cols,
                rows,
            ));
            offset += rows * cols;
            bias.copy_from_slice(&flat[offset..offset + rows]);
            offset += rows;
        }
        Ok(())
    }

    /// The outputs in [-1, 1] for one flattened window (H * obs_dim values).
    pub fn act(&mut self, window: &[f32]) -> anyhow::Result<&[f32]> {
        anyhow::ensure!(
            window.len() == self.shape.input_dim(),
            "a window of {} values, the actor takes {}",
            window.len(),
            self.shape.input_dim()
        );
        let input = DVectorView::from_slice(window, window.len());
        let last = self.layers.len() - 1;
        for (i, (weight, bias)) in self.layers.iter().enumerate() {
            let (before, from_here) = self.outputs.split_at_mut(i);
            let output = &mut from_here[0];
            output.copy_from(bias);
            match before.last() {
                Some(previous) => output.gemv(1.0, weight, previous, 1.0),
                None => output.gemv(1.0, weight, &input, 1.0),
            }
            if i < last {
                output.apply(|x| *x = x.max(0.0));
            } else {
                output.apply(|x| *x = x.tanh());
            }
        }
        Ok(self.outputs[last].as_slice())
    }

    /// The robot's command (v, w) for one flattened window (newest observation last), as its
    /// head makes it from the outputs.
    pub fn command(&mut self, window: &[f32], env: &EnvConfig) -> anyhow::Result<(f64, f64)> {
        let head = self.shape.head;
        let newest = &window[window.len().saturating_sub(self.shape.obs_dim)..];
        let outputs = self.act(window)?;
        Ok(match head {
            ActorHead::Command => env.command_from_action([outputs[0], outputs[1]]),
            ActorHead::Gains => ScriptedBaseline::new(env, BaselineGains::from_unit(outputs)).command(newest),
        })
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

/// The flat weights of the actor under `prefix` in a candle `VarMap` (a learner's or a
/// distiller's), in the order agents rebuild them.
pub fn var_map_actor_weights(vars: &candle_nn::VarMap, prefix: &str, shape: &ActorShape) -> anyhow::Result<Vec<f32>> {
    let data = vars
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    flatten_parameters(|name| data.get(name).map(|v| v.as_tensor().clone()), prefix, shape)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    #[test]
    fn dense_gives_the_values_and_gradients_of_linear() {
        use candle_core::Module;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let layer = candle_nn::linear(5, 3, vb.pp("layer")).expect("layer");
        let x = Tensor::randn(0f32, 1.0, (4, 2, 5), &Device::Cpu).expect("x");
        let reference = layer.forward(&x).expect("linear");
        let ours = dense(&layer, &x).expect("dense");
        assert_eq!(ours.dims(), reference.dims());
        let difference = (&ours - &reference).expect("sub").abs().expect("abs");
        assert!(difference.max_all().expect("max").to_scalar::<f32>().expect("scalar") < 1e-6);
        // Weighted sums so that every output element has its own gradient.
        let weights = Tensor::randn(0f32, 1.0, (4, 2, 3), &Device::Cpu).expect("w");
        let gradients = |y: &Tensor| {
            let grads = (y * &weights)
                .expect("mul")
                .sum_all()
                .expect("sum")
                .backward()
                .expect("backward");
            [layer.weight(), layer.bias().expect("bias")].map(|p| {
                grads
                    .get(p)
                    .expect("grad")
                    .flatten_all()
                    .expect("flat")
                    .to_vec1::<f32>()
                    .expect("vec")
            })
        };
        for (a, b) in gradients(&ours).iter().zip(gradients(&reference).iter()) {
            assert_eq!(a.len(), b.len());
            assert!(a.iter().zip(b).all(|(a, b)| (a - b).abs() < 1e-5), "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn frozen_actor_acts_as_the_trained_network() {
        for head in [ActorHead::Command, ActorHead::Gains] {
            let shape = ActorShape {
                obs_dim: 12,
                history: 4,
                hidden: vec![16, 8],
                head,
            };
            let varmap = VarMap::new();
            let actor = Actor::new(VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu), &shape).expect("actor");
            let data = varmap.data().lock().expect("lock").clone();
            let flat =
                flatten_parameters(|name| data.get(name).map(|v| v.as_tensor().clone()), "", &shape).expect("flat");
            assert_eq!(flat.len(), shape.parameter_count());
            let mut frozen = FrozenActor::from_flat(&flat, &shape).expect("from flat");
            for seed in 0..5 {
                let window: Vec<f32> = (0..shape.input_dim())
                    .map(|i| ((i + 7 * seed) as f32 * 0.37).sin() * 3.0)
                    .collect();
                let input = Tensor::from_slice(&window, (1, window.len()), &Device::Cpu).expect("tensor");
                let expected = actor.forward(&input).expect("forward").flatten_all().expect("flat");
                let expected = expected.to_vec1::<f32>().expect("vec");
                let got = frozen.act(&window).expect("act");
                assert_eq!(got.len(), head.outputs());
                for (a, b) in got.iter().zip(&expected) {
                    assert!((a - b).abs() < 1e-5, "frozen {got:?} vs candle {expected:?}");
                }
                assert!(got.iter().all(|v| (-1.0..=1.0).contains(v)));
            }
            assert!(frozen.act(&[0.0; 3]).is_err());
            assert!(FrozenActor::from_flat(&flat[1..], &shape).is_err());
            // New weights land in place: all zero gives tanh(0) = 0.
            frozen.load(&vec![0.0; flat.len()]).expect("load");
            assert!(
                frozen
                    .act(&vec![1.0; shape.input_dim()])
                    .expect("act")
                    .iter()
                    .all(|&v| v == 0.0)
            );
        }
    }

    #[test]
    fn a_gains_head_commands_as_the_baseline_with_its_gains_from_the_newest_observation() {
        use formation_core::config::{ObservationModel, RunConfig};
        use formation_core::observation::Layout;
        let env = RunConfig::default().env;
        assert_eq!(env.observation, ObservationModel::default());
        let obs_dim = Layout::of(env.observation).dim();
        let shape = ActorShape {
            obs_dim,
            history: 3,
            hidden: vec![4],
            head: ActorHead::Gains,
        };
        let gains = BaselineGains {
            k_form: 0.45,
            k_goal: 1.07,
            k_turn: 1.3,
            repulsion_range: 0.51,
            k_repulsion: 1.58,
            ..BaselineGains::default()
        };
        // Zero weights and a last bias of atanh(unit gains): the actor outputs the gains whatever
        // it reads.
        let mut flat = vec![0.0f32; shape.parameter_count()];
        let unit = gains.to_unit();
        let tail = flat.len() - unit.len();
        for (slot, u) in flat[tail..].iter_mut().zip(unit) {
            *slot = u.atanh();
        }
        let mut frozen = FrozenActor::from_flat(&flat, &shape).expect("actor");
        let window: Vec<f32> = (0..shape.input_dim())
            .map(|i| ((i as f32) * 0.61).sin() * 2.0)
            .collect();
        let newest = &window[2 * obs_dim..];
        let (v, w) = frozen.command(&window, &env).expect("command");
        let (v_ref, w_ref) = ScriptedBaseline::new(&env, gains).command(newest);
        assert!(
            (v - v_ref).abs() < 1e-4 && (w - w_ref).abs() < 1e-4,
            "({v}, {w}) vs ({v_ref}, {w_ref})"
        );
        let (v_default, w_default) = ScriptedBaseline::new(&env, BaselineGains::default()).command(newest);
        assert!(
            (v - v_default).abs() + (w - w_default).abs() > 1e-3,
            "the window does not tell the gains apart"
        );
    }
}
