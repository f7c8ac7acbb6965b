//! The last H observations of one robot, oldest first, padded with the first observation of an
//! episode (the same padding the replay uses, so training and acting see the same inputs).

use formation_protocol::OBS_DIM;

/// A fixed-size window of observations; no allocation after construction.
#[derive(Debug, Clone)]
pub struct ObservationHistory {
    length: usize,
    flat: Vec<f32>,
}

impl ObservationHistory {
    /// A window of `length` observations.
    pub fn new(length: usize) -> Self {
        Self {
            length,
            flat: vec![0.0; length * OBS_DIM],
        }
    }

    /// Observations in the window (H).
    pub fn len(&self) -> usize {
        self.length
    }

    /// Never empty once constructed with H >= 1.
    pub fn is_empty(&self) -> bool {
        self.length == 0
    }

    /// Starts a new episode: every slot holds `first`.
    pub fn reset(&mut self, first: &[f32; OBS_DIM]) {
        for slot in self.flat.chunks_exact_mut(OBS_DIM) {
            slot.copy_from_slice(first);
        }
    }

    /// Drops the oldest observation and appends `obs`.
    pub fn push(&mut self, obs: &[f32; OBS_DIM]) {
        self.flat.copy_within(OBS_DIM.., 0);
        let start = self.flat.len() - OBS_DIM;
        self.flat[start..].copy_from_slice(obs);
    }

    /// The window, oldest first, as one row of H * OBS_DIM values.
    pub fn as_flat(&self) -> &[f32] {
        &self.flat
    }

    /// The newest observation.
    pub fn latest(&self) -> &[f32] {
        &self.flat[self.flat.len() - OBS_DIM..]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pads_then_slides() {
        let mut h = ObservationHistory::new(3);
        h.reset(&[1.0; OBS_DIM]);
        assert!(h.as_flat().iter().all(|&v| v == 1.0));
        h.push(&[2.0; OBS_DIM]);
        h.push(&[3.0; OBS_DIM]);
        h.push(&[4.0; OBS_DIM]);
        let firsts: Vec<f32> = h.as_flat().chunks(OBS_DIM).map(|c| c[0]).collect();
        assert_eq!(firsts, vec![2.0, 3.0, 4.0]);
        assert_eq!(h.latest()[0], 4.0);
    }
}
