//! The last H observations of one robot, oldest first, padded with the first observation of an
//! episode (the same padding the replay uses, so training and acting see the same inputs).

/// A fixed-size window of observations; no allocation after construction.
#[derive(Debug, Clone)]
pub struct ObservationHistory {
    length: usize,
    dim: usize,
    flat: Vec<f32>,
}

impl ObservationHistory {
    /// A window of `length` observations of `dim` floats.
    pub fn new(length: usize, dim: usize) -> Self {
        Self {
            length,
            dim,
            flat: vec![0.0; length * dim],
        }
    }

    /// Floats per observation.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Observations in the window (H).
    pub fn len(&self) -> usize {
        self.length
    }

    /// Never empty once constructed with H >= 1.
    pub fn is_empty(&self) -> bool {
        self.length == 0
    }

    /// Starts a new episode: every slot holds `first` (its first `dim` floats).
    pub fn reset(&mut self, first: &[f32]) {
        for slot in self.flat.chunks_exact_mut(self.dim) {
            slot.copy_from_slice(&first[..self.dim]);
        }
    }

    /// Drops the oldest observation and appends `obs` (its first `dim` floats).
    pub fn push(&mut self, obs: &[f32]) {
        self.flat.copy_within(self.dim.., 0);
        let start = self.flat.len() - self.dim;
        self.flat[start..].copy_from_slice(&obs[..self.dim]);
    }

    /// The window, oldest first, as one row of H * dim values.
    pub fn as_flat(&self) -> &[f32] {
        &self.flat
    }

    /// The newest observation.
    pub fn latest(&self) -> &[f32] {
        &self.flat[self.flat.len() - self.dim..]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_then_slides() {
        let mut h = ObservationHistory::new(3, 12);
        h.reset(&[1.0; 16]);
        assert!(h.as_flat().iter().all(|&v| v == 1.0));
        assert_eq!(h.as_flat().len(), 36, "only the model's floats are kept");
        h.push(&[2.0; 16]);
        h.push(&[3.0; 16]);
        h.push(&[4.0; 16]);
        let firsts: Vec<f32> = h.as_flat().chunks(12).map(|c| c[0]).collect();
        assert_eq!(firsts, vec![2.0, 3.0, 4.0]);
        assert_eq!(h.latest()[0], 4.0);
    }
}
