//! The parameters `fit` estimates and their scales (docs/theory.md §16): `p` through its
//! logit, each variance through its logarithm.

use crate::config::{RawConfig, RawMatrix, RawProbability};
use crate::model::Model;

/// A group of parameters named in `params`: `p`, the diagonal of `Q`, the diagonal of `M`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum ParamGroup {
    P,
    Q,
    M,
}

impl std::str::FromStr for ParamGroup {
    type Err = super::FitError;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        match name.trim() {
            "p" => Ok(Self::P),
            "Q" => Ok(Self::Q),
            "M" => Ok(Self::M),
            other => Err(super::FitError::UnknownParameter(other.to_string())),
        }
    }
}

impl ParamGroup {
    /// `p,Q,M`, or any part of it, in any order.
    pub fn parse_list(text: &str) -> Result<Vec<Self>, super::FitError> {
        text.split(',')
            .filter(|part| !part.trim().is_empty())
            .map(str::parse)
            .collect()
    }
}

/// One scalar fitted: `p`, or the diagonal entry `k` (0-based) of `Q` or `M`, one value for
/// every subsystem, step and override.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parameter {
    P,
    Q(usize),
    M(usize),
}

impl Parameter {
    /// The scalars of `groups` on `model`: `p`, then `Q11..Qnn`, then `M11..Mqq`.
    pub fn all(model: &Model, groups: &[ParamGroup]) -> Vec<Self> {
        let mut all = Vec::new();
        for group in groups {
            match group {
                ParamGroup::P => all.push(Self::P),
                ParamGroup::Q => all.extend((0..model.dims.n).map(Self::Q)),
                ParamGroup::M => all.extend((0..model.dims.q).map(Self::M)),
            }
        }
        all
    }

    /// `p`, `Q11`, `M22`, …
    pub fn name(&self) -> String {
        match self {
            Self::P => "p".into(),
            Self::Q(k) => format!("Q{0}{0}", k + 1),
            Self::M(k) => format!("M{0}{0}", k + 1),
        }
    }

    /// The value in the config: the configured `Q_kk` or `M_kk` (outside any override), and
    /// `p` averaged over the subsystems at `t = 1`.
    pub fn configured(&self, model: &Model) -> f64 {
        let base = model.param_set(0);
        match *self {
            Self::P => {
                let p = &model.windows()[0].p;
                let (lo, hi) = p
                    .iter()
                    .fold((1.0f64, 0.0f64), |(lo, hi), &v| (lo.min(v), hi.max(v)));
                if lo == hi {
                    lo
                } else {
                    p.iter().sum::<f64>() / p.len() as f64
                }
            }
            Self::Q(k) => base.Q[(k, k)],
            Self::M(k) => base.M[(k, k)],
        }
    }

    /// Where the optimiser starts, in `θ`: the configured value (`p` kept inside the box, a
    /// variance configured as 0 at a hundredth of its diagonal's largest entry, or of `M`'s).
    pub fn start(&self, model: &Model) -> f64 {
        let value = self.configured(model);
        match self {
            Self::P => logit(value).clamp(-super::LOGIT_BOUND, super::LOGIT_BOUND),
            _ if value > 0.0 => value.ln(),
            _ => self.zero_start(model).ln(),
        }
    }

    /// The start of a variance configured as 0: a hundredth of the largest configured entry
    /// of the same diagonal, or of `M`'s when that diagonal is all zero.
    fn zero_start(&self, model: &Model) -> f64 {
        let base = model.param_set(0);
        let largest = |m: &nalgebra::DMatrix<f64>| m.diagonal().max();
        let scale = match self {
            Self::Q(_) if largest(&base.Q) > 0.0 => largest(&base.Q),
            _ => largest(&base.M),
        };
        0.01 * scale
    }

    /// The value at `θ`: the logistic function for `p`, the exponential for a variance.
    pub fn value(&self, theta: f64) -> f64 {
        match self {
            Self::P => 1.0 / (1.0 + (-theta).exp()),
            _ => theta.exp(),
        }
    }

    /// `d value / dθ` (the delta method's factor).
    pub fn slope(&self, theta: f64) -> f64 {
        let v = self.value(theta);
        match self {
            Self::P => v * (1.0 - v),
            _ => v,
        }
    }

    /// `model` with this parameter at `value`, in the base and in every override.
    pub fn set(&self, model: &Model, value: f64) -> Model {
        match *self {
            Self::P => model.with_arrival_probability(value),
            Self::Q(k) => model.with_diagonal_entry("Q", k, value),
            Self::M(k) => model.with_diagonal_entry("M", k, value),
        }
    }
}

impl Parameter {
    /// Puts `value` into the config tables: into `dropout.p` (one value, also where the config
    /// had a list) and every override's `p`, or into the diagonal entry of `model.Q` (made
    /// when left out) or `model.M` and of every override's.
    pub fn write(&self, raw: &mut RawConfig, value: f64) {
        let n = raw.model.A.len();
        let put = |m: &mut RawMatrix, k: usize| m.0[k][k] = value;
        match *self {
            Self::P => {
                raw.dropout.p = RawProbability::All(value);
                for o in &mut raw.overrides {
                    if o.p.is_some() {
                        o.p = Some(value);
                    }
                }
            }
            Self::Q(k) => {
                put(
                    raw.model
                        .Q
                        .get_or_insert_with(|| RawMatrix(vec![vec![0.0; n]; n])),
                    k,
                );
                for q in raw.overrides.iter_mut().filter_map(|o| o.Q.as_mut()) {
                    put(q, k);
                }
            }
            Self::M(k) => {
                put(&mut raw.model.M, k);
                for m in raw.overrides.iter_mut().filter_map(|o| o.M.as_mut()) {
                    put(m, k);
                }
            }
        }
    }
}

fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// What the user should know before the fit starts: a `p` that varies in the config is
/// fitted as one value, and a variance configured as 0 starts elsewhere.
pub fn start_warnings(model: &Model, parameters: &[Parameter]) -> Vec<String> {
    let mut warnings = Vec::new();
    for p in parameters {
        match p {
            Parameter::P => {
                let (time, space) = model.variation("p");
                if time || space {
                    warnings.push(format!(
                        "p varies in the config (across {}): it is fitted as one value for every subsystem and step",
                        match (time, space) {
                            (true, true) => "subsystems and steps",
                            (true, false) => "steps",
                            _ => "subsystems",
                        }
                    ));
                }
            }
            _ if p.configured(model) == 0.0 => warnings.push(format!(
                "{} is configured as 0: the fit starts from {:e}",
                p.name(),
                p.zero_start(model)
            )),
            _ => {}
        }
    }
    warnings
}

/// Whether every `M` is positive definite and every `Q` positive semidefinite (the fitted
/// diagonal with the configured off-diagonal entries may be neither).
pub fn noise_is_valid(model: &Model) -> bool {
    model.param_sets().iter().all(|set| {
        let q_scale = set.Q.amax();
        set.M.clone().cholesky().is_some()
            && set.Q.clone().symmetric_eigenvalues().min() >= -1e-12 * q_scale
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scales map back and forth, and the slope is the derivative.
    #[test]
    fn scales_invert_and_slopes_are_derivatives() {
        for (p, theta) in [
            (Parameter::P, 0.7),
            (Parameter::P, -3.0),
            (Parameter::Q(0), -2.0),
        ] {
            let v = p.value(theta);
            let back = match p {
                Parameter::P => logit(v),
                _ => v.ln(),
            };
            assert!((back - theta).abs() < 1e-12);
            let h = 1e-6;
            let numeric = (p.value(theta + h) - p.value(theta - h)) / (2.0 * h);
            assert!((numeric - p.slope(theta)).abs() < 1e-8 * p.slope(theta).max(1.0));
        }
    }

    #[test]
    fn lists_parse() {
        assert_eq!(
            ParamGroup::parse_list("p, M").unwrap(),
            [ParamGroup::P, ParamGroup::M]
        );
        assert!(ParamGroup::parse_list("p,R").is_err());
    }
}
