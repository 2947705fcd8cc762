//! The parameters `fit` estimates and their scales (docs/theory.md §16): `p` through its
//! logit, each variance through its logarithm.

use crate::config::{RawConfig, RawMatrix, RawOverride, RawProbability, RawRanges};
use crate::model::Model;

/// A group of parameters named in `params`: `p`, the diagonal of `Q`, the diagonal of `M`
/// (one for the chain), and `Q[i]`, `M[i]`: each subsystem's own diagonal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum ParamGroup {
    P,
    Q,
    M,
    QEach,
    MEach,
}

impl std::str::FromStr for ParamGroup {
    type Err = super::FitError;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        match name.trim() {
            "p" => Ok(Self::P),
            "Q" => Ok(Self::Q),
            "M" => Ok(Self::M),
            "Q[i]" => Ok(Self::QEach),
            "M[i]" => Ok(Self::MEach),
            other => Err(super::FitError::UnknownParameter(other.to_string())),
        }
    }
}

impl ParamGroup {
    /// The noise matrix the group's entries are of (`None` for `p`).
    pub fn key(&self) -> Option<&'static str> {
        match self {
            Self::P => None,
            Self::Q | Self::QEach => Some("Q"),
            Self::M | Self::MEach => Some("M"),
        }
    }

    /// One value per subsystem.
    pub fn per_subsystem(&self) -> bool {
        matches!(self, Self::QEach | Self::MEach)
    }

    /// `p,Q,M`, or any part of it, in any order.
    pub fn parse_list(text: &str) -> Result<Vec<Self>, super::FitError> {
        text.split(',')
            .filter(|part| !part.trim().is_empty())
            .map(str::parse)
            .collect()
    }
}

/// One scalar fitted: `p`, or the diagonal entry `k` (0-based) of `Q` or `M`, one value for
/// every subsystem, step and override, or (`QOf`, `MOf`) one value for every step of
/// subsystem `i` (0-based).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parameter {
    P,
    Q(usize),
    M(usize),
    QOf { i: usize, k: usize },
    MOf { i: usize, k: usize },
}

impl Parameter {
    /// The scalars of `groups` on `model`: `p`, then `Q11..Qnn`, then `M11..Mqq`, then each
    /// subsystem's `Q11..Qnn` in turn, then each subsystem's `M11..Mqq`.
    pub fn all(model: &Model, groups: &[ParamGroup]) -> Vec<Self> {
        let (big_n, n, q) = (model.subsystems, model.dims.n, model.dims.q);
        // A subsystem without a sensor at any step has no M of its own to fit.
        let measured: Vec<bool> = (0..big_n)
            .map(|i| model.windows().iter().any(|w| w.measured[i]))
            .collect();
        let each = |d: usize, sensors_only: bool, make: fn(usize, usize) -> Self| {
            let measured = &measured;
            (0..big_n)
                .filter(move |&i| !sensors_only || measured[i])
                .flat_map(move |i| (0..d).map(move |k| make(i, k)))
        };
        let mut all = Vec::new();
        for group in groups {
            match group {
                ParamGroup::P => all.push(Self::P),
                ParamGroup::Q => all.extend((0..n).map(Self::Q)),
                ParamGroup::M => all.extend((0..q).map(Self::M)),
                ParamGroup::QEach => all.extend(each(n, false, |i, k| Self::QOf { i, k })),
                ParamGroup::MEach => all.extend(each(q, true, |i, k| Self::MOf { i, k })),
            }
        }
        all
    }

    /// `p`, `Q11`, `M22`, `Q11[i=3]` (`i` 1-based), …
    pub fn name(&self) -> String {
        match self {
            Self::P => "p".into(),
            Self::Q(k) => format!("Q{0}{0}", k + 1),
            Self::M(k) => format!("M{0}{0}", k + 1),
            Self::QOf { i, k } => format!("Q{0}{0}[i={1}]", k + 1, i + 1),
            Self::MOf { i, k } => format!("M{0}{0}[i={1}]", k + 1, i + 1),
        }
    }

    /// One value for one subsystem (`QOf`, `MOf`).
    pub fn per_subsystem(&self) -> bool {
        matches!(self.entry(), Some((_, Some(_), _)))
    }

    /// The matrix (`Q` or `M`) a variance is of; `None` for `p`.
    pub fn key(&self) -> Option<&'static str> {
        self.entry().map(|(key, _, _)| key)
    }

    /// The matrix (`Q` or `M`), the subsystem (`None`: every one) and the diagonal entry of
    /// a variance; `None` for `p`.
    fn entry(&self) -> Option<(&'static str, Option<usize>, usize)> {
        match *self {
            Self::P => None,
            Self::Q(k) => Some(("Q", None, k)),
            Self::M(k) => Some(("M", None, k)),
            Self::QOf { i, k } => Some(("Q", Some(i), k)),
            Self::MOf { i, k } => Some(("M", Some(i), k)),
        }
    }

    /// The value in the config: the configured `Q_kk` or `M_kk` (outside any override, or
    /// subsystem `i`'s at `t = 1`), and `p` averaged over the subsystems at `t = 1`.
    pub fn configured(&self, model: &Model) -> f64 {
        match self.entry() {
            Some((key, i, k)) => {
                let id = i.map_or(0, |i| model.windows()[0].ids[i]);
                model.param_set(id).get(key)[(k, k)]
            }
            None => {
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
        let scale = match self.entry() {
            Some(("Q", _, _)) if largest(&base.Q) > 0.0 => largest(&base.Q),
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

    /// `model` with each parameter at its value: `p` and the chain's variances in the base
    /// and in every override, each subsystem's variances in every set it uses.
    pub fn set_all(model: &Model, values: impl IntoIterator<Item = (Self, f64)>) -> Model {
        let mut model = model.clone();
        let mut own: [(&str, Option<Vec<f64>>); 2] = [("Q", None), ("M", None)];
        for (parameter, value) in values {
            match parameter.entry() {
                None => model = model.with_arrival_probability(value),
                Some((key, None, k)) => model = model.with_diagonal_entry(key, k, value),
                Some((key, Some(i), k)) => {
                    let (_, list) = own
                        .iter_mut()
                        .find(|(name, _)| *name == key)
                        .expect("Q or M");
                    let d = model.param_set(0).get(key).nrows();
                    let list = list.get_or_insert_with(|| diagonals(&model, key));
                    list[i * d + k] = value;
                }
            }
        }
        for (key, list) in own {
            if let Some(list) = list {
                model = model.with_diagonals_per_subsystem(key, &list);
            }
        }
        model
    }
}

/// Each subsystem's diagonal of `key` at `t = 1`, `N·d` values.
fn diagonals(model: &Model, key: &str) -> Vec<f64> {
    model.windows()[0]
        .ids
        .iter()
        .flat_map(|&id| {
            model
                .param_set(id)
                .get(key)
                .diagonal()
                .iter()
                .copied()
                .collect::<Vec<_>>()
        })
        .collect()
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
            // Written by write_per_subsystem, all of a subsystem's matrix at once.
            Self::QOf { .. } | Self::MOf { .. } => {}
        }
    }
}

/// Puts each subsystem's `key` (`Q` or `M`) of `fitted` into the config: one `[[override]]`
/// per subsystem after the others, so that it decides, and `key` taken out of the overrides
/// for every step before it, which those replace (an override left setting nothing goes).
pub fn write_per_subsystem(raw: &mut RawConfig, fitted: &Model, key: &str) {
    for o in raw.overrides.iter_mut().filter(|o| o.steps.is_none()) {
        *o.noise_mut(key) = None;
    }
    raw.overrides.retain(|o| !o.sets_nothing());
    for (i, &id) in fitted.windows()[0].ids.iter().enumerate() {
        let matrix = fitted.param_set(id).get(key);
        let rows = matrix
            .row_iter()
            .map(|r| r.iter().copied().collect())
            .collect();
        let subsystem = i as i64 + 1;
        let mut o = RawOverride {
            subsystems: Some(RawRanges::Range([subsystem, subsystem])),
            ..RawOverride::default()
        };
        *o.noise_mut(key) = Some(RawMatrix(rows));
        raw.overrides.push(o);
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
        assert_eq!(
            ParamGroup::parse_list("Q[i],M").unwrap(),
            [ParamGroup::QEach, ParamGroup::M]
        );
        assert!(ParamGroup::parse_list("p,R").is_err());
        assert!(ParamGroup::parse_list("Q[j]").is_err());
    }
}
