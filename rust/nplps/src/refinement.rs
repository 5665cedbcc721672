//! The lights of a solver and their refinement as the loop sees them ([`LightRefinement`]):
//! the current lights, one light step of [`crate::refine`] per iteration, the refined
//! parameters for the acceleration of the joint iteration, and what the report needs.

use crate::error::Result;
use crate::options::Refine;
use crate::refine::{conditioning, Conditioning, LightData, Refiner};
use crate::rig::Light;

/// Levels of a pyramid with more unknowns than this keep the lights refined on the coarser
/// levels: a few dozen light parameters are determined by a million pixels as well as by ten,
/// and the refinement's memory (the Anderson history, a few copies of the unknowns) stays
/// bounded at camera resolution. A problem without coarser levels is refined whatever its size.
///
/// It is 4 x [`crate::refine::MAX_FACETS`] (about 362 x 362 pixels): every light step sees at
/// most `MAX_FACETS` facets (a regular subsample), so a finer level's steps have no more data
/// than those of the level below it, which already saw at least a quarter of its facets; they
/// only redraw the subsample (measured on bumps at 1 MP with 1 % noise: the positions moved by
/// 0.1-0.3 % of the distance again at each level above 256², about their standard error, and
/// the finest level ran into the iteration limit). 2^21 before issue 23, item 4.
pub const MAX_REFINE_UNKNOWNS: usize = 4 * crate::refine::MAX_FACETS;

/// The refinement on a finer level of a pyramid with `unknowns` unknowns: none above
/// [`MAX_REFINE_UNKNOWNS`].
pub(crate) fn on_level(refine: Refine, unknowns: usize) -> Refine {
    if unknowns > MAX_REFINE_UNKNOWNS {
        refine.off()
    } else {
        refine
    }
}

/// The residuals of the first level's runs without and with light refinement (position
/// refinement is kept only when it lowers the residual).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Monitor {
    pub without: f64,
    pub with: f64,
    pub fell_back: bool,
}

/// The lights of a solver and their refinement, as the loop sees them: the current lights, one
/// light step per iteration ([`LightRefinement::step`]), the refined parameters of the state
/// before and after that step (for the acceleration of the joint iteration) and what the
/// report needs.
#[derive(Debug, Clone)]
pub(crate) struct LightRefinement {
    /// The rig's lights (the prior's centre and the intensity gauge's reference).
    rig: Vec<Light>,
    /// The current lights (the rig's, or refined).
    lights: Vec<Light>,
    /// What the options ask to refine (its [`Refine::off`] when nothing is refined).
    asked: Refine,
    /// The refinement, while active.
    refiner: Option<Refiner>,
    /// Whether a light step of this run found nothing to improve: the lights then stay for the
    /// rest of the run (the mesh converges as with known lights).
    settled: bool,
    /// The refined parameters before this iteration's light step (None when none was taken).
    before: Option<Vec<f64>>,
    /// The working distance of the run (positions are refined in its units).
    distance: f64,
    /// Whether the refinement was stopped because the residual rose.
    pub diverged: bool,
    /// The first level's comparison of runs without and with refinement.
    pub monitor: Option<Monitor>,
}

impl LightRefinement {
    /// The rig's `lights`, refined as `refine` asks.
    pub fn new(refine: Refine, lights: &[Light]) -> LightRefinement {
        let mut refinement = LightRefinement {
            rig: lights.to_vec(),
            lights: lights.to_vec(),
            asked: refine,
            refiner: None,
            settled: false,
            before: None,
            distance: f64::NAN,
            diverged: false,
            monitor: None,
        };
        refinement.set_refine(refine);
        refinement
    }

    /// The current lights.
    pub fn lights(&self) -> &[Light] {
        &self.lights
    }

    /// Takes the current lights (the rig's stay).
    pub fn take_lights(&mut self) -> Vec<Light> {
        std::mem::take(&mut self.lights)
    }

    /// Replaces the current lights (the prior's centre stays the rig's).
    pub fn set_lights(&mut self, lights: Vec<Light>) {
        debug_assert_eq!(lights.len(), self.lights.len());
        self.lights = lights;
    }

    /// Goes back to the rig's lights.
    pub fn reset(&mut self) {
        self.lights = self.rig.clone();
    }

    /// What is refined now.
    pub fn refine(&self) -> Refine {
        self.refiner.as_ref().map_or(self.asked.off(), |r| r.refine)
    }

    /// Whether the lights are refined now.
    pub fn is_active(&self) -> bool {
        self.refiner.is_some()
    }

    /// Changes what is refined from now on.
    pub fn set_refine(&mut self, refine: Refine) {
        self.refiner = refine
            .is_active()
            .then(|| Refiner::new(refine, self.rig.clone()));
    }

    /// Starts the lights over: the rig's lights, `refine` from now on, no record of an earlier
    /// run's drift (each evaluation of the distance search starts this way).
    pub fn restart(&mut self, refine: Refine) {
        self.reset();
        self.set_refine(refine);
        self.diverged = false;
    }

    /// Stops the refinement for the rest of the run because the residual rose.
    pub fn stop(&mut self) {
        self.refiner = None;
        self.diverged = true;
    }

    /// Starts a run at the working distance `distance`: the light steps resume.
    pub fn begin(&mut self, distance: f64) {
        self.distance = distance;
        self.settled = false;
        self.before = None;
        if let Some(refiner) = self.refiner.as_mut() {
            refiner.forget_settled();
        }
    }

    /// The length of the refined parameter vector (0 without refinement).
    pub fn parameters(&self) -> usize {
        self.refiner
            .as_ref()
            .map_or(0, |r| r.encode(&self.lights, self.distance).len())
    }

    /// One light step at the unknowns `u` (none without refinement or once settled); returns
    /// the largest change of a light parameter.
    pub fn step(&mut self, data: &LightData<'_>, u: &[f64]) -> Result<f64> {
        self.before = None;
        let Some(refiner) = self.refiner.as_mut().filter(|_| !self.settled) else {
            return Ok(0.0);
        };
        let before = refiner.encode(&self.lights, self.distance);
        let outcome = refiner.try_step(data, &mut self.lights, u)?;
        if outcome.accepted {
            self.before = Some(before);
        } else {
            self.settled = true;
        }
        Ok(outcome.change)
    }

    /// Whether the light steps of this run have ended (nothing left to improve).
    pub fn settled(&self) -> bool {
        self.settled
    }

    /// The refined parameters before and after this iteration's light step, when one was
    /// taken and accepted (the state and image of the joint iteration's light part).
    pub fn moved(&mut self) -> Option<(Vec<f64>, Vec<f64>)> {
        let before = self.before.take()?;
        let refiner = self.refiner.as_ref()?;
        Some((before, refiner.encode(&self.lights, self.distance)))
    }

    /// Takes the lights whose refined parameters are `x` when they stay in front of the
    /// surface's nearest depth `nearest`; returns whether it did.
    pub fn adopt(&mut self, x: &[f64], nearest: f64) -> bool {
        let Some(refiner) = self.refiner.as_ref() else {
            return false;
        };
        let lights = refiner.decode(&self.lights, x, self.distance);
        if !lights.iter().all(|l| l.is_in_front_of(nearest)) {
            return false;
        }
        self.lights = lights;
        true
    }

    /// The conditioning of the asked refinement of the current lights (None when it cannot be
    /// computed): from the pass of the light step of the last run that left these lights as
    /// they were (see [`crate::refine::SettledPass`]) when there was one, else from a pass at
    /// the final unknowns `u`.
    pub fn conditioning(&self, data: &LightData<'_>, u: &[f64]) -> Option<Conditioning> {
        let settled = self
            .refiner
            .as_ref()
            .filter(|r| r.refine == self.asked)
            .and_then(|r| r.settled_pass())
            .and_then(|p| p.conditioning(&self.lights, &self.asked));
        match settled {
            Some(c) => c.ok(),
            None => conditioning(data, &self.lights, u, &self.asked).ok(),
        }
    }
}
