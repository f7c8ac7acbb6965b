//! The actor network pi(o_{t-H+1..t}) -> action in [-1, 1]^2: an MLP over the flattened
//! observation history with ReLU hidden layers and a tanh output.
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
use formation_protocol::ACTION_DIM;
use nalgebra::{DMatrix, DMatrixView, DVector, DVectorView};

/// Sizes of an actor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ActorShape {
    /// Floats per observation (the observation model's dimension).
    pub obs_dim: usize,
    /// Observations in the input window (H).
    pub history: usize,
    /// Widths of the hidden layers.
    pub hidden: Vec<usize>,
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

    /// Actions in [-1, 1]^2 for a batch of flattened windows (rows of H * obs_dim).
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

    /// The action in [-1, 1]^2 for one flattened window (H * obs_dim values).
    pub fn act(&mut self, window: &[f32]) -> anyhow::Result<[f32; ACTION_DIM]> {
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
        let action = &self.outputs[last];
        Ok([action[0], action[1]])
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
        let shape = ActorShape {
            obs_dim: 12,
            history: 4,
            hidden: vec![16, 8],
        };
        let varmap = VarMap::new();
        let actor = Actor::new(VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu), &shape).expect("actor");
        let data = varmap.data().lock().expect("lock").clone();
        let flat = flatten_parameters(|name| data.get(name).map(|v| v.as_tensor().clone()), "", &shape).expect("flat");
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
            for (a, b) in got.iter().zip(&expected) {
                assert!((a - b).abs() < 1e-5, "frozen {got:?} vs candle {expected:?}");
            }
            assert!(got.iter().all(|v| (-1.0..=1.0).contains(v)));
        }
        assert!(frozen.act(&[0.0; 3]).is_err());
        assert!(FrozenActor::from_flat(&flat[1..], &shape).is_err());
        // New weights land in place: all zero gives tanh(0) = 0.
        frozen.load(&vec![0.0; flat.len()]).expect("load");
        assert_eq!(frozen.act(&vec![1.0; shape.input_dim()]).expect("act"), [0.0, 0.0]);
    }
}
