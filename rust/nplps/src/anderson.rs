//! Anderson acceleration of a fixed-point iteration `z <- G(z)`.
//!
//! With the residuals `f_j = G(z_j) - z_j` of the last `m + 1` iterates, the next iterate is
//!
//! ```text
//! z_{k+1} = G(z_k) - sum_j gamma_j (G(z_{j+1}) - G(z_j)),
//! gamma = argmin | f_k - sum_j gamma_j (f_{j+1} - f_j) |_W
//! ```
//!
//! (Walker & Ni's "type II" form) in a weighted norm `|x|_W^2 = sum_i w_i x_i^2`. It solves
//! `G(z) = z` by a secant method on the few directions where the plain iteration is slow or
//! even unstable, which is what coupling the light refinement to the mesh deformation creates
//! (see [`crate::refine`]). Affine constraints that every `G(z)` satisfies (the gauge, the
//! intensity normalization) hold for the mixed iterate too: the coefficients of the `G` values
//! it combines sum to 1.

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use crate::error::Result;
use crate::memory::{try_copy, try_par_collect, try_vec, try_with_capacity};

/// The state of the acceleration.
#[derive(Debug, Clone)]
pub struct Anderson {
    depth: usize,
    weights: Vec<f64>,
    previous: Option<(Vec<f64>, Vec<f64>)>,
    delta_f: VecDeque<Vec<f64>>,
    delta_g: VecDeque<Vec<f64>>,
    best: f64,
}

/// Restart when the residual grows beyond this factor of the smallest one seen.
const RESTART_GROWTH: f64 = 100.0;

impl Anderson {
    /// Acceleration with memory `depth` and per-entry weights `weights` of the norm.
    pub fn new(depth: usize, weights: Vec<f64>) -> Anderson {
        Anderson {
            depth,
            weights,
            previous: None,
            delta_f: VecDeque::new(),
            delta_g: VecDeque::new(),
            best: f64::INFINITY,
        }
    }

    fn dot(&self, a: &[f64], b: &[f64]) -> f64 {
        a.par_iter()
            .zip(b)
            .zip(&self.weights)
            .with_min_len(1 << 14)
            .map(|((x, y), w)| x * y * w)
            .sum()
    }

    /// Forgets the history (the next call returns `G(z)` unchanged).
    pub fn restart(&mut self) {
        self.previous = None;
        self.delta_f.clear();
        self.delta_g.clear();
    }

    /// Starts over: the history and the smallest residual seen are forgotten.
    pub fn reset(&mut self) {
        self.restart();
        self.best = f64::INFINITY;
    }

    /// Given the iterate `z` and its image `g = G(z)`, overwrites `g` with the accelerated next
    /// iterate.
    ///
    /// When the history cannot be allocated, the acceleration restarts and `g` is left as it is
    /// (the plain iteration's next iterate); [`Anderson::try_mix`] reports it instead.
    #[cfg(test)]
    pub fn mix(&mut self, z: &[f64], g: &mut [f64]) {
        if self.try_mix(z, g).is_err() {
            self.restart();
        }
    }

    /// As `Anderson::mix` (tests), with [`Error::Memory`](crate::Error::Memory) (and `g` unchanged)
    /// when a vector of the history cannot be allocated.
    pub fn try_mix(&mut self, z: &[f64], g: &mut [f64]) -> Result<()> {
        const WHAT: &str = "the Anderson acceleration's history";
        let f = try_par_collect(g.par_iter().zip(z).map(|(a, b)| a - b), WHAT)?;
        let g_copy = try_copy(g, WHAT)?;
        let norm = self.dot(&f, &f).sqrt();
        if !norm.is_finite() {
            self.restart();
            return Ok(());
        }
        if norm > RESTART_GROWTH * self.best {
            self.restart();
        }
        self.best = self.best.min(norm);
        if let Some((f_prev, g_prev)) = self.previous.take() {
            // The differences overwrite the previous vectors (no new allocation).
            let (mut df, mut dg) = (f_prev, g_prev);
            df.par_iter_mut().zip(&f).for_each(|(d, a)| *d = a - *d);
            dg.par_iter_mut()
                .zip(&g_copy)
                .for_each(|(d, a)| *d = a - *d);
            self.delta_f.push_back(df);
            self.delta_g.push_back(dg);
            if self.delta_f.len() > self.depth {
                self.delta_f.pop_front();
                self.delta_g.pop_front();
            }
        }
        let m = self.delta_f.len();
        if m == 0 {
            self.previous = Some((f, g_copy));
            return Ok(());
        }
        let mut normal = DMatrix::zeros(m, m);
        let mut rhs = DVector::zeros(m);
        for a in 0..m {
            rhs[a] = self.dot(&self.delta_f[a], &f);
            for b in a..m {
                let v = self.dot(&self.delta_f[a], &self.delta_f[b]);
                normal[(a, b)] = v;
                normal[(b, a)] = v;
            }
        }
        self.previous = Some((f, g_copy));
        let trace = normal.trace().max(f64::MIN_POSITIVE);
        for a in 0..m {
            normal[(a, a)] += 1e-12 * trace;
        }
        let Some(gamma) = normal.cholesky().map(|c| c.solve(&rhs)) else {
            self.restart();
            return Ok(());
        };
        if !gamma.iter().all(|v| v.is_finite()) {
            self.restart();
            return Ok(());
        }
        for (a, dg) in self.delta_g.iter().enumerate() {
            let c = gamma[a];
            g.par_iter_mut().zip(dg).for_each(|(x, d)| *x -= c * d);
        }
        Ok(())
    }
}

/// How the solver's loop speeds up its fixed-point iteration over the joint state (the
/// unknowns followed by the refined light parameters, see [`Joint`]).
pub(crate) trait Acceleration {
    /// The next state proposed from the state `z` and its image `g = G(z)` (the plain
    /// iteration's next state), which it overwrites.
    fn propose(&mut self, z: &[f64], g: &mut [f64]) -> Result<()>;
    /// The last proposal was not usable: the next proposal is the image itself.
    fn reject(&mut self);
    /// Starts over, as if new (after the loop went back to an earlier state).
    fn reset(&mut self);
}

impl Acceleration for Anderson {
    fn propose(&mut self, z: &[f64], g: &mut [f64]) -> Result<()> {
        self.try_mix(z, g)
    }

    fn reject(&mut self) {
        self.restart();
    }

    fn reset(&mut self) {
        Anderson::reset(self);
    }
}

/// The joint state of `unknowns` followed by `lights` (light parameters).
pub(crate) fn joint(unknowns: &[f64], lights: &[f64]) -> Result<Vec<f64>> {
    let mut z = try_with_capacity(unknowns.len() + lights.len(), "the acceleration")?;
    z.extend_from_slice(unknowns);
    z.extend_from_slice(lights);
    Ok(z)
}

/// Memory of the acceleration of the joint iteration.
const JOINT_DEPTH: usize = 5;

/// Anderson acceleration of the joint iteration over the unknowns and the light parameters
/// (when refining): the light step with the normals eliminated and the mesh deformation are
/// each stable, but coupled they are not (a tilt of a nearly flat surface trades against a
/// smooth pattern of intensities), so the plain alternation can drift. A trust region keeps
/// the extrapolation of the lights near the light step.
#[derive(Debug, Clone)]
pub(crate) struct Joint {
    anderson: Anderson,
    /// How many entries of the state are unknowns (the light parameters follow).
    unknowns: usize,
}

impl Joint {
    /// The acceleration of `unknowns` unknowns measured in units `unit` (1 / the lateral size,
    /// times the distance for log-depths) and `parameters` light parameters.
    pub fn new(unknowns: usize, parameters: usize, unit: f64) -> Result<Joint> {
        let mut weights = try_vec(unknowns + parameters, 1.0, "the acceleration weights")?;
        weights[..unknowns].fill(unit * unit);
        Ok(Joint {
            anderson: Anderson::new(JOINT_DEPTH, weights),
            unknowns,
        })
    }
}

/// Euclidean distance `|a - b|`.
fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt()
}

impl Acceleration for Joint {
    fn propose(&mut self, z: &[f64], g: &mut [f64]) -> Result<()> {
        let n = self.unknowns;
        let plain = try_copy(g, "the acceleration")?;
        self.anderson.try_mix(z, g)?;
        // Trust region: the extrapolation may move the lights at most twice as far as the
        // light step itself did (and no more than 1 % of a parameter's scale beyond it).
        let step = distance(&plain[n..], &z[n..]);
        let extra = distance(&g[n..], &plain[n..]);
        let limit = 2.0 * step + 1e-2;
        if extra > limit {
            let t = limit / extra;
            for (x, p) in g.iter_mut().zip(&plain) {
                *x = p + t * (*x - p);
            }
        }
        Ok(())
    }

    fn reject(&mut self) {
        self.anderson.restart();
    }

    fn reset(&mut self) {
        self.anderson.reset();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An unstable linear iteration `z <- A z + b` (spectral radius 1.4) converges.
    #[test]
    fn converges_where_the_plain_iteration_diverges() {
        let a = [[1.4, 0.1, 0.0], [0.0, 0.5, 0.2], [0.1, 0.0, -0.3]];
        let b = [1.0, -2.0, 0.5];
        let g = |z: &[f64]| -> Vec<f64> {
            (0..3)
                .map(|i| (0..3).map(|j| a[i][j] * z[j]).sum::<f64>() + b[i])
                .collect()
        };
        let mut acc = Anderson::new(4, vec![1.0; 3]);
        let mut z = vec![0.0; 3];
        for _ in 0..20 {
            let mut next = g(&z);
            acc.mix(&z, &mut next);
            z = next;
        }
        let r: f64 = g(&z).iter().zip(&z).map(|(x, y)| (x - y).abs()).sum();
        assert!(r < 1e-9, "residual {r}");
    }
}
