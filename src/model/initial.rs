//! The initial conditions `x(1, i) ~ N(m0_i, P0_i)` (docs/theory.md §1): `[initial]` for every
//! subsystem (its `mean` one list, or one list per subsystem), and an override's
//! `initial.mean`, `initial.cov` for the subsystems it covers (a recording starts from its
//! first readings, which differ along the chain).

use std::collections::HashMap;

use nalgebra::{DMatrix, DVector};

use super::Override;
use super::checker::Checker;
use crate::config::{RawConfig, RawMatrix, RawMean};
use crate::error::Result;

/// The initial condition of one subsystem or more: `x(1, i) ~ N(mean, cov)`.
#[derive(Debug, Clone, PartialEq)]
pub struct InitialCondition {
    /// `m0`.
    pub mean: DVector<f64>,
    /// `P0`.
    pub cov: DMatrix<f64>,
}

/// Every distinct initial condition of a chain, and which one each subsystem starts from.
#[derive(Debug, Clone, PartialEq)]
pub struct InitialConditions {
    sets: Vec<InitialCondition>,
    /// Per subsystem (0-based), its index in `sets`.
    ids: Vec<u32>,
}

impl InitialConditions {
    /// Those of `raw` on a chain of `subsystems` subsystems of `n` states: `[initial]`, then
    /// each override with an `initial` in turn (later ones win); `overrides` are `raw`'s,
    /// checked.
    pub(super) fn from_raw(
        c: &Checker,
        raw: &RawConfig,
        overrides: &[Override],
        n: usize,
        subsystems: usize,
    ) -> Result<Self> {
        let mean = |key: &str, v: &[f64]| -> Result<DVector<f64>> {
            if v.len() != n {
                return Err(c.err(key, format!("expected {n} values (n), found {}", v.len())));
            }
            for &x in v {
                c.finite(key, x)?;
            }
            Ok(DVector::from_column_slice(v))
        };
        let cov = |key: &str, raw: &RawMatrix| -> Result<DMatrix<f64>> {
            let cov = c.matrix(key, raw, n, n, "n × n")?;
            c.positive_semidefinite(key, &cov)?;
            Ok(cov)
        };
        let base_cov = cov("initial.cov", &raw.initial.cov)?;
        let mut conditions = match &raw.initial.mean {
            None | Some(RawMean::All(_)) => InitialConditions {
                sets: vec![InitialCondition {
                    mean: match &raw.initial.mean {
                        Some(RawMean::All(v)) => mean("initial.mean", v)?,
                        _ => DVector::zeros(n),
                    },
                    cov: base_cov,
                }],
                ids: vec![0; subsystems],
            },
            Some(RawMean::PerSubsystem(means)) => {
                if means.len() != subsystems {
                    return Err(c.err(
                        "initial.mean",
                        format!(
                            "expected {n} values, or {subsystems} lists of {n} values (one per subsystem), found {} lists",
                            means.len()
                        ),
                    ));
                }
                // Subsystems with the same mean share a set (by the bits of its numbers).
                let mut conditions = InitialConditions {
                    sets: Vec::new(),
                    ids: Vec::with_capacity(subsystems),
                };
                let mut seen: HashMap<Vec<u64>, u32> = HashMap::new();
                for (i, v) in means.iter().enumerate() {
                    let key = format!("initial.mean[{}]", i + 1);
                    let m = mean(&key, v)?;
                    let bits = v.iter().map(|x| x.to_bits()).collect();
                    let id = *seen.entry(bits).or_insert_with(|| {
                        conditions.sets.push(InitialCondition {
                            mean: m,
                            cov: base_cov.clone(),
                        });
                        (conditions.sets.len() - 1) as u32
                    });
                    conditions.ids.push(id);
                }
                conditions
            }
        };
        for (k, (o, checked)) in raw.overrides.iter().zip(overrides).enumerate() {
            let Some(initial) = &o.initial else { continue };
            let prefix = format!("override[{}].", k + 1);
            if checked.steps.is_some() {
                return Err(c.err(
                    &format!("{prefix}steps"),
                    "an override with `initial` sets the state at t = 1: leave out steps (or give the initial condition an override of its own)",
                ));
            }
            let new_mean = initial
                .mean
                .as_ref()
                .map(|v| mean(&format!("{prefix}initial.mean"), v))
                .transpose()?;
            let new_cov = initial
                .cov
                .as_ref()
                .map(|m| cov(&format!("{prefix}initial.cov"), m))
                .transpose()?;
            let covered: Vec<usize> = match &checked.subsystems {
                None => (0..subsystems).collect(),
                Some(ranges) => ranges
                    .iter()
                    .flat_map(|&(first, last)| first - 1..last)
                    .collect(),
            };
            // What a subsystem becomes depends only on what it was: one new set per old one.
            let mut replaced: HashMap<u32, u32> = HashMap::new();
            for i in covered {
                let old = conditions.ids[i];
                let id = *replaced.entry(old).or_insert_with(|| {
                    let was = &conditions.sets[old as usize];
                    let now = InitialCondition {
                        mean: new_mean.clone().unwrap_or_else(|| was.mean.clone()),
                        cov: new_cov.clone().unwrap_or_else(|| was.cov.clone()),
                    };
                    conditions.intern(now)
                });
                conditions.ids[i] = id;
            }
        }
        conditions.drop_unused();
        Ok(conditions)
    }

    /// Keeps only the sets some subsystem starts from (in order of first use), so that one
    /// set means one start for the whole chain.
    fn drop_unused(&mut self) {
        let mut renumbered: HashMap<u32, u32> = HashMap::new();
        let mut sets = Vec::new();
        for id in &mut self.ids {
            *id = *renumbered.entry(*id).or_insert_with(|| {
                sets.push(self.sets[*id as usize].clone());
                (sets.len() - 1) as u32
            });
        }
        self.sets = sets;
    }

    /// The index of `condition` among the sets, added if new (compared by value).
    fn intern(&mut self, condition: InitialCondition) -> u32 {
        let id = self
            .sets
            .iter()
            .position(|s| *s == condition)
            .unwrap_or_else(|| {
                self.sets.push(condition);
                self.sets.len() - 1
            });
        id as u32
    }

    /// The initial condition of subsystem `i` (0-based).
    pub fn of(&self, i: usize) -> &InitialCondition {
        &self.sets[self.ids[i] as usize]
    }

    /// Every distinct initial condition.
    pub fn sets(&self) -> &[InitialCondition] {
        &self.sets
    }

    /// Per subsystem (0-based), the index of its initial condition in [`Self::sets`].
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// Whether every subsystem starts from the same condition.
    pub fn shared(&self) -> bool {
        self.sets.len() == 1
    }

    /// `[m0_1; …; m0_N]` (`N·n` values).
    pub fn means(&self) -> Vec<f64> {
        self.ids
            .iter()
            .flat_map(|&id| self.sets[id as usize].mean.iter().copied())
            .collect()
    }

    /// `P0_1, …, P0_N`, each `n × n` column-major (`N·n²` values).
    pub fn covs(&self) -> Vec<f64> {
        self.ids
            .iter()
            .flat_map(|&id| self.sets[id as usize].cov.iter().copied())
            .collect()
    }
}
