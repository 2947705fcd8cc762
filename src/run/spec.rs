//! What a run computes: [`RunSpec`], the settings as asked for, and [`CheckedSpec`], the same
//! settings once every combination rule has been checked (docs/theory.md §13). A front end
//! fills a `RunSpec`, calls [`RunSpec::check`] once, and builds filters and smoothers from the
//! checked form; nothing downstream checks a setting again.

use crate::filter::centralized::{CentralizedLimits, DEFAULT_MAX_LIFTED};
use crate::filter::{
    CentralizedFilter, ChainFilter, Dropouts, FilterKind, InterconnectFrom, JointFilter,
    JointOptions, SecondMoment, TwoStepOptions, Update, two_step,
};
use crate::interconnect::SolverKind;
use crate::io::estimates::{EstimateKind, EstimateOptions, EstimatesColumns, JointSettings};
use crate::memory::DEFAULT_MAX_MEMORY;
use crate::model::Model;
use crate::run::HoldOut;
use crate::smoother::{
    CentralizedSmoother, DistributedSmoother, JointSmoother, Smoother, SmootherKind,
};

/// A setting of a [`RunSpec`] that a [`SpecError`] is about, by its field name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Setting {
    Band,
    BandTol,
    Loading,
    SecondMomentBand,
}

impl Setting {
    /// The setting as the library names it (`band_tol`, `second_moment = band`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Band => "band",
            Self::BandTol => "band_tol",
            Self::Loading => "loading",
            Self::SecondMomentBand => "second_moment = band",
        }
    }
}

/// A [`RunSpec`] whose settings do not go together, or a value out of its range. Each names the
/// settings by their field names; a front end may put them in its own words (the command line
/// names its flags).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    /// The mixture update detects lost measurements; with known dropouts there is nothing to
    /// detect (docs/theory.md §10).
    #[error(
        "update = mixture needs dropouts = unknown: with known dropouts there is nothing to detect"
    )]
    MixtureWithKnownDropouts,
    /// `band`, `band_tol`, `loading` and `second_moment = band` are the joint filter's.
    #[error("{} belongs to the joint filter (filter = joint)", .0.name())]
    JointOnly(Setting),
    /// The paper's moment recursion is the two-step filter's.
    #[error(
        "second_moment = paper belongs to the distributed filter; the joint filter takes band, lifted or local"
    )]
    PaperMomentInJoint,
    /// A smoothed run writes `x̂(t|T)`, a predicted one `x̂(t+1|t)`: one or the other.
    #[error("smooth and predicted exclude each other")]
    SmoothAndPredicted,
    /// `band_tol` and `loading` are finite numbers ≥ 0.
    #[error("{} = {value}: expected a finite number ≥ 0", .setting.name())]
    NotFiniteNonNegative { setting: Setting, value: f64 },
    /// A share of readings to hold out is a probability strictly between 0 and 1.
    #[error("hold_out = {0}: expected a share above 0 and below 1")]
    HoldOutShare(f64),
    /// Row `t` of a predicted run estimates step `t + 1`, not the step of the readings held
    /// out of it.
    #[error(
        "hold_out and predicted exclude each other: held-out readings are scored against the estimate of their own step"
    )]
    HoldOutPredicted,
}

/// The one rule on how the measurements update the estimate: the mixture update needs unknown
/// dropouts. [`RunSpec::check`] applies it; so do the filters' own constructors, for callers that
/// build one directly.
pub fn check_update(dropouts: Dropouts, update: Update) -> Result<(), SpecError> {
    if update == Update::Mixture && dropouts == Dropouts::Known {
        return Err(SpecError::MixtureWithKnownDropouts);
    }
    Ok(())
}

/// Checks that `value` of `setting` is a finite number ≥ 0.
pub(crate) fn check_non_negative(setting: Setting, value: f64) -> Result<(), SpecError> {
    if !value.is_finite() || value < 0.0 {
        return Err(SpecError::NotFiniteNonNegative { setting, value });
    }
    Ok(())
}

/// The settings of a run, as asked for (docs/theory.md §13). `None` means the default, which
/// may depend on other settings (the paper's preset, the filter); [`RunSpec::check`] resolves
/// them.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSpec {
    pub filter: FilterKind,
    pub update: Update,
    pub dropouts: Dropouts,
    /// The paper's two-step filter ([`TwoStepOptions::paper`]); the explicit two-step settings
    /// below win over it.
    pub paper: bool,
    /// Step 1's solver (two-step filter).
    pub solver: Option<SolverKind>,
    /// `S = E[x xᵀ]` in Nahi's update (two-step filter; `band` is the joint filter's default).
    pub second_moment: Option<SecondMoment>,
    /// The estimate fed to step 1 (two-step filter).
    pub interconnect_from: Option<InterconnectFrom>,
    /// The joint filter's covariance band `K`.
    pub band: Option<usize>,
    /// The joint filter's relative tolerance of `A_eff`'s band.
    pub band_tol: Option<f64>,
    /// The joint filter's diagonal loading `ε`.
    pub loading: Option<f64>,
    /// `x̂(t|T)`, `P(t|T)` from every measurement instead of the filtered estimates.
    pub smooth: bool,
    /// `x̂(t+1|t)`, `T(t+1)` on row `t` instead of the filtered estimates.
    pub predicted: bool,
    /// Largest lifted state `N·n` the centralized filter accepts.
    pub max_lifted: usize,
    /// Largest memory (bytes) the run may hold: the filter's arrays ([`crate::memory`]) and
    /// the smoother's stored forward pass, each checked before it is allocated.
    pub max_memory: Option<u64>,
    /// The estimates gain the column `nis`, the normalised innovation squared of every
    /// `(t, i)` (docs/theory.md §14; the innovation check itself runs whatever).
    pub nis_column: bool,
    /// Keep this share of the readings from the run and score its estimates on them
    /// (docs/theory.md §17), drawn with `hold_out_seed`.
    pub hold_out: Option<f64>,
    pub hold_out_seed: u64,
}

impl Default for RunSpec {
    /// The distributed filter with its default options, filtered estimates.
    fn default() -> Self {
        Self {
            filter: FilterKind::Distributed,
            update: Update::Linear,
            dropouts: Dropouts::Unknown,
            paper: false,
            solver: None,
            second_moment: None,
            interconnect_from: None,
            band: None,
            band_tol: None,
            loading: None,
            smooth: false,
            predicted: false,
            max_lifted: DEFAULT_MAX_LIFTED,
            max_memory: None,
            nis_column: false,
            hold_out: None,
            hold_out_seed: 1,
        }
    }
}

impl RunSpec {
    /// Every combination rule, in one place; the first broken one is the error.
    pub fn check(&self) -> Result<CheckedSpec, SpecError> {
        check_update(self.dropouts, self.update)?;
        let mut two_step = if self.paper {
            TwoStepOptions::paper()
        } else {
            TwoStepOptions::default()
        };
        two_step.solver = self.solver.unwrap_or(two_step.solver);
        two_step.second_moment = self.second_moment.unwrap_or(two_step.second_moment);
        two_step.interconnect_from = self.interconnect_from.unwrap_or(two_step.interconnect_from);
        two_step.dropouts = self.dropouts;
        two_step.update = self.update;
        let joint = self.joint_options()?;
        let output = match (self.smooth, self.predicted) {
            (true, true) => return Err(SpecError::SmoothAndPredicted),
            (true, false) => EstimateKind::Smoothed,
            (false, true) => EstimateKind::Predicted,
            (false, false) => EstimateKind::Filtered,
        };
        let hold_out = match self.hold_out {
            None => None,
            Some(_) if output == EstimateKind::Predicted => {
                return Err(SpecError::HoldOutPredicted);
            }
            Some(share) => Some(
                HoldOut::new(share, self.hold_out_seed).ok_or(SpecError::HoldOutShare(share))?,
            ),
        };
        Ok(CheckedSpec {
            filter: self.filter,
            paper: self.paper,
            two_step,
            joint,
            output,
            max_lifted: self.max_lifted,
            max_memory: self.max_memory.unwrap_or(DEFAULT_MAX_MEMORY),
            nis_column: self.nis_column,
            hold_out,
        })
    }

    /// The joint filter's options (`None` for the other filters, which refuse the joint
    /// filter's settings).
    fn joint_options(&self) -> Result<Option<JointOptions>, SpecError> {
        if self.filter != FilterKind::Joint {
            let only_joint = [
                (self.band.is_some(), Setting::Band),
                (self.band_tol.is_some(), Setting::BandTol),
                (self.loading.is_some(), Setting::Loading),
                (
                    self.second_moment == Some(SecondMoment::Band),
                    Setting::SecondMomentBand,
                ),
            ];
            return match only_joint.iter().find(|(given, _)| *given) {
                Some(&(_, setting)) => Err(SpecError::JointOnly(setting)),
                None => Ok(None),
            };
        }
        let second_moment = match self.second_moment {
            Some(SecondMoment::Paper) => return Err(SpecError::PaperMomentInJoint),
            Some(s) => s,
            None => SecondMoment::Band,
        };
        let defaults = JointOptions::default();
        let joint = JointOptions {
            band: self.band.unwrap_or(defaults.band),
            band_tol: self.band_tol.unwrap_or(defaults.band_tol),
            loading: self.loading,
            second_moment,
            dropouts: self.dropouts,
            update: self.update,
            max_memory: self.max_memory.unwrap_or(DEFAULT_MAX_MEMORY),
        };
        joint.check()?;
        Ok(Some(joint))
    }
}

/// A [`RunSpec`] whose settings go together, with every default resolved: made only by
/// [`RunSpec::check`]. It builds the filter or smoother it describes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckedSpec {
    filter: FilterKind,
    paper: bool,
    /// The two-step filter's options; the dropout mode and the update serve every filter.
    two_step: TwoStepOptions,
    /// The joint filter's options (`filter = joint` only).
    joint: Option<JointOptions>,
    output: EstimateKind,
    max_lifted: usize,
    max_memory: u64,
    nis_column: bool,
    hold_out: Option<HoldOut>,
}

impl CheckedSpec {
    /// The readings a run keeps from its filter to score it on, if any (docs/theory.md §17).
    pub fn hold_out(&self) -> Option<HoldOut> {
        self.hold_out
    }

    pub fn filter_kind(&self) -> FilterKind {
        self.filter
    }

    pub fn dropouts(&self) -> Dropouts {
        self.two_step.dropouts
    }

    pub fn update(&self) -> Update {
        self.two_step.update
    }

    /// Whether a run's files are best read on a thread of their own, ahead of the filter
    /// ([`super::ReadAhead`]): when a step of the filter costs far more than parsing it, as the
    /// centralized filter's `O((N n)³)` does, the otherwise idle second core takes the parsing.
    /// A distributed filter's step costs about what parsing it costs; there the writer thread
    /// already keeps the second core busy, and a third thread only contends with it (20 %
    /// slower at N = 100).
    pub fn reads_ahead(&self) -> bool {
        self.filter == FilterKind::Centralized
    }

    /// Which estimates the run gives: filtered, predicted or smoothed.
    pub fn output(&self) -> EstimateKind {
        self.output
    }

    /// The filter refuses to start above this many bytes, and the smoother stops once its
    /// stored forward pass would exceed them.
    pub fn max_memory(&self) -> u64 {
        self.max_memory
    }

    /// The joint filter's options (`filter = joint` only).
    pub fn joint_options(&self) -> Option<JointOptions> {
        self.joint
    }

    /// The same run by the joint filter at band `k` (this spec's joint options otherwise), or
    /// with `None` by the centralized filter, the joint filter's exact form (docs/theory.md
    /// §8): the objectives among which `fit` chooses (docs/theory.md §16).
    pub fn with_band(&self, band: Option<usize>) -> CheckedSpec {
        let mut spec = *self;
        match band {
            Some(k) => {
                spec.filter = FilterKind::Joint;
                spec.joint = Some(JointOptions {
                    band: k,
                    dropouts: self.dropouts(),
                    update: self.update(),
                    max_memory: self.max_memory,
                    ..self.joint.unwrap_or_default()
                });
            }
            None => {
                spec.filter = FilterKind::Centralized;
                spec.joint = None;
            }
        }
        spec
    }

    /// The centralized filter refuses chains of more lifted states.
    pub fn max_lifted(&self) -> usize {
        self.max_lifted
    }

    /// The smoother, for its memory estimate.
    pub fn smoother_kind(&self) -> SmootherKind {
        match (self.filter, self.joint) {
            (FilterKind::Joint, Some(j)) => SmootherKind::Joint(j.band),
            (FilterKind::Centralized, _) => SmootherKind::Centralized,
            _ => SmootherKind::Distributed,
        }
    }

    pub fn centralized_limits(&self) -> CentralizedLimits {
        CentralizedLimits {
            max_lifted: self.max_lifted,
            max_memory: self.max_memory,
        }
    }

    /// The joint filter's band `k` as it runs on `model`: at most `N − 1`.
    fn joint_band(&self, model: &Model) -> Option<usize> {
        self.joint.map(|j| j.band.min(model.subsystems - 1))
    }

    /// The columns of the run's estimates on `model`: `t_given` first for predicted
    /// estimates, the covariance band `k` beside the
    /// diagonal blocks (the joint filter's, at most `N − 1`; 0 for the others), and `π` with
    /// the mixture update.
    pub fn columns(&self, model: &Model) -> EstimatesColumns {
        EstimatesColumns {
            predicted: self.output() == EstimateKind::Predicted,
            n: model.dims.n,
            cross: self.joint_band(model).unwrap_or(0),
            arrival: self.update() == Update::Mixture,
            nis: self.nis_column,
        }
    }

    /// The filter (docs/theory.md §4, §7, §8, §10).
    pub fn build_filter(&self, model: &Model) -> crate::Result<Box<dyn ChainFilter>> {
        Ok(match (self.filter, self.joint) {
            (FilterKind::Joint, Some(j)) => Box::new(JointFilter::new(model, j)?),
            (FilterKind::Centralized, _) => {
                let known = self.dropouts() == Dropouts::Known;
                let filter = CentralizedFilter::new(model, known, self.centralized_limits())?;
                match self.update() {
                    Update::Linear => Box::new(filter),
                    Update::Mixture => Box::new(filter.with_mixture_update()?),
                }
            }
            _ => two_step(model, self.two_step)?,
        })
    }

    /// The smoother of the filter (docs/theory.md §9).
    pub fn build_smoother(&self, model: &Model) -> crate::Result<Box<dyn Smoother>> {
        Ok(match (self.filter, self.joint) {
            (FilterKind::Joint, Some(j)) => Box::new(JointSmoother::new(model, j)?),
            (FilterKind::Centralized, _) => {
                let known = self.dropouts() == Dropouts::Known;
                let smoother = CentralizedSmoother::new(model, known, self.centralized_limits())?;
                match self.update() {
                    Update::Linear => Box::new(smoother),
                    Update::Mixture => Box::new(smoother.with_mixture_update()?),
                }
            }
            _ => Box::new(DistributedSmoother::new(
                model,
                two_step(model, self.two_step)?,
            )),
        })
    }

    /// The options as an estimates file records them, on `model`.
    pub fn recorded(&self, model: &Model) -> EstimateOptions {
        // The two-step filter's options; the other filters ignore them.
        let two_step = (self.filter == FilterKind::Distributed).then_some(self.two_step);
        EstimateOptions {
            dropouts: self.dropouts(),
            filter: self.filter,
            interconnect_from: two_step.map(|o| o.interconnect_from),
            joint: self.joint.map(|j| JointSettings {
                band: self.joint_band(model).unwrap_or(j.band),
                band_tol: j.band_tol,
                loading: j.loading_for(model),
                second_moment: j.second_moment,
            }),
            output: self.output,
            paper: self.paper,
            // The mixture update has no second moment.
            second_moment: two_step
                .filter(|o| o.update == Update::Linear)
                .map(|o| o.second_moment),
            solver: two_step.map(|o| o.solver),
            update: self.update(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_spec_is_the_distributed_filter_with_its_defaults() {
        let checked = RunSpec::default().check().unwrap();
        assert_eq!(checked.filter_kind(), FilterKind::Distributed);
        assert_eq!(checked.two_step, TwoStepOptions::default());
        assert_eq!(checked.joint, None);
        assert_eq!(checked.output(), EstimateKind::Filtered);
        assert_eq!(checked.max_memory(), DEFAULT_MAX_MEMORY);
    }

    #[test]
    fn the_paper_preset_yields_to_explicit_settings() {
        let spec = RunSpec {
            paper: true,
            solver: Some(SolverKind::Banded),
            ..RunSpec::default()
        };
        let checked = spec.check().unwrap();
        assert_eq!(
            checked.two_step,
            TwoStepOptions {
                solver: SolverKind::Banded,
                ..TwoStepOptions::paper()
            }
        );
    }

    #[test]
    fn the_joint_filter_defaults_to_its_band_moment() {
        let spec = RunSpec {
            filter: FilterKind::Joint,
            band: Some(4),
            ..RunSpec::default()
        };
        let joint = spec.check().unwrap().joint.unwrap();
        assert_eq!(joint.second_moment, SecondMoment::Band);
        assert_eq!(joint.band, 4);
        assert_eq!(joint.band_tol, JointOptions::default().band_tol);
    }

    /// Each rule refuses once, with the message that names the settings.
    #[test]
    fn every_rule_refuses_with_one_message_naming_the_settings() {
        let joint = RunSpec {
            filter: FilterKind::Joint,
            ..RunSpec::default()
        };
        let cases = [
            (
                RunSpec {
                    update: Update::Mixture,
                    dropouts: Dropouts::Known,
                    ..joint.clone()
                },
                SpecError::MixtureWithKnownDropouts,
                "update = mixture needs dropouts = unknown: with known dropouts there is nothing to detect",
            ),
            (
                RunSpec {
                    loading: Some(1e-3),
                    ..RunSpec::default()
                },
                SpecError::JointOnly(Setting::Loading),
                "loading belongs to the joint filter (filter = joint)",
            ),
            (
                RunSpec {
                    filter: FilterKind::Centralized,
                    second_moment: Some(SecondMoment::Band),
                    ..RunSpec::default()
                },
                SpecError::JointOnly(Setting::SecondMomentBand),
                "second_moment = band belongs to the joint filter (filter = joint)",
            ),
            (
                RunSpec {
                    second_moment: Some(SecondMoment::Paper),
                    ..joint.clone()
                },
                SpecError::PaperMomentInJoint,
                "second_moment = paper belongs to the distributed filter; the joint filter takes band, lifted or local",
            ),
            (
                RunSpec {
                    smooth: true,
                    predicted: true,
                    ..RunSpec::default()
                },
                SpecError::SmoothAndPredicted,
                "smooth and predicted exclude each other",
            ),
            (
                RunSpec {
                    band_tol: Some(-1.0),
                    ..joint.clone()
                },
                SpecError::NotFiniteNonNegative {
                    setting: Setting::BandTol,
                    value: -1.0,
                },
                "band_tol = -1: expected a finite number ≥ 0",
            ),
            (
                RunSpec {
                    loading: Some(f64::INFINITY),
                    ..joint
                },
                SpecError::NotFiniteNonNegative {
                    setting: Setting::Loading,
                    value: f64::INFINITY,
                },
                "loading = inf: expected a finite number ≥ 0",
            ),
        ];
        for (spec, error, message) in cases {
            let refused = spec.check().unwrap_err();
            assert_eq!(refused, error);
            assert_eq!(refused.to_string(), message);
        }
    }
}
